"""ISO 6892-1 results of a metal's tensile test from extensometer strain and machine force.

Stress is the force over the original cross-section S0, R = F / S0, MPa; e is the
extensometer's engineering strain. Only valid samples with a force reading are used (a frame
of the broken specimen is not valid). Each result names the samples it was taken from:

* **Rm**, tensile strength: the largest stress. Determined once the force has fallen
  `RM_DROP_FRACTION` (0.5 %) below its maximum afterwards, or the specimen broke; a test
  that ends while the force still rises has not shown its maximum.
* **ReH, ReL**, upper and lower yield strength (discontinuous yielding only): ReH is the
  stress before the first fall of force by `YIELD_DROP_FRACTION` (1 %) before Rm, from a
  stress of at least `YIELD_MIN_FRACTION` (20 %) of Rm (noise at the start is no yield), at
  the end of the elastic range: its plastic extension from the first elastic line (10 % to
  40 % of the largest stress) below `YIELD_MAX_PLASTIC` (1 %). A later first fall is a
  serration of work hardening (the Portevin-Le Chatelier effect), not a yield point; ReL the
  lowest stress of the yield phase that follows (up to where the stress rises past ReH again,
  or Rm), leaving out the initial transient (the first local minimum, when there are
  several). Without such a fall the material yields continuously, and both are reported as
  not determined, saying so.
* **E**, the modulus: least-squares line R = E e + R0 through the loading samples whose stress
  lies between `MODULUS_FIT_RANGE` (10 % and 50 %) of the yield strength (ReH with
  discontinuous yielding, else Rp0.2), the first estimate taken between 10 % and 40 % of the
  largest stress and refined with the Rp0.2 it gives until the range stops changing. At least
  `MIN_FIT_SAMPLES` (5) samples; the basis gives the fit range, the samples and the slope's
  standard error.
  The 10 % to 50 % range is this product's choice, not a clause of ISO 6892-1.
* **Rp0.2**, proof strength: the stress where the plastic extension e - (R - R0) / E first
  reaches 0.2 % (the line parallel to the elastic line, ISO 6892-1 13.1), linearly
  interpolated between the two samples around it.
* **Ag**, plastic extension at maximum force (ISO 6892-1 3.6.3): the plastic extension
  e - (R - R0) / E at Agt and Rm. The force's noise moves the single largest sample along the
  flat top of the curve, so Agt is where a cubic least-squares fit of stress against strain
  peaks (a cubic, as the top of a curve is not symmetric about its maximum), fitted to the
  samples from the first to the last whose stress lies within `AGT_BAND_NOISE` (10) times the
  stress's noise of the largest, at most `AGT_BAND_FRACTION` (0.5 %) of it; the noise is
  the robust spread of the second differences of the stress around the top. A noiseless
  curve thus keeps Agt at its largest sample, where a sharp maximum (necking setting in)
  lies. With fewer than `MIN_FIT_SAMPLES` samples in the band, or a fit that does not peak
  among them, Agt is the strain of the sample of largest stress; the basis says which. The
  fit is this product's way of finding where a noisy top lies.
* **A**, percentage elongation after fracture, from the extensometer (ISO 6892-1 20.2): the
  plastic extension e - (R - R0) / E of the last valid sample before the fracture (its
  elastic part is the extension the specimen gives back when the force falls). Determined
  only when the test ran to the break; it is the standard's A only when the fracture lies
  between the gauge marks.

After these, a sheet's Poisson's ratio nu, plastic strain ratio r (ISO 10113) and strain
hardening exponent n (ISO 10275): `appliance.results.sheet_metal`.

Ag, A and Rp0.2 all take the strain from the elastic line's zero (R0 its stress at e = 0), so
a strain offset at the start of the test (slack taken up, a toe) does not move them.

References:
    ISO 6892-1:2019 Metallic materials - Tensile testing - Part 1: Method of test at room
    temperature.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from appliance.results.result import Result, TestResults
from appliance.results.series import TestSeries, why_no_stress
from appliance.results.sheet_metal import sheet_missing, sheet_results

RM_DROP_FRACTION = 0.005
YIELD_DROP_FRACTION = 0.01
YIELD_MIN_FRACTION = 0.2
YIELD_MAX_PLASTIC = 0.01
AGT_BAND_FRACTION = 0.005
AGT_BAND_NOISE = 10.0
MODULUS_FIT_RANGE = (0.10, 0.50)
FIRST_FIT_RANGE = (0.10, 0.40)
MIN_FIT_SAMPLES = 5
MAX_REFINEMENTS = 5
PROOF_EXTENSION = 0.002
STANDARD = "ISO 6892-1"
MAIN = ("E", "Rp0.2", "Rm", "Ag", "A")

_NAMES = {
    "E": ("modulus of elasticity", "GPa"),
    "Rp0.2": ("proof strength, plastic extension 0.2 %", "MPa"),
    "ReH": ("upper yield strength", "MPa"),
    "ReL": ("lower yield strength", "MPa"),
    "Rm": ("tensile strength", "MPa"),
    "Ag": ("plastic extension at maximum force", "%"),
    "A": ("percentage elongation after fracture (extensometer)", "%"),
}
_ORDER = ("E", "Rp0.2", "ReH", "ReL", "Rm", "Ag", "A")


def _result(
    symbol: str, value: float, samples: tuple[int, int], basis: str, at_sample: int | None = None
) -> Result:
    name, unit = _NAMES[symbol]
    return Result.determined(symbol, name, unit, value, samples, basis, at_sample=at_sample)


def _missing(symbol: str, reason: str) -> Result:
    name, unit = _NAMES[symbol]
    return Result.not_determined(symbol, name, unit, reason)


def metal_results(
    series: TestSeries, cross_section_mm2: float | None, *, broke: bool
) -> TestResults:
    """The ISO 6892-1 results of a test; see the module docstring.

    Args:
        series: the test's samples.
        cross_section_mm2: S0, mm^2; None: every result is not determined, naming `[specimen]`.
        broke: the test ended at the specimen's fracture (A needs it; Rm is then shown).
    """
    reason = why_no_stress(series, cross_section_mm2)
    if reason is not None:
        missing = [_missing(s, reason) for s in _ORDER]
        return TestResults(STANDARD, cross_section_mm2, [*missing, *sheet_missing(reason)], MAIN)
    assert cross_section_mm2 is not None
    usable = series.valid & np.isfinite(series.force_n) & np.isfinite(series.strain)
    curve = _Curve(
        series.index[usable], series.strain[usable], series.force_n[usable] / cross_section_mm2
    )
    found = {"Rm": curve.tensile_strength(broke)}
    found.update(curve.yield_point())
    found.update(curve.modulus_and_proof(found.get("ReH")))
    found["Ag"] = curve.plastic_extension_at_maximum(found["Rm"], found["E"])
    found["A"] = curve.elongation_after_fracture(found["E"], broke)
    sheet = sheet_results(series, cross_section_mm2, found["E"], int(curve.index[curve.peak]))
    return TestResults(STANDARD, cross_section_mm2, [*(found[s] for s in _ORDER), *sheet], MAIN)


class _Curve:
    """The usable samples' stress-strain curve."""

    def __init__(self, index: np.ndarray, strain: np.ndarray, stress_mpa: np.ndarray) -> None:
        self.index = index
        self.strain = strain
        self.stress = stress_mpa
        self.peak = int(np.argmax(stress_mpa))
        self.line: _Line | None = None

    def tensile_strength(self, broke: bool) -> Result:
        stress, peak = self.stress, self.peak
        later = stress[peak + 1 :]
        fell = later.size > 0 and later.min() < stress[peak] * (1.0 - RM_DROP_FRACTION)
        sample = int(self.index[peak])
        if not (fell or broke):
            return _missing(
                "Rm",
                f"the force had not fallen {100 * RM_DROP_FRACTION:g} % below its largest "
                f"value (sample {sample}) when the test ended: its maximum was not reached",
            )
        return _result("Rm", stress[peak], (sample, sample), f"largest stress, sample {sample}")

    def yield_point(self) -> dict[str, Result]:
        """ReH and ReL, or both not determined (continuous yielding)."""
        stress = self.stress[: self.peak + 1]
        running = np.maximum.accumulate(stress)
        loaded = running >= YIELD_MIN_FRACTION * stress.max()
        falls = np.flatnonzero(loaded & (stress < running * (1.0 - YIELD_DROP_FRACTION)))
        if falls.size == 0:
            reason = (
                f"continuous yielding: the force did not fall {100 * YIELD_DROP_FRACTION:g} % "
                "before its maximum"
            )
            return {"ReH": _missing("ReH", reason), "ReL": _missing("ReL", reason)}
        fall = int(falls[0])
        upper = int(np.argmax(stress[:fall]))
        late = self._late_first_fall(upper)
        if late is not None:
            return {"ReH": _missing("ReH", late), "ReL": _missing("ReL", late)}
        above = np.flatnonzero(stress[fall:] > stress[upper])
        end = fall + int(above[0]) if above.size else self.peak
        phase = stress[upper:end]
        minima = [
            k
            for k in range(1, phase.size - 1)
            if phase[k] <= phase[k - 1] and phase[k] <= phase[k + 1]
        ]
        candidates = minima[1:] if len(minima) > 1 else minima or [int(np.argmin(phase))]
        lowest = upper + min(candidates, key=lambda k: phase[k])
        first, last = int(self.index[upper]), int(self.index[end - 1])
        transient = " leaving out the initial transient" if len(minima) > 1 else ""
        return {
            "ReH": _result(
                "ReH",
                stress[upper],
                (first, first),
                f"stress before the first fall of force, sample {first}",
            ),
            "ReL": _result(
                "ReL",
                stress[lowest],
                (first, last),
                f"lowest stress of the yield phase, samples {first} to {last}{transient}: "
                f"sample {int(self.index[lowest])}",
                at_sample=int(self.index[lowest]),
            ),
        }

    def _late_first_fall(self, upper: int) -> str | None:
        """Why the first fall of force, after sample position `upper`, is no yield point (it
        came past `YIELD_MAX_PLASTIC` of plastic extension), or None."""
        reference_mpa = float(self.stress[: self.peak + 1].max())
        fit = self._fit((FIRST_FIT_RANGE[0] * reference_mpa, FIRST_FIT_RANGE[1] * reference_mpa))
        if isinstance(fit, str):
            return None
        plastic = float(self._plastic(fit)[upper])
        if plastic < YIELD_MAX_PLASTIC:
            return None
        return (
            f"continuous yielding: the first fall of force by {100 * YIELD_DROP_FRACTION:g} % "
            f"(after sample {int(self.index[upper])}) came at a plastic extension of "
            f"{100 * plastic:.3g} %, past the end of the elastic range "
            f"({100 * YIELD_MAX_PLASTIC:g} %): a serration of work hardening, no yield point"
        )

    def modulus_and_proof(self, upper_yield: Result | None) -> dict[str, Result]:
        """E and Rp0.2, each refining the other's fit range."""
        fractions, reference = FIRST_FIT_RANGE, "the largest stress"
        reference_mpa = float(self.stress[: self.peak + 1].max())
        for _ in range(MAX_REFINEMENTS):
            fit = self._fit((fractions[0] * reference_mpa, fractions[1] * reference_mpa))
            if isinstance(fit, str):
                return {"E": _missing("E", fit), "Rp0.2": _missing("Rp0.2", f"E: {fit}")}
            proof = self._proof(fit)
            used = (fractions, reference)
            if upper_yield is not None and upper_yield.value is not None:
                refined = ("ReH", upper_yield.value)
            elif proof.value is not None:
                refined = ("Rp0.2", proof.value)
            else:
                break
            if refined[0] == reference and math.isclose(refined[1], reference_mpa, rel_tol=1e-6):
                break
            fractions, (reference, reference_mpa) = MODULUS_FIT_RANGE, refined
        (low, high), name = used
        self.line = fit
        fit_basis = (
            f"least-squares line through samples {fit.first} to {fit.last} ({fit.count} "
            f"samples) with stress from {fit.low_mpa:.4g} to {fit.high_mpa:.4g} MPa "
            f"({100 * low:g} % to {100 * high:g} % of {name}); "
            f"slope standard error {100 * fit.relative_error:.2g} %"
        )
        return {
            "E": _result("E", fit.slope_mpa / 1e3, (fit.first, fit.last), fit_basis),
            "Rp0.2": proof,
        }

    def _fit(self, bounds: tuple[float, float]) -> _Line | str:
        low, high = bounds
        beyond = np.flatnonzero(self.stress > high)
        end = int(beyond[0]) if beyond.size else self.stress.size
        chosen = np.flatnonzero(self.stress[:end] >= low)
        if chosen.size < MIN_FIT_SAMPLES:
            return (
                f"{chosen.size} loading samples with stress from {low:.4g} to {high:.4g} MPa, "
                f"fewer than {MIN_FIT_SAMPLES}"
            )
        e, r = self.strain[chosen], self.stress[chosen]
        design = np.column_stack([e, np.ones_like(e)])
        (slope, intercept), residuals, *_ = np.linalg.lstsq(design, r, rcond=None)
        dof = max(chosen.size - 2, 1)
        spread = float(np.sum((e - e.mean()) ** 2))
        rss = float(residuals[0]) if residuals.size else 0.0
        error = math.sqrt(rss / dof / spread) if spread > 0 else math.inf
        if not slope > 0:
            return f"the stress does not rise with strain from {low:.4g} to {high:.4g} MPa"
        return _Line(
            float(slope),
            float(intercept),
            int(self.index[chosen[0]]),
            int(self.index[chosen[-1]]),
            int(chosen.size),
            low,
            high,
            error / float(slope),
        )

    def _plastic(self, line: _Line) -> np.ndarray:
        return self.strain - (self.stress - line.intercept_mpa) / line.slope_mpa

    def _proof(self, line: _Line) -> Result:
        plastic = self._plastic(line)
        reached = np.flatnonzero(plastic >= PROOF_EXTENSION)
        if reached.size == 0:
            return _missing(
                "Rp0.2",
                f"the test ended at a plastic extension of {100 * plastic.max():.3g} %, "
                f"before {100 * PROOF_EXTENSION:g} %",
            )
        j = int(reached[0])
        if j == 0:
            return _missing("Rp0.2", "the first sample is already past 0.2 % plastic extension")
        weight = (PROOF_EXTENSION - plastic[j - 1]) / (plastic[j] - plastic[j - 1])
        value = self.stress[j - 1] + weight * (self.stress[j] - self.stress[j - 1])
        first, last = int(self.index[j - 1]), int(self.index[j])
        return _result(
            "Rp0.2",
            value,
            (first, last),
            f"0.2 % plastic extension from the modulus line, interpolated between samples "
            f"{first} and {last}",
        )

    def plastic_extension_at_maximum(self, tensile: Result, modulus: Result) -> Result:
        if tensile.value is None:
            return _missing("Ag", f"Rm: {tensile.reason}")
        if modulus.value is None or self.line is None:
            return _missing("Ag", f"E: {modulus.reason}")
        total, at, how = self._strain_at_maximum()
        value = 100.0 * (total - (tensile.value - self.line.intercept_mpa) / self.line.slope_mpa)
        return _result(
            "Ag",
            value,
            (int(self.index[at[0]]), int(self.index[at[1]])),
            f"Agt {100 * total:.4g} %, {how}; less (Rm - R0) / E",
            at_sample=int(self.index[at[2]]),
        )

    def _strain_at_maximum(self) -> tuple[float, tuple[int, int, int], str]:
        """Agt, the positions (first, last, nearest) of the samples it was taken from, and
        how it was taken."""
        stress, strain = self.stress, self.strain
        top = float(stress[self.peak])
        region = stress[stress >= top * (1.0 - AGT_BAND_FRACTION)]
        noise_mpa = _noise_mpa(stress[self.peak - region.size : self.peak + region.size + 1])
        band_mpa = min(AGT_BAND_NOISE * noise_mpa, AGT_BAND_FRACTION * top)
        near = np.flatnonzero(stress >= top - band_mpa)
        first, last = int(near[0]), int(near[-1])
        band = f"{band_mpa:.3g} MPa of the largest, {AGT_BAND_NOISE:g} times its noise"
        if last - first + 1 >= MIN_FIT_SAMPLES:
            e = strain[first : last + 1]
            centre = float(e.mean())
            cubic = np.polynomial.Polynomial.fit(e - centre, stress[first : last + 1], 3)
            slope, bend = cubic.deriv(1), cubic.deriv(2)
            tops = [
                float(root.real) + centre
                for root in slope.roots()
                if abs(root.imag) < 1e-12 and bend(root.real) < 0
            ]
            inside = [agt for agt in tops if e.min() <= agt <= e.max()]
            if inside:
                agt = inside[0]
                nearest = first + int(np.argmin(np.abs(e - agt)))
                return (
                    agt,
                    (first, last, nearest),
                    f"the peak of a cubic least-squares fit of stress against strain through "
                    f"samples {int(self.index[first])} to {int(self.index[last])} "
                    f"(stress within {band})",
                )
        peak = self.peak
        return (
            float(strain[peak]),
            (peak, peak, peak),
            f"the strain of the sample of largest stress ({int(self.index[peak])}; no "
            f"cubic fit peaks among the {last - first + 1} samples with stress within "
            f"{band})",
        )

    def elongation_after_fracture(self, modulus: Result, broke: bool) -> Result:
        if not broke:
            return _missing("A", "the test ended before the fracture")
        if modulus.value is None or self.line is None:
            return _missing("A", f"E: {modulus.reason}")
        last = self.stress.size - 1
        value = 100.0 * float(self._plastic(self.line)[last])
        sample = int(self.index[last])
        return _result(
            "A",
            value,
            (sample, sample),
            f"plastic extension e - (R - R0) / E of the last valid sample before the fracture "
            f"({sample}); the standard's A when the fracture lies between the gauge marks",
        )


def _noise_mpa(stress_mpa: np.ndarray) -> float:
    """The stress's noise, MPa: the robust spread of its second differences (each holds the
    noise of three samples, sqrt(6) times one's), 0 with fewer than three samples."""
    if stress_mpa.size < 3:
        return 0.0
    second = np.diff(stress_mpa, 2)
    return float(np.median(np.abs(second - np.median(second)))) / 0.6745 / math.sqrt(6.0)


@dataclass(frozen=True)
class _Line:
    """The elastic line R = slope e + intercept and the samples it was fitted to."""

    slope_mpa: float
    intercept_mpa: float
    first: int
    last: int
    count: int
    low_mpa: float
    high_mpa: float
    relative_error: float
