import numpy as np
import pytest
from scipy import ndimage

from appliance.dic.bspline import PAD
from appliance.dic.icgn import ICGN, ICGNResult, PointStatus, PreparedTarget
from tests.unit.cosine_texture import CosineTexture

SIZE = 200


def grid(start=40, stop=161, step=30):
    ys, xs = np.mgrid[start:stop:step, start:stop:step]
    return np.c_[xs.ravel(), ys.ravel()].astype(float)


def affine_inverse(u, v, ux, uy, vx, vy, centre=(100.0, 100.0)):
    """Inverse of x = X + u + ux (X - xc) + uy (Y - yc), y = Y + v + vx (X - xc) + vy (Y - yc)."""
    a = np.array([[1 + ux, uy], [vx, 1 + vy]])
    ai = np.linalg.inv(a)
    xc, yc = centre

    def inverse(x, y):
        dx = x - xc - u
        dy = y - yc - v
        return xc + ai[0, 0] * dx + ai[0, 1] * dy, yc + ai[1, 0] * dx + ai[1, 1] * dy

    return inverse


@pytest.fixture(scope="module")
def texture():
    return CosineTexture(seed=11)


@pytest.mark.parametrize("shift", [(0.1, -0.7), (0.5, 0.5), (0.83, 0.27), (1.4, -2.2)])
def test_recovers_subpixel_translation(texture, shift):
    du, dv = shift
    reference = texture.image(SIZE, SIZE)
    target = texture.image(SIZE, SIZE, inverse=lambda x, y: (x - du, y - dv))
    icgn = ICGN(subset=31)
    icgn.prepare(reference, grid())
    result = icgn.compute(target, np.tile(np.round(shift), (25, 1)))
    assert np.all(result.status == PointStatus.CONVERGED)
    np.testing.assert_allclose(result.u, du, atol=2e-3)
    np.testing.assert_allclose(result.v, dv, atol=2e-3)
    assert result.zncc.min() > 0.9999


def test_recovers_affine_deformation_with_gradients(texture):
    p = dict(u=0.6, v=-1.3, ux=0.02, uy=-0.015, vx=0.01, vy=-0.03)
    reference = texture.image(SIZE, SIZE)
    target = texture.image(SIZE, SIZE, inverse=affine_inverse(**p))
    points = grid()
    icgn = ICGN(subset=41)
    icgn.prepare(reference, points)
    dx = points[:, 0] - 100.0
    dy = points[:, 1] - 100.0
    true_u = p["u"] + p["ux"] * dx + p["uy"] * dy
    true_v = p["v"] + p["vx"] * dx + p["vy"] * dy
    guess = np.c_[np.round(true_u), np.round(true_v)]
    result = icgn.compute(target, guess)
    assert np.all(result.ok())
    np.testing.assert_allclose(result.u, true_u, atol=3e-3)
    np.testing.assert_allclose(result.v, true_v, atol=3e-3)
    for name in ("ux", "uy", "vx", "vy"):
        np.testing.assert_allclose(getattr(result, name), p[name], atol=2e-4)


def test_subpixel_points_of_interest(texture):
    reference = texture.image(SIZE, SIZE)
    target = texture.image(SIZE, SIZE, inverse=lambda x, y: (x - 0.35, y + 0.6))
    icgn = ICGN(subset=31)
    icgn.prepare(reference, grid() + np.array([0.37, -0.21]))
    result = icgn.compute(target)
    assert np.all(result.ok())
    np.testing.assert_allclose(result.u, 0.35, atol=2e-3)
    np.testing.assert_allclose(result.v, -0.6, atol=2e-3)


def test_batch_equals_single_points_and_thread_count_does_not_matter(texture):
    reference = texture.image(SIZE, SIZE)
    target = texture.image(SIZE, SIZE, inverse=affine_inverse(0.3, 0.2, 0.01, 0, 0, 0.005))
    points = grid(step=20)
    batch = ICGN(subset=21, threads=2)
    batch.prepare(reference, points)
    together = batch.compute(target)
    single = ICGN(subset=21, threads=1)
    single.prepare(reference, points)
    assert np.array_equal(single.compute(target).u, together.u)
    for k in (0, 7, len(points) - 1):
        one = ICGN(subset=21, threads=1)
        one.prepare(reference, points[k : k + 1])
        alone = one.compute(target)
        assert alone.u[0] == together.u[k] and alone.vy[0] == together.vy[k]
        assert alone.iterations[0] == together.iterations[k]


