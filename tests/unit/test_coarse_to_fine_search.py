"""The coarse-to-fine ZNCC search finds the full search's integer peaks, and falls back to it
where the coarse level cannot resolve the speckle."""

from __future__ import annotations

import numpy as np
import pytest

from appliance.dic.batched_search import ZNCCSearch
from appliance.dic.blur import motion_blur
from appliance.dic.integer_search import zncc_search
from appliance.dic.synthetic import AffineMapping, gaussian_speckle, render

SIZE = 320
RADIUS = 30


def _points() -> np.ndarray:
    g = np.linspace(70, SIZE - 71, 5)
    gx, gy = np.meshgrid(g, g)
    return np.column_stack([gx.ravel(), gy.ravel()]) + 0.3


def _pair(speckle_px: float, shift: tuple[float, float], seed: int, blur_px: float):
    radius = speckle_px / 2.0
    count = round(1200 * SIZE * SIZE / 700**2 * (4.0 / radius) ** 2)
    pattern = gaussian_speckle(SIZE, SIZE, count=count, radius=radius, seed=seed)
    reference = render(pattern, SIZE, SIZE)
    target = render(pattern, SIZE, SIZE, AffineMapping.translation(*shift))
    if blur_px > 0:
        reference = motion_blur(reference, blur_px, 30.0)
        target = motion_blur(target, blur_px, 30.0)
    return reference, target


@pytest.mark.parametrize("speckle_px", [3, 4, 6])
@pytest.mark.parametrize("seed", [1, 2])
@pytest.mark.parametrize("blur_px", [0.0, 8.0])
def test_same_integer_peaks_as_the_full_search(speckle_px, seed, blur_px) -> None:
    rng = np.random.default_rng(seed * 10 + speckle_px)
    shift = tuple(rng.uniform(-RADIUS + 1, RADIUS - 1, 2))
    reference, target = _pair(speckle_px, shift, seed, blur_px)
    points = _points()
    full = zncc_search(reference, target, points, subset=41, radius=RADIUS)
    search = ZNCCSearch(subset=41, radius=RADIUS, coarse_to_fine=True)
    search.prepare(reference, points)
    found = search.search(target)
    np.testing.assert_array_equal(found.valid, full.valid)
    np.testing.assert_array_equal(found.u, full.u)
    np.testing.assert_array_equal(found.v, full.v)
    assert np.all(np.abs(found.u - shift[0]) <= 1) and np.all(np.abs(found.v - shift[1]) <= 1)
    assert search.fallback.mean() < 0.5
    np.testing.assert_allclose(found.score, full.score, atol=1e-5)


def test_a_translation_at_the_radius_with_a_guess() -> None:
    reference, target = _pair(4, (RADIUS + 6.2, -RADIUS + 3.4), 3, 0.0)
    points = _points()
    guess = np.tile([6.0, 3.0], (len(points), 1))
    full = zncc_search(reference, target, points, subset=41, radius=RADIUS, guess=guess)
    search = ZNCCSearch(subset=41, radius=RADIUS, coarse_to_fine=True)
    search.prepare(reference, points)
    found = search.search(target, guess)
    np.testing.assert_array_equal(found.u, full.u)
    np.testing.assert_array_equal(found.v, full.v)
    assert np.all(found.u == 36) and np.all(found.v == -27)


def test_a_speckle_too_fine_for_the_coarse_level_falls_back() -> None:
    """A speckle carried at the Nyquist frequency (a smooth pattern times a checkerboard) is
    flat after the half-resolution Gaussian: every point falls back and is still found."""
    base, _ = _pair(6, (0.0, 0.0), 4, 0.0)
    rows, cols = np.indices(base.shape)
    checker = np.where((rows + cols) % 2 == 0, 1.0, -1.0)
    reference = 128.0 + checker * (base - base.mean())
    shift = (17, -23)
    target = np.roll(reference, shift=(shift[1], shift[0]), axis=(0, 1))
    points = _points()
    search = ZNCCSearch(subset=41, radius=RADIUS, coarse_to_fine=True)
    search.prepare(reference, points)
    found = search.search(target)
    assert search.fallback.all()
    assert np.all(found.u == shift[0]) and np.all(found.v == shift[1])
    full = zncc_search(reference, target, points, subset=41, radius=RADIUS)
    np.testing.assert_allclose(found.reliability, full.reliability, atol=1e-4)


def test_small_radii_and_prewarps_search_in_full() -> None:
    reference, target = _pair(4, (3.2, -2.6), 5, 0.0)
    points = _points()
    small = ZNCCSearch(subset=41, radius=10, coarse_to_fine=True)
    small.prepare(reference, points)
    small.search(target)
    assert small.fallback is None
    wide = ZNCCSearch(subset=41, radius=RADIUS, coarse_to_fine=True)
    wide.prepare(reference, points)
    warped = wide.search(target, prewarps=[[0.0, 0.0, 0.0, 0.0], [0.02, 0.0, 0.0, 0.0]])
    assert wide.fallback is None
    full = zncc_search(
        reference,
        target,
        points,
        subset=41,
        radius=RADIUS,
        prewarps=[[0.0, 0.0, 0.0, 0.0], [0.02, 0.0, 0.0, 0.0]],
    )
    np.testing.assert_array_equal(warped.u, full.u)
    np.testing.assert_array_equal(warped.gradient, full.gradient)
