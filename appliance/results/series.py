"""The series of one test that its results and report are taken from, and its cross-section.

`TestSeries` holds, per measured sample: its index, time, engineering strain, the machine's
force, the data-valid flag, the points lost in the frame, the camera frames dropped so far,
and (a simulated test only, for scoring) the true strain. `SeriesRecorder` builds it from the
samples of a run or a replay. `cross_section_mm2` is the original cross-section S0 of a
`[specimen]` table.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from appliance.config import SpecimenConfig
from appliance.measure.frame_measurer import StrainSample


@dataclass(frozen=True)
class TestSeries:
    """Per-sample arrays of one test, all of one length.

    Attributes:
        index: sample numbers (`StrainSample.index`).
        time_s: seconds since the reference frame.
        strain: axial engineering strain.
        force_n: the machine's force, N (NaN where it gave none).
        valid: the data-valid flag.
        points_lost: points not measured in the frame.
        frames_dropped: camera frames dropped so far in the test.
        truth_strain: the true engineering strain of a simulated test (scoring only; NaN
            where unknown).
        transverse_strain: the transverse engineering strain: from the specimen's width at
            its edges when measured (`[transverse] stations`), else the transverse gauge's;
            None when the test measured neither.
        transverse_source: where `transverse_strain` comes from, for the results' bases.
    """

    index: np.ndarray
    time_s: np.ndarray
    strain: np.ndarray
    force_n: np.ndarray
    valid: np.ndarray
    points_lost: np.ndarray
    frames_dropped: np.ndarray
    truth_strain: np.ndarray
    transverse_strain: np.ndarray | None = None
    transverse_source: str = ""

    @classmethod
    def of(
        cls,
        strain: np.ndarray,
        force_n: np.ndarray,
        *,
        time_s: np.ndarray | None = None,
        valid: np.ndarray | None = None,
        transverse_strain: np.ndarray | None = None,
    ) -> TestSeries:
        """A series of strain and force alone (every sample valid, no loss, no truth), with
        a transverse strain when given."""
        strain = np.asarray(strain, np.float64)
        n = strain.size
        return cls(
            index=np.arange(n),
            time_s=np.arange(n, dtype=np.float64) if time_s is None else np.asarray(time_s),
            strain=strain,
            force_n=np.asarray(force_n, np.float64),
            valid=np.ones(n, bool) if valid is None else np.asarray(valid, bool),
            points_lost=np.zeros(n, np.int64),
            frames_dropped=np.zeros(n, np.int64),
            truth_strain=np.full(n, math.nan),
            transverse_strain=(
                None if transverse_strain is None else np.asarray(transverse_strain, np.float64)
            ),
            transverse_source="" if transverse_strain is None else "given",
        )

    def __len__(self) -> int:
        return int(self.strain.size)

    @property
    def has_force(self) -> bool:
        """Whether any valid sample has a force reading."""
        return bool(np.any(self.valid & np.isfinite(self.force_n)))

    @property
    def has_truth(self) -> bool:
        """Whether the series carries a true strain to score against."""
        return bool(np.any(np.isfinite(self.truth_strain)))


class SeriesRecorder:
    """Collects the series of a run or a replay, sample by sample.

    Args:
        truth: (true strain, true elongation mm) of the sample just measured, for a simulated
            test (the runner's truth, which only scores); None otherwise.
    """

    def __init__(self, truth: Callable[[StrainSample], tuple[float, float]] | None = None) -> None:
        self._truth = truth
        self._rows: list[tuple[float, ...]] = []
        self._transverse: list[float] = []
        self._sources: set[str] = set()

    def add(self, sample: StrainSample) -> None:
        """Record one sample."""
        machine = sample.machine
        true_strain = self._truth(sample)[0] if self._truth is not None else math.nan
        if sample.width is not None:
            self._sources.add("the specimen's width at its edges")
            self._transverse.append(sample.width.transverse_strain)
        else:
            if math.isfinite(sample.reading.transverse_strain):
                self._sources.add("the transverse gauge")
            self._transverse.append(sample.reading.transverse_strain)
        self._rows.append(
            (
                sample.index,
                sample.time_s,
                sample.reading.engineering_strain,
                machine.force_n if machine is not None else math.nan,
                sample.data_valid,
                sample.points_lost,
                sample.frames_dropped,
                true_strain,
            )
        )

    def series(self) -> TestSeries:
        """The series recorded so far."""
        columns = np.array(self._rows, dtype=np.float64).reshape(-1, 8).T
        return TestSeries(
            index=columns[0].astype(np.int64),
            time_s=columns[1],
            strain=columns[2],
            force_n=columns[3],
            valid=columns[4].astype(bool),
            points_lost=columns[5].astype(np.int64),
            frames_dropped=columns[6].astype(np.int64),
            truth_strain=columns[7],
            transverse_strain=np.array(self._transverse, np.float64) if self._sources else None,
            transverse_source=" and ".join(sorted(self._sources)),
        )


def cross_section_mm2(specimen: SpecimenConfig) -> float | None:
    """S0 of the configured specimen, mm^2: width x thickness, or pi d^2 / 4; None when the
    table gives neither."""
    if specimen.diameter_mm is not None:
        return math.pi * specimen.diameter_mm**2 / 4.0
    if specimen.width_mm is not None and specimen.thickness_mm is not None:
        return specimen.width_mm * specimen.thickness_mm
    return None


def why_no_stress(series: TestSeries, cross_section_mm2: float | None) -> str | None:
    """Why the series gives no stress (no S0, no valid sample, no force), or None."""
    if cross_section_mm2 is None:
        return (
            "no cross-section: [specimen] width_mm and thickness_mm (or diameter_mm) "
            "are not configured"
        )
    if not np.any(series.valid):
        return "no valid sample"
    if not series.has_force:
        return "no force readings from the machine"
    return None
