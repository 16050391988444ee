"""Bicubic B-spline interpolation on prefiltered coefficients.

A cubic B-spline interpolant passes exactly through the grey values at pixel centres and is
C2-continuous between them. Its coefficients come from a recursive prefilter over the whole
image (Unser, "Splines: a perfect fit for signal and image processing", IEEE SPM 1999); the
interpolant is then evaluated with the local 4 x 4 cubic B-spline kernel on those coefficients.
Evaluating the same 4 x 4 kernel directly on raw grey values (no prefilter) is a smoothing
approximation, not an interpolant, and leaves a periodic S-shaped bias in subpixel
displacements; the prefilter removes it.

Coefficients are those of `scipy.ndimage.spline_filter` (order 3, mirror boundary), padded by
`PAD` samples on each side with the same mirror symmetry, so the kernel can be evaluated
anywhere in the closed image rectangle [0, W-1] x [0, H-1] without bounds tests. They are
computed here by a compiled kernel that repeats scipy's arithmetic operation for operation
(ndimage's `ni_splines.c`; for the optional Gaussian pre-smoothing, `gaussian_filter`'s
symmetric correlation of `ni_filters.c` with its mirror line extension), so the numbers are
scipy's bit for bit (pinned by the unit tests) while the small windows of live tracking do
not pay scipy's per-call and per-line overhead: the whole pipeline (conversion to float64,
smoothing, both spline passes, padding) is one call that reads any real dtype and any strided
2-D view in place.

Coordinates: 0-based pixel coordinates, pixel centres at integers, x = column, y = row.
"""

from __future__ import annotations

import functools
import math

import numba
import numpy as np

PAD = 3
"""Samples of mirror padding around the coefficient array."""

_POLE = -0.267949192431122706472553658494127633
"""The pole sqrt(3) - 2 of the cubic B-spline filter, as scipy's `get_filter_poles` spells it."""
_GAIN = (1.0 - _POLE) * (1.0 - 1.0 / _POLE)
_INTERLEAVE = 8
"""Rows filtered together along the rows, so that their recursions overlap."""
_STEEP_LINE = 0.1
"""|dx - 1| + |dy| beyond which `interpolate_line` goes point by point: runs get too short."""


def spline_coefficients(image: np.ndarray, *, gaussian_sigma: float = 0.0) -> np.ndarray:
    """Return padded cubic B-spline coefficients of a grey image, optionally smoothed first.

    The result is, bit for bit,

        np.pad(ndimage.spline_filter(smoothed, order=3, mode="mirror"), PAD, mode="reflect")

    with `smoothed = ndimage.gaussian_filter(image.astype(float64), gaussian_sigma,
    mode="mirror", truncate=4.0)` (or the image itself when `gaussian_sigma` is 0), computed
    in one compiled call.

    Args:
        image: 2-D array (H, W) of grey values, any real dtype, any strides (a view into a
            larger frame is read in place).
        gaussian_sigma: standard deviation of the Gaussian low-pass applied before the spline
            filter, px (0 = none).

    Returns:
        float64 array (H + 2*PAD, W + 2*PAD). Coefficient of pixel (row r, col c) is at
        [r + PAD, c + PAD]; the border holds the mirror-symmetric continuation.

    The compiled call releases the GIL: other threads run while an image is prepared.
    """
    if image.ndim != 2:
        raise ValueError(f"expected a 2-D grey image, got shape {image.shape}")
    if not gaussian_sigma >= 0:
        raise ValueError(f"gaussian_sigma must be >= 0, got {gaussian_sigma}")
    if image.size == 0:
        raise ValueError(f"expected a non-empty image, got shape {image.shape}")
    height, width = image.shape
    out = np.empty((height + 2 * PAD, width + 2 * PAD))
    _coefficients(
        image,
        _gaussian_weights(float(gaussian_sigma)),
        math.pow(_POLE, height - 1),
        math.pow(_POLE, width - 1),
        out,
    )
    return out


