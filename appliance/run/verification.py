"""ISO 9513 verification of the extensometer: bias, resolution and gauge length against a
calibrator, graded into the standard's classes.

A calibration lab moves one target relative to another with a precision calibrator in known
steps over the extensometer's range and compares the extensometer's reading l_i with the
calibrator's elongation l_t at every step (ISO 9513:2012, calibration procedure). The rules
this module applies, and where they come from:

* series: at least two series of measurements (ISO 9513); this product runs them in
  alternate directions, the first increasing from zero, the second decreasing from the top
  of the range (`calibration_steps`, `series_directions`), each starting from a reading zeroed
  at zero elongation;
* steps: at least 10 calibration points per series, spread over the range (ISO 9513). This
  product's plan puts 10 evenly spaced points at 10 %, 20 % ... 100 % of the range's upper
  limit and, when the range's lower limit is below 10 % of the upper, adds points at 1, 2
  and 5 times each power of ten from the lower limit up (the lower range, where the
  absolute limits decide; 300 um and below for class 0.5);
* bias at each point: absolute l_i - l_t (um) and relative q = (l_i - l_t) / l_t (%); a
  point at zero elongation has no relative bias and is graded on the absolute limit;
* resolution r: the larger of the display step of the reading and half the range of the
  readings taken at rest (a still calibrator; ISO 7500-1's rule for a fluctuating indicator,
  which ISO 9513 follows), graded at every calibration point against the larger of the
  class's relative limit (of the reading) and its absolute one; the standard deviation of the
  readings at rest is reported beside it;
* gauge length: the relative error (L_measured - L_nominal) / L_nominal of the mean measured
  gauge length;
* class: the worst of the three criteria's best classes (`appliance.run.iso9513` holds the
  limits). A criterion with nothing to grade it on (no readings at rest and no display step,
  no measured gauge length) is reported as not assessed, and the class stands on the others.
  A run that breaks the procedure (fewer than two series, a series with fewer than 10 points)
  reaches no class.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from appliance.run.iso9513 import CLASSES, ExtensometerClass

MIN_SERIES = 2
"""Series of measurements ISO 9513 asks for."""
MIN_POINTS_PER_SERIES = 10
"""Calibration points per series ISO 9513 asks for, spread over the range."""
CRITERIA = ("bias", "resolution", "gauge_length")
"""The three criteria of ISO 9513's table of classes, in the order they are reported."""


def calibration_steps(upper_um: float, lower_um: float | None = None) -> tuple[float, ...]:
    """The calibrator's elongations of one series, increasing, um (the module's rule).

    Args:
        upper_um: the range's upper limit, um (> 0).
        lower_um: the range's lower limit, um (0 < lower <= upper); None = 10 % of the upper.

    Returns:
        10 points at 10 % ... 100 % of `upper_um`, preceded (when `lower_um` is below 10 % of
        it) by the points 1, 2 and 5 x 10^k from `lower_um` up to below 10 % of the upper.
    """
    if not (math.isfinite(upper_um) and upper_um > 0):
        raise ValueError(f"upper_um must be finite and > 0, got {upper_um}")
    even = [upper_um * (i + 1) / MIN_POINTS_PER_SERIES for i in range(MIN_POINTS_PER_SERIES)]
    if lower_um is None or lower_um >= even[0]:
        if lower_um is not None and lower_um > upper_um:
            raise ValueError(f"lower_um ({lower_um}) exceeds upper_um ({upper_um})")
        return tuple(even)
    if not lower_um > 0:
        raise ValueError(f"lower_um must be > 0, got {lower_um}")
    low = [lower_um]
    exponent = math.floor(math.log10(lower_um))
    while True:
        for mantissa in (1.0, 2.0, 5.0):
            value = mantissa * 10.0**exponent
            if value >= even[0] * (1 - 1e-9):
                return tuple(low + even)
            if value > lower_um * (1 + 1e-9):
                low.append(value)
        exponent += 1


def series_directions(count: int) -> tuple[str, ...]:
    """Directions of `count` series: "increasing", "decreasing", "increasing", ..."""
    return tuple("increasing" if i % 2 == 0 else "decreasing" for i in range(count))


def series_elongations(steps_um: Sequence[float], direction: str) -> tuple[float, ...]:
    """The calibrator's elongations of one series in the order they are set, um."""
    ordered = sorted(steps_um)
    return tuple(ordered if direction == "increasing" else reversed(ordered))


