import numpy as np
import pytest
from scipy import ndimage

from appliance.dic.bspline import (
    PAD,
    interpolate_line,
    interpolate_row_with_gradient,
    sample,
    spline_coefficients,
)
from tests.unit.cosine_texture import CosineTexture


def test_interpolant_passes_through_samples():
    image = np.random.default_rng(3).uniform(0, 255, (40, 50))
    c = spline_coefficients(image)
    y, x = np.mgrid[0:40, 0:50].astype(float)
    np.testing.assert_allclose(sample(c, x, y), image, atol=1e-9)


def test_reproduces_cubic_polynomial_in_the_interior():
    y, x = np.mgrid[0:60, 0:60].astype(float)
    poly = lambda x, y: 0.001 * x**3 - 0.02 * x * y + 0.5 * y + 3.0  # noqa: E731
    c = spline_coefficients(poly(x, y))
    xs = np.linspace(25.0, 35.0, 37)
    ys = np.linspace(26.3, 33.9, 37)
    values, gx, gy = sample(c, xs, ys, gradient=True)
    np.testing.assert_allclose(values, poly(xs, ys), atol=1e-6)
    np.testing.assert_allclose(gx, 0.003 * xs**2 - 0.02 * ys, atol=1e-5)
    np.testing.assert_allclose(gy, -0.02 * xs + 0.5, atol=1e-5)


def test_band_limited_texture_is_interpolated_without_s_curve_bias():
    texture = CosineTexture(seed=5)
    c = spline_coefficients(texture.image(80, 80))
    fractions = np.linspace(0.0, 1.0, 21)
    xs = 40.0 + fractions
    errors = [
        np.abs(sample(c, xs, np.full_like(xs, y)) - texture(xs, np.full_like(xs, y))).max()
        for y in (30.0, 40.25, 50.5)
    ]
    spread = texture.image(80, 80).std()
    assert max(errors) < 0.01 * spread


def test_gradient_matches_finite_difference():
    c = spline_coefficients(CosineTexture(seed=8).image(50, 50))
    x = np.array([10.3, 20.7, 33.1])
    y = np.array([12.9, 25.5, 40.0])
    _, gx, gy = sample(c, x, y, gradient=True)
    h = 1e-5
    np.testing.assert_allclose(gx, (sample(c, x + h, y) - sample(c, x - h, y)) / (2 * h), atol=1e-4)
    np.testing.assert_allclose(gy, (sample(c, x, y + h) - sample(c, x, y - h)) / (2 * h), atol=1e-4)


def test_edges_are_reachable_and_outside_is_refused():
    c = spline_coefficients(np.arange(30.0 * 20).reshape(20, 30))
    assert sample(c, np.array([0.0, 29.0]), np.array([0.0, 19.0])).shape == (2,)
    with pytest.raises(ValueError, match="outside"):
        sample(c, np.array([29.5]), np.array([3.0]))


def _scipy_coefficients(image, sigma):
    """The pipeline the compiled kernel reproduces: scipy's Gaussian, spline filter, pad."""
    data = np.asarray(image, dtype=np.float64)
    if sigma > 0:
        data = ndimage.gaussian_filter(data, sigma, mode="mirror", truncate=4.0)
    filtered = ndimage.spline_filter(data, order=3, mode="mirror", output=np.float64)
    return np.pad(filtered, PAD, mode="reflect")


@pytest.mark.parametrize("sigma", [0.0, 0.1, 0.6, 0.8, 2.5])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.int16, np.float32, np.float64])
def test_coefficients_are_scipys_bit_for_bit(sigma, dtype):
    """Every shape from a single pixel up, contiguous, cut from a larger frame or transposed."""
    rng = np.random.default_rng(7)
    shapes = [(1, 1), (1, 6), (5, 1), (2, 3), (3, 2), (4, 4), (7, 3), (13, 29), (69, 149)]
    for height, width in shapes:
        frame = rng.uniform(0, 250, (height + 9, width + 11)).astype(dtype)
        for image in (
            np.ascontiguousarray(frame[:height, :width]),
            frame[4 : 4 + height, 7 : 7 + width],
            np.ascontiguousarray(frame[:width, :height]).T,
        ):
            assert np.array_equal(
                spline_coefficients(image, gaussian_sigma=sigma), _scipy_coefficients(image, sigma)
            ), (image.shape, image.strides)


def test_coefficients_refuse_bad_input():
    with pytest.raises(ValueError, match="2-D"):
        spline_coefficients(np.zeros((3, 4, 5)))
    with pytest.raises(ValueError, match="non-empty"):
        spline_coefficients(np.zeros((0, 4)))
    with pytest.raises(ValueError, match="gaussian_sigma"):
        spline_coefficients(np.zeros((4, 4)), gaussian_sigma=-1.0)


@pytest.mark.parametrize(
    "step",
    [(1.0, 0.0), (1.004, -0.003), (0.97, 0.021), (1.06, 0.03), (0.8, 0.25), (0.3, 1.1)],
)
def test_line_interpolation_is_point_interpolation_bit_for_bit(step):
    """`interpolate_line` (vectorised runs, or point by point for steep lines) gives what
    `interpolate` gives at every point, up to the image edges."""
    rng = np.random.default_rng(9)
    height, width = 60, 90
    c = spline_coefficients(rng.uniform(0, 255, (height, width)), gaussian_sigma=0.8)
    c.flags.writeable = False
    dx, dy = step
    n = 41
    scratch = np.empty((10, n))
    out = np.empty(n)
    starts = [(0.0, 10.0), (width - 1 - (n - 1) * dx, 10.0), (0.37, 0.0 if dy >= 0 else 59.0)]
    starts += [tuple(p) for p in rng.uniform([0, 5], [40, 15], (20, 2))]
    for x, y in starts:
        i = np.arange(n)
        xs, ys = x + i * dx, y + i * dy
        inside = (xs <= width - 1) & (ys >= 0) & (ys <= height - 1)
        m = n if inside.all() else int(inside.argmin())
        assert m >= 10
        interpolate_line(c, x, y, dx, dy, out[:m], scratch)
        assert np.array_equal(out[:m], sample(c, xs[:m], ys[:m])), (x, y)


def test_row_interpolation_with_gradient_is_point_interpolation_bit_for_bit():
    """`interpolate_row_with_gradient` at (x + k, y) gives what `interpolate_with_gradient`
    gives there, for fractional and integer positions up to the image edges."""
    rng = np.random.default_rng(10)
    height, width = 50, 80
    c = spline_coefficients(rng.uniform(0, 255, (height, width)), gaussian_sigma=0.8)
    c.flags.writeable = False
    half = 20
    n = 2 * half + 1
    scratch = np.empty((9, n))
    out = np.empty((3, n))
    centres = [(20.0, 20.0), (half + 0.0, 0.0), (width - 1.0 - half, height - 1.0)]
    centres += [tuple(p) for p in rng.uniform([half, 0], [width - 1 - half, height - 1], (20, 2))]
    for x, y in centres:
        interpolate_row_with_gradient(c, x, y, -half, out[0], out[1], out[2], scratch)
        xs = x + np.arange(-half, half + 1)
        expected = sample(c, xs, np.full(n, y), gradient=True)
        for got, want in zip(out, expected, strict=True):
            assert np.array_equal(got, want), (x, y)
