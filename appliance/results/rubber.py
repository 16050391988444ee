"""ISO 37 results of a rubber's tensile test from extensometer strain and machine force.

Stress is the force over the original cross-section of the narrow portion, S = F / (W t),
MPa; the elongation is the extensometer's engineering strain in %. Only valid samples with a
force reading are used (a frame of the broken specimen is not valid).

* **S100, S200, S300**, stress at 100, 200 and 300 % elongation: linearly interpolated between
  the two samples around the elongation (the first time it is reached). Not determined when
  the test ended (or broke) before it.
* **TS**, tensile strength: the largest stress recorded up to the break.
* **Eb**, elongation at break: the strain of the last valid sample before the break; it may
  read low by up to one frame's strain step.

TS and Eb need a test that ran to the break; otherwise they are reported as not determined.

References:
    ISO 37:2017 Rubber, vulcanized or thermoplastic - Determination of tensile stress-strain
    properties.
"""

from __future__ import annotations

import numpy as np

from appliance.results.result import Result, TestResults
from appliance.results.series import TestSeries, why_no_stress

STANDARD = "ISO 37"
STRESS_AT_ELONGATION_PERCENT = (100, 200, 300)
MAIN = ("TS", "Eb", "S100", "S300")


def rubber_results(
    series: TestSeries, cross_section_mm2: float | None, *, broke: bool
) -> TestResults:
    """The ISO 37 results of a test; see the module docstring.

    Args:
        series: the test's samples.
        cross_section_mm2: W t of the narrow portion, mm^2; None: the stresses are not
            determined, naming `[specimen]`.
        broke: the test ended at the break (TS and Eb need it).
    """
    usable = series.valid & np.isfinite(series.strain)
    index, strain = series.index[usable], series.strain[usable]
    stress = series.force_n[usable] / (cross_section_mm2 or np.nan)
    reason = why_no_stress(series, cross_section_mm2)
    results = [
        _stress_at(index, strain, stress, percent, reason)
        for percent in STRESS_AT_ELONGATION_PERCENT
    ]
    results.insert(0, _elongation_at_break(index, strain, broke))
    results.insert(0, _tensile_strength(index, stress, broke, reason))
    return TestResults(STANDARD, cross_section_mm2, results, MAIN)


def _tensile_strength(
    index: np.ndarray, stress: np.ndarray, broke: bool, reason: str | None
) -> Result:
    name = "tensile strength"
    if reason is not None:
        return Result.not_determined("TS", name, "MPa", reason)
    if not broke:
        return Result.not_determined("TS", name, "MPa", "the test ended before the break")
    finite = np.isfinite(stress)
    peak = int(np.flatnonzero(finite)[np.argmax(stress[finite])])
    sample = int(index[peak])
    return Result.determined(
        "TS", name, "MPa", stress[peak], (sample, sample), f"largest stress, sample {sample}"
    )


def _elongation_at_break(index: np.ndarray, strain: np.ndarray, broke: bool) -> Result:
    name = "elongation at break"
    if not broke:
        return Result.not_determined("Eb", name, "%", "the test ended before the break")
    if strain.size == 0:
        return Result.not_determined("Eb", name, "%", "no valid sample")
    sample = int(index[-1])
    return Result.determined(
        "Eb",
        name,
        "%",
        100.0 * strain[-1],
        (sample, sample),
        f"strain of the last valid sample before the break ({sample})",
    )


def _stress_at(
    index: np.ndarray, strain: np.ndarray, stress: np.ndarray, percent: int, reason: str | None
) -> Result:
    symbol, name = f"S{percent}", f"stress at {percent} % elongation"
    if reason is not None:
        return Result.not_determined(symbol, name, "MPa", reason)
    target = percent / 100.0
    reached = np.flatnonzero(strain >= target)
    if reached.size == 0 or reached[0] == 0:
        ended = 100.0 * strain.max() if strain.size else 0.0
        why = (
            f"the test ended at {ended:.4g} % elongation"
            if reached.size == 0
            else "the first valid sample is already past it"
        )
        return Result.not_determined(symbol, name, "MPa", why)
    j = int(reached[0])
    if not (np.isfinite(stress[j - 1]) and np.isfinite(stress[j])):
        return Result.not_determined(
            symbol, name, "MPa", f"no force reading at samples {index[j - 1]} and {index[j]}"
        )
    weight = (target - strain[j - 1]) / (strain[j] - strain[j - 1])
    value = stress[j - 1] + weight * (stress[j] - stress[j - 1])
    first, last = int(index[j - 1]), int(index[j])
    return Result.determined(
        symbol,
        name,
        "MPa",
        value,
        (first, last),
        f"interpolated between samples {first} and {last}",
    )