@dataclass(frozen=True)
class CalibrationPoint:
    """One calibration point: the calibrator's elongation and the extensometer's reading.

    Attributes:
        series: the series' name ("1", "2", ...).
        calibrator_um: l_t, the calibrator's elongation, um.
        reading_um: l_i, the extensometer's reading, um (NaN: no reading).
        gauge_length_mm: the extensometer's gauge length measured at this point, mm; None =
            not measured.
    """

    series: str
    calibrator_um: float
    reading_um: float
    gauge_length_mm: float | None = None

    @property
    def bias_um(self) -> float:
        """l_i - l_t, um."""
        return self.reading_um - self.calibrator_um

    @property
    def relative_bias_percent(self) -> float | None:
        """100 (l_i - l_t) / l_t, %; None at zero elongation."""
        if self.calibrator_um == 0:
            return None
        return 100.0 * self.bias_um / self.calibrator_um

    def describe_bias(self) -> str:
        """The bias as one line: "+0.410 um (+0.410 %) at 100 um, series 1"."""
        relative = self.relative_bias_percent
        return (
            f"{self.bias_um:+.3f} um"
            + (f" ({relative:+.3f} %)" if relative is not None else "")
            + f" at {self.calibrator_um:g} um, series {self.series}"
        )


@dataclass(frozen=True)
class VerificationData:
    """What a verification grades.

    Attributes:
        points: every calibration point of every series, in the order measured.
        rest_readings_um: readings with the calibrator at rest (for the resolution), um.
        display_step_um: the reading's display step, um (0 = none: a continuous reading).
        nominal_gauge_length_mm: the nominal gauge length, mm; None = not known (the gauge
            length is then not assessed).
        directions: each series' direction ("increasing"/"decreasing"), by series name;
            series not named are told from their readings.
        source: where the readings come from, one line (for the report).
    """

    points: tuple[CalibrationPoint, ...]
    rest_readings_um: tuple[float, ...] = ()
    display_step_um: float = 0.0
    nominal_gauge_length_mm: float | None = None
    directions: dict[str, str] = field(default_factory=dict)
    source: str = ""

    def series_names(self) -> list[str]:
        """The series' names, in the order they first appear."""
        return list(dict.fromkeys(p.series for p in self.points))

    def direction_of(self, series: str) -> str:
        """A series' direction: as given, else from its calibrator elongations (first to last)."""
        if series in self.directions:
            return self.directions[series]
        values = [p.calibrator_um for p in self.points if p.series == series]
        return "decreasing" if len(values) > 1 and values[-1] < values[0] else "increasing"


@dataclass(frozen=True)
class Criterion:
    """One criterion's outcome.

    Attributes:
        name: "bias", "resolution" or "gauge_length".
        assessed: False when there was nothing to grade it on.
        best_class: the best class it meets; None when it meets none (or is not assessed).
        findings: for the requested class, every way it falls short, one line each.
    """

    name: str
    assessed: bool
    best_class: str | None
    findings: tuple[str, ...] = ()


