"""The strain series of a run as a CSV file, one row per measured frame.

Columns (units in the names): sample index, camera frame id, device time, exposure, the
strains, elongation and current gauge length, the data-valid flag, points lost in the frame,
reference updates, the frames dropped so far in the test (a rise is a gap in the series), the
controller's crosshead position and force, and the processing latency;
then any extra columns the caller adds (a simulation's ground truth, for instance). Every row
is flushed as it is written, so a run that ends abruptly keeps every sample measured before.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from appliance.measure.frame_measurer import StrainSample

COLUMNS: tuple[str, ...] = (
    "index",
    "frame_id",
    "time_s",
    "timestamp_ns",
    "exposure_us",
    "engineering_strain",
    "true_strain",
    "transverse_strain",
    "poisson_ratio",
    "elongation_mm",
    "gauge_length_mm",
    "data_valid",
    "points_lost",
    "reference_updates",
    "frames_dropped",
    "crosshead_mm",
    "force_n",
    "latency_ms",
)


def sample_row(sample: StrainSample) -> dict[str, Any]:
    """The standard columns of one sample."""
    reading = sample.reading
    machine = sample.machine
    return {
        "index": sample.index,
        "frame_id": sample.frame_id,
        "time_s": sample.time_s,
        "timestamp_ns": sample.timestamp_ns,
        "exposure_us": sample.exposure_us,
        "engineering_strain": reading.engineering_strain,
        "true_strain": reading.true_strain,
        "transverse_strain": reading.transverse_strain,
        "poisson_ratio": reading.poisson_ratio,
        "elongation_mm": reading.elongation_mm,
        "gauge_length_mm": reading.gauge_length_mm,
        "data_valid": int(sample.data_valid),
        "points_lost": sample.points_lost,
        "frames_dropped": sample.frames_dropped,
        "reference_updates": sample.reference_updates,
        "crosshead_mm": machine.crosshead_mm if machine is not None else math.nan,
        "force_n": machine.force_n if machine is not None else math.nan,
        "latency_ms": sample.latency_s * 1e3,
    }


class StrainCsvWriter:
    """A sink writing every sample as a CSV row.

    Args:
        path: file to create (its directory must exist).
        extra_columns: names of additional columns, after the standard ones.
        extras: returns the values of the extra columns for a sample.
    """

    def __init__(
        self,
        path: str | Path,
        extra_columns: Sequence[str] = (),
        extras: Callable[[StrainSample], Mapping[str, Any]] | None = None,
    ) -> None:
        self.path = Path(path)
        self._extras = extras
        self._file = self.path.open("w", newline="", encoding="utf-8")
        self._writer = csv.DictWriter(self._file, fieldnames=[*COLUMNS, *extra_columns])
        self._writer.writeheader()
        self._file.flush()

    def __call__(self, sample: StrainSample) -> None:
        row = sample_row(sample)
        if self._extras is not None:
            row.update(self._extras(sample))
        self._writer.writerow({k: _format(v) for k, v in row.items()})
        self._file.flush()

    def close(self) -> None:
        """Close the file; safe to call twice."""
        if not self._file.closed:
            self._file.close()


def _format(value: Any) -> Any:
    if isinstance(value, float):
        return "" if math.isnan(value) else repr(value)
    return value
