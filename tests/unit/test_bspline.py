import numpy as np
import pytest

from appliance.dic.bspline import sample, spline_coefficients
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