@functools.lru_cache(maxsize=16)
def _gaussian_weights(sigma: float) -> np.ndarray:
    """`scipy.ndimage.gaussian_filter`'s kernel (truncate 4), computed as it computes it."""
    if not sigma > 1e-15:
        weights = np.zeros(0)
    else:
        radius = int(4.0 * sigma + 0.5)
        x = np.arange(-radius, radius + 1)
        phi = np.exp(-0.5 / (sigma * sigma) * x**2)
        weights = phi / phi.sum()
    weights.flags.writeable = False
    return weights


@numba.njit(inline="always", cache=True)
def _mirror(i, n):
    """Index of sample i of a line of n extended by mirror symmetry (d c b | a b c d | c b a)."""
    if n == 1:
        return 0
    period = 2 * n - 2
    i = abs(i) % period
    return period - i if i >= n else i


@numba.njit(cache=True)
def _smooth_columns(src, weights, dst):
    # dst = src correlated along axis 0; weights symmetric, summed from the outermost pair in
    # as ni_filters.c does, so the sums round alike.
    h, w = src.shape
    r = weights.size // 2
    centre = weights[r]
    for i in range(h):
        for j in range(w):
            dst[i, j] = np.float64(src[i, j]) * centre
        for k in range(r, 0, -1):
            lo = _mirror(i - k, h)
            hi = _mirror(i + k, h)
            wk = weights[r - k]
            for j in range(w):
                dst[i, j] += (np.float64(src[lo, j]) + np.float64(src[hi, j])) * wk


@numba.njit(cache=True)
def _smooth_rows(src, weights, dst):
    h, w = src.shape
    r = weights.size // 2
    centre = weights[r]
    line = np.empty(w + 2 * r)
    for i in range(h):
        for j in range(w):
            line[j + r] = src[i, j]
        for k in range(1, r + 1):
            line[r - k] = src[i, _mirror(-k, w)]
            line[r + w - 1 + k] = src[i, _mirror(w - 1 + k, w)]
        row = dst[i]
        for j in range(w):
            row[j] = line[j + r] * centre
        for k in range(r, 0, -1):
            wk = weights[r - k]
            before = line[r - k : r - k + w]
            after = line[r + k : r + k + w]
            for j in range(w):
                row[j] += (before[j] + after[j]) * wk


@numba.njit(cache=True)
def _spline_columns(c, z_n_1):
    # ni_splines.c apply_filter (one pole, mirror) on every column of c in place, the columns
    # side by side; z_n_1 = pow(z, n - 1) from the caller, as libm computes it for scipy.
    n, w = c.shape
    if n < 2:
        return
    z = _POLE
    for i in range(n):
        for j in range(w):
            c[i, j] *= _GAIN
    for j in range(w):
        c[0, j] = c[0, j] + z_n_1 * c[n - 1, j]
    z_i = z
    for i in range(1, n - 1):
        for j in range(w):
            c[0, j] += z_i * (c[i, j] + z_n_1 * c[n - 1 - i, j])
        z_i *= z
    denominator = 1 - z_n_1 * z_n_1
    for j in range(w):
        c[0, j] /= denominator
    for i in range(1, n):
        for j in range(w):
            c[i, j] += z * c[i - 1, j]
    scale = z * z - 1
    for j in range(w):
        c[n - 1, j] = (z * c[n - 2, j] + c[n - 1, j]) * z / scale
    for i in range(n - 2, -1, -1):
        for j in range(w):
            c[i, j] = z * (c[i + 1, j] - c[i, j])


