"""Integer-pixel subset search: LPQ histograms compared by chi-square, and ZNCC.

The integer search gives IC-GN its starting point. ``lpq_search`` follows Zhang et al. 2016
("Image matching based on local phase quantization applied for measuring the tensile properties
of high elongation materials", Math. Probl. Eng., article 5182106): every candidate subset of the
target is described by the 256-bin histogram of its LPQ codes (``appliance.dic.lpq``) and
compared with the reference subset's histogram by the chi-square distance, which keeps working
under the centrally symmetric motion blur of a fast test. ``zncc_search`` is the conventional
zero-normalised cross-correlation baseline (``cv2.matchTemplate``).

Conventions
-----------
Images are 2-D arrays ``[row, col] = [y, x]``; 0-based pixel coordinates with pixel centres at
integers, x right and y down. ``points`` is a float64 ``(n, 2)`` array of ``(x, y)`` positions in
the reference image. The reference subset of a point is the ``S x S`` block (``S`` odd) centred at
``(round(x), round(y))``, where ``round(z) = floor(z + 0.5)``. Displacements ``(u, v)`` are target
position minus reference position, in px. A candidate is a target block centred at
``(round(x) + u, round(y) + v)`` with ``|u - gu| <= radius`` and ``|v - gv| <= radius`` around the
rounded guess ``(gu, gv)``, restricted to blocks lying entirely inside the target image.

Choosing a method
-----------------
Measured on synthetic speckle (noise smoothed by a Gaussian of sigma 1.5 to 3 px, sensor noise of
sigma 2 grey levels, subset 41, radius 40, 96 points per case, success = within 1 px of the truth):

* ``zncc_search``: 98 to 100 % on the undisturbed pair and under a 10 px centred line blur
  along x, y or a diagonal, a contrast change ``0.6 I + 40``, a brightness gradient or a
  low-contrast texture;
  51 % on a one-step 30 % stretch, 100 % with pre-warps.
* ``lpq_search`` with the default 7 px window: 93 to 96 % without blur (also under the
  contrast change and the gradient), 3 to 7 % under 10 px blur, 1 % on the low-contrast texture;
  with a 15 px window: 100 %, 42 to 54 %, 79 %; with pre-warps 95 % (7 px) and 100 % (15 px) on
  the 30 % stretch.

A centred symmetric blur lowers the ZNCC peak without moving it, so ZNCC remains the more robust
integer search; LPQ needs a window of about three times the blur length
(``appliance.dic.lpq``; in the accuracy benchmark a window of 3 L found 86 to 100 % of the
points under blur L up to 10 px, against 0 to 8 % for the 7 px window at 8 and 10 px).
Combining the two (LPQ's best separated minima confirmed by ZNCC around each, ZNCC's best peaks
re-ranked by chi-square, or the sum of both normalised cost maps) was not better than ZNCC alone
in any of these cases nor under 20 px blur, strong noise or glare, so no combined search is
offered.

Reliability
-----------
Both searches turn their score map into a cost map ``c >= 0`` over the candidate grid, with 0 for
a perfect match (chi-square for LPQ, ``1 - ZNCC`` for ZNCC), and report a ratio test between the
best minimum and the best *separated* one. With ``c1`` the global minimum and ``m`` the mean of
the map (the typical cost of a wrong candidate):

* if ``m <= c1`` (flat map) the reliability is 0;
* the basin of the best candidate is the 8-connected set of candidates reachable from it through
  candidates with ``c <= (c1 + m) / 2`` (the half-depth region of the winning minimum);
* ``c2`` is the lowest cost among the local minima (cost ``<=`` all 8-neighbours inside the grid)
  outside that basin, or ``m`` if none is lower than ``m``;
* ``reliability = clip(1 - c1 / c2, 0, 1)`` (0 when ``c2 = 0``).

0 means that a separated minimum is as good as the winner (periodic texture) or that the winner
is no better than the rest (flat or unrelated subset); values near 1 mean a near-perfect match
whose competitors all cost much more. Unlike a nearest-neighbour ratio on the raw map, the basin
keeps the winner's own neighbours (a histogram match degrades gradually over about a subset
width) from counting as competitors.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numba import get_num_threads, njit, prange

from .lpq import N_BINS, LPQParams, lpq_codes

__all__ = [
    "IntegerMatch",
    "chi_square_map",
    "lpq_search",
    "zncc_search",
]

_MIN_BAND_ROWS = 16
_DEFAULT_LPQ = LPQParams()


@dataclass(frozen=True, eq=False)
class IntegerMatch:
    """Integer-pixel search result for ``n`` points.

    Attributes:
        u, v: int64 ``(n,)`` displacement in px (target minus reference) along x and y; 0 where
            ``valid`` is False.
        score: float64 ``(n,)`` matching score of the winner: chi-square distance between
            normalised histograms (0 = identical, 2 = disjoint) for LPQ, ZNCC in [-1, 1] for
            ZNCC; NaN where not valid.
        reliability: float64 ``(n,)`` in [0, 1], 0 ambiguous and 1 unique (see the module
            docstring for the exact definition); 0 where not valid.
        valid: bool ``(n,)``; False when the reference subset is not entirely inside the
            reference image or no candidate block of the search window lies inside the target.
        ux, uy, vx, vy: float64 ``(n,)`` displacement gradients (du/dx, du/dy, dv/dx, dv/dy) of
            the winning pre-warp; zeros for a translation-only search or where not valid.
    """

    u: np.ndarray
    v: np.ndarray
    score: np.ndarray
    reliability: np.ndarray
    valid: np.ndarray
    ux: np.ndarray
    uy: np.ndarray
    vx: np.ndarray
    vy: np.ndarray

    @property
    def displacement(self) -> np.ndarray:
        """float64 ``(n, 2)`` array of ``(u, v)`` in px."""
        return np.stack([self.u, self.v], axis=1).astype(np.float64)

    @property
    def gradient(self) -> np.ndarray:
        """float64 ``(n, 4)`` array of ``(ux, uy, vx, vy)``."""
        return np.stack([self.ux, self.uy, self.vx, self.vy], axis=1)

    def __len__(self) -> int:
        return int(self.u.shape[0])


# ---------------------------------------------------------------------------------------------
# Numba kernels


@njit(cache=True)
def _chi_term(ref: int, count: int, weight: float, scale: float) -> np.int64:
    den = ref + count
    if den == 0:
        return np.int64(0)
    diff = ref - count
    return np.int64(np.floor(weight * (diff * diff) / den * scale + 0.5))


@njit(cache=True)
def _chi_table(codes, subset, ref_counts, weights, scale):
    """Fixed-point chi-square term differences for every bin and reachable count.

    ``delta[offsets[b] + h] = T_b(h + 1) - T_b(h)`` with ``T_b(h)`` the bin's term
    ``w_b (r_b - h)**2 / (r_b + h)`` in units of ``1 / scale`` (rounded to int64; 0 when
    ``r_b + h = 0``), for ``h`` below the smaller of the block area and the bin's count in
    ``codes`` (no block can hold more). ``base = sum_b T_b(0)`` is the total of an empty block.
    """
    region = np.zeros(256, dtype=np.int64)
    rows, cols = codes.shape
    for i in range(rows):
        for j in range(cols):
            region[codes[i, j]] += 1
    area = subset * subset
    offsets = np.empty(257, dtype=np.int64)
    offsets[0] = 0
    for b in range(256):
        offsets[b + 1] = offsets[b] + min(region[b], area)
    delta = np.empty(max(offsets[256], 1), dtype=np.int64)
    base = np.int64(0)
    for b in range(256):
        ref = ref_counts[b]
        wb = weights[b]
        prev = _chi_term(ref, 0, wb, scale)
        base += prev
        start = offsets[b]
        for h in range(offsets[b + 1] - start):
            nxt = _chi_term(ref, h + 1, wb, scale)
            delta[start + h] = nxt - prev
            prev = nxt
    return delta, offsets, base


@njit(cache=True)
def _slide(leaving, entering, ptr, delta):
    """Fixed-point change of the total when ``leaving`` codes go and ``entering`` codes come.

    ``ptr[b]`` (uint32, so that indexing needs no negative-index handling) is the position of
    bin ``b``'s current count in ``delta``.
    """
    one = np.uint32(1)
    removed = np.int64(0)
    for k in range(leaving.shape[0]):
        b = leaving[k]
        q = ptr[b] - one
        ptr[b] = q
        removed += delta[q]
    added = np.int64(0)
    for k in range(entering.shape[0]):
        b = entering[k]
        q = ptr[b]
        ptr[b] = q + one
        added += delta[q]
    return added - removed


@njit(cache=True)
def _chi_band(codes, codes_t, subset, delta, offsets, base, inv, out, first, stop):
    """Rows ``first:stop`` of the chi-square map, along a boustrophedon path.

    Each one-pixel step removes the codes of the column (or row) leaving the block and adds
    those entering it: ``2 * subset`` bin updates, each one table load and one integer add.
    """
    ptr = offsets[:256].astype(np.uint32)
    total = base
    for i in range(first, first + subset):
        for j in range(subset):
            b = codes[i, j]
            total += delta[ptr[b]]
            ptr[b] += np.uint32(1)
    n_cols = codes.shape[1] - subset + 1
    j = 0
    for i in range(first, stop):
        if i > first:
            total += _slide(
                codes[i - 1, j : j + subset], codes[i + subset - 1, j : j + subset], ptr, delta
            )
        out[i, j] = total * inv
        forward = (i - first) % 2 == 0
        for _ in range(n_cols - 1):
            if forward:
                total += _slide(
                    codes_t[j, i : i + subset], codes_t[j + subset, i : i + subset], ptr, delta
                )
                j += 1
            else:
                total += _slide(
                    codes_t[j + subset - 1, i : i + subset],
                    codes_t[j - 1, i : i + subset],
                    ptr,
                    delta,
                )
                j -= 1
            out[i, j] = total * inv


@njit(cache=True, parallel=True)
def _chi_square_map_kernel(codes, codes_t, subset, ref_counts, weights, scale, out, n_bands):
    """Chi-square of every ``subset x subset`` block of ``codes`` against ``ref_counts``.

    ``out[i, j]`` receives the chi-square of the block with top-left ``(i, j)`` divided by
    ``subset**2`` (i.e. between normalised histograms). The rows of ``out`` are split into
    ``n_bands`` bands, each slid independently (in parallel). The running total is a sum of
    exact integers, so the result does not depend on the path or the banding.
    """
    delta, offsets, base = _chi_table(codes, subset, ref_counts, weights, scale)
    inv = 1.0 / (scale * subset * subset)
    n_rows = out.shape[0]
    for band in prange(n_bands):
        first = band * n_rows // n_bands
        stop = (band + 1) * n_rows // n_bands
        if stop > first:
            _chi_band(codes, codes_t, subset, delta, offsets, base, inv, out, first, stop)


@njit(cache=True)
def _chi_square_map_serial(codes, codes_t, subset, ref_counts, weights, scale, out):
    """Single-band ``_chi_square_map_kernel`` without the parallel launch."""
    delta, offsets, base = _chi_table(codes, subset, ref_counts, weights, scale)
    inv = 1.0 / (scale * subset * subset)
    _chi_band(codes, codes_t, subset, delta, offsets, base, inv, out, 0, out.shape[0])


@njit(cache=True)
def _reliability_kernel(cost, bi, bj):
    """Reliability of the minimum at ``(bi, bj)`` of ``cost``; see the module docstring."""
    rows, cols = cost.shape
    c1 = cost[bi, bj]
    mean = np.mean(cost)
    depth = mean - c1
    if not depth > 0.0:
        return 0.0
    level = c1 + 0.5 * depth
    basin = np.zeros((rows, cols), dtype=np.bool_)
    stack = np.empty(rows * cols, dtype=np.int64)
    basin[bi, bj] = True
    stack[0] = bi * cols + bj
    top = 1
    while top > 0:
        top -= 1
        i = stack[top] // cols
        j = stack[top] % cols
        for di in range(-1, 2):
            for dj in range(-1, 2):
                ii = i + di
                jj = j + dj
                if 0 <= ii < rows and 0 <= jj < cols and not basin[ii, jj]:
                    if cost[ii, jj] <= level:
                        basin[ii, jj] = True
                        stack[top] = ii * cols + jj
                        top += 1
    c2 = mean
    for i in range(rows):
        for j in range(cols):
            cij = cost[i, j]
            if basin[i, j] or cij >= c2:
                continue
            is_min = True
            for di in range(-1, 2):
                for dj in range(-1, 2):
                    ii = i + di
                    jj = j + dj
                    if 0 <= ii < rows and 0 <= jj < cols and cost[ii, jj] < cij:
                        is_min = False
            if is_min:
                c2 = cij
    if not c2 > 0.0:
        return 0.0
    return min(max(1.0 - c1 / c2, 0.0), 1.0)


@njit(cache=True)
def _lpq_point(
    k, codes, codes_t, offsets, shapes, subset, ref_counts, weights, scale, maps, map_offsets, best
):
    rows, cols = shapes[k, 0], shapes[k, 1]
    region = codes[offsets[k] : offsets[k] + rows * cols].reshape((rows, cols))
    region_t = codes_t[offsets[k] : offsets[k] + rows * cols].reshape((cols, rows))
    map_rows, map_cols = rows - subset + 1, cols - subset + 1
    cost = maps[map_offsets[k] : map_offsets[k] + map_rows * map_cols].reshape((map_rows, map_cols))
    _chi_square_map_serial(region, region_t, subset, ref_counts[k], weights, scale, cost)
    flat = np.argmin(cost)
    bi, bj = flat // map_cols, flat % map_cols
    best[k, 0] = cost[bi, bj]
    best[k, 1] = _reliability_kernel(cost, bi, bj)
    best[k, 2] = bi
    best[k, 3] = bj


@njit(cache=True, parallel=True)
def _lpq_points(
    codes, codes_t, offsets, shapes, subset, ref_counts, weights, scale, maps, map_offsets, best
):
    """Chi-square map, winner and reliability of every point, in one parallel pass: the
    kernels `lpq_search` runs point by point (the maps are sums of exact integers, the same
    on any path), so the numbers are the same."""
    for k in prange(shapes.shape[0]):
        _lpq_point(
            k,
            codes,
            codes_t,
            offsets,
            shapes,
            subset,
            ref_counts,
            weights,
            scale,
            maps,
            map_offsets,
            best,
        )


# ---------------------------------------------------------------------------------------------
# Geometry helpers


def _round_half_up(values: np.ndarray) -> np.ndarray:
    return np.floor(np.asarray(values, dtype=np.float64) + 0.5).astype(np.int64)


def _check_image(image: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(image)
    if arr.ndim != 2:
        raise ValueError(f"{name} must be a 2-D array, got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise TypeError(f"{name} must be real-valued, got {arr.dtype}")
    return arr


def _check_points(points: np.ndarray, guess: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"points must have shape (n, 2), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("points must be finite")
    if guess is None:
        g = np.zeros_like(pts)
    else:
        g = np.asarray(guess, dtype=np.float64)
        if g.shape != pts.shape:
            raise ValueError(f"guess must have shape {pts.shape}, got {g.shape}")
        if not np.all(np.isfinite(g)):
            raise ValueError("guess must be finite")
    return pts, g


def _check_subset_radius(subset: int, radius: int) -> tuple[int, int]:
    if int(subset) != subset or subset < 3 or subset % 2 == 0:
        raise ValueError(f"subset must be an odd integer >= 3, got {subset}")
    if int(radius) != radius or radius < 0:
        raise ValueError(f"radius must be a non-negative integer, got {radius}")
    return int(subset), int(radius)


def _check_prewarps(prewarps: Sequence[Sequence[float]] | np.ndarray | None) -> np.ndarray | None:
    if prewarps is None:
        return None
    arr = np.asarray(prewarps, dtype=np.float64)
    if arr.ndim == 1:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 4 or arr.shape[0] == 0:
        raise ValueError(f"prewarps must have shape (k, 4) with k >= 1, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError("prewarps must be finite")
    det = (1.0 + arr[:, 0]) * (1.0 + arr[:, 3]) - arr[:, 1] * arr[:, 2]
    if np.any(det <= 0.0):
        raise ValueError("every prewarp must keep orientation (det(I + grad) > 0)")
    return arr


@dataclass(frozen=True)
class _Layout:
    """Per-point integer geometry shared by the searches (all arrays ``(n,)`` int64/bool)."""

    cx: np.ndarray
    cy: np.ndarray
    x_lo: np.ndarray
    x_hi: np.ndarray
    y_lo: np.ndarray
    y_hi: np.ndarray
    valid: np.ndarray


def _layout(
    ref_shape: tuple[int, int],
    tgt_shape: tuple[int, int],
    points: np.ndarray,
    guess: np.ndarray,
    subset: int,
    radius: int,
) -> _Layout:
    half = subset // 2
    cx = _round_half_up(points[:, 0])
    cy = _round_half_up(points[:, 1])
    gx = _round_half_up(guess[:, 0])
    gy = _round_half_up(guess[:, 1])
    ref_ok = (cx >= half) & (cx <= ref_shape[1] - 1 - half)
    ref_ok &= (cy >= half) & (cy <= ref_shape[0] - 1 - half)
    x_lo = np.maximum(cx + gx - radius, half)
    x_hi = np.minimum(cx + gx + radius, tgt_shape[1] - 1 - half)
    y_lo = np.maximum(cy + gy - radius, half)
    y_hi = np.minimum(cy + gy + radius, tgt_shape[0] - 1 - half)
    valid = ref_ok & (x_lo <= x_hi) & (y_lo <= y_hi)
    return _Layout(cx, cy, x_lo, x_hi, y_lo, y_hi, valid)


def _code_boxes(layout: _Layout, subset: int, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The boxes (row start, row stop, column start, column stop) whose LPQ codes the points
    `idx` read: each one's target search window widened by half a subset, and its reference
    subset."""
    half = subset // 2
    target = np.stack(
        [layout.y_lo - half, layout.y_hi + half + 1, layout.x_lo - half, layout.x_hi + half + 1],
        axis=1,
    )[idx]
    reference = np.stack(
        [layout.cy - half, layout.cy + half + 1, layout.cx - half, layout.cx + half + 1], axis=1
    )[idx]
    return target, reference


