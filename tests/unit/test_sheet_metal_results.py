"""Poisson's ratio, r (ISO 10113) and n (ISO 10275) from synthetic curves of known values."""

from __future__ import annotations

import math

import numpy as np
import pytest

from appliance.results.metals import metal_results
from appliance.results.series import TestSeries

E_MPA = 200_000.0
AREA_MM2 = 25.0


def _sheet(nu: float, r: float, n: float, *, end_strain: float = 0.25, noise: float = 0.0):
    """A Hollomon sheet (sigma = K eps_p^n above yield, elastic below) pulled to `end_strain`:
    engineering strain, force and the width's engineering strain."""
    k_mpa, yield_mpa = 550.0, 200.0
    true_stress = np.concatenate(
        [np.linspace(0.0, yield_mpa, 200)[1:], k_mpa * np.linspace(0.002, 0.3, 3000) ** n]
    )
    plastic = np.where(true_stress <= yield_mpa, 0.0, (true_stress / k_mpa) ** (1.0 / n))
    plastic = np.maximum.accumulate(plastic)
    true_axial = true_stress / E_MPA + plastic
    strain = np.expm1(true_axial)
    width = np.expm1(-nu * true_stress / E_MPA - r / (1.0 + r) * plastic)
    thickness = np.expm1(-nu * true_stress / E_MPA - 1.0 / (1.0 + r) * plastic)
    force = true_stress * (1.0 + width) * (1.0 + thickness) * AREA_MM2
    keep = strain <= end_strain
    rng = np.random.default_rng(3)
    width = width + noise * rng.standard_normal(width.size)
    return strain[keep], force[keep], width[keep]


@pytest.mark.parametrize(("nu", "r", "n"), [(0.3, 1.8, 0.22), (0.33, 0.7, 0.15), (0.28, 1.0, 0.3)])
def test_nu_r_and_n_of_a_synthetic_sheet_are_found(nu, r, n):
    strain, force, width = _sheet(nu, r, n)
    series = TestSeries.of(strain, force, transverse_strain=width)
    results = metal_results(series, AREA_MM2, broke=False)
    assert results["nu"].value == pytest.approx(nu, abs=0.002)
    assert results["r"].value == pytest.approx(r, abs=0.01)
    assert results["n"].value == pytest.approx(n, abs=0.005)
    assert "r_8-12" in results["r"].basis
    first, last = results["r"].samples
    assert 0.08 <= strain[first] and strain[last] <= 0.12
    assert "n_10-" in results["n"].basis


def test_r_holds_with_the_width_noise_of_an_edge_measurement():
    strain, force, width = _sheet(0.3, 1.8, 0.2, noise=2e-5)
    results = metal_results(
        TestSeries.of(strain, force, transverse_strain=width), AREA_MM2, broke=False
    )
    assert results["r"].value == pytest.approx(1.8, abs=0.05)


def test_without_a_transverse_strain_nu_and_r_say_why_and_n_is_still_found():
    strain, force, _ = _sheet(0.3, 1.8, 0.2)
    results = metal_results(TestSeries.of(strain, force), AREA_MM2, broke=False)
    assert not results["nu"].is_determined and "transverse" in results["nu"].reason
    assert not results["r"].is_determined and "transverse" in results["r"].reason
    assert results["n"].value == pytest.approx(0.2, abs=0.005)


def test_a_test_that_stops_short_of_the_range_gives_no_r_nor_n():
    strain, force, width = _sheet(0.3, 1.8, 0.2, end_strain=0.05)
    results = metal_results(
        TestSeries.of(strain, force, transverse_strain=width), AREA_MM2, broke=False
    )
    assert results["nu"].is_determined
    assert not results["r"].is_determined and "12 %" in results["r"].reason
    assert not results["n"].is_determined and "10 %" in results["n"].reason
    assert math.isfinite(results["nu"].value)


def test_without_a_modulus_r_and_n_neglect_the_elastic_strain_and_say_so():
    strain, force, width = _sheet(0.3, 1.8, 0.22)
    plastic_only = force / AREA_MM2 > 210.0
    series = TestSeries.of(
        strain[plastic_only], force[plastic_only], transverse_strain=width[plastic_only]
    )
    results = metal_results(series, AREA_MM2, broke=False)
    assert not results["E"].is_determined
    assert not results["nu"].is_determined and "no modulus E" in results["nu"].reason
    assert results["r"].value == pytest.approx(1.8, abs=0.03)
    assert results["n"].value == pytest.approx(0.22, abs=0.01)
    for symbol in ("r", "n"):
        assert "elastic strain neglected (no modulus E" in results[symbol].basis
