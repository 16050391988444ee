"""The batched integer searches give the per-point searches' peaks.

`zncc_search` (one `cv2.matchTemplate` per point) is the plain path; `ZNCCSearch` the batched
one. Their numerators are rounded differently (both float32), so peaks, validity and pre-warps
must be identical and the scores and reliabilities agree within a stated tolerance.
"""

from __future__ import annotations

import numba
import numpy as np
import pytest

from appliance.dic.batched_search import ZNCCSearch, dft_tile_size, zncc_search_batched
from appliance.dic.integer_search import IntegerMatch, chi_square_map, lpq_search, zncc_search
from appliance.dic.lpq import code_histogram, lpq_codes
from tests.unit.test_integer_search import affine_target, grid_points, speckle

SCORE_TOLERANCE = 1e-5
RELIABILITY_TOLERANCE = 1e-4


def assert_same_peaks(plain: IntegerMatch, batched: IntegerMatch) -> None:
    np.testing.assert_array_equal(batched.valid, plain.valid)
    np.testing.assert_array_equal(batched.u, plain.u)
    np.testing.assert_array_equal(batched.v, plain.v)
    np.testing.assert_array_equal(batched.gradient, plain.gradient)
    valid = plain.valid
    np.testing.assert_allclose(
        batched.score[valid], plain.score[valid], rtol=0, atol=SCORE_TOLERANCE
    )
    assert np.all(np.isnan(batched.score[~valid]))
    np.testing.assert_allclose(
        batched.reliability, plain.reliability, rtol=0, atol=RELIABILITY_TOLERANCE
    )


@pytest.fixture(scope="module")
def pair() -> tuple[np.ndarray, np.ndarray]:
    reference = speckle((260, 300), seed=3)
    target = affine_target(reference, np.eye(2), np.array([3.4, -5.6]))
    return reference, target