class _CodeSource:
    """LPQ codes of rectangles of one image, as if ``lpq_codes`` ran on the whole image.

    Codes are computed once over the bounding box of the requested rectangles when that box is
    no larger than their summed areas, otherwise rectangle by rectangle.
    """

    def __init__(self, image: np.ndarray, params: LPQParams, boxes: np.ndarray) -> None:
        self._image = image
        self._params = params
        self._cache: np.ndarray | None = None
        self._origin = (0, 0)
        if boxes.shape[0] == 0:
            return
        areas = (boxes[:, 1] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 2])
        y0, y1 = int(boxes[:, 0].min()), int(boxes[:, 1].max())
        x0, x1 = int(boxes[:, 2].min()), int(boxes[:, 3].max())
        if (y1 - y0) * (x1 - x0) <= int(areas.sum()):
            self._cache = self._compute(y0, y1, x0, x1)
            self._origin = (y0, x0)

    def _compute(self, y0: int, y1: int, x0: int, x1: int) -> np.ndarray:
        r = self._params.radius
        rows, cols = self._image.shape
        ya, yb = max(y0 - r, 0), min(y1 + r, rows)
        xa, xb = max(x0 - r, 0), min(x1 + r, cols)
        patch = np.asarray(self._image[ya:yb, xa:xb], dtype=np.float64)
        pads = (r - (y0 - ya), r - (yb - y1), r - (x0 - xa), r - (xb - x1))
        if any(pads):
            patch = cv2.copyMakeBorder(patch, *pads, cv2.BORDER_REFLECT_101)
        return lpq_codes(patch, self._params, border="valid")

    def get(self, y0: int, y1: int, x0: int, x1: int) -> np.ndarray:
        """Codes of rows ``y0:y1`` and columns ``x0:x1`` (inside the image)."""
        if self._cache is None:
            return self._compute(y0, y1, x0, x1)
        oy, ox = self._origin
        return self._cache[y0 - oy : y1 - oy, x0 - ox : x1 - ox]


