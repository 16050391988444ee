"""Unit tests of the integer-pixel searches (LPQ + chi-square, ZNCC)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from appliance.dic.integer_search import IntegerMatch, chi_square_map, lpq_search, zncc_search
from appliance.dic.lpq import LPQParams, chi_square, code_histogram, lpq_codes

SEARCHES = [lpq_search, zncc_search]


def speckle(shape: tuple[int, int], sigma: float = 2.0, seed: int = 0) -> np.ndarray:
    """Seeded noise smoothed by a Gaussian of ``sigma`` px, scaled to about 128 +- 40."""
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.random(shape), (0, 0), sigma)
    return 128.0 + 40.0 * (tex - tex.mean()) / tex.std()


def affine_target(reference: np.ndarray, matrix: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """Target with ``target(matrix @ p + shift) = reference(p)`` (bicubic, reflected border)."""
    forward = np.hstack([matrix, np.asarray(shift, dtype=float)[:, None]])
    return cv2.warpAffine(
        reference,
        forward,
        (reference.shape[1], reference.shape[0]),
        flags=cv2.INTER_CUBIC,
        borderMode=cv2.BORDER_REFLECT_101,
    )


def centred_line_blur(image: np.ndarray, length: int) -> np.ndarray:
    kernel = np.full((1, length), 1.0 / length)
    return cv2.filter2D(image, -1, kernel, borderType=cv2.BORDER_REFLECT_101)


def grid_points(lo: float, hi: float, count: int, jitter: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    g = np.linspace(lo, hi, count)
    gx, gy = np.meshgrid(g, g)
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    return pts + rng.uniform(-jitter, jitter, pts.shape)


# --------------------------------------------------------------------------------------------
# chi_square_map (sliding histograms)


@pytest.mark.parametrize("subset", [21, 41])
@pytest.mark.parametrize("source", ["speckle", "uniform"])
def test_chi_square_map_equals_brute_force(subset: int, source: str) -> None:
    rng = np.random.default_rng(subset)
    if source == "speckle":
        codes = lpq_codes(speckle((150, 170), seed=5))[10:140, 5:165]
    else:
        codes = rng.integers(0, 256, (130, 160)).astype(np.uint8)
    reference = code_histogram(lpq_codes(speckle((subset, subset), seed=6), border="reflect"))
    weights = rng.uniform(0.0, 3.0, 256)
    area = subset * subset
    for w in (None, weights):
        cmap = chi_square_map(codes, reference, subset, weights=w)
        assert cmap.shape == (130 - subset + 1, 160 - subset + 1)
        rows = rng.integers(0, cmap.shape[0], 40)
        cols = rng.integers(0, cmap.shape[1], 40)
        for i, j in zip(rows, cols, strict=True):
            block = code_histogram(codes[i : i + subset, j : j + subset])
            expected = chi_square(reference / area, block / area, w)
            assert cmap[i, j] == pytest.approx(expected, abs=1e-10)
        for i, j in [(0, 0), (cmap.shape[0] - 1, cmap.shape[1] - 1), (cmap.shape[0] - 1, 0)]:
            block = code_histogram(codes[i : i + subset, j : j + subset])
            assert cmap[i, j] == pytest.approx(
                chi_square(reference / area, block / area, w), abs=1e-10
            )


def test_chi_square_map_finds_its_own_block() -> None:
    codes = lpq_codes(speckle((120, 120), seed=9))
    reference = code_histogram(codes[37:78, 52:93])
    cmap = chi_square_map(codes, reference, 41)
    assert cmap[37, 52] == 0.0
    assert np.unravel_index(np.argmin(cmap), cmap.shape) == (37, 52)
    assert cmap.max() <= 2.0


def test_chi_square_map_validates_inputs() -> None:
    codes = np.zeros((50, 50), dtype=np.uint8)
    hist = np.zeros(256)
    hist[0] = 41 * 41
    with pytest.raises(TypeError):
        chi_square_map(codes.astype(np.int16), hist, 41)
    with pytest.raises(ValueError):
        chi_square_map(codes, hist[:100], 41)
    with pytest.raises(ValueError):
        chi_square_map(codes, hist, 21)
    with pytest.raises(ValueError):
        chi_square_map(codes, hist, 61)


# --------------------------------------------------------------------------------------------
# Searches: shifts, guesses, borders


@pytest.mark.parametrize("search", SEARCHES)
def test_recovers_integer_shift(search) -> None:
    reference = speckle((260, 260), seed=1)
    target = np.roll(reference, shift=(7, -12), axis=(0, 1))
    points = np.array([[130.0, 130.0], [90.4, 160.6], [170.0, 95.2], [60.0, 200.0]])
    result = search(reference, target, points, subset=41, radius=20)
    assert isinstance(result, IntegerMatch) and len(result) == 4
    assert result.u.dtype == np.int64 and result.v.dtype == np.int64
    np.testing.assert_array_equal(result.u, -12)
    np.testing.assert_array_equal(result.v, 7)
    assert result.valid.all()
    assert np.all(result.reliability > 0.5)
    np.testing.assert_array_equal(result.gradient, 0.0)
    if search is lpq_search:
        np.testing.assert_allclose(result.score, 0.0, atol=1e-12)
    else:
        np.testing.assert_allclose(result.score, 1.0, atol=1e-5)


@pytest.mark.parametrize("search", SEARCHES)
def test_subpixel_shift_is_found_within_one_pixel(search) -> None:
    reference = speckle((240, 240), seed=2)
    shift = np.array([5.4, -3.7])
    target = affine_target(reference, np.eye(2), shift)
    points = grid_points(80, 160, 3, 2.0, seed=0)
    result = search(reference, target, points, subset=41, radius=12)
    assert np.abs(result.displacement - shift).max() <= 1.0


@pytest.mark.parametrize("search", SEARCHES)
def test_guess_is_honoured(search) -> None:
    reference = speckle((300, 300), seed=3)
    target = np.roll(reference, shift=(-25, 60), axis=(0, 1))
    points = np.array([[110.0, 150.0], [140.0, 170.0]])
    guess = np.array([[57.6, -23.2], [63.0, -27.4]])
    found = search(reference, target, points, subset=41, radius=6, guess=guess)
    np.testing.assert_array_equal(found.u, 60)
    np.testing.assert_array_equal(found.v, -25)
    missed = search(reference, target, points, subset=41, radius=6)
    assert np.all(np.abs(missed.u) <= 6) and np.all(np.abs(missed.v) <= 6)


@pytest.mark.parametrize("search", SEARCHES)
def test_points_near_borders_are_invalid_not_errors(search) -> None:
    reference = speckle((200, 220), seed=4)
    target = np.roll(reference, shift=(3, 4), axis=(0, 1))
    points = np.array(
        [
            [19.0, 100.0],  # subset pokes out on the left of the reference
            [100.0, 180.4],  # ... at the bottom
            [-50.0, -50.0],  # far outside
            [20.0, 100.0],  # subset exactly inside
            [100.0, 100.0],
        ]
    )
    result = search(reference, target, points, subset=41, radius=10)
    np.testing.assert_array_equal(result.valid, [False, False, False, True, True])
    assert np.all(result.u[:3] == 0) and np.all(result.v[:3] == 0)
    assert np.all(np.isnan(result.score[:3])) and np.all(result.reliability[:3] == 0)
    # The subset touching the edge has reflected LPQ codes in its outer columns, which the
    # shifted target does not share, so only the interior point is held to the exact shift.
    assert abs(result.u[3] - 4) <= 1 and abs(result.v[3] - 3) <= 1
    assert result.u[4] == 4 and result.v[4] == 3
    off_window = search(
        reference, target, points[4:], subset=41, radius=10, guess=np.array([[500.0, 0.0]])
    )
    assert not off_window.valid[0]


def test_lpq_codes_near_borders_match_the_whole_image() -> None:
    reference = speckle((150, 160), seed=5)
    target = np.roll(reference, shift=(2, -3), axis=(0, 1))
    points = np.array([[20.0, 20.0], [139.0, 129.0], [80.0, 75.0]])
    params = LPQParams(window=9)
    result = lpq_search(reference, target, points, subset=41, radius=8, params=params)
    ref_codes = lpq_codes(reference, params)
    tgt_codes = lpq_codes(target, params)
    for k, (x, y) in enumerate(points.astype(int)):
        h_ref = code_histogram(ref_codes[y - 20 : y + 21, x - 20 : x + 21])
        tx, ty = x + result.u[k], y + result.v[k]
        h_tgt = code_histogram(tgt_codes[ty - 20 : ty + 21, tx - 20 : tx + 21])
        assert result.score[k] == pytest.approx(chi_square(h_ref, h_tgt) / 41**2, abs=1e-12)
    spread = lpq_search(reference, target, points[:2], subset=41, radius=8, params=params)
    np.testing.assert_array_equal(spread.u, result.u[:2])
    np.testing.assert_array_equal(spread.score, result.score[:2])


def test_results_do_not_depend_on_the_other_points() -> None:
    reference = speckle((400, 400), seed=6)
    target = affine_target(reference, np.eye(2), np.array([3.3, -2.6]))
    near = np.array([[150.0, 150.0], [170.0, 160.0]])
    far = np.array([[150.0, 150.0], [350.0, 340.0]])
    a = lpq_search(reference, target, near, subset=31, radius=10)
    b = lpq_search(reference, target, far, subset=31, radius=10)
    assert a.u[0] == b.u[0] and a.v[0] == b.v[0] and a.score[0] == b.score[0]
    assert a.reliability[0] == b.reliability[0]


# --------------------------------------------------------------------------------------------
# Robustness


def test_lpq_search_under_strong_centred_line_blur() -> None:
    reference = speckle((300, 300), sigma=2.0, seed=7)
    shift = np.array([8.3, -5.6])
    target = centred_line_blur(affine_target(reference, np.eye(2), shift), 7)
    points = grid_points(100, 200, 3, 3.0, seed=1)
    result = lpq_search(
        reference, target, points, subset=41, radius=15, params=LPQParams(window=21)
    )
    errors = np.abs(result.displacement - shift).max(axis=1)
    assert np.all(errors <= 1.0)


def test_lpq_search_under_contrast_and_offset_change() -> None:
    reference = speckle((260, 260), seed=8)
    target = 0.6 * np.roll(reference, shift=(-4, 9), axis=(0, 1)) + 40.0
    points = grid_points(90, 170, 3, 2.0, seed=2)
    result = lpq_search(reference, target, points, subset=41, radius=15)
    np.testing.assert_array_equal(result.u, 9)
    np.testing.assert_array_equal(result.v, -4)


@pytest.mark.parametrize("search", SEARCHES)
def test_reliability_high_on_texture_low_on_flat_and_periodic(search) -> None:
    rng = np.random.default_rng(9)
    yy, xx = np.mgrid[:220, :220]
    scenes = {
        "textured": speckle((220, 220), seed=9),
        "flat": np.full((220, 220), 100.0),
        "periodic": 128 + 50 * np.sin(2 * np.pi * xx / 8.0) * np.sin(2 * np.pi * yy / 8.0),
    }
    points = np.array([[110.0, 110.0], [100.0, 120.0]])
    reliability = {}
    for name, scene in scenes.items():
        reference = scene + rng.normal(0.0, 1.0, scene.shape)
        target = np.roll(scene, shift=(2, 3), axis=(0, 1)) + rng.normal(0.0, 1.0, scene.shape)
        result = search(reference, target, points, subset=41, radius=20)
        assert result.valid.all()
        reliability[name] = result.reliability
    assert np.all(reliability["textured"] > 0.5)
    assert np.all(reliability["flat"] < 0.2)
    assert np.all(reliability["periodic"] < 0.2)


def _stretch_case() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    reference = speckle((300, 420), sigma=2.0, seed=10)
    eps = 0.30
    matrix = np.diag([1.0 + eps, 1.0 - 0.3 * eps])
    centre = np.array([210.0, 150.0])
    shift = centre - matrix @ centre + np.array([2.2, -1.4])
    target = affine_target(reference, matrix, shift)
    xs = np.array([120.0, 150.0, 180.0, 240.0, 270.0, 300.0])
    points = np.column_stack([xs, np.full_like(xs, 150.0) + np.array([-20, 15, 0, 20, -15, 5])])
    centres = np.floor(points + 0.5)
    truth = centres @ matrix.T + shift - centres
    return reference, target, points, truth


@pytest.mark.parametrize("search", SEARCHES)
def test_prewarps_recover_a_thirty_percent_stretch(search) -> None:
    reference, target, points, truth = _stretch_case()
    eps = np.array([0.0, 0.1, 0.2, 0.3, 0.4])
    prewarps = np.column_stack([eps, 0 * eps, 0 * eps, -0.3 * eps])
    plain = search(reference, target, points, subset=41, radius=40)
    warped = search(reference, target, points, subset=41, radius=40, prewarps=prewarps)
    plain_err = np.abs(plain.displacement - truth).max(axis=1)
    warped_err = np.abs(warped.displacement - truth).max(axis=1)
    assert np.all(warped_err <= 1.0)
    assert np.sum(plain_err > 1.0) >= 2
    np.testing.assert_allclose(warped.ux, 0.3)
    np.testing.assert_allclose(warped.vy, -0.09)
    np.testing.assert_array_equal(warped.uy, 0.0)


@pytest.mark.parametrize("search", SEARCHES)
def test_identity_prewarp_equals_translation_search(search) -> None:
    reference = speckle((200, 200), seed=11)
    target = np.roll(reference, shift=(5, -6), axis=(0, 1))
    points = np.array([[100.0, 100.0], [70.0, 120.0]])
    plain = search(reference, target, points, subset=41, radius=10)
    warped = search(reference, target, points, subset=41, radius=10, prewarps=[(0, 0, 0, 0)])
    np.testing.assert_array_equal(plain.u, warped.u)
    np.testing.assert_array_equal(plain.v, warped.v)
    np.testing.assert_allclose(plain.score, warped.score, atol=1e-6)


# --------------------------------------------------------------------------------------------
# Validation


@pytest.mark.parametrize("search", SEARCHES)
def test_rejects_bad_arguments(search) -> None:
    image = speckle((100, 100))
    pts = np.array([[50.0, 50.0]])
    with pytest.raises(ValueError):
        search(image, image, pts, subset=40)
    with pytest.raises(ValueError):
        search(image, image, pts, radius=-1)
    with pytest.raises(ValueError):
        search(image, image, np.array([50.0, 50.0]))
    with pytest.raises(ValueError):
        search(image, image, pts, guess=np.zeros((2, 2)))
    with pytest.raises(ValueError):
        search(image, image, pts, prewarps=[(-2.0, 0.0, 0.0, 0.0)])
    with pytest.raises(ValueError):
        search(image[None], image, pts)


def test_lpq_window_must_fit_in_subset() -> None:
    image = speckle((100, 100))
    with pytest.raises(ValueError):
        lpq_search(image, image, np.array([[50.0, 50.0]]), subset=9, params=LPQParams(window=11))


def test_empty_point_set() -> None:
    image = speckle((100, 100))
    for search in SEARCHES:
        result = search(image, image, np.zeros((0, 2)))
        assert len(result) == 0 and result.displacement.shape == (0, 2)
