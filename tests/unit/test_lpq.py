"""Unit tests of the LPQ code image, its histograms and the chi-square distance."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from appliance.dic.lpq import (
    N_BINS,
    LPQParams,
    chi_square,
    code_histogram,
    decorrelation_matrix,
    lpq_codes,
    lpq_coefficients,
    lpq_kernels,
    max_invariant_line_blur,
)


def speckle(shape: tuple[int, int], sigma: float = 2.0, seed: int = 0) -> np.ndarray:
    """Seeded noise smoothed by a Gaussian of ``sigma`` px, scaled to about 128 +- 40."""
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.random(shape), (0, 0), sigma)
    return 128.0 + 40.0 * (tex - tex.mean()) / tex.std()


def horizontal_line_blur(image: np.ndarray, length: int) -> np.ndarray:
    """Centred horizontal line PSF of ``length`` pixels (odd), reflected borders."""
    kernel = np.full((1, length), 1.0 / length)
    return cv2.filter2D(image, -1, kernel, borderType=cv2.BORDER_REFLECT_101)


def interior(arr: np.ndarray, margin: int) -> np.ndarray:
    return arr[margin:-margin, margin:-margin]


PARAM_SETS = [
    LPQParams(),
    LPQParams(gaussian_window=True),
    LPQParams(decorrelate=False),
    LPQParams(window=11, rho=0.8),
]


@pytest.mark.parametrize("params", PARAM_SETS)
def test_codes_are_uint8_with_documented_shapes(params: LPQParams) -> None:
    image = speckle((90, 120))
    codes = lpq_codes(image, params)
    assert codes.dtype == np.uint8
    assert codes.shape == image.shape
    valid = lpq_codes(image, params, border="valid")
    r = params.radius
    assert valid.shape == (90 - 2 * r, 120 - 2 * r)
    np.testing.assert_array_equal(valid, codes[r:-r, r:-r])
    assert len(np.unique(codes)) > 200


def test_codes_accept_integer_images() -> None:
    image = np.clip(speckle((60, 60)), 0, 255).astype(np.uint8)
    np.testing.assert_array_equal(lpq_codes(image), lpq_codes(image.astype(np.float64)))


def test_bit_order_on_an_impulse() -> None:
    # For an impulse at p, the coefficients at x are the kernel values at d = p - x:
    # F(u) = w(d) exp(-2j pi u.d). With M = 7, a = 1/7:
    # d = (1, 2): phases u1 -2pi/7, u2 -4pi/7, u3 -6pi/7, u4 +2pi/7
    #   -> Re/Im signs (+-), (--), (--), (++) -> bits 0, 6, 7 -> 1 + 64 + 128 = 193
    # d = (-2, 1): phases u1 +4pi/7, u2 -2pi/7, u3 +2pi/7, u4 +6pi/7
    #   -> (-+), (+-), (++), (-+) -> bits 1, 2, 4, 5, 7 -> 2 + 4 + 16 + 32 + 128 = 182
    image = np.full((21, 21), 50.0)
    image[10, 10] += 1.0
    codes = lpq_codes(image, LPQParams(decorrelate=False))
    assert codes[8, 9] == 193
    assert codes[9, 12] == 182


def test_kernels_are_the_documented_stft() -> None:
    params = LPQParams(window=7)
    kernels = lpq_kernels(params)
    d = np.arange(-3, 4, dtype=float)
    dx, dy = d[None, :], d[:, None]
    a = 1.0 / 7.0
    for k, (ux, uy) in enumerate([(a, 0.0), (0.0, a), (a, a), (a, -a)]):
        expected = np.exp(-2j * np.pi * (ux * dx + uy * dy)) / 49.0
        np.testing.assert_allclose(kernels[2 * k] + 1j * kernels[2 * k + 1], expected, atol=1e-15)


def test_raw_coefficients_correlate_the_kernels() -> None:
    params = LPQParams(decorrelate=False, gaussian_window=True)
    image = speckle((40, 40), seed=3)
    coeffs = lpq_coefficients(image, params, border="valid")
    kernels = lpq_kernels(params)
    assert abs(kernels.sum(axis=(1, 2))).max() < 1e-15
    for y, x in [(0, 0), (5, 17), (33, 33)]:
        block = image[y : y + 7, x : x + 7]
        np.testing.assert_allclose(coeffs[y, x], (kernels * block).sum(axis=(1, 2)), atol=1e-9)


@pytest.mark.parametrize("params", [LPQParams(), LPQParams(window=9, gaussian_window=True)])
def test_decorrelated_bits_are_signs_of_the_documented_components(params: LPQParams) -> None:
    image = speckle((50, 60), seed=4)
    raw = lpq_coefficients(
        image, LPQParams(params.window, params.rho, params.gaussian_window, decorrelate=False)
    )
    vt = decorrelation_matrix(params)
    np.testing.assert_allclose(vt @ vt.T, np.eye(8), atol=1e-12)
    for row in vt:
        lead = np.flatnonzero(np.abs(row) >= np.abs(row).max() * (1 - 1e-3))[0]
        assert row[lead] > 0
    decorrelated = lpq_coefficients(image, params)
    np.testing.assert_allclose(decorrelated, raw @ vt.T, atol=1e-9)
    codes = lpq_codes(image, params)
    expected = sum(((decorrelated[..., k] > 0) << k) for k in range(8))
    np.testing.assert_array_equal(codes, expected.astype(np.uint8))


def test_decorrelation_matrix_is_deterministic_and_block_structured() -> None:
    vt = decorrelation_matrix(LPQParams())
    assert not vt.flags.writeable
    for row in vt:
        nonzero = np.flatnonzero(row)
        assert len(set(nonzero % 2)) == 1
    np.testing.assert_array_equal(vt, decorrelation_matrix(LPQParams(window=7)))


@pytest.mark.parametrize("params", PARAM_SETS)
@pytest.mark.parametrize("scale,offset", [(2.5, 30.0), (0.4, -80.0), (1.0, 1000.0)])
def test_codes_invariant_to_intensity_scale_and_offset(
    params: LPQParams, scale: float, offset: float
) -> None:
    image = speckle((80, 80), seed=1)
    base = lpq_codes(image, params, border="valid")
    np.testing.assert_array_equal(lpq_codes(scale * image + offset, params, border="valid"), base)


def test_max_invariant_line_blur() -> None:
    assert max_invariant_line_blur(LPQParams(window=7)) == pytest.approx(7.0)
    assert max_invariant_line_blur(LPQParams(window=7), 90.0) == pytest.approx(7.0)
    assert max_invariant_line_blur(LPQParams(window=7), 45.0) == pytest.approx(7 / math.sqrt(2))
    assert max_invariant_line_blur(LPQParams(window=15), -45.0) == pytest.approx(15 / math.sqrt(2))


def test_line_blur_shorter_than_window_keeps_most_codes() -> None:
    # Measured on this texture: L = 3 keeps 81 %, L = 5 52 %, L = 15 2 %, L = 21 1.5 %.
    params = LPQParams(window=7)
    image = speckle((300, 300), sigma=2.0)
    sharp = interior(lpq_codes(image, params), 30)

    def kept(length: int) -> float:
        blurred = interior(lpq_codes(horizontal_line_blur(image, length), params), 30)
        return float(np.mean(blurred == sharp))

    short, medium, long_, very_long = kept(3), kept(5), kept(15), kept(21)
    assert short > 0.75
    assert medium > 0.45
    assert long_ < 0.06 and very_long < 0.06
    assert medium > 8 * max(long_, very_long)


def test_larger_window_tolerates_longer_blur() -> None:
    image = speckle((300, 300), sigma=2.0, seed=2)
    blurred = horizontal_line_blur(image, 7)
    fractions = []
    for window in (7, 15):
        params = LPQParams(window=window)
        sharp = interior(lpq_codes(image, params), 30)
        fractions.append(np.mean(interior(lpq_codes(blurred, params), 30) == sharp))
    assert fractions[1] > 0.5 > 0.35 > fractions[0]


def test_code_histogram_counts() -> None:
    codes = np.array([[0, 255, 3], [3, 3, 0]], dtype=np.uint8)
    hist = code_histogram(codes)
    assert hist.shape == (N_BINS,) and hist.dtype == np.float64
    assert hist[0] == 2 and hist[3] == 3 and hist[255] == 1 and hist.sum() == 6
    with pytest.raises(TypeError):
        code_histogram(codes.astype(np.int32))


def test_chi_square_properties() -> None:
    rng = np.random.default_rng(0)
    h1 = rng.integers(0, 20, N_BINS).astype(float)
    h2 = rng.integers(0, 20, N_BINS).astype(float)
    h1[:10] = 0
    h2[:10] = 0
    assert chi_square(h1, h1) == 0.0
    assert chi_square(h1, h2) == pytest.approx(chi_square(h2, h1))
    keep = (h1 + h2) > 0
    expected = np.sum((h1[keep] - h2[keep]) ** 2 / (h1[keep] + h2[keep]))
    assert chi_square(h1, h2) == pytest.approx(expected)
    assert np.isfinite(chi_square(h1, h2))
    assert chi_square([1.0, 0.0, 2.0], [0.0, 0.0, 2.0]) == pytest.approx(1.0)
    disjoint = chi_square([0.5, 0.5, 0.0, 0.0], [0.0, 0.0, 0.25, 0.75])
    assert disjoint == pytest.approx(2.0)


def test_chi_square_weights() -> None:
    h1 = np.array([4.0, 1.0, 0.0, 2.0])
    h2 = np.array([1.0, 1.0, 3.0, 0.0])
    terms = np.array([9 / 5, 0.0, 3.0, 2.0])
    w = np.array([2.0, 7.0, 0.0, 0.5])
    assert chi_square(h1, h2, w) == pytest.approx(np.sum(w * terms))
    assert chi_square(h1, h2, np.ones(4)) == pytest.approx(chi_square(h1, h2))
    assert chi_square(h1, h2, np.zeros(4)) == 0.0
    batch = chi_square(np.stack([h1, h2]), h2)
    np.testing.assert_allclose(batch, [terms.sum(), 0.0])


@pytest.mark.parametrize(
    "kwargs", [{"window": 6}, {"window": 1}, {"rho": 0.0}, {"rho": 1.0}, {"window": 7.5}]
)
def test_params_validation(kwargs: dict) -> None:
    with pytest.raises((ValueError, TypeError)):
        LPQParams(**kwargs)


def test_rejects_bad_images() -> None:
    with pytest.raises(ValueError):
        lpq_codes(np.zeros((5, 5, 3)))
    with pytest.raises(ValueError):
        lpq_codes(np.zeros((5, 40)), LPQParams(window=7), border="valid")
    with pytest.raises(ValueError):
        lpq_codes(np.zeros((40, 40)), border="same")