def _warp_template(
    image32: np.ndarray, cx: int, cy: int, size: int, gradient: np.ndarray
) -> np.ndarray:
    """``size x size`` block of ``image32`` deformed by ``I + gradient`` about ``(cx, cy)``.

    Output pixel at offset ``e`` from the block centre samples the image at
    ``(cx, cy) + (I + gradient)^-1 e`` (bicubic, reflected borders).
    """
    ux, uy, vx, vy = gradient
    inv = np.linalg.inv(np.array([[1.0 + ux, uy], [vx, 1.0 + vy]]))
    centre = (size - 1) / 2.0
    offset = np.array([cx, cy], dtype=np.float64) - inv @ np.array([centre, centre])
    matrix = np.hstack([inv, offset[:, None]])
    return cv2.warpAffine(
        image32,
        matrix,
        (size, size),
        flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REFLECT_101,
    )


def _empty_result(n: int) -> dict[str, np.ndarray]:
    return {
        "u": np.zeros(n, dtype=np.int64),
        "v": np.zeros(n, dtype=np.int64),
        "score": np.full(n, np.nan),
        "reliability": np.zeros(n),
        "valid": np.zeros(n, dtype=bool),
        "ux": np.zeros(n),
        "uy": np.zeros(n),
        "vx": np.zeros(n),
        "vy": np.zeros(n),
    }


