"""IC-GN subpixel refinement: inverse-compositional Gauss-Newton with a first-order shape function.

For each point of interest (x0, y0) an S x S reference subset f, at offsets (dx, dy) in
[-h, h]^2 with h = S // 2, is matched to the target image g under the first-order warp

    x = x0 + dx + u + ux dx + uy dy
    y = y0 + dy + v + vx dx + vy dy

by minimising the zero-normalised sum of squared differences (Pan et al., Exp. Mech. 2013;
Zhang et al., Math. Probl. Eng. 2016, Eqs. 10-19)

    C_ZNSSD = sum [ (f - f_m) / df  -  (g - g_m) / dg ]^2,
    df = sqrt(sum (f - f_m)^2),  dg = sqrt(sum (g - g_m)^2),

which is insensitive to offset and scale changes of the grey levels; ZNCC = 1 - C_ZNSSD / 2.

The inverse-compositional scheme linearises the *reference* side, so the steepest-descent
images J = grad f . dW/dp and the Hessian H = sum J^T J are computed once per reference
(`ICGN.prepare`) and reused for every target image and every iteration (`ICGN.compute`):

    dp = -H^-1 sum J^T [ (f - f_m) - (df / dg) (g(W(p)) - g_m) ],    W(p) <- W(p) o W(dp)^-1.

Reference values, reference gradients and target values all come from the cubic B-spline
interpolant of `appliance.dic.bspline`, so subpixel points of interest are exact too.

The target side has a per-image cost too: the B-spline coefficients of the whole (pre-filtered)
target, of the order of 6 ms at 700 x 700 px, 50 ms at 2048 x 2048 px and 40 us for a live
tracking window of 70 x 150 px on one core of a desktop CPU. `ICGN.prepare_target` pays it
once and returns a `PreparedTarget`, which `compute` accepts in place of the image, and
`compute(..., indices=...)` refines any subset of the prepared points. Together they let a
caller refine the points of one image pair in many small batches, as the seed-and-propagate
scheme of `appliance.dic.propagation` does, for the price of one coefficient computation.
The result of a point depends only on the point, its guess and the images: refining it alone,
in a subset or in the whole batch, with one thread or many, gives the same numbers bit for
bit.

The kernel is compiled with numba, runs over many points per call and allocates nothing inside
the iteration loop: each worker allocates one scratch buffer per block of points. It runs in
parallel over blocks of points when more than one thread is allowed and there is more than one
block; otherwise on the calling thread alone, since for a handful of points (a tracker's
mark) starting the thread pool costs more than it saves. The target subset is sampled a row at
a time (`appliance.dic.bspline.interpolate_line`), which vectorises the interpolation without
changing a single operation of it.

The kernels release the GIL, and so does `prepare_target`'s coefficient computation: a caller
may prepare the next target on another thread while this one is refined (`extensometer track`
does).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numba
import numpy as np

from appliance.dic.bspline import (
    interpolate_line,
    interpolate_row_with_gradient,
    spline_coefficients,
)


class PointStatus(enum.IntEnum):
    """Outcome of the refinement of one point.

    CONVERGED: a stop rule was met (step below `step_tolerance` or ZNSSD change below
        `znssd_tolerance`).
    MAX_ITERATIONS: `max_iterations` updates without meeting a stop rule; the last estimate
        is reported.
    OUT_OF_IMAGE: the reference subset, or the warped subset during the iterations, left the
        image rectangle.
    FLAT_SUBSET: the reference subset has no usable texture (zero variance or a singular
        Hessian).
    DIVERGED: the iteration ran away (non-finite values, a step larger than the subset, a
        folded warp) or the warped target subset is flat.

    `ICGN.compute` reports only the five values above. Schemes that decide which points to
    refine, and accept or reject the outcome, add two (`appliance.dic.propagation`):

    NOT_REACHED: the point was never refined, because no accepted point led to it (for
        propagation: it is not connected to a seed through accepted points). Its
        displacements, gradients and ZNCC are NaN and its iteration count 0.
    LOW_ZNCC: IC-GN converged, but the ZNCC of the result is below the caller's acceptance
        threshold, so the match is not trusted (a wrong basin, a damaged or occluded
        subset). The converged estimate and its ZNCC are reported as they are.
    """

    CONVERGED = 0
    MAX_ITERATIONS = 1
    OUT_OF_IMAGE = 2
    FLAT_SUBSET = 3
    DIVERGED = 4
    NOT_REACHED = 5
    LOW_ZNCC = 6


_PENDING = -1
_RELATIVE_PIVOT_FLOOR = 1e-12
_KERNEL_ORDER = np.array([0, 2, 3, 1, 4, 5])
"""Columns of a public (u, v, ux, uy, vx, vy) guess in the kernel's (u, ux, uy, v, vx, vy)."""


