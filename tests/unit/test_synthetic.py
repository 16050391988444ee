"""Tests of the synthetic speckle images and their ground truth (appliance.dic.synthetic)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.dic import synthetic as syn


def brute_force_intensity(pattern: syn.SpecklePattern, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Reference evaluation: every speckle (and its periodic images), no cut-off."""
    shifts = [(0.0, 0.0)]
    if pattern.period is not None:
        w, h = pattern.period
        shifts = [(i * w, j * h) for i in (-1, 0, 1) for j in (-1, 0, 1)]
    acc = np.zeros(np.broadcast(X, Y).shape)
    for sx, sy in shifts:
        for xk, yk, rk, pk in zip(pattern.x, pattern.y, pattern.radius, pattern.peak, strict=True):
            d2 = (X - (xk + sx)) ** 2 + (Y - (yk + sy)) ** 2
            if pattern.kind == "gaussian":
                acc += pk * np.exp(-d2 / rk**2)
            else:
                inside = (d2 <= rk**2) & (np.abs(pk) > np.abs(acc))
                acc = np.where(inside, pk, acc)
    return pattern.background + acc


def pixel_grid(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    return np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))


GENERATORS = {
    "gaussian": lambda seed: syn.gaussian_speckle(80, 60, count=40, radius=4.0, seed=seed),
    "dense": lambda seed: syn.dense_speckle(80, 60, seed=seed),
    "disc": lambda seed: syn.disc_speckle(80, 60, seed=seed),
}


# ------------------------------------------------------------------------------------------
# Patterns
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(GENERATORS))
def test_same_seed_gives_identical_pattern_and_image(name: str) -> None:
    a, b = GENERATORS[name](7), GENERATORS[name](7)
    assert a == b
    np.testing.assert_array_equal(syn.render(a, 60, 80), syn.render(b, 60, 80))


@pytest.mark.parametrize("name", sorted(GENERATORS))
def test_different_seeds_give_different_patterns(name: str) -> None:
    a, b = GENERATORS[name](7), GENERATORS[name](8)
    assert a != b
    ia, ib = syn.render(a, 60, 80), syn.render(b, 60, 80)
    assert np.abs(ia - ib).mean() > 10.0


def test_pattern_arrays_are_read_only_copies() -> None:
    x = np.array([1.0, 2.0])
    p = syn.SpecklePattern(x=x, y=[3.0, 4.0], radius=2.0, peak=[1.0, 1.0])
    x[0] = 99.0
    assert p.x[0] == 1.0
    np.testing.assert_array_equal(p.radius, [2.0, 2.0])
    with pytest.raises(ValueError):
        p.x[0] = 5.0


def test_eq21_value_of_an_isolated_speckle() -> None:
    p = syn.gaussian_speckle(64, 64, count=1, radius=4.0, seed=3, margin=0.0)
    assert p.count == 1
    xk, yk, i0 = p.x[0], p.y[0], p.peak[0]
    bg = syn.DEFAULT_LEVELS[0]
    assert p.background == bg
    assert 0.4 * 215.0 <= i0 <= 0.8 * 215.0
    ang = np.array([0.0, 1.0, 2.5])
    for dist, expected in [(0.0, 1.0), (4.0, math.exp(-1.0)), (8.0, math.exp(-4.0))]:
        got = p.intensity(xk + dist * np.cos(ang), yk + dist * np.sin(ang))
        np.testing.assert_allclose(got, bg + i0 * expected, rtol=0, atol=1e-12)


def test_eq21_paper_case_isolated_speckle_peaks_at_background_plus_i0() -> None:
    p = syn.gaussian_speckle(700, 700, count=1200, radius=4.0, seed=11)
    inside = (p.x >= -0.5) & (p.x < 699.5) & (p.y >= -0.5) & (p.y < 699.5)
    assert inside.sum() == 1200
    assert p.count > 1200
    d2 = (p.x[:, None] - p.x[None, :]) ** 2 + (p.y[:, None] - p.y[None, :]) ** 2
    np.fill_diagonal(d2, np.inf)
    isolated = np.flatnonzero(inside & (d2.min(axis=1) > (4.0 * 4.0) ** 2))
    assert isolated.size > 100
    got = p.intensity(p.x[isolated], p.y[isolated])
    np.testing.assert_allclose(got, p.background + p.peak[isolated], rtol=0, atol=1e-12)