@numba.njit(cache=True)
def _spline_rows(c, z_n_1):
    # The same filter along every row, _INTERLEAVE rows at a time.
    h, n = c.shape
    if n < 2:
        return
    z = _POLE
    first = np.empty(_INTERLEAVE)
    denominator = 1 - z_n_1 * z_n_1
    scale = z * z - 1
    for r0 in range(0, h, _INTERLEAVE):
        r1 = min(r0 + _INTERLEAVE, h)
        for r in range(r0, r1):
            for i in range(n):
                c[r, i] *= _GAIN
            first[r - r0] = c[r, 0] + z_n_1 * c[r, n - 1]
        z_i = z
        for i in range(1, n - 1):
            for r in range(r0, r1):
                first[r - r0] += z_i * (c[r, i] + z_n_1 * c[r, n - 1 - i])
            z_i *= z
        for r in range(r0, r1):
            c[r, 0] = first[r - r0] / denominator
        for i in range(1, n):
            for r in range(r0, r1):
                c[r, i] += z * c[r, i - 1]
        for r in range(r0, r1):
            c[r, n - 1] = (z * c[r, n - 2] + c[r, n - 1]) * z / scale
        for i in range(n - 2, -1, -1):
            for r in range(r0, r1):
                c[r, i] = z * (c[r, i + 1] - c[r, i])


@numba.njit(cache=True, nogil=True)
def _coefficients(src, weights, z_h, z_w, out):
    h, w = src.shape
    work = np.empty((h, w))
    if weights.size:
        smoothed = np.empty((h, w))
        _smooth_columns(src, weights, smoothed)
        _smooth_rows(smoothed, weights, work)
    else:
        for i in range(h):
            for j in range(w):
                work[i, j] = np.float64(src[i, j])
    _spline_columns(work, z_h)
    _spline_rows(work, z_w)
    for i in range(-PAD, h + PAD):
        row = work[_mirror(i, h)]
        for j in range(w):
            out[i + PAD, j + PAD] = row[j]
        for k in range(1, PAD + 1):
            out[i + PAD, PAD - k] = row[_mirror(-k, w)]
            out[i + PAD, PAD + w - 1 + k] = row[_mirror(w - 1 + k, w)]


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