@dataclass(frozen=True)
class ICGNResult:
    """Refined displacements of n points; every array has shape (n,).

    Attributes:
        u, v: displacement of the subset centre along x and y, px.
        ux, uy, vx, vy: displacement gradients du/dx, du/dy, dv/dx, dv/dy (dimensionless).
        zncc: zero-normalised cross-correlation of the last evaluated warp, in [-1, 1];
            NaN for points that were never evaluated.
        iterations: Gauss-Newton updates performed.
        status: `PointStatus` values (int8).
    """

    u: np.ndarray
    v: np.ndarray
    ux: np.ndarray
    uy: np.ndarray
    vx: np.ndarray
    vy: np.ndarray
    zncc: np.ndarray
    iterations: np.ndarray
    status: np.ndarray

    def ok(self) -> np.ndarray:
        """Boolean mask of converged points."""
        return self.status == PointStatus.CONVERGED


@dataclass(frozen=True, eq=False)
class PreparedTarget:
    """A target image made ready for `ICGN.compute`: its pre-filtered spline coefficients.

    Made by `ICGN.prepare_target`; pass it to `ICGN.compute` in place of the image to refine
    the same target many times (different points, different guesses) without recomputing the
    coefficients. It is tied to the pre-filter of the `ICGN` that made it (`compute` refuses
    one made with another `prefilter_sigma`) and to the image shape, not to the prepared
    reference or points: one prepared target serves every `ICGN` with that pre-filter.

    Attributes:
        coefficients: read-only float64 (H + 2 PAD, W + 2 PAD) padded cubic B-spline
            coefficients of the pre-filtered image (`appliance.dic.bspline`).
        shape: (H, W) of the image, px.
        prefilter_sigma: the Gaussian pre-filter applied before the spline, px (0 = none).
    """

    coefficients: np.ndarray
    shape: tuple[int, int]
    prefilter_sigma: float


@numba.njit(cache=True)
def _cholesky_inverse(matrix, out):
    """Invert a symmetric positive definite 6 x 6 matrix; False when it is not usable."""
    n = 6
    lower = np.zeros((n, n))
    trace = 0.0
    for i in range(n):
        trace += matrix[i, i]
    if not trace > 0.0:
        return False
    for j in range(n):
        s = matrix[j, j]
        for k in range(j):
            s -= lower[j, k] * lower[j, k]
        if s <= _RELATIVE_PIVOT_FLOOR * trace:
            return False
        lower[j, j] = np.sqrt(s)
        for i in range(j + 1, n):
            s = matrix[i, j]
            for k in range(j):
                s -= lower[i, k] * lower[j, k]
            lower[i, j] = s / lower[j, j]
    inv_lower = np.zeros((n, n))
    for i in range(n):
        inv_lower[i, i] = 1.0 / lower[i, i]
        for j in range(i):
            s = 0.0
            for k in range(j, i):
                s -= lower[i, k] * inv_lower[k, j]
            inv_lower[i, j] = s / lower[i, i]
    for i in range(n):
        for j in range(n):
            s = 0.0
            for k in range(max(i, j), n):
                s += inv_lower[k, i] * inv_lower[k, j]
            out[i, j] = s
    return True