def test_paper_case_uses_the_8bit_range_with_little_clipping() -> None:
    img = syn.render(syn.gaussian_speckle(700, 700, count=1200, radius=4.0, seed=1), 700, 700)
    assert img.min() == pytest.approx(20.0, abs=1e-3)
    assert np.percentile(img, 99.9) > 200.0
    assert (img > 255.0).mean() < 0.002


def test_dense_pattern_statistics_match_documented_scaling() -> None:
    img = syn.render(syn.dense_speckle(400, 300, seed=5), 300, 400)
    assert img.mean() == pytest.approx(127.5, abs=1.5)
    assert img.std() == pytest.approx(215.0 / 6.0, rel=0.05)
    assert ((img < 20.0) | (img > 235.0)).mean() < 0.01
    gy, gx = np.gradient(img)
    assert np.hypot(gx, gy).mean() > 15.0


@pytest.mark.parametrize("dark_on_bright", [True, False])
def test_disc_pattern_coverage_and_levels(dark_on_bright: bool) -> None:
    p = syn.disc_speckle(400, 300, seed=2, radius=2.5, coverage=0.4, dark_on_bright=dark_on_bright)
    img = syn.render(p, 300, 400)
    ink = 20.0 if dark_on_bright else 235.0
    assert set(np.unique(img)) == {20.0, 235.0}
    assert (img == ink).mean() == pytest.approx(0.4, abs=0.02)
    smooth = syn.render(p, 300, 400, oversample=3)
    assert 0.05 < ((smooth > 20.0) & (smooth < 235.0)).mean() < 0.6


# ------------------------------------------------------------------------------------------
# Rendering
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("periodic", [False, True])
@pytest.mark.parametrize("name", ["gaussian", "dense"])
def test_identity_render_equals_direct_evaluation(name: str, periodic: bool) -> None:
    if name == "gaussian":
        p = syn.gaussian_speckle(48, 40, count=30, radius=3.0, seed=4, periodic=periodic)
    else:
        p = syn.dense_speckle(48, 40, seed=4, density=0.1, periodic=periodic)
    X, Y = pixel_grid(40, 48)
    img = syn.render(p, 40, 48)
    ref = brute_force_intensity(p, X, Y)
    np.testing.assert_allclose(img, ref, rtol=0, atol=1e-5 * np.abs(p.peak).max())
    assert np.ptp(img) > 50.0
    np.testing.assert_array_equal(img, p.intensity(X, Y))


def test_identity_render_of_discs_equals_direct_evaluation() -> None:
    p = syn.disc_speckle(48, 40, seed=4, radius=3.0)
    X, Y = pixel_grid(40, 48)
    np.testing.assert_array_equal(syn.render(p, 40, 48), brute_force_intensity(p, X, Y))


def test_oversampled_render_is_mean_of_subpixel_samples() -> None:
    p = syn.disc_speckle(30, 20, seed=9, radius=2.0)
    img = syn.render(p, 20, 30, oversample=2)
    X, Y = pixel_grid(20, 30)
    ref = np.mean([p.intensity(X + ox, Y + oy) for ox in (-0.25, 0.25) for oy in (-0.25, 0.25)], 0)
    np.testing.assert_allclose(img, ref, rtol=0, atol=1e-12)


def test_render_blocks_cover_all_rows(monkeypatch: pytest.MonkeyPatch) -> None:
    p = syn.gaussian_speckle(37, 23, count=20, radius=3.0, seed=1)
    whole = syn.render(p, 23, 37, oversample=2)
    monkeypatch.setattr(syn, "_BLOCK_SAMPLES", 37 * 4 * 3)
    np.testing.assert_array_equal(syn.render(p, 23, 37, oversample=2), whole)