@numba.njit(cache=True)
def interpolate_line(coefficients, x, y, dx, dy, out, scratch):
    """Values of the interpolant at (x + i dx, y + i dy), i = 0 .. out.size - 1, into `out`.

    Each value equals `interpolate` at that point bit for bit: the same operations on the
    same numbers, in an order the compiler can vectorise. The kernel weights of the whole
    line are computed first (their divisions dominate a point-by-point evaluation); then each
    run of points that shares the 4 x 4 coefficient block's row and its column offset from
    the point index (a line close to a pixel row: dx near 1, dy near 0) is combined with
    contiguous loads. Lines that cross many blocks are evaluated point by point with
    `interpolate`. Bounds as `interpolate`, for every point.

    Args:
        coefficients: output of `spline_coefficients`.
        x, y, dx, dy: start and step of the line, px.
        out: (n,) float64 output.
        scratch: (10, n) float64 work array (any contents), reused between calls.
    """
    n = out.size
    if abs(dx - 1.0) + abs(dy) > _STEEP_LINE:
        for i in range(n):
            out[i] = interpolate(coefficients, x + i * dx, y + i * dy)
        return
    for i in range(n):
        xi = x + i * dx
        yi = y + i * dy
        ix = int(np.floor(xi))
        iy = int(np.floor(yi))
        scratch[0, i], scratch[1, i], scratch[2, i], scratch[3, i] = cubic_weights(xi - ix)
        scratch[4, i], scratch[5, i], scratch[6, i], scratch[7, i] = cubic_weights(yi - iy)
        scratch[8, i] = ix + PAD - 1 - i
        scratch[9, i] = iy + PAD - 1
    stride = coefficients.shape[1]
    flat = coefficients.reshape(coefficients.size)
    start = 0
    while start < n:
        offset = scratch[8, start]
        row = scratch[9, start]
        stop = start + 1
        while stop < n and scratch[8, stop] == offset and scratch[9, stop] == row:
            stop += 1
        # Slices starting at the run, indexed from 0, so that no index can be negative and
        # the loads stay contiguous (a possibly negative index makes numba wrap it around).
        base = int(row) * stride + int(offset) + start
        c0 = flat[base:]
        c1 = flat[base + stride :]
        c2 = flat[base + 2 * stride :]
        c3 = flat[base + 3 * stride :]
        wx0 = scratch[0, start:]
        wx1 = scratch[1, start:]
        wx2 = scratch[2, start:]
        wx3 = scratch[3, start:]
        wy0 = scratch[4, start:]
        wy1 = scratch[5, start:]
        wy2 = scratch[6, start:]
        wy3 = scratch[7, start:]
        values = out[start:]
        for q in range(stop - start):
            row0 = wx0[q] * c0[q] + wx1[q] * c0[q + 1] + wx2[q] * c0[q + 2] + wx3[q] * c0[q + 3]
            row1 = wx0[q] * c1[q] + wx1[q] * c1[q + 1] + wx2[q] * c1[q + 2] + wx3[q] * c1[q + 3]
            row2 = wx0[q] * c2[q] + wx1[q] * c2[q + 1] + wx2[q] * c2[q + 2] + wx3[q] * c2[q + 3]
            row3 = wx0[q] * c3[q] + wx1[q] * c3[q + 1] + wx2[q] * c3[q + 2] + wx3[q] * c3[q + 3]
            values[q] = wy0[q] * row0 + wy1[q] * row1 + wy2[q] * row2 + wy3[q] * row3
        start = stop


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
def interpolate_row_with_gradient(coefficients, x, y, first, values, gx, gy, scratch):
    """Value and gradient of the interpolant at (x + k, y), k = first .. first + n - 1.

    The points of a subset row at pixel offsets k from (x, y); n = values.size. Each result
    equals `interpolate_with_gradient` at (x + k, y) bit for bit, computed as
    `interpolate_line` computes values: weights of the whole row first, then contiguous runs.
    Bounds as `interpolate`, for every point.

    Args:
        coefficients: output of `spline_coefficients`.
        x, y: position the offsets are added to, px; first: the first offset (an integer).
        values, gx, gy: (n,) float64 outputs: value, d/dx and d/dy.
        scratch: (9, n) float64 work array (any contents), reused between calls.
    """
    n = values.size
    iy = int(np.floor(y))
    ty = y - iy
    for i in range(n):
        xi = x + (first + i)
        ix = int(np.floor(xi))
        tx = xi - ix
        scratch[0, i], scratch[1, i], scratch[2, i], scratch[3, i] = cubic_weights(tx)
        scratch[4, i], scratch[5, i], scratch[6, i], scratch[7, i] = cubic_derivative_weights(tx)
        scratch[8, i] = ix + PAD - 1 - i
    wy = cubic_weights(ty)
    dy = cubic_derivative_weights(ty)
    stride = coefficients.shape[1]
    flat = coefficients.reshape(coefficients.size)
    top = (iy + PAD - 1) * stride
    start = 0
    while start < n:
        offset = scratch[8, start]
        stop = start + 1
        while stop < n and scratch[8, stop] == offset:
            stop += 1
        wx0 = scratch[0, start:]
        wx1 = scratch[1, start:]
        wx2 = scratch[2, start:]
        wx3 = scratch[3, start:]
        dx0 = scratch[4, start:]
        dx1 = scratch[5, start:]
        dx2 = scratch[6, start:]
        dx3 = scratch[7, start:]
        value = values[start:]
        ddx = gx[start:]
        ddy = gy[start:]
        for q in range(stop - start):
            value[q] = 0.0
            ddx[q] = 0.0
            ddy[q] = 0.0
        for j in range(4):
            c = flat[top + j * stride + int(offset) + start :]
            for q in range(stop - start):
                row_w = (
                    0.0 + wx0[q] * c[q] + wx1[q] * c[q + 1] + wx2[q] * c[q + 2] + wx3[q] * c[q + 3]
                )
                row_d = (
                    0.0 + dx0[q] * c[q] + dx1[q] * c[q + 1] + dx2[q] * c[q + 2] + dx3[q] * c[q + 3]
                )
                value[q] += wy[j] * row_w
                ddx[q] += wy[j] * row_d
                ddy[q] += dy[j] * row_w
        start = stop


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