@numba.njit(cache=True)
def _prepare_point(
    k, coefficients, width, height, points, half, fz, fx, fy, df, hinv, min_df, status
):
    side = 2 * half + 1
    count = side * side
    x0 = points[k, 0]
    y0 = points[k, 1]
    if x0 - half < 0.0 or y0 - half < 0.0 or x0 + half > width - 1 or y0 + half > height - 1:
        status[k] = 2
        return
    scratch = np.empty((9, side))
    for j in range(side):
        row = slice(j * side, (j + 1) * side)
        interpolate_row_with_gradient(
            coefficients, x0, y0 + (j - half), -half, fz[k, row], fx[k, row], fy[k, row], scratch
        )
    total = 0.0
    for idx in range(count):
        total += fz[k, idx]
    mean = total / count
    ssd = 0.0
    for idx in range(count):
        fz[k, idx] -= mean
        ssd += fz[k, idx] * fz[k, idx]
    if not np.sqrt(ssd) > min_df:
        status[k] = 3
        return
    df[k] = np.sqrt(ssd)
    hessian = np.zeros((6, 6))
    jac = np.empty(6)
    idx = 0
    for j in range(side):
        dy = float(j - half)
        for i in range(side):
            dx = float(i - half)
            gx = fx[k, idx]
            gy = fy[k, idx]
            jac[0] = gx
            jac[1] = gx * dx
            jac[2] = gx * dy
            jac[3] = gy
            jac[4] = gy * dx
            jac[5] = gy * dy
            for a in range(6):
                for b in range(a, 6):
                    hessian[a, b] += jac[a] * jac[b]
            idx += 1
    for a in range(6):
        for b in range(a):
            hessian[a, b] = hessian[b, a]
    if not _cholesky_inverse(hessian, hinv[k]):
        status[k] = 3
        return
    status[k] = _PENDING


@numba.njit(parallel=True, cache=True, nogil=True)
def _prepare_parallel(
    coefficients, width, height, points, half, fz, fx, fy, df, hinv, min_df, status
):
    for k in numba.prange(points.shape[0]):
        _prepare_point(
            k, coefficients, width, height, points, half, fz, fx, fy, df, hinv, min_df, status
        )


@numba.njit(cache=True, nogil=True)
def _prepare_serial(
    coefficients, width, height, points, half, fz, fx, fy, df, hinv, min_df, status
):
    for k in range(points.shape[0]):
        _prepare_point(
            k, coefficients, width, height, points, half, fz, fx, fy, df, hinv, min_df, status
        )


