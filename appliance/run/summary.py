"""The summary of a run: throughput, latency and, against a known truth, the strain errors.

`RunSummary.from_run` condenses the loop's result and the per-sample records into the figures
a test report (and `extensometer run --json`) gives. With a ground truth (a simulated test, or
a calibration device) it adds the errors:

* `max_abs_strain_error`: largest |measured - true| engineering strain over valid samples;
* `max_rel_strain_error`: largest |measured - true| / |measured| over valid samples whose
  reading exceeds 1 % strain;
* `max_elongation_error_um`: largest |measured - true| elongation, um; and the same over the
  samples whose true elongation is below `small_elongation_um` (300 um: the range where
  ISO 9513's absolute limits decide);
* `iso9513_class`: the best ISO 9513 class whose bias limits every valid sample meets;
* `lost_points`: point-frames not measured, over every sample (the sum of the strain file's
  `points_lost` column, and of the recording's); `lost_points_in_valid_samples` the same over
  valid samples only (a frame of the broken specimen is not valid).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from appliance.measure.frame_measurer import StrainSample
from appliance.run.iso9513 import best_class
from appliance.run.loop import LoopResult
from appliance.run.state import ExitStatus

REL_ERROR_MIN_STRAIN = 0.01
SMALL_ELONGATION_UM = 300.0


@dataclass(frozen=True)
class SampleRecord:
    """What the summary needs of one sample.

    Attributes:
        strain: measured engineering strain.
        elongation_mm: measured elongation, mm.
        valid: the data-valid flag.
        points_lost: points not measured in the frame.
        reference_updates: references replaced after the frame.
        truth_strain: the engineering strain the truth gives (a simulation's, a calibrator's;
            NaN when unknown).
        truth_elongation_mm: the elongation the truth gives, mm (NaN when unknown).
    """

    strain: float
    elongation_mm: float
    valid: bool
    points_lost: int
    reference_updates: int
    truth_strain: float = math.nan
    truth_elongation_mm: float = math.nan

    @classmethod
    def of(
        cls,
        sample: StrainSample,
        truth_strain: float = math.nan,
        truth_elongation_mm: float = math.nan,
    ) -> SampleRecord:
        """The record of a measured sample, with its truth where known."""
        return cls(
            strain=sample.reading.engineering_strain,
            elongation_mm=sample.reading.elongation_mm,
            valid=sample.data_valid,
            points_lost=sample.points_lost,
            reference_updates=sample.reference_updates,
            truth_strain=truth_strain,
            truth_elongation_mm=truth_elongation_mm,
        )


@dataclass(frozen=True)
class RunSummary:
    """Figures of one run (JSON-ready: floats, ints, strings and None)."""

    exit_status: ExitStatus
    reason: str
    frames_processed: int
    frames_dropped: int
    latency_ms_p50: float | None
    latency_ms_p99: float | None
    tracking_fps: float | None
    final_strain: float | None
    truth_final_strain: float | None
    max_abs_strain_error: float | None
    max_rel_strain_error: float | None
    max_elongation_error_um: float | None
    max_elongation_error_um_below_300um: float | None
    lost_points: int
    lost_points_in_valid_samples: int
    invalid_samples: int
    reference_updates: int
    iso9513_class: str | None

    @classmethod
    def from_run(cls, result: LoopResult, records: Sequence[SampleRecord]) -> RunSummary:
        """Summarise a run from the loop's result and its per-sample records."""
        latency = np.asarray(result.latencies_s) * 1e3
        valid = [r for r in records if r.valid and math.isfinite(r.strain)]
        truthful = [r for r in valid if math.isfinite(r.truth_strain)]
        strain = np.array([r.strain for r in truthful])
        true = np.array([r.truth_strain for r in truthful])
        elong = np.array([r.elongation_mm for r in truthful]) * 1e3
        true_elong = np.array([r.truth_elongation_mm for r in truthful]) * 1e3
        strain_error = np.abs(strain - true)
        elong_error = np.abs(elong - true_elong)
        large = np.abs(strain) > REL_ERROR_MIN_STRAIN
        small = np.abs(true_elong) < SMALL_ELONGATION_UM
        return cls(
            exit_status=result.exit_status,
            reason=result.reason,
            frames_processed=result.frames_processed,
            frames_dropped=result.frames_dropped,
            latency_ms_p50=_stat(np.percentile, latency, 50),
            latency_ms_p99=_stat(np.percentile, latency, 99),
            tracking_fps=(
                result.frames_processed / result.tracking_time_s
                if result.tracking_time_s > 0
                else None
            ),
            final_strain=valid[-1].strain if valid else None,
            truth_final_strain=truthful[-1].truth_strain if truthful else None,
            max_abs_strain_error=_stat(np.max, strain_error),
            max_rel_strain_error=_stat(np.max, strain_error[large] / np.abs(strain[large])),
            max_elongation_error_um=_stat(np.max, elong_error),
            max_elongation_error_um_below_300um=_stat(np.max, elong_error[small]),
            lost_points=sum(r.points_lost for r in records),
            lost_points_in_valid_samples=sum(r.points_lost for r in valid),
            invalid_samples=sum(not r.valid for r in records),
            reference_updates=sum(r.reference_updates for r in records),
            iso9513_class=best_class(elong, true_elong) if truthful else None,
        )

    def as_dict(self) -> dict:
        """The summary as a plain dictionary (for JSON)."""
        return asdict(self)


def _stat(function, values: np.ndarray, *args) -> float | None:
    return float(function(values, *args)) if values.size else None


@dataclass
class RunOutcome:
    """What a run (or a replay) produced.

    Attributes:
        summary: the figures of the run (with `extra` merged in `as_dict`).
        extra: run facts beyond the summary: exposure plan, gauge length, duration, counts
            of the devices and outputs.
        csv_path, summary_path: files written (None without an output directory).
    """

    summary: RunSummary
    extra: dict[str, Any] = field(default_factory=dict)
    csv_path: Path | None = None
    summary_path: Path | None = None

    def as_dict(self) -> dict[str, Any]:
        """Summary and facts as one dictionary."""
        return {**self.summary.as_dict(), **self.extra}

    def to_json(self) -> str:
        """Summary and facts as JSON (NaN and infinities as null)."""
        return json.dumps(_json_ready(self.as_dict()), indent=2)


def _json_ready(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _json_ready(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_json_ready(v) for v in value]
    return value
