"""Bicubic B-spline interpolation on prefiltered coefficients.

A cubic B-spline interpolant passes exactly through the grey values at pixel centres and is
C2-continuous between them. Its coefficients come from a recursive prefilter over the whole
image (Unser, "Splines: a perfect fit for signal and image processing", IEEE SPM 1999); the
interpolant is then evaluated with the local 4 x 4 cubic B-spline kernel on those coefficients.
Evaluating the same 4 x 4 kernel directly on raw grey values (no prefilter) is a smoothing
approximation, not an interpolant, and leaves a periodic S-shaped bias in subpixel
displacements; the prefilter removes it.

Coefficients are computed with `scipy.ndimage.spline_filter` (order 3, mirror boundary) and
padded by `PAD` samples on each side with the same mirror symmetry, so the kernel can be
evaluated anywhere in the closed image rectangle [0, W-1] x [0, H-1] without bounds tests.

Coordinates: 0-based pixel coordinates, pixel centres at integers, x = column, y = row.
"""

from __future__ import annotations

import numba
import numpy as np
from scipy import ndimage

PAD = 3
"""Samples of mirror padding around the coefficient array."""


def spline_coefficients(image: np.ndarray) -> np.ndarray:
    """Return padded cubic B-spline coefficients of a grey image.

    Args:
        image: 2-D array (H, W) of grey values, any real dtype.

    Returns:
        float64 array (H + 2*PAD, W + 2*PAD). Coefficient of pixel (row r, col c) is at
        [r + PAD, c + PAD]; the border holds the mirror-symmetric continuation.
    """
    if image.ndim != 2:
        raise ValueError(f"expected a 2-D grey image, got shape {image.shape}")
    coefficients = ndimage.spline_filter(
        np.asarray(image, dtype=np.float64), order=3, mode="mirror", output=np.float64
    )
    return np.pad(coefficients, PAD, mode="reflect")


@numba.njit(inline="always", fastmath=False, cache=True)
def cubic_weights(t: float) -> tuple[float, float, float, float]:
    """Cubic B-spline weights of the samples at offsets -1, 0, 1, 2 for fraction t in [0, 1)."""
    s = 1.0 - t
    t2 = t * t
    t3 = t2 * t
    return (
        s * s * s / 6.0,
        (4.0 - 6.0 * t2 + 3.0 * t3) / 6.0,
        (1.0 + 3.0 * (t + t2 - t3)) / 6.0,
        t3 / 6.0,
    )


@numba.njit(inline="always", fastmath=False, cache=True)
def cubic_derivative_weights(t: float) -> tuple[float, float, float, float]:
    """Derivatives with respect to t of `cubic_weights`."""
    s = 1.0 - t
    return (
        -0.5 * s * s,
        -2.0 * t + 1.5 * t * t,
        0.5 + t - 1.5 * t * t,
        0.5 * t * t,
    )


@numba.njit(inline="always", cache=True)
def interpolate(coefficients: np.ndarray, x: float, y: float) -> float:
    """Value of the interpolant at (x, y); caller guarantees 0 <= x <= W-1, 0 <= y <= H-1."""
    ix = int(np.floor(x))
    iy = int(np.floor(y))
    wx0, wx1, wx2, wx3 = cubic_weights(x - ix)
    wy0, wy1, wy2, wy3 = cubic_weights(y - iy)
    c = ix + PAD - 1
    r = iy + PAD - 1
    row0 = (
        wx0 * coefficients[r, c]
        + wx1 * coefficients[r, c + 1]
        + wx2 * coefficients[r, c + 2]
        + wx3 * coefficients[r, c + 3]
    )
    row1 = (
        wx0 * coefficients[r + 1, c]
        + wx1 * coefficients[r + 1, c + 1]
        + wx2 * coefficients[r + 1, c + 2]
        + wx3 * coefficients[r + 1, c + 3]
    )
    row2 = (
        wx0 * coefficients[r + 2, c]
        + wx1 * coefficients[r + 2, c + 1]
        + wx2 * coefficients[r + 2, c + 2]
        + wx3 * coefficients[r + 2, c + 3]
    )
    row3 = (
        wx0 * coefficients[r + 3, c]
        + wx1 * coefficients[r + 3, c + 1]
        + wx2 * coefficients[r + 3, c + 2]
        + wx3 * coefficients[r + 3, c + 3]
    )
    return wy0 * row0 + wy1 * row1 + wy2 * row2 + wy3 * row3


@numba.njit(inline="always", cache=True)
def interpolate_with_gradient(
    coefficients: np.ndarray, x: float, y: float
) -> tuple[float, float, float]:
    """Value and gradient (d/dx, d/dy) of the interpolant at (x, y); bounds as `interpolate`."""
    ix = int(np.floor(x))
    iy = int(np.floor(y))
    tx = x - ix
    ty = y - iy
    wx = cubic_weights(tx)
    wy = cubic_weights(ty)
    dx = cubic_derivative_weights(tx)
    dy = cubic_derivative_weights(ty)
    c = ix + PAD - 1
    r = iy + PAD - 1
    value = 0.0
    gx = 0.0
    gy = 0.0
    for j in range(4):
        row_w = 0.0
        row_d = 0.0
        for i in range(4):
            coefficient = coefficients[r + j, c + i]
            row_w += wx[i] * coefficient
            row_d += dx[i] * coefficient
        value += wy[j] * row_w
        gx += wy[j] * row_d
        gy += dy[j] * row_w
    return value, gx, gy


@numba.njit(cache=True)
def _sample(coefficients, xs, ys, with_gradient, out):
    for k in range(xs.size):
        if with_gradient:
            out[0, k], out[1, k], out[2, k] = interpolate_with_gradient(coefficients, xs[k], ys[k])
        else:
            out[0, k] = interpolate(coefficients, xs[k], ys[k])


def sample(
    coefficients: np.ndarray, x: np.ndarray, y: np.ndarray, *, gradient: bool = False
) -> np.ndarray | tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Evaluate the interpolant at arbitrary points.

    Args:
        coefficients: output of `spline_coefficients` for an image (H, W).
        x, y: arrays of equal shape, 0 <= x <= W-1 and 0 <= y <= H-1.
        gradient: also return the partial derivatives.

    Returns:
        Values with the shape of x, or (values, d/dx, d/dy) when `gradient` is set.

    Raises:
        ValueError: a point lies outside the image rectangle.
    """
    xs = np.ascontiguousarray(x, dtype=np.float64).ravel()
    ys = np.ascontiguousarray(y, dtype=np.float64).ravel()
    if xs.shape != ys.shape:
        raise ValueError("x and y must have the same shape")
    height = coefficients.shape[0] - 2 * PAD
    width = coefficients.shape[1] - 2 * PAD
    if xs.size and (xs.min() < 0 or ys.min() < 0 or xs.max() > width - 1 or ys.max() > height - 1):
        raise ValueError(f"sample points outside the image rectangle {width} x {height}")
    out = np.empty((3 if gradient else 1, xs.size), dtype=np.float64)
    _sample(coefficients, xs, ys, gradient, out)
    shape = np.shape(x)
    if gradient:
        return out[0].reshape(shape), out[1].reshape(shape), out[2].reshape(shape)
    return out[0].reshape(shape)