@numba.njit(cache=True)
def _refine_block(
    lo,
    hi,
    coefficients,
    width,
    height,
    points,
    indices,
    half,
    fz,
    fx,
    fy,
    df,
    hinv,
    params,
    max_iterations,
    znssd_tolerance,
    step_tolerance,
    zncc,
    iterations,
    status,
):
    # Refines rows lo..hi-1; row m of params, zncc, iterations and status belongs to prepared
    # point indices[m].
    side = 2 * half + 1
    count = side * side
    xmax = width - 1.0
    ymax = height - 1.0
    g = np.empty(count)
    scratch = np.empty((10, side))
    b = np.empty(6)
    dp = np.empty(6)
    for m in range(lo, hi):
        if status[m] != _PENDING:
            continue
        k = indices[m]
        x0 = points[k, 0]
        y0 = points[k, 1]
        u = params[m, 0]
        ux = params[m, 1]
        uy = params[m, 2]
        v = params[m, 3]
        vx = params[m, 4]
        vy = params[m, 5]
        previous = np.inf
        outcome = 1
        done = 0
        while done < max_iterations:
            inside = True
            for cy in (-half, half):
                for cx in (-half, half):
                    xc = x0 + cx + u + ux * cx + uy * cy
                    yc = y0 + cy + v + vx * cx + vy * cy
                    if not (0.0 <= xc <= xmax and 0.0 <= yc <= ymax):
                        inside = False
            if not inside:
                outcome = 2
                break
            for j in range(side):
                dy = float(j - half)
                xs = x0 - half + u + uy * dy - ux * half
                ys = y0 + dy + v + vy * dy - vx * half
                interpolate_line(
                    coefficients, xs, ys, 1.0 + ux, vx, g[j * side : (j + 1) * side], scratch
                )
            total = 0.0
            total2 = 0.0
            for idx in range(count):
                value = g[idx]
                total += value
                total2 += value * value
            gm = total / count
            dg2 = total2 - count * gm * gm
            if not dg2 > 0.0:
                outcome = 4
                break
            scale = df[k] / np.sqrt(dg2)
            for a in range(6):
                b[a] = 0.0
            cost = 0.0
            idx = 0
            for j in range(side):
                dy = float(j - half)
                for i in range(side):
                    dx = float(i - half)
                    r = fz[k, idx] - scale * (g[idx] - gm)
                    cost += r * r
                    ax = fx[k, idx] * r
                    ay = fy[k, idx] * r
                    b[0] += ax
                    b[1] += ax * dx
                    b[2] += ax * dy
                    b[3] += ay
                    b[4] += ay * dx
                    b[5] += ay * dy
                    idx += 1
            cost /= df[k] * df[k]
            zncc[m] = 1.0 - 0.5 * cost
            for a in range(6):
                s = 0.0
                for c in range(6):
                    s -= hinv[k, a, c] * b[c]
                dp[a] = s
            # W(p) <- W(p) o W(dp)^-1, with W as the 3 x 3 affine matrix [[1+ux, uy, u], ...].
            a11 = 1.0 + dp[1]
            a12 = dp[2]
            a21 = dp[4]
            a22 = 1.0 + dp[5]
            det = a11 * a22 - a12 * a21
            if not det > 0.0:
                outcome = 4
                break
            i11 = a22 / det
            i12 = -a12 / det
            i21 = -a21 / det
            i22 = a11 / det
            it1 = -(i11 * dp[0] + i12 * dp[3])
            it2 = -(i21 * dp[0] + i22 * dp[3])
            p11 = 1.0 + ux
            p12 = uy
            p21 = vx
            p22 = 1.0 + vy
            n11 = p11 * i11 + p12 * i21
            n12 = p11 * i12 + p12 * i22
            n21 = p21 * i11 + p22 * i21
            n22 = p21 * i12 + p22 * i22
            u = p11 * it1 + p12 * it2 + u
            v = p21 * it1 + p22 * it2 + v
            ux = n11 - 1.0
            uy = n12
            vx = n21
            vy = n22 - 1.0
            done += 1
            step = np.sqrt(
                dp[0] * dp[0]
                + dp[3] * dp[3]
                + half * half * (dp[1] * dp[1] + dp[2] * dp[2] + dp[4] * dp[4] + dp[5] * dp[5])
            )
            if not (step < side and np.isfinite(u) and np.isfinite(v)):
                outcome = 4
                break
            if (1.0 + ux) * (1.0 + vy) - uy * vx <= 0.0:
                outcome = 4
                break
            if step < step_tolerance or abs(previous - cost) < znssd_tolerance:
                outcome = 0
                break
            previous = cost
        params[m, 0] = u
        params[m, 1] = ux
        params[m, 2] = uy
        params[m, 3] = v
        params[m, 4] = vx
        params[m, 5] = vy
        iterations[m] = done
        status[m] = outcome


