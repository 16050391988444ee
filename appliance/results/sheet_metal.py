"""A sheet metal's strain ratios and hardening: Poisson's ratio, r (ISO 10113), n (ISO 10275).

From the extensometer's axial engineering strain e, the transverse engineering strain e_w
(the specimen's width at its edges, `appliance.measure.edge_width`, or a transverse gauge)
and the stress R = F / S0. Only valid samples with a force, a strain and (for nu and r) a
transverse strain are used, on the rising branch (up to the largest stress). Each result
names the samples it was taken from, or says why it was not determined:

* **nu**, Poisson's ratio: minus the slope of the least-squares line of e_w against e over
  the samples the modulus E was fitted over (stress `MODULUS_FIT_RANGE`, 10 % to 50 %, of the
  proof strength: the elastic range). At least `MIN_FIT_SAMPLES` samples.
* **r**, plastic strain ratio (ISO 10113, the linear regression method): the true plastic
  width strain eps_b = ln(1 + e_w) + nu sigma / E and length strain eps_l = ln(1 + e) -
  sigma / E (sigma = R (1 + e) the true stress; nu and E as measured, nu = 0 when not
  determined; without E the elastic parts are neglected, which the basis says: about 0.2 % of
  strain beside 8 to 12 % for a steel), the thickness strain by constant volume
  eps_a = -(eps_b + eps_l); the slope m of eps_b against eps_l by least squares over the
  samples with e in `R_RANGE` (8 % to 12 %) gives r = eps_b / eps_a = -m / (1 + m) (reported
  as r_8-12). A test that did not reach the range's end before its maximum force, or with
  fewer than `MIN_FIT_SAMPLES` samples in it, gives no r.
* **n**, strain hardening exponent (ISO 10275): the slope of the least-squares line of
  ln(sigma) against ln(eps_p), eps_p = ln(1 + e) - sigma / E the true plastic strain, over the
  samples with e from `N_RANGE` (10 % to 20 %), the upper limit the strain at maximum force
  (Agt) when it comes first (ISO 10275's n_10-20, or n_10-Ag). At least `MIN_FIT_SAMPLES`.
  Without E the elastic part of eps_p is neglected, as for r.

References:
    ISO 10113:2020 Metallic materials - Sheet and strip - Determination of plastic strain
    ratio. ISO 10275:2020 Metallic materials - Sheet and strip - Determination of tensile
    strain hardening exponent.
"""

from __future__ import annotations

import numpy as np

from appliance.results.result import Result
from appliance.results.series import TestSeries

R_RANGE = (0.08, 0.12)
"""Engineering strain range of the r regression."""
N_RANGE = (0.10, 0.20)
"""Engineering strain range of the n regression (its end at most the strain at maximum
force)."""
MIN_FIT_SAMPLES = 5

_NAMES = {
    "nu": ("Poisson's ratio, elastic range", "1"),
    "r": ("plastic strain ratio, ISO 10113", "1"),
    "n": ("strain hardening exponent, ISO 10275", "1"),
}


def _missing(symbol: str, reason: str) -> Result:
    name, unit = _NAMES[symbol]
    return Result.not_determined(symbol, name, unit, reason)


def _result(symbol: str, value: float, samples: tuple[int, int], basis: str) -> Result:
    name, unit = _NAMES[symbol]
    return Result.determined(symbol, name, unit, value, samples, basis)


def sheet_missing(reason: str) -> list[Result]:
    """nu, r and n, none determined, for `reason`."""
    return [_missing(symbol, reason) for symbol in _NAMES]


def sheet_results(
    series: TestSeries, cross_section_mm2: float, modulus: Result, tensile_peak: int | None
) -> list[Result]:
    """nu, r and n of a metal test (see the module docstring).

    Args:
        series: the test's samples.
        cross_section_mm2: S0, mm^2.
        modulus: the test's E (GPa), with the samples it was fitted over.
        tensile_peak: the sample (`index`) of the largest stress; None = the last sample.
    """
    usable = series.valid & np.isfinite(series.force_n) & np.isfinite(series.strain)
    if tensile_peak is not None:
        usable &= series.index <= tensile_peak
    index = series.index[usable]
    strain = series.strain[usable]
    stress = series.force_n[usable] / cross_section_mm2
    transverse = series.transverse_strain[usable] if series.transverse_strain is not None else None
    source = series.transverse_source
    sigma = stress * (1.0 + strain)
    if not modulus.is_determined:
        reason = f"no modulus E: {modulus.reason}"
        elastic = f"; elastic strain neglected ({reason})"
        r = _strain_ratio(index, strain, transverse, sigma, np.inf, _missing("nu", reason), source)
        n = _hardening(index, strain, sigma, np.inf)
        return [_missing("nu", reason), _with_basis(r, elastic), _with_basis(n, elastic)]
    e_mpa = float(modulus.value) * 1e3
    nu = _poisson(index, strain, transverse, modulus, source)
    r = _strain_ratio(index, strain, transverse, sigma, e_mpa, nu, source)
    n = _hardening(index, strain, sigma, e_mpa)
    return [nu, r, n]