def test_statuses(texture):
    reference = texture.image(SIZE, SIZE)
    reference[120:181, 120:181] = 77.0
    points = np.array([[100.0, 100.0], [5.0, 100.0], [150.0, 150.0], [100.0, 60.0], [60.0, 100.0]])
    target = texture.image(SIZE, SIZE, inverse=lambda x, y: (x - 0.4, y))
    icgn = ICGN(subset=21)
    prepared = icgn.prepare(reference, points)
    assert prepared[1] == PointStatus.OUT_OF_IMAGE
    assert prepared[2] == PointStatus.FLAT_SUBSET
    guess = np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, -55.0], [0.0, 0.0]])
    result = icgn.compute(target, guess)
    assert result.status[0] == PointStatus.CONVERGED
    assert result.status[1] == PointStatus.OUT_OF_IMAGE
    assert result.status[2] == PointStatus.FLAT_SUBSET
    assert result.status[3] == PointStatus.OUT_OF_IMAGE
    assert np.isnan(result.zncc[1]) and np.isnan(result.zncc[2])
    capped = ICGN(subset=21, max_iterations=1, znssd_tolerance=0, step_tolerance=0)
    capped.prepare(reference, points[:1])
    out = capped.compute(target)
    assert out.status[0] == PointStatus.MAX_ITERATIONS and out.iterations[0] == 1


def test_far_wrong_guess_does_not_report_convergence_to_truth(texture):
    reference = texture.image(SIZE, SIZE)
    flat_target = np.full((SIZE, SIZE), 90.0)
    icgn = ICGN(subset=21)
    icgn.prepare(reference, grid(step=60))
    result = icgn.compute(flat_target)
    assert np.all(result.status == PointStatus.DIVERGED)


def test_noise_prefilter_is_applied_to_both_images(texture):
    rng = np.random.default_rng(2)
    reference = texture.image(SIZE, SIZE) + rng.normal(0, 3, (SIZE, SIZE))
    target = texture.image(SIZE, SIZE, inverse=lambda x, y: (x - 0.5, y)) + rng.normal(
        0, 3, (SIZE, SIZE)
    )
    icgn = ICGN(subset=41, prefilter_sigma=0.8)
    icgn.prepare(reference, grid())
    result = icgn.compute(target)
    assert np.all(result.ok())
    assert abs(result.u.mean() - 0.5) < 0.01


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="subset"):
        ICGN(subset=40)
    icgn = ICGN(subset=11)
    with pytest.raises(RuntimeError, match="prepare"):
        icgn.compute(np.zeros((30, 30)))
    icgn.prepare(np.random.default_rng(0).uniform(size=(30, 30)), np.array([[15.0, 15.0]]))
    with pytest.raises(ValueError, match="shape"):
        icgn.compute(np.zeros((31, 30)))
    with pytest.raises(ValueError, match="guess"):
        icgn.compute(np.zeros((30, 30)), np.zeros((2, 2)))


FIELDS = ("u", "v", "ux", "uy", "vx", "vy", "zncc", "iterations", "status")


def assert_rows_identical(part: ICGNResult, whole: ICGNResult, rows: np.ndarray) -> None:
    """Every field of `part` equals rows `rows` of `whole` bit for bit (NaN matching NaN)."""
    for name in FIELDS:
        a, b = getattr(part, name), getattr(whole, name)[rows]
        assert a.dtype == b.dtype, name
        assert np.array_equal(a, b, equal_nan=True), name


@pytest.fixture(scope="module")
def deformed_pair(texture):
    """Reference, affinely deformed target and 49 points, a few of them out of the image."""
    reference = texture.image(SIZE, SIZE)
    target = texture.image(
        SIZE, SIZE, inverse=affine_inverse(0.7, -0.4, 0.012, -0.006, 0.004, -0.01)
    )
    points = np.r_[grid(start=30, stop=171, step=20), [[4.0, 100.0], [100.0, 196.0]]]
    return reference, target, points


@pytest.mark.parametrize("prefilter_sigma", [0.0, 0.8])
def test_prepared_target_gives_the_image_result_bit_for_bit(deformed_pair, prefilter_sigma):
    reference, target, points = deformed_pair
    icgn = ICGN(subset=21, prefilter_sigma=prefilter_sigma)
    icgn.prepare(reference, points)
    guess = np.tile([1.0, 0.0], (len(points), 1))
    from_image = icgn.compute(target, guess)
    prepared = icgn.prepare_target(target)
    assert isinstance(prepared, PreparedTarget)
    assert prepared.shape == (SIZE, SIZE) and prepared.prefilter_sigma == prefilter_sigma
    assert not prepared.coefficients.flags.writeable
    assert np.array_equal(prepared.coefficients, icgn.coefficients(target))
    assert_rows_identical(icgn.compute(prepared, guess), from_image, np.arange(len(points)))
    assert from_image.ok().sum() == len(points) - 2
    assert np.all(from_image.status[-2:] == PointStatus.OUT_OF_IMAGE)