@numba.njit(parallel=True, cache=True, nogil=True)
def _refine_parallel(
    coefficients,
    width,
    height,
    points,
    indices,
    half,
    fz,
    fx,
    fy,
    df,
    hinv,
    params,
    max_iterations,
    znssd_tolerance,
    step_tolerance,
    block,
    zncc,
    iterations,
    status,
):
    n = indices.shape[0]
    for blk in numba.prange((n + block - 1) // block):
        _refine_block(
            blk * block,
            min(n, (blk + 1) * block),
            coefficients,
            width,
            height,
            points,
            indices,
            half,
            fz,
            fx,
            fy,
            df,
            hinv,
            params,
            max_iterations,
            znssd_tolerance,
            step_tolerance,
            zncc,
            iterations,
            status,
        )


@numba.njit(cache=True, nogil=True)
def _refine_serial(
    coefficients,
    width,
    height,
    points,
    indices,
    half,
    fz,
    fx,
    fy,
    df,
    hinv,
    params,
    max_iterations,
    znssd_tolerance,
    step_tolerance,
    block,
    zncc,
    iterations,
    status,
):
    _refine_block(
        0,
        indices.shape[0],
        coefficients,
        width,
        height,
        points,
        indices,
        half,
        fz,
        fx,
        fy,
        df,
        hinv,
        params,
        max_iterations,
        znssd_tolerance,
        step_tolerance,
        zncc,
        iterations,
        status,
    )


class ICGN:
    """Batched IC-GN subpixel refinement with a first-order shape function and ZNSSD.

    Two-phase use, after OpenCorr: `prepare(reference, points)` once per reference image and
    set of points of interest (interpolant, reference subsets, steepest-descent images,
    inverse Hessians), then `compute(target, guess)` for every target image.

    To refine one target in several batches (different points, or guesses that depend on
    earlier results), prepare it once with `prepare_target(target)` and pass the
    `PreparedTarget` to `compute` with `indices`, the prepared points to refine:

        icgn.prepare(reference, points)
        prepared = icgn.prepare_target(target)
        first = icgn.compute(prepared, seed_guess, indices=[12])
        more = icgn.compute(prepared, neighbour_guesses, indices=[11, 13, 2, 22])

    Args:
        subset: side S of the square subset, px (odd, >= 5).
        max_iterations: most Gauss-Newton updates per point (the paper uses 20).
        znssd_tolerance: stop when C_ZNSSD changes by less than this between iterations (the
            paper's rule, 1e-8). 0 disables the rule.
        step_tolerance: stop when the update is smaller than this, measured as
            sqrt(du^2 + dv^2 + h^2 (dux^2 + duy^2 + dvx^2 + dvy^2)) px, i.e. the largest
            displacement change inside the subset. 0 disables the rule.
        prefilter_sigma: standard deviation, px, of a Gaussian low-pass applied to the
            reference and every target before interpolation (0 = none). A mild pre-filter
            (0.6 to 1.0 px) removes the noise-induced bias of the spline interpolant on noisy
            images.
        min_subset_std: a reference subset whose grey-level standard deviation is below this
            is reported FLAT_SUBSET. Images are in grey levels (0..255 for 8 bit, 0..4095
            for 12 bit).
        threads: worker threads for the batch (None = numba's default, all cores). With 1,
            or a batch too small to split, the kernels run on the calling thread without a
            parallel launch; the numbers are the same either way.
    """

    def __init__(
        self,
        *,
        subset: int = 41,
        max_iterations: int = 20,
        znssd_tolerance: float = 1e-8,
        step_tolerance: float = 1e-4,
        prefilter_sigma: float = 0.0,
        min_subset_std: float = 0.01,
        threads: int | None = None,
    ) -> None:
        if subset < 5 or subset % 2 == 0:
            raise ValueError(f"subset must be an odd size >= 5, got {subset}")
        if max_iterations < 1:
            raise ValueError(f"max_iterations must be >= 1, got {max_iterations}")
        if znssd_tolerance < 0 or step_tolerance < 0 or prefilter_sigma < 0 or min_subset_std < 0:
            raise ValueError("tolerances, prefilter_sigma and min_subset_std must be >= 0")
        if threads is not None and not 1 <= threads <= numba.config.NUMBA_NUM_THREADS:
            raise ValueError(
                f"threads must be in 1..{numba.config.NUMBA_NUM_THREADS}, got {threads}"
            )
        self.subset = subset
        self.max_iterations = max_iterations
        self.znssd_tolerance = znssd_tolerance
        self.step_tolerance = step_tolerance
        self.prefilter_sigma = prefilter_sigma
        self.min_subset_std = min_subset_std
        self.threads = threads
        self._shape: tuple[int, int] | None = None

    @property
    def half(self) -> int:
        """Half width h of the subset: offsets run over [-h, h]."""
        return self.subset // 2

    @property
    def points(self) -> np.ndarray:
        """Read-only (n, 2) float64 view of the prepared points (x, y), px."""
        if self._shape is None:
            raise RuntimeError("prepare() must be called before the points are known")
        view = self._points.view()
        view.flags.writeable = False
        return view

    def coefficients(self, image: np.ndarray) -> np.ndarray:
        """Spline coefficients of an image after the configured pre-filter.

        The Gaussian pre-filter (mirror boundary, truncated at 4 sigma) and the spline filter
        give scipy's numbers bit for bit (`appliance.dic.bspline.spline_coefficients`).
        """
        return spline_coefficients(np.asarray(image), gaussian_sigma=self.prefilter_sigma)

    def prepare(self, reference: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Prepare the reference subsets of the points of interest.

        Args:
            reference: 2-D grey image (H, W).
            points: (n, 2) subset centres (x, y) in reference pixel coordinates; need not be
                integers.

        Returns:
            (n,) int8 preliminary status: -1 for usable points, otherwise `PointStatus`
            OUT_OF_IMAGE or FLAT_SUBSET.
        """
        if reference.ndim != 2:
            raise ValueError(f"reference must be a 2-D grey image, got shape {reference.shape}")
        pts = np.array(points, dtype=np.float64, order="C")
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise ValueError(f"points must have shape (n, 2), got {pts.shape}")
        if not np.all(np.isfinite(pts)):
            raise ValueError("points must be finite")
        height, width = reference.shape
        n = pts.shape[0]
        count = self.subset * self.subset
        self._points = pts
        self._every_point = np.arange(n, dtype=np.int64)
        self._shape = (height, width)
        self._fz = np.zeros((n, count))
        self._fx = np.zeros((n, count))
        self._fy = np.zeros((n, count))
        self._df = np.zeros(n)
        self._hinv = np.zeros((n, 6, 6))
        self._ready = np.zeros(n, dtype=np.int8)
        self._run(
            _prepare_serial,
            _prepare_parallel,
            n,
            self.coefficients(reference),
            width,
            height,
            pts,
            self.half,
            self._fz,
            self._fx,
            self._fy,
            self._df,
            self._hinv,
            self.min_subset_std * np.sqrt(count),
            self._ready,
        )
        return self._ready.copy()

    def prepare_target(self, target: np.ndarray) -> PreparedTarget:
        """Pre-filter a target image and compute its spline coefficients, once.

        This is the whole per-image cost of `compute` apart from the refinement itself (of
        the order of 6 ms at 700 x 700 px, 50 ms at 2048 x 2048 px); a `PreparedTarget` can
        then be refined any number of times. It does not need `prepare` to have been called.

        Args:
            target: 2-D grey image (H, W), any real dtype.

        Returns:
            `PreparedTarget` with read-only coefficients.
        """
        image = np.asarray(target)
        if image.ndim != 2:
            raise ValueError(f"target must be a 2-D grey image, got shape {image.shape}")
        coefficients = spline_coefficients(image, gaussian_sigma=self.prefilter_sigma)
        coefficients.flags.writeable = False
        return PreparedTarget(
            coefficients=coefficients,
            shape=(int(image.shape[0]), int(image.shape[1])),
            prefilter_sigma=float(self.prefilter_sigma),
        )

    def compute(
        self,
        target: np.ndarray | PreparedTarget,
        guess: np.ndarray | None = None,
        *,
        indices: np.ndarray | None = None,
    ) -> ICGNResult:
        """Refine the displacements of prepared points in a target image.

        Args:
            target: 2-D grey image with the reference's shape, or a `PreparedTarget` of such
                an image made by `prepare_target` (of this or another `ICGN` with the same
                `prefilter_sigma`); an image is prepared on every call.
            guess: initial estimate for the refined points, (m, 2) as (u, v) px or (m, 6) as
                (u, v, ux, uy, vx, vy), m = len(indices) (all prepared points when indices is
                None); None = zero. IC-GN converges from within about half a speckle of the
                truth; use an integer search, or a neighbour's result, to get there.
            indices: 1-D integer array of prepared point indices in [0, n) to refine, in any
                order, repeats allowed; None = all n prepared points in their order. The
                result of a point does not depend on which other points are refined with it.

        Returns:
            `ICGNResult` with one row per refined point, in the order of `indices` (of the
            prepared points when indices is None).
        """
        if self._shape is None:
            raise RuntimeError("prepare() must be called before compute()")
        prepared = target if isinstance(target, PreparedTarget) else None
        shape = prepared.shape if prepared is not None else np.shape(target)
        if tuple(shape) != self._shape:
            raise ValueError(f"target shape {tuple(shape)} differs from reference {self._shape}")
        if prepared is not None and prepared.prefilter_sigma != self.prefilter_sigma:
            raise ValueError(
                f"target was prepared with prefilter_sigma {prepared.prefilter_sigma}, "
                f"this ICGN uses {self.prefilter_sigma}"
            )
        rows = self._indices(indices)
        m = rows.shape[0]
        params = self._initial_parameters(guess, m)
        if prepared is None:
            prepared = self.prepare_target(target)
        status = self._ready[rows]
        zncc = np.full(m, np.nan)
        iterations = np.zeros(m, dtype=np.int32)
        height, width = self._shape
        threads = self.threads or numba.get_num_threads()
        block = max(1, min(64, -(-m // (4 * threads))))
        self._run(
            _refine_serial,
            _refine_parallel,
            -(-m // block),
            prepared.coefficients,
            width,
            height,
            self._points,
            rows,
            self.half,
            self._fz,
            self._fx,
            self._fy,
            self._df,
            self._hinv,
            params,
            self.max_iterations,
            self.znssd_tolerance,
            self.step_tolerance,
            block,
            zncc,
            iterations,
            status,
        )
        u, ux, uy, v, vx, vy = params.T.copy()
        return ICGNResult(
            u=u,
            v=v,
            ux=ux,
            uy=uy,
            vx=vx,
            vy=vy,
            zncc=zncc,
            iterations=iterations,
            status=status,
        )

    def _indices(self, indices: np.ndarray | None) -> np.ndarray:
        n = self._points.shape[0]
        if indices is None:
            return self._every_point
        rows = np.asarray(indices)
        if rows.ndim != 1 or not (rows.size == 0 or np.issubdtype(rows.dtype, np.integer)):
            raise ValueError(f"indices must be a 1-D integer array, got {rows.dtype} {rows.shape}")
        rows = rows.astype(np.int64)
        if rows.size and (rows.min() < 0 or rows.max() >= n):
            raise ValueError(f"indices must lie in [0, {n}), got {rows.min()}..{rows.max()}")
        return rows

    @staticmethod
    def _initial_parameters(guess: np.ndarray | None, m: int) -> np.ndarray:
        """(m, 6) kernel parameters (u, ux, uy, v, vx, vy) from a guess in the public order."""
        if guess is None:
            return np.zeros((m, 6))
        g = np.asarray(guess, dtype=np.float64)
        if g.shape == (m, 2):
            params = np.zeros((m, 6))
            params[:, 0] = g[:, 0]
            params[:, 3] = g[:, 1]
        elif g.shape == (m, 6):
            params = g.take(_KERNEL_ORDER, axis=1)
        else:
            raise ValueError(f"guess must have shape ({m}, 2) or ({m}, 6), got {g.shape}")
        if not np.isfinite(params).all():
            raise ValueError("guess must be finite")
        return params

    def _run(self, serial, parallel, tasks: int, *args) -> None:
        """Run a kernel over `tasks` independent work items: on this thread alone when one
        worker is allowed or there is at most one item (a parallel launch would only add the
        thread pool's start-up), otherwise in parallel on `threads` workers."""
        if tasks <= 1 or (self.threads or numba.get_num_threads()) == 1:
            serial(*args)
        elif self.threads is None:
            parallel(*args)
        else:
            saved = numba.get_num_threads()
            numba.set_num_threads(self.threads)
            try:
                parallel(*args)
            finally:
                numba.set_num_threads(saved)
