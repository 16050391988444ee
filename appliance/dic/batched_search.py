"""ZNCC integer search of many points at once: FFT cross-correlation in batches.

`integer_search.zncc_search` matches one point at a time with `cv2.matchTemplate`: right for
the few points of a tracker's mark, but for hundreds of points of interest the per-point calls
and the reference subsets, cut and transformed again for every target, dominate.
`ZNCCSearch` prepares the reference once (`prepare`: the zero-mean reference subsets and their
spectra) and searches a target for all points in batches (`search`):

1. every point's target window (the candidate blocks, as `zncc_search` clips them) is copied,
   less its mean, into one zero-padded N x N tile of a batch (N >= 2 radius + S, a size
   OpenCV's DFT transforms fast: `dft_tile_size`), in one compiled pass;
2. the tiles' spectra times the conjugate reference spectra, transformed back (`cv2.dft`,
   `cv2.mulSpectrums`, `cv2.idft` per tile), are the numerators sum (t - t_m) (w - c) of every
   candidate (a circular correlation of size N >= window has no wrap-around in the candidate
   region);
3. one compiled pass over the batch divides them by each candidate's norm (its sums of w - c
   and (w - c)^2 from an integral image of the window, in float64), takes the winner (first in
   row-major order on ties) and its reliability (the module docstring of `integer_search`).

The arithmetic follows `cv2.TM_CCOEFF_NORMED`'s rules: a flat reference subset scores 1
everywhere, a flat candidate block 0, a ratio up to 1.125 is clipped to +-1 and beyond that is
0, and scores are rounded to float32 as OpenCV returns them. The numerators differ from
OpenCV's by float32 rounding (about 1e-6 of the score; removing the window's mean first keeps
it there), so the winners are the same wherever no other candidate scores within that of the
winner: the same integer peaks on speckle, pinned by the unit tests against `zncc_search`.

Conventions, arguments and the result (`IntegerMatch`) are those of `zncc_search`.

Coarse to fine (`ZNCCSearch(coarse_to_fine=True)`, translation only, radius >= 20 px): both
images are reduced to half resolution (`cv2.pyrDown`: a 5-tap Gaussian, then every other pixel),
every point is searched there with a subset of about S / 2 over ceil(radius / 2) + 1 px, and the
coarse peak, doubled, is refined at full resolution within +-3 px. A point falls back to the
full-resolution search of its whole window when the coarse level cannot vouch for it: its coarse
subset or window leaves the coarse image, its coarse reliability (the module docstring of
`integer_search`) is below `MIN_COARSE_RELIABILITY` (0.5: the winner's cost 1 - ZNCC is at most
half that of the best separated minimum; a speckle finer than the coarse level resolves leaves a
flat or noisy coarse map, reliability near 0), its refined ZNCC is below `MIN_REFINED_ZNCC` (0.8:
a wrong speckle match scores about 0.2 ... 0.5 at full resolution, a right one 0.9 and more, even
under the blur a matched reference leaves), or its refined peak sits on the edge of the
refinement window (+-3 px) or outside the full search's candidates. A point on the coarse path
reports the refined ZNCC as its score and its coarse reliability; a fallen-back point reports
exactly what the full search does. On rendered speckle of 3 ... 6 px, sharp or blurred, the
coarse-to-fine peaks are the full search's (the unit tests).
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

import cv2
import numba
import numpy as np

from appliance.dic.integer_search import (
    IntegerMatch,
    _check_image,
    _check_points,
    _check_prewarps,
    _check_subset_radius,
    _empty_result,
    _Layout,
    _layout,
    _reliability_kernel,
    _round_half_up,
    _to_float32,
    _warp_template,
)

__all__ = [
    "MIN_COARSE_RADIUS",
    "MIN_COARSE_RELIABILITY",
    "MIN_REFINED_ZNCC",
    "ZNCCSearch",
    "zncc_search_batched",
]

MIN_COARSE_RADIUS = 20
"""Smallest search radius, px, searched coarse to fine; below it the full search is as cheap."""
MIN_COARSE_RELIABILITY = 0.5
"""Coarse reliability below which a point falls back to the full search (module docstring)."""
MIN_REFINED_ZNCC = 0.8
"""Refined full-resolution ZNCC below which a point falls back to the full search."""
_REFINE_RADIUS = 3
"""Half-width, px, of the full-resolution refinement around the doubled coarse peak: the
doubled peak is off by up to 2 px (half a coarse pixel of the point and of the peak, doubled),
so a right peak lies inside the window, never on its edge."""

_BATCH_POINTS = 64
"""Points transformed together: large enough to amortise the FFT calls, small enough that a
batch's tiles stay in cache."""
_SPECTRA_CACHE_BYTES = 256 * 2**20
"""Largest store of reference spectra kept between targets; beyond it they are recomputed."""