def test_indices_refine_any_subset_bit_for_bit(deformed_pair):
    """Subsets, any order and repeats give the rows of the full computation exactly."""
    reference, target, points = deformed_pair
    rng = np.random.default_rng(4)
    n = len(points)
    guess = np.c_[rng.integers(0, 2, (n, 2)), rng.normal(0.0, 0.01, (n, 4))]
    icgn = ICGN(subset=21, threads=2)
    icgn.prepare(reference, points)
    prepared = icgn.prepare_target(target)
    whole = icgn.compute(prepared, guess)
    assert whole.ok().sum() == n - 2
    for rows in (
        np.array([3]),
        np.array([n - 1, 0, 17, 17, n - 2, 5]),
        rng.permutation(n),
        np.arange(0, n, 7, dtype=np.int32),
    ):
        assert_rows_identical(icgn.compute(prepared, guess[rows], indices=rows), whole, rows)
        single = ICGN(subset=21, threads=1)
        single.prepare(reference, points)
        assert_rows_identical(single.compute(target, guess[rows], indices=rows), whole, rows)
    translation = icgn.compute(prepared, guess[[8, 2], :2], indices=[8, 2])
    assert_rows_identical(translation, icgn.compute(prepared, guess[:, :2]), np.array([8, 2]))
    empty = icgn.compute(prepared, np.zeros((0, 6)), indices=np.zeros(0, dtype=int))
    assert empty.u.shape == (0,) and empty.status.shape == (0,)


def test_prefilter_and_spline_are_scipys_bit_for_bit(deformed_pair):
    _, target, _ = deformed_pair
    smoothed = ndimage.gaussian_filter(target, 0.8, mode="mirror", truncate=4.0)
    expected = np.pad(ndimage.spline_filter(smoothed, order=3, mode="mirror"), PAD, mode="reflect")
    assert np.array_equal(ICGN(prefilter_sigma=0.8).coefficients(target), expected)


def test_serial_and_parallel_kernels_agree_bit_for_bit(deformed_pair):
    """One thread runs the serial kernels, two the parallel ones; small batches go serial."""
    reference, target, points = deformed_pair
    rng = np.random.default_rng(8)
    guess = np.c_[rng.integers(0, 2, (len(points), 2)), rng.normal(0.0, 0.01, (len(points), 4))]
    results = []
    for threads in (1, 2, None):
        icgn = ICGN(subset=21, prefilter_sigma=0.8, threads=threads)
        results.append((icgn.prepare(reference, points), icgn.compute(target, guess)))
        for row in (np.array([5]), np.array([6, 2])):
            assert_rows_identical(icgn.compute(target, guess[row], indices=row), results[0][1], row)
    for status, result in results[1:]:
        assert np.array_equal(status, results[0][0])
        assert_rows_identical(result, results[0][1], np.arange(len(points)))


def test_one_prepared_target_serves_every_icgn_with_its_prefilter(deformed_pair):
    reference, target, points = deformed_pair
    first = ICGN(subset=21, prefilter_sigma=0.8)
    first.prepare(reference, points[:10])
    second = ICGN(subset=31, prefilter_sigma=0.8)
    second.prepare(reference, points[10:30])
    prepared = first.prepare_target(target)
    assert_rows_identical(second.compute(prepared), second.compute(target), np.arange(20))
    other = ICGN(subset=21)
    other.prepare(reference, points[:10])
    with pytest.raises(ValueError, match="prefilter_sigma"):
        other.compute(prepared)


def test_prepared_points_are_a_read_only_copy():
    icgn = ICGN(subset=11)
    with pytest.raises(RuntimeError, match="prepare"):
        _ = icgn.points
    points = np.array([[15.0, 15.0], [14.5, 16.0]])
    icgn.prepare(np.random.default_rng(0).uniform(size=(30, 30)), points)
    points[0, 0] = 99.0
    assert np.array_equal(icgn.points, [[15.0, 15.0], [14.5, 16.0]])
    assert not icgn.points.flags.writeable


def test_bad_targets_and_indices_are_named():
    rng = np.random.default_rng(0)
    icgn = ICGN(subset=11)
    icgn.prepare(rng.uniform(size=(30, 30)), np.array([[15.0, 15.0], [12.0, 14.0]]))
    with pytest.raises(ValueError, match="2-D"):
        icgn.prepare_target(np.zeros((3, 30, 30)))
    with pytest.raises(ValueError, match="shape"):
        icgn.compute(icgn.prepare_target(np.zeros((31, 30))))
    target = icgn.prepare_target(rng.uniform(size=(30, 30)))
    for bad in ([2], [-1], [0.0], [[0]], np.array([True, False])):
        with pytest.raises(ValueError, match="indices"):
            icgn.compute(target, indices=bad)
    with pytest.raises(ValueError, match=r"guess must have shape \(1, 2\)"):
        icgn.compute(target, np.zeros((2, 2)), indices=[1])