@dataclass(frozen=True)
class Verification:
    """The graded verification (see the module docstring for the rules).

    Attributes:
        data: what was graded.
        requested: the class asked for.
        resolution_um: r, um (None: not assessed).
        rest_std_um: standard deviation of the readings at rest, um (None: fewer than 2).
        gauge_length_mm: mean measured gauge length, mm (None: not measured).
        gauge_length_error_percent: its relative error against the nominal, % (None: not
            assessed).
        criteria: the three criteria, by name.
        procedure_findings: how the run breaks the procedure's rules, one line each.
        achieved: the class the run reaches (None: none).
    """

    data: VerificationData
    requested: ExtensometerClass
    resolution_um: float | None
    rest_std_um: float | None
    gauge_length_mm: float | None
    gauge_length_error_percent: float | None
    criteria: dict[str, Criterion]
    procedure_findings: tuple[str, ...]
    achieved: str | None

    @property
    def met(self) -> bool:
        """The run reaches the requested class (or a better one)."""
        return self.achieved is not None and _rank(self.achieved) <= _rank(self.requested.name)

    @property
    def findings(self) -> tuple[str, ...]:
        """Why the requested class is not met, one line each (empty when it is)."""
        if self.met:
            return ()
        lines = list(self.procedure_findings)
        for criterion in self.criteria.values():
            lines += criterion.findings
        return tuple(lines)

    @property
    def worst_bias(self) -> CalibrationPoint | None:
        """The point whose |bias| is largest relative to the requested class's limit."""
        points = [p for p in self.data.points if math.isfinite(p.reading_um)]
        if not points:
            return None
        limits = self.requested.limit_um(np.array([p.calibrator_um for p in points]))
        ratios = [abs(p.bias_um) / limit for p, limit in zip(points, limits, strict=True)]
        return points[int(np.argmax(ratios))]

    def to_document(self) -> dict[str, Any]:
        """The verification as a JSON-ready mapping (non-finite numbers as None)."""
        requested = self.requested
        points = []
        for p in self.data.points:
            points.append(
                {
                    "series": p.series,
                    "direction": self.data.direction_of(p.series),
                    "calibrator_um": _finite(p.calibrator_um),
                    "reading_um": _finite(p.reading_um),
                    "bias_um": _finite(p.bias_um),
                    "relative_bias_percent": _finite(p.relative_bias_percent),
                    "bias_limit_um": float(requested.limit_um(np.array([p.calibrator_um]))[0]),
                    "resolution_limit_um": float(
                        requested.resolution_limit_um(np.array([p.reading_um]))[0]
                    )
                    if math.isfinite(p.reading_um)
                    else None,
                    "bias_class": _point_class(p),
                    "gauge_length_mm": _finite(p.gauge_length_mm),
                }
            )
        worst = self.worst_bias
        return {
            "standard": "ISO 9513:2012",
            "source": self.data.source,
            "requested_class": requested.name,
            "achieved_class": self.achieved,
            "met": self.met,
            "findings": list(self.findings),
            "procedure_findings": list(self.procedure_findings),
            "criteria": {
                name: {
                    "assessed": c.assessed,
                    "best_class": c.best_class,
                    "findings": list(c.findings),
                }
                for name, c in self.criteria.items()
            },
            "series": [
                {
                    "name": name,
                    "direction": self.data.direction_of(name),
                    "points": sum(p.series == name for p in self.data.points),
                }
                for name in self.data.series_names()
            ],
            "worst_bias": None
            if worst is None
            else {
                "series": worst.series,
                "calibrator_um": worst.calibrator_um,
                "bias_um": _finite(worst.bias_um),
                "relative_bias_percent": _finite(worst.relative_bias_percent),
            },
            "max_abs_bias_um": _finite(
                max((abs(p.bias_um) for p in self.data.points), default=math.nan)
            ),
            "resolution_um": _finite(self.resolution_um),
            "resolution_rule": "larger of the display step and half the range of the "
            "readings at rest",
            "display_step_um": self.data.display_step_um,
            "rest_readings_um": [_finite(v) for v in self.data.rest_readings_um],
            "rest_std_um": _finite(self.rest_std_um),
            "nominal_gauge_length_mm": _finite(self.data.nominal_gauge_length_mm),
            "gauge_length_mm": _finite(self.gauge_length_mm),
            "gauge_length_error_percent": _finite(self.gauge_length_error_percent),
            "class_limits": [
                {
                    "class": c.name,
                    "bias_percent": 100 * c.relative,
                    "bias_um": c.absolute_um,
                    "resolution_percent": 100 * c.resolution_relative,
                    "resolution_um": c.resolution_um,
                    "gauge_length_percent": 100 * c.gauge_length_relative,
                }
                for c in CLASSES
            ],
            "points": points,
        }


def verify(data: VerificationData, requested: ExtensometerClass) -> Verification:
    """Grade `data` against ISO 9513's classes and the requested class (module docstring)."""
    resolution, rest_std = _resolution(data)
    gauge_length, gauge_error = _gauge_length(data)
    criteria = {
        "bias": _bias_criterion(data.points, requested),
        "resolution": _resolution_criterion(data.points, resolution, requested),
        "gauge_length": _gauge_length_criterion(gauge_error, requested),
    }
    procedure = _procedure_findings(data)
    achieved = None
    assessed = [c for c in criteria.values() if c.assessed]
    if not procedure and all(c.best_class is not None for c in assessed):
        achieved = max((c.best_class for c in assessed), key=_rank)  # type: ignore[arg-type]
    return Verification(
        data=data,
        requested=requested,
        resolution_um=resolution,
        rest_std_um=rest_std,
        gauge_length_mm=gauge_length,
        gauge_length_error_percent=gauge_error,
        criteria=criteria,
        procedure_findings=procedure,
        achieved=achieved,
    )


def _rank(name: str) -> int:
    return [c.name for c in CLASSES].index(name)


def _finite(value: float | None) -> float | None:
    return float(value) if value is not None and math.isfinite(value) else None