@pytest.mark.parametrize("name", sorted(GENERATORS))
def test_translation_render_equals_shifted_speckle_centres(name: str) -> None:
    p = GENERATORS[name](21)
    dx, dy = 2.37, -1.61
    moved = syn.render(p, 60, 80, syn.AffineMapping.translation(dx, dy))
    shifted = dataclasses.replace(p, x=p.x + dx, y=p.y + dy)
    expected = syn.render(shifted, 60, 80)
    if p.kind == "disc":
        assert (moved != expected).mean() < 1e-3
    else:
        np.testing.assert_allclose(moved, expected, rtol=0, atol=1e-6)
    assert np.abs(moved - syn.render(p, 60, 80)).mean() > 5.0


def test_render_samples_reference_intensity_at_inverse_mapped_pixels() -> None:
    p = syn.gaussian_speckle(90, 70, count=60, radius=3.0, seed=8)
    m = syn.sinusoidal_displacement(2.0, 1.0, 40.0, angle_deg=20.0)
    X, Y = m.inverse(*pixel_grid(70, 90))
    np.testing.assert_allclose(
        syn.render(p, 70, 90, m), brute_force_intensity(p, X, Y), rtol=0, atol=1e-4
    )


def test_periodic_pattern_wraps_seamlessly() -> None:
    p = syn.gaussian_speckle(64, 48, count=30, radius=4.0, seed=2, periodic=True)
    ref = syn.render(p, 48, 64)
    wrapped = syn.render(p, 48, 64, syn.AffineMapping.translation(64.0, -48.0))
    np.testing.assert_allclose(wrapped, ref, rtol=0, atol=1e-9)
    rolled = syn.render(p, 48, 64, syn.AffineMapping.translation(5.0, 3.0))
    np.testing.assert_allclose(rolled, np.roll(ref, (3, 5), axis=(0, 1)), rtol=0, atol=1e-9)


def test_non_periodic_pattern_has_speckled_margin() -> None:
    p = syn.gaussian_speckle(100, 100, count=150, radius=3.0, seed=6)
    out = syn.render(p, 100, 100, syn.AffineMapping.translation(-20.0, 20.0))
    assert out[:, -20:].std() > 0.5 * out[:, :-20].std()


# ------------------------------------------------------------------------------------------
# Fourier shift
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("dx", "dy"), [(3.3, -1.7), (0.5, 0.5), (-20.25, 7.1)])
def test_fourier_shift_matches_analytic_render_of_shifted_periodic_pattern(
    dx: float, dy: float
) -> None:
    # Tolerance 1e-4 grey levels (peaks are ~100-190): the shift is exact for this
    # band-limited (R = 4) periodic pattern; what remains is the 4 R truncation of the render.
    p = syn.gaussian_speckle(128, 96, count=40, radius=4.0, seed=3, periodic=True)
    shifted = syn.fourier_shift(syn.render(p, 96, 128), dx, dy)
    expected = syn.render(p, 96, 128, syn.AffineMapping.translation(dx, dy))
    assert np.abs(shifted - expected).max() < 1e-4
    assert np.abs(expected - syn.render(p, 96, 128)).max() > 20.0


def test_fourier_shift_by_whole_pixels_is_a_roll() -> None:
    img = np.random.default_rng(0).random((17, 24))
    expected = np.roll(img, (-2, 5), axis=(0, 1))
    np.testing.assert_allclose(syn.fourier_shift(img, 5, -2), expected, rtol=0, atol=1e-12)


# ------------------------------------------------------------------------------------------
# Mappings
# ------------------------------------------------------------------------------------------

grad = st.floats(-0.3, 0.3)
coord = st.floats(-500.0, 500.0)