def dft_tile_size(window_px: int) -> int:
    """Side of the square tile a window of `window_px` is transformed in: the smallest
    multiple of 16 at least `window_px` whose quotient by 16 has no prime factor beyond 5.

    OpenCV's own choice (`cv2.getOptimalDFTSize`, any product of 2, 3 and 5) picks sizes such
    as 75 or 81 whose odd radices transform at about half the speed of a larger even size:
    measured on one core for a forward and an inverse transform of a tile, 146 us at 75
    against 78 us at 80, 171 us at 81 against 117 us at 96, 517 us at 125 against 185 us at
    128.
    """
    size = max(16, -(-int(window_px) // 16) * 16)
    while True:
        rest = size // 16
        for prime in (2, 3, 5):
            while rest % prime == 0:
                rest //= prime
        if rest == 1:
            return size
        size += 16


@numba.njit(cache=True, nogil=True)
def _fill_tiles(image, top, left, rows, cols, tiles, means):
    """Copy window k of `image` (rows x cols at top, left), less its mean, into `tiles[k]`,
    zeros to its right (the rows below are never read: the transforms are told where the
    window ends)."""
    for k in range(tiles.shape[0]):
        h = rows[k]
        w = cols[k]
        tiles[k, :h, w:] = 0.0
        total = 0.0
        for i in range(h):
            for j in range(w):
                total += np.float64(np.float32(image[top[k] + i, left[k] + j]))
        mean = total / (h * w)
        means[k] = mean
        for i in range(h):
            for j in range(w):
                tiles[k, i, j] = np.float32(
                    np.float64(np.float32(image[top[k] + i, left[k] + j])) - mean
                )


@numba.njit(cache=True, nogil=True)
def _zncc_cost(numerator, image, top, left, mean, subset, map_rows, map_cols, norm, cost):
    """1 - ZNCC of every candidate of one point into `cost[:map_rows, :map_cols]`.

    The candidates' sums of w - c and (w - c)^2 slide down the window's columns, then along
    the rows of those column sums.
    """
    area = subset * subset
    w = map_cols + subset - 1
    down1 = np.zeros((map_rows, w))
    down2 = np.zeros((map_rows, w))
    for i in range(subset):
        for j in range(w):
            value = np.float64(np.float32(image[top + i, left + j])) - mean
            down1[0, j] += value
            down2[0, j] += value * value
    for i in range(1, map_rows):
        for j in range(w):
            leaving = np.float64(np.float32(image[top + i - 1, left + j])) - mean
            entering = np.float64(np.float32(image[top + i + subset - 1, left + j])) - mean
            down1[i, j] = down1[i - 1, j] + (entering - leaving)
            down2[i, j] = down2[i - 1, j] + (entering * entering - leaving * leaving)
    for i in range(map_rows):
        total = 0.0
        total2 = 0.0
        for j in range(subset):
            total += down1[i, j]
            total2 += down2[i, j]
        for j in range(map_cols):
            if j > 0:
                total += down1[i, j + subset - 1] - down1[i, j - 1]
                total2 += down2[i, j + subset - 1] - down2[i, j - 1]
            bound = np.sqrt(max(total2 - total * total / area, 0.0)) * norm
            num = np.float64(numerator[i, j])
            if abs(num) < bound:
                score = num / bound
            elif abs(num) < bound * 1.125:
                score = 1.0 if num > 0 else -1.0
            else:
                score = 0.0
            cost[i, j] = 1.0 - np.float64(np.float32(score))


@numba.njit(cache=True, nogil=True)
def _finish_point(
    k, numerator, image, top, left, means, subset, map_rows, map_cols, norms, cost, best, where
):
    rows = map_rows[k]
    cols = map_cols[k]
    view = cost[k, :rows, :cols]
    if norms[k] < 0.0:
        view[:, :] = 0.0
    else:
        _zncc_cost(
            numerator[k], image, top[k], left[k], means[k], subset, rows, cols, norms[k], view
        )
    bi = 0
    bj = 0
    low = view[0, 0]
    for i in range(rows):
        for j in range(cols):
            if view[i, j] < low:
                low = view[i, j]
                bi = i
                bj = j
    best[k, 0] = low
    best[k, 1] = _reliability_kernel(np.ascontiguousarray(view), bi, bj)
    where[k, 0] = bi
    where[k, 1] = bj


@numba.njit(cache=True, nogil=True)
def _finish_points(
    numerator, image, top, left, means, subset, map_rows, map_cols, norms, cost, best, where
):
    for k in range(map_rows.shape[0]):
        _finish_point(
            k,
            numerator,
            image,
            top,
            left,
            means,
            subset,
            map_rows,
            map_cols,
            norms,
            cost,
            best,
            where,
        )


class ZNCCSearch:
    """ZNCC integer search of many points against one reference, prepared once.

    `prepare(reference, points)` once, then `search(target, guess)` for every target: the
    same result as `integer_search.zncc_search(reference, target, points, ...)` (see the module
    docstring for how far "the same" goes), computed in batches.

    Args:
        subset: odd subset side S, px.
        radius: search half-width around the rounded guess, per axis, px.
        threads: worker threads, each searching whole batches of points (None = numba's
            default, all cores); the numbers do not depend on it.
        coarse_to_fine: search translation-only targets at half resolution first when the
            radius is at least `MIN_COARSE_RADIUS` (the module docstring); `fallback` then
            says which points of the last search fell back to the full search.
    """

    def __init__(
        self,
        *,
        subset: int = 41,
        radius: int = 50,
        threads: int | None = None,
        coarse_to_fine: bool = False,
    ) -> None:
        self.subset, self.radius = _check_subset_radius(subset, radius)
        self.coarse_to_fine = bool(coarse_to_fine) and self.radius >= MIN_COARSE_RADIUS
        self.fallback: np.ndarray | None = None
        if threads is not None and not 1 <= threads <= numba.config.NUMBA_NUM_THREADS:
            raise ValueError(
                f"threads must be in 1..{numba.config.NUMBA_NUM_THREADS}, got {threads}"
            )
        self.threads = threads
        self.tile = dft_tile_size(2 * self.radius + self.subset)
        self._reference: np.ndarray | None = None

    def prepare(self, reference: np.ndarray, points: np.ndarray) -> None:
        """Take the reference image and the points ((n, 2) x, y px) to search for."""
        self._reference = _check_image(reference, "reference")
        self._points, _ = _check_points(points, None)
        n = self._points.shape[0]
        cached = n * self.tile * self.tile * 4 <= _SPECTRA_CACHE_BYTES
        self._spectra = np.empty((n, self.tile, self.tile), np.float32) if cached else None
        self._norms = np.empty(n)
        self._known = np.zeros(n, dtype=bool)
        if self.coarse_to_fine:
            coarse_subset = (self.subset // 2) | 1
            self._coarse = ZNCCSearch(
                subset=max(coarse_subset, 3),
                radius=(self.radius + 1) // 2 + 1,
                threads=self.threads,
            )
            self._coarse.prepare(cv2.pyrDown(_to_float32(self._reference)), self._points / 2.0)
            self._fine = ZNCCSearch(subset=self.subset, radius=_REFINE_RADIUS, threads=self.threads)
            self._fine.prepare(self._reference, self._points)

    def search(
        self,
        target: np.ndarray,
        guess: np.ndarray | None = None,
        *,
        prewarps: Sequence[Sequence[float]] | np.ndarray | None = None,
    ) -> IntegerMatch:
        """Search the prepared points in `target`, as `zncc_search` with the same arguments.

        Args:
            target: 2-D image.
            guess: optional (n, 2) initial displacements (u, v) px (rounded); default zeros.
            prewarps: optional (k, 4) displacement gradients (ux, uy, vx, vy) applied to the
                reference subsets, as in `zncc_search`; the first of equally good ones wins.

        Returns:
            `IntegerMatch` with `score` = ZNCC of the winner.
        """
        if self._reference is None:
            raise RuntimeError("prepare() must be called before search()")
        tgt = _check_image(target, "target")
        pts, g = _check_points(self._points, guess)
        warps = _check_prewarps(prewarps)
        layout = _layout(self._reference.shape, tgt.shape, pts, g, self.subset, self.radius)
        fields = _empty_result(pts.shape[0])
        valid = np.flatnonzero(layout.valid)
        self.fallback = None
        if self.coarse_to_fine and warps is None:
            valid = self._coarse_then_fine(tgt, g, layout, fields)
        self._search_rows(tgt, layout, valid, warps, fields)
        return IntegerMatch(**fields)

    def _coarse_then_fine(
        self, target: np.ndarray, guess: np.ndarray, layout: _Layout, fields: dict[str, np.ndarray]
    ) -> np.ndarray:
        """Search every valid point coarse to fine into `fields`; return the points that fall
        back to the full search."""
        coarse = self._coarse.search(cv2.pyrDown(_to_float32(target)), guess / 2.0)
        start = 2.0 * coarse.displacement
        fine = self._fine.search(target, start)
        gx = _round_half_up(guess[:, 0])
        gy = _round_half_up(guess[:, 1])
        inside = (np.abs(fine.u - gx) <= self.radius) & (np.abs(fine.v - gy) <= self.radius)
        inside &= (layout.x_lo <= layout.cx + fine.u) & (layout.cx + fine.u <= layout.x_hi)
        inside &= (layout.y_lo <= layout.cy + fine.v) & (layout.cy + fine.v <= layout.y_hi)
        sx = _round_half_up(start[:, 0])
        sy = _round_half_up(start[:, 1])
        interior = (np.abs(fine.u - sx) < _REFINE_RADIUS) & (np.abs(fine.v - sy) < _REFINE_RADIUS)
        with np.errstate(invalid="ignore"):
            trusted = (
                coarse.valid
                & fine.valid
                & (coarse.reliability >= MIN_COARSE_RELIABILITY)
                & (fine.score >= MIN_REFINED_ZNCC)
            )
        trusted &= inside & interior & layout.valid
        fields["u"][trusted] = fine.u[trusted]
        fields["v"][trusted] = fine.v[trusted]
        fields["score"][trusted] = fine.score[trusted]
        fields["reliability"][trusted] = coarse.reliability[trusted]
        fields["valid"][trusted] = True
        self.fallback = layout.valid & ~trusted
        return np.flatnonzero(self.fallback)

    def _search_rows(
        self,
        tgt: np.ndarray,
        layout: _Layout,
        valid: np.ndarray,
        warps: np.ndarray | None,
        fields: dict[str, np.ndarray],
    ) -> None:
        """Full search of the points `valid` into `fields`, in batches on the threads."""
        if valid.size == 0:
            return
        batches = [valid[k : k + _BATCH_POINTS] for k in range(0, valid.size, _BATCH_POINTS)]
        workers = min(self.threads or numba.get_num_threads(), len(batches))
        if workers <= 1:
            for rows in batches:
                self._search_batch(tgt, layout, rows, warps, fields)
        else:
            with ThreadPoolExecutor(max_workers=workers) as pool:
                for done in [
                    pool.submit(self._search_batch, tgt, layout, rows, warps, fields)
                    for rows in batches
                ]:
                    done.result()

    def _search_batch(
        self,
        target: np.ndarray,
        layout: _Layout,
        rows: np.ndarray,
        warps: np.ndarray | None,
        fields: dict[str, np.ndarray],
    ) -> None:
        half = self.subset // 2
        top = layout.y_lo[rows] - half
        left = layout.x_lo[rows] - half
        map_rows = (layout.y_hi[rows] - layout.y_lo[rows] + 1).astype(np.int64)
        map_cols = (layout.x_hi[rows] - layout.x_lo[rows] + 1).astype(np.int64)
        size = self.tile
        tiles = np.empty((rows.size, size, size), dtype=np.float32)
        means = np.empty(rows.size)
        _fill_tiles(
            target, top, left, map_rows + self.subset - 1, map_cols + self.subset - 1, tiles, means
        )
        window_spectra = np.empty_like(tiles)
        for i in range(rows.size):
            cv2.dft(tiles[i], window_spectra[i], nonzeroRows=int(map_rows[i]) + self.subset - 1)
        height, width = int(map_rows.max()), int(map_cols.max())
        cost = np.empty((rows.size, height, width))
        best = np.empty((rows.size, 2))
        where = np.empty((rows.size, 2), dtype=np.int64)
        chosen: np.ndarray | None = None
        for w, warp in enumerate([None] if warps is None else list(warps)):
            spectra, norms = self._reference_spectra(layout, rows, warp)
            numerator = tiles
            for i in range(rows.size):
                product = cv2.mulSpectrums(window_spectra[i], spectra[i], 0, conjB=True)
                cv2.idft(
                    product, numerator[i], cv2.DFT_REAL_OUTPUT | cv2.DFT_SCALE, int(map_rows[i])
                )
            _finish_points(
                numerator,
                target,
                top,
                left,
                means,
                self.subset,
                map_rows,
                map_cols,
                norms,
                cost,
                best,
                where,
            )
            if w == 0:
                kept_best, kept_where = best.copy(), where.copy()
                chosen = np.zeros(rows.size, dtype=np.int64)
                continue
            better = best[:, 0] < kept_best[:, 0]
            kept_best[better] = best[better]
            kept_where[better] = where[better]
            chosen[better] = w
        if warps is None:
            kept_best, kept_where = best, where
        fields["u"][rows] = layout.x_lo[rows] + kept_where[:, 1] - layout.cx[rows]
        fields["v"][rows] = layout.y_lo[rows] + kept_where[:, 0] - layout.cy[rows]
        fields["score"][rows] = 1.0 - kept_best[:, 0]
        fields["reliability"][rows] = kept_best[:, 1]
        fields["valid"][rows] = True
        if warps is not None:
            gradient = warps[chosen]
            fields["ux"][rows], fields["uy"][rows] = gradient[:, 0], gradient[:, 1]
            fields["vx"][rows], fields["vy"][rows] = gradient[:, 2], gradient[:, 3]

    def _reference_spectra(
        self, layout: _Layout, rows: np.ndarray, warp: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Conjugate spectra of the zero-mean reference subsets of `rows`, and their norms
        (-1 for a flat subset, which scores 1 everywhere); kept between targets when unwarped
        and the store is small enough."""
        keep = warp is None and self._spectra is not None
        if keep and self._known[rows].all():
            return self._spectra[rows], self._norms[rows]
        half = self.subset // 2
        size = self.tile
        templates = np.zeros((rows.size, size, size), dtype=np.float32)
        norms = np.empty(rows.size)
        reference32 = np.ascontiguousarray(self._reference, dtype=np.float32)
        for i, k in enumerate(rows):
            cx, cy = int(layout.cx[k]), int(layout.cy[k])
            if warp is None:
                block = reference32[cy - half : cy + half + 1, cx - half : cx + half + 1]
            else:
                block = _warp_template(reference32, cx, cy, self.subset, warp)
            values = block.astype(np.float64)
            centred = values - values.mean()
            energy = float(np.sum(centred * centred))
            norms[i] = -1.0 if energy / values.size < np.finfo(np.float64).eps else np.sqrt(energy)
            templates[i, : self.subset, : self.subset] = centred
        spectra = np.empty_like(templates)
        for i in range(rows.size):
            cv2.dft(templates[i], spectra[i], nonzeroRows=self.subset)
        if keep:
            self._spectra[rows] = spectra
            self._norms[rows] = norms
            self._known[rows] = True
        return spectra, norms


def zncc_search_batched(
    reference: np.ndarray,
    target: np.ndarray,
    points: np.ndarray,
    *,
    subset: int = 41,
    radius: int = 50,
    guess: np.ndarray | None = None,
    prewarps: Sequence[Sequence[float]] | np.ndarray | None = None,
    threads: int | None = None,
) -> IntegerMatch:
    """`integer_search.zncc_search` computed by `ZNCCSearch`: the same arguments and result."""
    search = ZNCCSearch(subset=subset, radius=radius, threads=threads)
    search.prepare(reference, points)
    return search.search(target, guess, prewarps=prewarps)