def _point_class(point: CalibrationPoint) -> str | None:
    if not math.isfinite(point.reading_um):
        return None
    for c in CLASSES:
        if abs(point.bias_um) <= c.limit_um(np.array([point.calibrator_um]))[0]:
            return c.name
    return None


def _where(point: CalibrationPoint) -> str:
    return f"series {point.series} at {point.calibrator_um:g} um"


def _bias_criterion(points: Sequence[CalibrationPoint], requested: ExtensometerClass) -> Criterion:
    if not points:
        return Criterion("bias", False, None)
    classes = [_point_class(p) for p in points]
    best = None if None in classes else max(classes, key=_rank)  # type: ignore[arg-type]
    findings = []
    for p in points:
        limit = float(requested.limit_um(np.array([p.calibrator_um]))[0])
        if not math.isfinite(p.reading_um):
            findings.append(f"{_where(p)}: no reading")
        elif abs(p.bias_um) > limit:
            relative = p.relative_bias_percent
            told = f" ({relative:+.3f} %)" if relative is not None else ""
            findings.append(
                f"{_where(p)}: bias {p.bias_um:+.3f} um{told} beyond class {requested.name}'s "
                f"+-{limit:.3g} um"
            )
    return Criterion("bias", True, best, tuple(findings))


def _resolution(data: VerificationData) -> tuple[float | None, float | None]:
    rest = np.asarray(data.rest_readings_um, dtype=np.float64)
    std = float(np.std(rest, ddof=1)) if rest.size >= 2 else None
    if rest.size == 0 and data.display_step_um <= 0:
        return None, std
    if not np.all(np.isfinite(rest)):
        return math.nan, std
    half_range = 0.5 * float(np.ptp(rest)) if rest.size else 0.0
    return max(data.display_step_um, half_range), std


def _resolution_criterion(
    points: Sequence[CalibrationPoint], resolution: float | None, requested: ExtensometerClass
) -> Criterion:
    if resolution is None:
        return Criterion("resolution", False, None)
    readings = np.array([p.reading_um for p in points if math.isfinite(p.reading_um)])
    if readings.size == 0:
        readings = np.zeros(1)
    best = None
    for c in CLASSES:
        if math.isfinite(resolution) and np.all(resolution <= c.resolution_limit_um(readings)):
            best = c.name
            break
    findings = []
    limits = requested.resolution_limit_um(readings)
    if not math.isfinite(resolution):
        findings.append("resolution unknown: a reading at rest was not measured")
    elif not np.all(resolution <= limits):
        tightest = float(limits.min())
        findings.append(
            f"resolution {resolution:.3g} um beyond class {requested.name}'s {tightest:.3g} um "
            f"at the smallest reading ({float(np.abs(readings).min()):g} um)"
        )
    return Criterion("resolution", True, best, tuple(findings))


def _gauge_length(data: VerificationData) -> tuple[float | None, float | None]:
    measured = [p.gauge_length_mm for p in data.points if p.gauge_length_mm is not None]
    if not measured:
        return None, None
    mean = float(np.mean(measured))
    nominal = data.nominal_gauge_length_mm
    if nominal is None or not nominal > 0:
        return mean, None
    return mean, 100.0 * (mean - nominal) / nominal


def _gauge_length_criterion(error_percent: float | None, requested: ExtensometerClass) -> Criterion:
    if error_percent is None:
        return Criterion("gauge_length", False, None)
    relative = abs(error_percent) / 100.0
    best = next(
        (
            c.name
            for c in CLASSES
            if math.isfinite(relative) and relative <= c.gauge_length_relative
        ),
        None,
    )
    findings = []
    if not relative <= requested.gauge_length_relative:
        findings.append(
            f"gauge length error {error_percent:+.3f} % beyond class {requested.name}'s "
            f"+-{100 * requested.gauge_length_relative:g} %"
        )
    return Criterion("gauge_length", True, best, tuple(findings))


def _procedure_findings(data: VerificationData) -> tuple[str, ...]:
    names = data.series_names()
    findings = []
    if len(names) < MIN_SERIES:
        findings.append(
            f"{len(names)} series of measurements: ISO 9513 asks for at least {MIN_SERIES}"
        )
    for name in names:
        count = sum(p.series == name and p.calibrator_um != 0 for p in data.points)
        if count < MIN_POINTS_PER_SERIES:
            findings.append(
                f"series {name}: {count} calibration points: ISO 9513 asks for at least "
                f"{MIN_POINTS_PER_SERIES} over the range"
            )
    return tuple(findings)