@settings(max_examples=60, deadline=None)
@given(u=coord, v=coord, ux=grad, uy=grad, vx=grad, vy=grad, xc=coord, yc=coord)
def test_affine_inverse_of_forward_is_identity(
    u: float, v: float, ux: float, uy: float, vx: float, vy: float, xc: float, yc: float
) -> None:
    m = syn.AffineMapping(u=u, v=v, ux=ux, uy=uy, vx=vx, vy=vy, xc=xc, yc=yc)
    X, Y = np.meshgrid(np.linspace(-800, 800, 7), np.linspace(-600, 600, 5))
    Xb, Yb = m.inverse(*m.forward(X, Y))
    np.testing.assert_allclose(Xb, X, rtol=0, atol=1e-9)
    np.testing.assert_allclose(Yb, Y, rtol=0, atol=1e-9)


def test_affine_forward_formula_and_true_displacement() -> None:
    m = syn.AffineMapping(u=1.5, v=-2.0, ux=0.01, uy=0.02, vx=-0.03, vy=0.04, xc=10.0, yc=20.0)
    x, y = m.forward(30.0, 25.0)
    assert x == pytest.approx(30.0 + 1.5 + 0.01 * 20.0 + 0.02 * 5.0)
    assert y == pytest.approx(25.0 - 2.0 - 0.03 * 20.0 + 0.04 * 5.0)
    u, v = syn.true_displacement(m, 30.0, 25.0)
    assert (u, v) == pytest.approx((x - 30.0, y - 25.0))
    with pytest.raises(ValueError):
        syn.AffineMapping(ux=-1.0)


@pytest.mark.parametrize(
    ("stretch", "axis", "nu", "lateral"),
    [
        (1.2, "x", None, 1.2**-0.5),
        (2.5, "y", None, 2.5**-0.5),
        (1.05, "x", 0.3, 1.0 - 0.3 * 0.05),
        (0.9, "y", 0.45, 1.0 + 0.45 * 0.1),
    ],
)
def test_uniaxial_stretch(stretch: float, axis: str, nu: float | None, lateral: float) -> None:
    m = syn.UniaxialStretch(stretch, axis=axis, poisson_ratio=nu, xc=100.0, yc=50.0)
    assert m.lateral_stretch == pytest.approx(lateral, rel=1e-14)
    X, Y = np.meshgrid(np.linspace(0, 300, 11), np.linspace(0, 120, 9))
    u, v = syn.true_displacement(m, X, Y)
    along, across = (u, v) if axis == "x" else (v, u)
    dA, dT = (X - 100.0, Y - 50.0) if axis == "x" else (Y - 50.0, X - 100.0)
    np.testing.assert_allclose(along, (stretch - 1.0) * dA, atol=1e-12)
    np.testing.assert_allclose(across, (lateral - 1.0) * dT, atol=1e-12)
    Xb, Yb = m.inverse(*m.forward(X, Y))
    np.testing.assert_allclose(Xb, X, atol=1e-11)
    np.testing.assert_allclose(Yb, Y, atol=1e-11)


def test_sinusoidal_field_inverse_is_accurate_to_1e_10_px() -> None:
    m = syn.sinusoidal_displacement(3.0, -1.5, 32.0, angle_deg=30.0, phase=0.4)
    x, y = np.meshgrid(np.linspace(-10, 510, 131), np.linspace(-10, 310, 77))
    X, Y = m.inverse(x, y)
    xf, yf = m.forward(X, Y)
    assert np.abs(xf - x).max() <= 1e-10
    assert np.abs(yf - y).max() <= 1e-10
    Xb, Yb = m.inverse(*m.forward(x, y))
    assert max(np.abs(Xb - x).max(), np.abs(Yb - y).max()) < 1e-9
    u, v = syn.true_displacement(m, X, Y)
    k = 2 * np.pi / 32.0 * np.array([np.cos(np.pi / 6), np.sin(np.pi / 6)])
    np.testing.assert_allclose(u, 3.0 * np.sin(k[0] * X + k[1] * Y + 0.4), atol=1e-12)
    assert np.abs(u).max() > 2.9