@pytest.mark.parametrize("subset, radius", [(21, 5), (31, 12), (41, 30)])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float64])
def test_same_peaks_as_the_per_point_search(pair, subset, radius, dtype) -> None:
    reference, target = pair
    if dtype is np.uint16:
        reference, target = reference * 200, target * 200
    reference = np.clip(reference, 0, np.iinfo(dtype).max if dtype != np.float64 else 1e9)
    target = np.clip(target, 0, np.iinfo(dtype).max if dtype != np.float64 else 1e9)
    reference, target = reference.astype(dtype), target.astype(dtype)
    points = grid_points(subset, 300 - subset, 7, jitter=3.0, seed=subset)
    points[:, 1] = np.clip(points[:, 1], subset // 2, 259 - subset // 2)
    guess = np.tile([3.0, -6.0], (len(points), 1))
    plain = zncc_search(reference, target, points, subset=subset, radius=radius, guess=guess)
    batched = zncc_search_batched(
        reference, target, points, subset=subset, radius=radius, guess=guess
    )
    assert plain.valid.all()
    assert_same_peaks(plain, batched)
    assert np.abs(plain.u - 3).max() <= 1 and np.abs(plain.v + 6).max() <= 1


def test_windows_clipped_by_the_border_and_subsets_outside(pair) -> None:
    reference, target = pair
    points = np.array(
        [[10.0, 10.0], [25.0, 130.0], [289.0, 249.0], [150.0, 20.0], [150.0, 3.0], [299.0, 5.0]]
    )
    guess = np.array([[-12.0, -12.0], [-12.0, 0.0], [8.0, 8.0], [0.0, -15.0], [0, 0], [0, 0]])
    plain = zncc_search(reference, target, points, subset=21, radius=15, guess=guess)
    batched = zncc_search_batched(reference, target, points, subset=21, radius=15, guess=guess)
    assert plain.valid.tolist() == [True, True, True, True, False, False]
    assert_same_peaks(plain, batched)


def test_flat_reference_subsets_and_flat_target_windows() -> None:
    reference = speckle((200, 200), seed=8)
    reference[20:80, 20:80] = 77.0
    target = affine_target(reference, np.eye(2), np.array([1.0, 2.0]))
    target[120:190, 120:190] = 200.0
    points = np.array([[50.0, 50.0], [155.0, 155.0], [100.0, 100.0], [60.0, 150.0]])
    plain = zncc_search(reference, target, points, subset=21, radius=6)
    batched = zncc_search_batched(reference, target, points, subset=21, radius=6)
    assert plain.score[0] == 1.0 and plain.reliability[0] == 0.0
    assert_same_peaks(plain, batched)


def test_prewarps_choose_the_same_warp(pair) -> None:
    reference, _ = pair
    stretch = np.array([[1.0, 0.0], [0.0, 1.25]])
    target = affine_target(reference, stretch, np.array([0.0, -30.0]))
    points = grid_points(60, 240, 5, jitter=0.0, seed=1)
    points[:, 1] = np.clip(points[:, 1], 40, 200)
    guess = np.column_stack([np.zeros(len(points)), 0.25 * points[:, 1] - 30.0])
    warps = [(0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.12), (0.0, 0.0, 0.0, 0.25)]
    plain = zncc_search(reference, target, points, subset=31, radius=8, guess=guess, prewarps=warps)
    batched = zncc_search_batched(
        reference, target, points, subset=31, radius=8, guess=guess, prewarps=warps
    )
    assert (plain.vy > 0).any()
    assert_same_peaks(plain, batched)


def test_threads_and_prepared_reference_give_the_same_numbers(pair) -> None:
    reference, target = pair
    other = affine_target(reference, np.eye(2), np.array([-7.2, 2.1]))
    points = grid_points(30, 230, 12, jitter=2.0, seed=4)
    one = ZNCCSearch(subset=21, radius=9, threads=1)
    many = ZNCCSearch(subset=21, radius=9, threads=2)
    one.prepare(reference, points)
    many.prepare(reference, points)
    guesses = [np.tile([3.0, -6.0], (len(points), 1)), np.tile([-7.0, 2.0], (len(points), 1))]
    for image, guess in zip([target, other, target], guesses + guesses[:1], strict=True):
        a, b = one.search(image, guess), many.search(image, guess)
        fresh = zncc_search_batched(reference, image, points, subset=21, radius=9, guess=guess)
        for result in (b, fresh):
            for name in ("u", "v", "score", "reliability", "valid"):
                np.testing.assert_array_equal(getattr(result, name), getattr(a, name))


def test_search_before_prepare_and_bad_arguments_are_refused() -> None:
    with pytest.raises(RuntimeError):
        ZNCCSearch().search(np.zeros((50, 50)))
    with pytest.raises(ValueError):
        ZNCCSearch(subset=20)
    with pytest.raises(ValueError):
        ZNCCSearch(radius=-1)


@pytest.mark.parametrize("threads", [1, 2])
def test_lpq_search_of_all_points_at_once_is_the_per_point_composition(pair, threads) -> None:
    """LPQ's maps are sums of exact integers: the one-pass search must equal, bit for bit,
    each point's map built from the public pieces (code image, histogram, chi-square map)."""
    reference, target = pair
    subset, radius, half = 21, 7, 10
    points = np.vstack(
        [grid_points(30, 230, 6, jitter=2.0, seed=2), [[12.0, 11.0], [289.0, 200.0]]]
    )
    guess = np.tile([3.0, -6.0], (len(points), 1))
    guess[-2:] = [[-5.0, -5.0], [5.0, 0.0]]
    saved = numba.get_num_threads()
    numba.set_num_threads(threads)
    try:
        found = lpq_search(reference, target, points, subset=subset, radius=radius, guess=guess)
    finally:
        numba.set_num_threads(saved)
    target_codes, reference_codes = lpq_codes(target), lpq_codes(reference)
    assert found.valid.all()
    for k, ((x, y), (gu, gv)) in enumerate(zip(points, guess, strict=True)):
        cx, cy = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
        x_lo, x_hi = max(cx + int(gu) - radius, half), min(cx + int(gu) + radius, 299 - half)
        y_lo, y_hi = max(cy + int(gv) - radius, half), min(cy + int(gv) + radius, 259 - half)
        region = target_codes[y_lo - half : y_hi + half + 1, x_lo - half : x_hi + half + 1]
        counts = code_histogram(
            reference_codes[cy - half : cy + half + 1, cx - half : cx + half + 1]
        )
        cost = chi_square_map(region, counts, subset)
        bi, bj = divmod(int(np.argmin(cost)), cost.shape[1])
        assert (found.u[k], found.v[k]) == (x_lo + bj - cx, y_lo + bi - cy)
        assert found.score[k] == cost.min()


def test_the_transform_tile_is_the_smallest_fast_size_that_holds_the_window():
    """A multiple of 16 whose quotient by 16 has no prime factor beyond 5, the smallest that
    holds the window: 80 for the 73 px window of a coarse search (OpenCV's choice was 75)."""

    def fast(size):
        if size < 16 or size % 16:
            return False
        rest = size // 16
        for prime in (2, 3, 5):
            while rest % prime == 0:
                rest //= prime
        return rest == 1

    for window in range(1, 600):
        size = dft_tile_size(window)
        assert size >= window and fast(size), window
        assert not any(fast(smaller) for smaller in range(window, size)), window
    assert [dft_tile_size(w) for w in (47, 61, 73, 81, 101)] == [48, 64, 80, 96, 128]