def _to_float32(image: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(image, dtype=np.float32)


# ---------------------------------------------------------------------------------------------
# Public API


def chi_square_map(
    codes: np.ndarray,
    reference_histogram: np.ndarray,
    subset: int,
    *,
    weights: np.ndarray | None = None,
) -> np.ndarray:
    """Chi-square distance of every ``subset x subset`` block of a code image to a histogram.

    The block histograms come from a sliding update (each one-pixel step removes the codes
    leaving the block and adds those entering it), never from a fresh count per block; the
    chi-square sum is updated for the changed bins only, in exact integer arithmetic on terms
    rounded to a power-of-two fraction of a count (the finest that keeps the sum in int64; about
    ``2e-13`` of a count for ``S = 41`` and unit weights), so the map does not depend on the
    order of the updates.

    Args:
        codes: uint8 LPQ code image ``(H, W)`` with ``H, W >= subset``.
        reference_histogram: ``(256,)`` counts of a ``subset x subset`` block (non-negative
            integers, summing to ``subset**2``), e.g. ``code_histogram`` of the reference subset.
        subset: block side ``S`` in px.
        weights: optional non-negative ``(256,)`` bin weights of the chi-square.

    Returns:
        float64 ``(H - S + 1, W - S + 1)``; entry ``[i, j]`` is
        ``chi_square(reference_histogram / S**2, code_histogram(codes[i:i+S, j:j+S]) / S**2,
        weights)``.
    """
    arr = np.ascontiguousarray(codes)
    if arr.dtype != np.uint8 or arr.ndim != 2:
        raise TypeError("codes must be a 2-D uint8 array")
    subset = int(subset)
    if subset < 1 or arr.shape[0] < subset or arr.shape[1] < subset:
        raise ValueError(f"codes {arr.shape} smaller than subset {subset}")
    ref = np.asarray(reference_histogram, dtype=np.float64)
    if ref.shape != (N_BINS,):
        raise ValueError(f"reference_histogram must have shape (256,), got {ref.shape}")
    ref_counts = np.rint(ref).astype(np.int64)
    if (
        np.any(ref_counts < 0)
        or not np.allclose(ref, ref_counts)
        or (ref_counts.sum() != subset * subset)
    ):
        raise ValueError("reference_histogram must hold the integer counts of a subset block")
    return _chi_map(arr, ref_counts, subset, _check_weights(weights, subset))


def _check_weights(weights: np.ndarray | None, subset: int) -> tuple[np.ndarray, float]:
    """Contiguous float64 weights and the fixed-point scale that keeps the sums in int64."""
    w = np.ones(N_BINS) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (N_BINS,) or np.any(w < 0) or not np.all(np.isfinite(w)):
        raise ValueError("weights must be 256 finite non-negative values")
    w_max = float(w.max())
    if w_max <= 0.0:
        return np.ascontiguousarray(w), 1.0
    bound = N_BINS * w_max * 2.0 * subset * subset
    return np.ascontiguousarray(w), float(2.0 ** np.floor(np.log2(2.0**62 / bound)))


def _chi_map(
    codes: np.ndarray, ref_counts: np.ndarray, subset: int, weighting: tuple[np.ndarray, float]
) -> np.ndarray:
    out = np.empty((codes.shape[0] - subset + 1, codes.shape[1] - subset + 1))
    n_bands = max(1, min(get_num_threads(), out.shape[0] // _MIN_BAND_ROWS))
    args = (codes, np.ascontiguousarray(codes.T), subset, ref_counts, *weighting, out)
    if n_bands == 1:
        _chi_square_map_serial(*args)
    else:
        _chi_square_map_kernel(*args, n_bands)
    return out


def _finish(
    fields: dict[str, np.ndarray],
    k: int,
    cost: np.ndarray,
    score: float,
    layout: _Layout,
    gradient: np.ndarray | None,
) -> None:
    flat = int(np.argmin(cost))
    bi, bj = divmod(flat, cost.shape[1])
    fields["u"][k] = layout.x_lo[k] + bj - layout.cx[k]
    fields["v"][k] = layout.y_lo[k] + bi - layout.cy[k]
    fields["score"][k] = score
    fields["reliability"][k] = _reliability_kernel(cost, bi, bj)
    fields["valid"][k] = True
    if gradient is not None:
        fields["ux"][k], fields["uy"][k], fields["vx"][k], fields["vy"][k] = gradient


def _lpq_cost_maps(
    ref: np.ndarray,
    tgt: np.ndarray,
    layout: _Layout,
    subset: int,
    params: LPQParams,
    warps: np.ndarray | None,
    weighting: tuple[np.ndarray, float],
) -> Iterator[tuple[int, np.ndarray, np.ndarray | None]]:
    """Yield ``(point index, chi-square map, winning pre-warp)`` for every valid point."""
    idx = np.flatnonzero(layout.valid)
    if idx.size == 0:
        return
    tgt_boxes, ref_boxes = _code_boxes(layout, subset, idx)
    tgt_codes = _CodeSource(tgt, params, tgt_boxes)
    ref_codes = _CodeSource(ref, params, ref_boxes) if warps is None else None
    ref32 = _to_float32(ref) if warps is not None else None
    size = subset + 2 * params.radius
    for row, k in enumerate(idx):
        region = np.ascontiguousarray(tgt_codes.get(*tgt_boxes[row]))
        if ref_codes is not None:
            counts = np.bincount(ref_codes.get(*ref_boxes[row]).ravel(), minlength=N_BINS)
            yield int(k), _chi_map(region, counts, subset, weighting), None
            continue

        def lpq_cost(warp: np.ndarray, k: int = k, region: np.ndarray = region) -> np.ndarray:
            patch = _warp_template(ref32, int(layout.cx[k]), int(layout.cy[k]), size, warp)
            counts = np.bincount(lpq_codes(patch, params, border="valid").ravel(), minlength=N_BINS)
            return _chi_map(region, counts, subset, weighting)

        yield (int(k), *_best_over_warps(warps, lpq_cost))


def _best_over_warps(
    warps: np.ndarray, cost_of: Callable[[np.ndarray], np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """The cost map with the lowest minimum over the pre-warps, and that pre-warp."""
    best_cost, best_warp = cost_of(warps[0]), warps[0]
    for warp in warps[1:]:
        cost = cost_of(warp)
        if cost.min() < best_cost.min():
            best_cost, best_warp = cost, warp
    return best_cost, best_warp


def _zncc_cost_maps(
    ref: np.ndarray,
    tgt: np.ndarray,
    layout: _Layout,
    subset: int,
    warps: np.ndarray | None,
) -> Iterator[tuple[int, np.ndarray, np.ndarray | None]]:
    """Yield ``(point index, 1 - ZNCC map, winning pre-warp)`` for every valid point."""
    half = subset // 2
    idx = np.flatnonzero(layout.valid)
    if idx.size == 0:
        return
    ref32 = _to_float32(ref) if warps is not None else None
    for k in idx:
        window = _to_float32(
            tgt[
                layout.y_lo[k] - half : layout.y_hi[k] + half + 1,
                layout.x_lo[k] - half : layout.x_hi[k] + half + 1,
            ]
        )
        cx, cy = int(layout.cx[k]), int(layout.cy[k])
        if warps is None:
            template = _to_float32(ref[cy - half : cy + half + 1, cx - half : cx + half + 1])
            zncc = cv2.matchTemplate(window, template, cv2.TM_CCOEFF_NORMED)
            yield int(k), 1.0 - zncc.astype(np.float64), None
            continue

        def zncc_cost(
            warp: np.ndarray, cx: int = cx, cy: int = cy, window: np.ndarray = window
        ) -> np.ndarray:
            template = _warp_template(ref32, cx, cy, subset, warp)
            return 1.0 - cv2.matchTemplate(window, template, cv2.TM_CCOEFF_NORMED).astype(
                np.float64
            )

        yield (int(k), *_best_over_warps(warps, zncc_cost))


def lpq_search(
    reference: np.ndarray,
    target: np.ndarray,
    points: np.ndarray,
    *,
    subset: int = 41,
    radius: int = 50,
    guess: np.ndarray | None = None,
    params: LPQParams = _DEFAULT_LPQ,
    prewarps: Sequence[Sequence[float]] | np.ndarray | None = None,
    weights: np.ndarray | None = None,
) -> IntegerMatch:
    """Integer search by LPQ histograms and chi-square (Zhang et al. 2016).

    The target's LPQ code image is computed once over the union of the search regions (over
    their bounding box when that is no larger than their summed areas, else region by region),
    and the reference subset's histogram once per point (and pre-warp); without pre-warps the
    maps of all points are computed in one compiled pass, in parallel on numba's threads. The
    histograms of all candidate blocks come from the sliding update of ``chi_square_map``; the
    winner is the minimum of the chi-square map (first in row-major order on ties) and its
    reliability follows the module docstring.

    Codes near an image edge are those of ``lpq_codes`` with reflected borders, so a subset may
    touch the edge. A histogram ignores where in the subset each code sits, so the chi-square map
    is a broad cone around the truth (moving a block by ``d`` px replaces about ``2 d S`` of its
    ``S**2`` codes): the minimum is well defined but shallow, and flips by a pixel or two under
    strong blur or noise. ZNCC is sharper (see the module docstring).

    Args:
        reference: 2-D reference image ``(H, W)``.
        target: 2-D target image ``(H', W')``.
        points: float64 ``(n, 2)`` reference positions ``(x, y)`` in px.
        subset: odd subset side ``S`` in px.
        radius: search half-width in px around the rounded guess, per axis.
        guess: optional float ``(n, 2)`` initial displacements ``(u, v)`` in px (rounded);
            default zeros.
        params: LPQ parameters (``window`` must not exceed ``S``).
        prewarps: optional ``(k, 4)`` displacement gradients ``(ux, uy, vx, vy)``. For each one
            the reference subset (with a margin of ``window // 2`` px for the LPQ filters) is
            resampled bicubically as deformed by ``I + gradient`` about its centre before its
            histogram is taken; the lowest chi-square over all pre-warps wins and its gradient
            is reported. Include ``(0, 0, 0, 0)`` to keep the undeformed subset among the
            candidates. Default: translation only.
        weights: optional ``(256,)`` non-negative chi-square bin weights.

    Returns:
        ``IntegerMatch`` with ``score`` = chi-square between normalised histograms.
    """
    ref = _check_image(reference, "reference")
    tgt = _check_image(target, "target")
    pts, g = _check_points(points, guess)
    subset, radius = _check_subset_radius(subset, radius)
    warps = _check_prewarps(prewarps)
    if params.window > subset:
        raise ValueError(f"LPQ window {params.window} exceeds subset {subset}")
    weighting = _check_weights(weights, subset)
    fields = _empty_result(pts.shape[0])
    layout = _layout(ref.shape, tgt.shape, pts, g, subset, radius)
    if warps is None:
        _lpq_all_points(ref, tgt, layout, subset, params, weighting, fields)
        return IntegerMatch(**fields)
    for k, cost, warp in _lpq_cost_maps(ref, tgt, layout, subset, params, warps, weighting):
        _finish(fields, k, cost, float(cost.min()), layout, warp)
    return IntegerMatch(**fields)


_LPQ_BATCH_POINTS = 256
"""Points whose maps are held at once by `_lpq_all_points`."""


def _lpq_all_points(
    ref: np.ndarray,
    tgt: np.ndarray,
    layout: _Layout,
    subset: int,
    params: LPQParams,
    weighting: tuple[np.ndarray, float],
    fields: dict[str, np.ndarray],
) -> None:
    """`lpq_search` without pre-warps: the codes gathered, then every point's map, winner and
    reliability in one compiled pass per batch of points, on numba's threads."""
    idx = np.flatnonzero(layout.valid)
    if idx.size == 0:
        return
    tgt_boxes, ref_boxes = _code_boxes(layout, subset, idx)
    tgt_codes = _CodeSource(tgt, params, tgt_boxes)
    ref_codes = _CodeSource(ref, params, ref_boxes)
    for start in range(0, idx.size, _LPQ_BATCH_POINTS):
        part = slice(start, start + _LPQ_BATCH_POINTS)
        regions = [np.ascontiguousarray(tgt_codes.get(*box)) for box in tgt_boxes[part]]
        shapes = np.array([r.shape for r in regions], dtype=np.int64)
        sizes = shapes[:, 0] * shapes[:, 1]
        offsets = np.r_[0, np.cumsum(sizes)[:-1]].astype(np.int64)
        map_sizes = (shapes[:, 0] - subset + 1) * (shapes[:, 1] - subset + 1)
        map_offsets = np.r_[0, np.cumsum(map_sizes)[:-1]].astype(np.int64)
        counts = np.stack(
            [np.bincount(ref_codes.get(*box).ravel(), minlength=N_BINS) for box in ref_boxes[part]]
        ).astype(np.int64)
        best = np.empty((len(regions), 4))
        _lpq_points(
            np.concatenate([r.ravel() for r in regions]),
            np.concatenate([r.T.ravel() for r in regions]),
            offsets,
            shapes,
            subset,
            counts,
            *weighting,
            np.empty(int(map_sizes.sum())),
            map_offsets,
            best,
        )
        rows = idx[part]
        bi, bj = best[:, 2].astype(np.int64), best[:, 3].astype(np.int64)
        fields["u"][rows] = layout.x_lo[rows] + bj - layout.cx[rows]
        fields["v"][rows] = layout.y_lo[rows] + bi - layout.cy[rows]
        fields["score"][rows] = best[:, 0]
        fields["reliability"][rows] = best[:, 1]
        fields["valid"][rows] = True


def zncc_search(
    reference: np.ndarray,
    target: np.ndarray,
    points: np.ndarray,
    *,
    subset: int = 41,
    radius: int = 50,
    guess: np.ndarray | None = None,
    prewarps: Sequence[Sequence[float]] | np.ndarray | None = None,
) -> IntegerMatch:
    """Integer search by zero-normalised cross-correlation (``cv2.TM_CCOEFF_NORMED``).

    For each point the reference subset is matched over the target window spanning the
    candidate blocks (``2 radius + S`` px square around the point plus the rounded guess,
    clipped to the image so that candidates stay inside it). The winner maximises ZNCC (first in
    row-major order on ties); reliability uses the cost ``1 - ZNCC`` as in the module docstring.
    A flat reference subset gives ZNCC 1 everywhere (OpenCV's convention) and reliability 0.

    Args:
        reference, target: 2-D images.
        points: float64 ``(n, 2)`` reference positions ``(x, y)`` in px.
        subset: odd subset side ``S`` in px.
        radius: search half-width in px around the rounded guess, per axis.
        guess: optional float ``(n, 2)`` initial displacements ``(u, v)`` in px (rounded).
        prewarps: optional ``(k, 4)`` displacement gradients ``(ux, uy, vx, vy)``; the reference
            subset is resampled bicubically as deformed by ``I + gradient`` about its centre,
            one template per pre-warp, and the highest ZNCC over all of them wins. Include
            ``(0, 0, 0, 0)`` to keep the undeformed template. Default: translation only.

    Returns:
        ``IntegerMatch`` with ``score`` = ZNCC of the winner.
    """
    ref = _check_image(reference, "reference")
    tgt = _check_image(target, "target")
    pts, g = _check_points(points, guess)
    subset, radius = _check_subset_radius(subset, radius)
    warps = _check_prewarps(prewarps)
    fields = _empty_result(pts.shape[0])
    layout = _layout(ref.shape, tgt.shape, pts, g, subset, radius)
    for k, cost, warp in _zncc_cost_maps(ref, tgt, layout, subset, warps):
        _finish(fields, k, cost, 1.0 - float(cost.min()), layout, warp)
    return IntegerMatch(**fields)