def test_displacement_field_without_gradient_uses_finite_differences() -> None:
    m = syn.DisplacementField(
        u=lambda X, Y: 0.05 * X + 1e-4 * X * Y, v=lambda X, Y: 2.0 * np.cos(X / 50.0)
    )
    x, y = np.meshgrid(np.linspace(0, 400, 41), np.linspace(0, 300, 31))
    X, Y = m.inverse(x, y)
    xf, yf = m.forward(X, Y)
    assert max(np.abs(xf - x).max(), np.abs(yf - y).max()) <= 1e-10
    with pytest.raises(RuntimeError):
        dataclasses.replace(m, max_iter=0).inverse(x, y)


def test_sinusoidal_field_rejects_folding_amplitude() -> None:
    with pytest.raises(ValueError):
        syn.sinusoidal_displacement(6.0, 0.0, 32.0)


# ------------------------------------------------------------------------------------------
# Motion blur
# ------------------------------------------------------------------------------------------


def psf_moments(k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First moments (x, y) and second-moment matrix of a kernel about its centre element."""
    hr, hc = k.shape[0] // 2, k.shape[1] // 2
    Y, X = np.mgrid[-hr : hr + 1, -hc : hc + 1]
    first = np.array([(k * X).sum(), (k * Y).sum()])
    xy = (k * X * Y).sum()
    second = np.array([[(k * X * X).sum(), xy], [xy, (k * Y * Y).sum()]])
    return first, second


@settings(max_examples=80, deadline=None)
@given(length=st.floats(0.0, 40.0), angle=st.floats(-360.0, 360.0))
def test_line_psf_is_normalised_point_symmetric_with_exact_moments(
    length: float, angle: float
) -> None:
    k = syn.line_psf(length, angle)
    assert k.shape[0] % 2 == 1 and k.shape[1] % 2 == 1
    assert k.sum() == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_array_equal(k, k[::-1, ::-1])
    assert k.min() >= -0.08 * k.max()
    assert max(k.shape) <= 2 * math.ceil(length / 2) + 5
    first, second = psf_moments(k)
    np.testing.assert_allclose(first, 0.0, atol=1e-12)
    d = np.array([math.cos(math.radians(angle)), math.sin(math.radians(angle))])
    expected = length**2 / 12.0 * np.outer(d, d)
    np.testing.assert_allclose(second, expected, rtol=0, atol=1e-11 * (1.0 + length**2))


@pytest.mark.parametrize(("length", "angle"), [(15.0, 30.0), (7.3, -72.0), (3.0, 5.0)])
def test_line_psf_second_moments_give_length_and_direction(length: float, angle: float) -> None:
    w, vec = np.linalg.eigh(psf_moments(syn.line_psf(length, angle))[1])
    assert w[1] == pytest.approx(length**2 / 12.0, rel=1e-12)
    assert abs(w[0]) < 1e-12
    direction = math.degrees(math.atan2(vec[1, 1], vec[0, 1]))
    assert abs((direction - angle + 90.0) % 180.0 - 90.0) < 1e-9


def test_line_psf_of_horizontal_and_vertical_motion_is_one_line() -> None:
    h = syn.line_psf(4.0, 0.0)
    assert h.shape[0] == 1 and h.shape[1] >= 5
    np.testing.assert_allclose(syn.line_psf(4.0, 90.0), h.T, atol=1e-15)
    np.testing.assert_array_equal(syn.line_psf(0.0, 33.0), [[1.0]])
    np.testing.assert_array_equal(syn.line_psf(1e-300, 33.0), [[1.0]])


def test_zero_length_blur_is_identity() -> None:
    img = np.random.default_rng(1).random((20, 30)) * 255
    np.testing.assert_array_equal(syn.motion_blur(img, 0.0, 45.0), img)


def test_motion_blur_of_an_impulse_is_the_centred_kernel() -> None:
    img = np.zeros((31, 31))
    img[15, 15] = 1.0
    k = syn.line_psf(9.5, 20.0)
    out = syn.motion_blur(img, 9.5, 20.0)
    hr, hc = k.shape[0] // 2, k.shape[1] // 2
    np.testing.assert_allclose(out[15 - hr : 16 + hr, 15 - hc : 16 + hc], k, atol=1e-15)
    assert out.sum() == pytest.approx(1.0)


def test_exposure_of_constant_velocity_translation_equals_line_blur() -> None:
    # The continuous exposure and the line blur of the sampled image agree to 0.2 % of the
    # image's standard deviation (RMS, away from the borders) and 1 grey level at worst.
    p = syn.gaussian_speckle(160, 120, count=300, radius=4.0, seed=5)
    length, angle = 6.5, 30.0
    c, s = math.cos(math.radians(angle)), math.sin(math.radians(angle))

    def mapping_at(t: float) -> syn.AffineMapping:
        return syn.AffineMapping.translation(length * c * t, length * s * t)

    exposed = syn.render_exposure(p, 120, 160, mapping_at, start=-0.5, stop=0.5, samples=64)
    sharp = syn.render(p, 120, 160)
    blurred = syn.motion_blur(sharp, length, angle)
    diff = (exposed - blurred)[12:-12, 12:-12]
    assert np.sqrt((diff**2).mean()) < 0.002 * exposed.std()
    assert np.abs(diff).max() < 1.0
    assert np.sqrt(((exposed - sharp)[12:-12, 12:-12] ** 2).mean()) > 0.1 * exposed.std()


def test_exposure_uses_midpoint_times() -> None:
    p = syn.gaussian_speckle(40, 30, count=10, radius=3.0, seed=5)
    times: list[float] = []

    def mapping_at(t: float) -> None:
        times.append(t)

    out = syn.render_exposure(p, 30, 40, mapping_at, start=1.0, stop=2.0, samples=4)
    assert times == pytest.approx([1.125, 1.375, 1.625, 1.875])
    np.testing.assert_allclose(out, syn.render(p, 30, 40), atol=1e-12)


# ------------------------------------------------------------------------------------------
# Noise and quantisation
# ------------------------------------------------------------------------------------------


def test_gaussian_noise_has_requested_sigma_and_is_seeded() -> None:
    img = np.full((512, 512), 100.0)
    noisy = syn.add_gaussian_noise(img, 2.5, seed=3)
    assert noisy.std() == pytest.approx(2.5, rel=0.015)
    assert noisy.mean() == pytest.approx(100.0, abs=0.05)
    np.testing.assert_array_equal(noisy, syn.add_gaussian_noise(img, 2.5, seed=3))
    assert not np.array_equal(noisy, syn.add_gaussian_noise(img, 2.5, seed=4))
    np.testing.assert_array_equal(img, 100.0)


@pytest.mark.parametrize(("level", "gain", "black"), [(100.0, 4.0, 0.0), (100.0, 2.0, 20.0)])
def test_poisson_noise_variance_matches_signal_over_gain(
    level: float, gain: float, black: float
) -> None:
    img = np.full((512, 512), level)
    noisy = syn.add_poisson_noise(img, gain, seed=5, black_level=black)
    assert noisy.var() == pytest.approx((level - black) / gain, rel=0.02)
    assert noisy.mean() == pytest.approx(level, abs=0.05)
    electrons = (noisy - black) * gain
    np.testing.assert_allclose(electrons, np.round(electrons), atol=1e-9)
    again = syn.add_poisson_noise(img, gain, seed=5, black_level=black)
    np.testing.assert_array_equal(noisy, again)


def test_quantize_8_bit() -> None:
    q = syn.quantize(np.array([-5.0, 0.4, 0.6, 127.5, 254.4, 254.6, 300.0]), 8)
    assert q.dtype == np.uint8
    np.testing.assert_array_equal(q, [0, 0, 1, 128, 254, 255, 255])


def test_quantize_12_bit() -> None:
    q = syn.quantize(np.array([[-1.0, 1000.49], [4094.6, 5000.0]]), 12)
    assert q.dtype == np.uint16
    np.testing.assert_array_equal(q, [[0, 1000], [4095, 4095]])


def test_quantize_rejects_bad_input() -> None:
    with pytest.raises(ValueError):
        syn.quantize(np.array([np.nan]), 8)
    with pytest.raises(ValueError):
        syn.quantize(np.zeros(3), 17)