def _with_basis(result: Result, addition: str) -> Result:
    """`result` with `addition` appended to its basis (unchanged when not determined)."""
    if not result.is_determined:
        return result
    return _result(result.symbol, float(result.value), result.samples, result.basis + addition)


def _poisson(
    index: np.ndarray,
    strain: np.ndarray,
    transverse: np.ndarray | None,
    modulus: Result,
    source: str,
) -> Result:
    if transverse is None:
        return _missing(
            "nu", "no transverse strain ([transverse] stations = 0, no transverse gauge)"
        )
    first, last = modulus.samples or (0, -1)
    chosen = (index >= first) & (index <= last) & np.isfinite(transverse)
    if np.count_nonzero(chosen) < MIN_FIT_SAMPLES:
        return _missing(
            "nu",
            f"fewer than {MIN_FIT_SAMPLES} samples with a transverse strain in E's fit range "
            f"(samples {first} to {last})",
        )
    slope = np.polyfit(strain[chosen], transverse[chosen], 1)[0]
    picked = index[chosen]
    return _result(
        "nu",
        float(-slope),
        (int(picked[0]), int(picked[-1])),
        f"-slope of the transverse against the axial strain over E's fit range, samples "
        f"{int(picked[0])} to {int(picked[-1])} ({picked.size} samples; transverse strain "
        f"from {source})",
    )


def _strain_ratio(
    index: np.ndarray,
    strain: np.ndarray,
    transverse: np.ndarray | None,
    sigma: np.ndarray,
    e_mpa: float,
    nu: Result,
    source: str,
) -> Result:
    if transverse is None:
        return _missing(
            "r", "no transverse strain ([transverse] stations = 0, no transverse gauge)"
        )
    low, high = R_RANGE
    if strain.size == 0 or strain.max() < high:
        return _missing(
            "r",
            f"the strain did not reach {100 * high:g} % before the maximum force "
            f"(r over {100 * low:g} % to {100 * high:g} %)",
        )
    chosen = (strain >= low) & (strain <= high) & np.isfinite(transverse)
    if np.count_nonzero(chosen) < MIN_FIT_SAMPLES:
        return _missing(
            "r",
            f"fewer than {MIN_FIT_SAMPLES} samples with a transverse strain in {low:g} to {high:g}",
        )
    poisson = float(nu.value) if nu.is_determined else 0.0
    width = np.log1p(transverse[chosen]) + poisson * sigma[chosen] / e_mpa
    length = np.log1p(strain[chosen]) - sigma[chosen] / e_mpa
    slope = np.polyfit(length, width, 1)[0]
    picked = index[chosen]
    return _result(
        "r",
        float(-slope / (1.0 + slope)),
        (int(picked[0]), int(picked[-1])),
        f"r_{100 * low:g}-{100 * high:g}: regression of the plastic width strain on the plastic "
        f"length strain, samples {int(picked[0])} to {int(picked[-1])} ({picked.size} "
        f"samples; thickness strain by constant volume; width from {source})",
    )


def _hardening(index: np.ndarray, strain: np.ndarray, sigma: np.ndarray, e_mpa: float) -> Result:
    low, high = N_RANGE
    if strain.size == 0 or strain.max() < low:
        return _missing("n", f"the strain did not reach {100 * low:g} % before the maximum force")
    top = float(strain.max())
    end = min(high, top)
    plastic = np.log1p(strain) - sigma / e_mpa
    chosen = (strain >= low) & (strain <= end) & (plastic > 0) & (sigma > 0)
    if np.count_nonzero(chosen) < MIN_FIT_SAMPLES:
        return _missing(
            "n",
            f"fewer than {MIN_FIT_SAMPLES} samples between {100 * low:g} % and {100 * end:.3g} %",
        )
    slope = np.polyfit(np.log(plastic[chosen]), np.log(sigma[chosen]), 1)[0]
    picked = index[chosen]
    label = f"n_{100 * low:g}-{100 * end:.3g}"
    return _result(
        "n",
        float(slope),
        (int(picked[0]), int(picked[-1])),
        f"{label}: slope of ln true stress on ln true plastic strain, engineering strain "
        f"{100 * low:g} % to {100 * end:.3g} %, samples {int(picked[0])} to "
        f"{int(picked[-1])} ({picked.size} samples)",
    )
