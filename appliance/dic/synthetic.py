"""Synthetic speckle images with exact ground truth.

The tracker is tested and benchmarked on images rendered here, and the simulated camera reuses
the same renderer. Everything is seeded and deterministic, and the truth is exact: a speckle
pattern is an analytic intensity function of material (reference) coordinates, and an image of
the deformed specimen is obtained by evaluating that function at the inverse-mapped position of
every pixel (or sub-pixel sample). Speckles therefore deform with the material, and the true
displacement of any material point is known to machine precision from the mapping.

Conventions (project-wide):

* Images are 2-D ``numpy`` arrays indexed ``[row, col] = [y, x]``.
* Coordinates are 0-based pixel coordinates with pixel centres at integers; ``x`` grows to the
  right (column), ``y`` grows downwards (row). Pixel ``(r, c)`` covers the square
  ``[c - 0.5, c + 0.5] x [r - 0.5, r + 0.5]``.
* A *mapping* takes a material point at reference position ``(X, Y)`` to its deformed position
  ``(x, y)``. Displacements ``u = x - X``, ``v = y - Y`` are given at reference positions.
* Grey levels are floats on the 8-bit scale unless stated otherwise; ``quantize`` turns them
  into camera counts.

Contents:

* Patterns: ``SpecklePattern`` and its generators ``gaussian_speckle`` (the classic sum of
  Gaussian spots, Zhang et al. 2016, Eq. 21, after Zhou & Goodson), ``dense_speckle`` (heavily
  overlapping small Gaussian spots, the high-gradient pattern good DIC practice asks for) and
  ``disc_speckle`` (a Boolean model of discs at Poisson positions).
* Mappings: ``AffineMapping``, ``UniaxialStretch``, ``DisplacementField`` (any smooth field,
  inverted by Newton iteration) with ``sinusoidal_displacement``, and ``true_displacement``.
* Rendering: ``render`` (analytic, with optional supersampling) and ``render_exposure`` (motion
  blur as integration of the exposure over time).
* Image operations: ``fourier_shift`` (exact rigid sub-pixel shift of a periodic band-limited
  image), ``line_psf`` and ``motion_blur`` (from ``appliance.dic.blur``, re-exported here),
  ``add_gaussian_noise``, ``add_poisson_noise`` and ``quantize``.

The module does no file I/O and imports nothing from the project outside ``appliance.dic``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from typing import Literal, Protocol

import numba
import numpy as np
import numpy.typing as npt

from appliance.dic.blur import line_psf, motion_blur

__all__ = [
    "DEFAULT_LEVELS",
    "AffineMapping",
    "DisplacementField",
    "PointMapping",
    "SpeckleKind",
    "SpecklePattern",
    "UniaxialStretch",
    "add_gaussian_noise",
    "add_poisson_noise",
    "dense_speckle",
    "disc_speckle",
    "fourier_shift",
    "gaussian_speckle",
    "line_psf",
    "motion_blur",
    "quantize",
    "render",
    "render_exposure",
    "sinusoidal_displacement",
    "true_displacement",
]

FloatArray = npt.NDArray[np.float64]
SpeckleKind = Literal["gaussian", "disc"]
Seed = int | np.random.Generator

DEFAULT_LEVELS: tuple[float, float] = (20.0, 235.0)
"""Default grey-level span ``(dark, bright)`` of generated patterns on the 8-bit scale.

Twenty grey levels of head-room at each end keep an 8-bit image (0..255) almost unclipped while
using about 85 % of its range, so that added noise and small overlaps of speckles rarely
saturate. Every generator takes ``levels`` as a parameter; for a 12-bit camera pass the span
scaled by ``4095 / 255``.
"""

_ORIGIN = -0.5
"""Left/top edge of the image domain: pixel centres are at integers, so pixel 0 starts here."""

_BLOCK_SAMPLES = 1 << 20
"""Sub-pixel samples evaluated per block in ``render`` (bounds temporary memory)."""


# --------------------------------------------------------------------------------------------
# Speckle evaluation kernels
# --------------------------------------------------------------------------------------------


@numba.njit(cache=True, inline="always")
def _value_at(
    X: float,
    Y: float,
    sx: FloatArray,
    sy: FloatArray,
    sinv: FloatArray,
    scut: FloatArray,
    sp: FloatArray,
    cell_start: npt.NDArray[np.int64],
    gx0: float,
    gy0: float,
    cell: float,
    ncx: int,
    ncy: int,
    wrap_w: float,
    wrap_h: float,
    is_disc: bool,
    background: float,
) -> float:
    """Pattern intensity at one material point, from the speckles of the 3 x 3 nearby cells."""
    if not (np.isfinite(X) and np.isfinite(Y)):
        return np.nan
    if wrap_w > 0.0:
        X = X - wrap_w * np.floor((X - _ORIGIN) / wrap_w)
    if wrap_h > 0.0:
        Y = Y - wrap_h * np.floor((Y - _ORIGIN) / wrap_h)
    fx = (X - gx0) / cell
    fy = (Y - gy0) / cell
    if fx < -1.0 or fy < -1.0 or fx >= ncx + 1.0 or fy >= ncy + 1.0:
        return background
    ix = int(np.floor(fx))
    iy = int(np.floor(fy))
    acc = 0.0
    for cy in range(max(iy - 1, 0), min(iy + 2, ncy)):
        for cx in range(max(ix - 1, 0), min(ix + 2, ncx)):
            c = cy * ncx + cx
            for k in range(cell_start[c], cell_start[c + 1]):
                dx = X - sx[k]
                dy = Y - sy[k]
                d2 = dx * dx + dy * dy
                if is_disc:
                    if d2 <= scut[k] and abs(sp[k]) > abs(acc):
                        acc = sp[k]
                elif d2 < scut[k]:
                    acc += sp[k] * np.exp(-d2 * sinv[k])
    return background + acc


@numba.njit(cache=True, parallel=True)
def _evaluate(
    px: FloatArray,
    py: FloatArray,
    out: FloatArray,
    sx: FloatArray,
    sy: FloatArray,
    sinv: FloatArray,
    scut: FloatArray,
    sp: FloatArray,
    cell_start: npt.NDArray[np.int64],
    gx0: float,
    gy0: float,
    cell: float,
    ncx: int,
    ncy: int,
    wrap_w: float,
    wrap_h: float,
    is_disc: bool,
    background: float,
) -> None:
    """``out[i] = intensity(px[i], py[i])`` for all points, in parallel."""
    for i in numba.prange(px.shape[0]):
        out[i] = _value_at(
            px[i],
            py[i],
            sx,
            sy,
            sinv,
            scut,
            sp,
            cell_start,
            gx0,
            gy0,
            cell,
            ncx,
            ncy,
            wrap_w,
            wrap_h,
            is_disc,
            background,
        )


@dataclass(frozen=True)
class _SpeckleIndex:
    """Speckles sorted into square cells at least one cut-off radius wide (reference frame)."""

    sx: FloatArray
    sy: FloatArray
    sinv: FloatArray
    scut: FloatArray
    sp: FloatArray
    cell_start: npt.NDArray[np.int64]
    gx0: float
    gy0: float
    cell: float
    ncx: int
    ncy: int


def _build_index(pattern: SpecklePattern) -> _SpeckleIndex:
    x, y, r, p = pattern.x, pattern.y, pattern.radius, pattern.peak
    reach = r if pattern.kind == "disc" else pattern.cutoff * r
    max_reach = float(reach.max()) if reach.size else 1.0
    if pattern.period is not None and x.size:
        # Wrap centres into the fundamental domain and add ghost copies within reach of its
        # edges, so a wrapped query point sees every periodic image of every speckle.
        w, h = pattern.period
        x = x - w * np.floor((x - _ORIGIN) / w)
        y = y - h * np.floor((y - _ORIGIN) / h)
        mx = math.ceil(max_reach / w)
        my = math.ceil(max_reach / h)
        parts = []
        for j in range(-my, my + 1):
            for i in range(-mx, mx + 1):
                gx, gy = x + i * w, y + j * h
                keep = (
                    (gx >= _ORIGIN - max_reach)
                    & (gx <= _ORIGIN + w + max_reach)
                    & (gy >= _ORIGIN - max_reach)
                    & (gy <= _ORIGIN + h + max_reach)
                )
                parts.append((gx[keep], gy[keep], r[keep], p[keep], reach[keep]))
        x, y, r, p, reach = (np.concatenate(a) for a in zip(*parts, strict=True))
    n = x.size
    if n == 0:
        empty = np.zeros(0)
        return _SpeckleIndex(
            empty, empty, empty, empty, empty, np.zeros(2, np.int64), 0.0, 0.0, 1.0, 1, 1
        )
    gx0, gy0 = float(x.min()), float(y.min())
    span_x = float(x.max()) - gx0
    span_y = float(y.max()) - gy0
    # Cells no narrower than the reach; widened if needed to keep about 4 cells per speckle.
    cell = max(max_reach, math.sqrt((span_x + 1.0) * (span_y + 1.0) / (4.0 * n + 16.0)))
    ncx = int(span_x // cell) + 1
    ncy = int(span_y // cell) + 1
    cx = np.minimum(((x - gx0) // cell).astype(np.int64), ncx - 1)
    cy = np.minimum(((y - gy0) // cell).astype(np.int64), ncy - 1)
    cid = cy * ncx + cx
    order = np.argsort(cid, kind="stable")
    counts = np.bincount(cid, minlength=ncx * ncy)
    cell_start = np.zeros(ncx * ncy + 1, np.int64)
    np.cumsum(counts, out=cell_start[1:])
    rs = r[order]
    if pattern.kind == "disc":
        scut = rs * rs
    else:
        scut = (pattern.cutoff * rs) ** 2
    return _SpeckleIndex(
        sx=np.ascontiguousarray(x[order]),
        sy=np.ascontiguousarray(y[order]),
        sinv=1.0 / (rs * rs),
        scut=scut,
        sp=np.ascontiguousarray(p[order]),
        cell_start=cell_start,
        gx0=gx0,
        gy0=gy0,
        cell=cell,
        ncx=ncx,
        ncy=ncy,
    )


# --------------------------------------------------------------------------------------------
# Speckle patterns
# --------------------------------------------------------------------------------------------


def _frozen_vector(values: npt.ArrayLike, n: int | None, name: str) -> FloatArray:
    a = np.asarray(values, dtype=np.float64)
    if a.ndim == 0 and n is not None:
        a = np.full(n, float(a))
    if a.ndim != 1:
        raise ValueError(f"{name} must be a 1-D array")
    if n is not None and a.size != n:
        raise ValueError(f"{name} has {a.size} entries, expected {n}")
    a = np.array(a, dtype=np.float64, copy=True, order="C")
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class SpecklePattern:
    """A speckle pattern: an analytic grey-level function of reference coordinates.

    The intensity at material point ``(X, Y)`` (px, reference configuration) is

    * ``kind == "gaussian"``: ``background + sum_k peak[k] * exp(-d_k**2 / radius[k]**2)`` with
      ``d_k`` the distance to centre ``k`` (Zhang et al. 2016, Eq. 21, after Zhou & Goodson).
      Each term is truncated at ``d_k >= cutoff * radius[k]``; the default ``cutoff = 4``
      leaves at most ``exp(-16) = 1.1e-7`` of a peak per speckle.
    * ``kind == "disc"``: ``background + peak[k]`` inside the discs ``d_k <= radius[k]``,
      ``background`` elsewhere. Where discs overlap, the covering disc whose ``peak`` has the
      largest magnitude wins, so equal peaks give the union of the discs (Boolean model).
      The edges are sharp; render disc patterns with ``oversample >= 3`` for anti-aliasing.

    If ``period = (width, height)`` is given, the pattern is periodic: every speckle repeats
    with that period in x and y, with the fundamental domain starting at the image edge
    ``-0.5``. A pattern generated periodic on a ``width x height`` image renders seamlessly
    wrapped, so rigid sub-pixel shifts by ``fourier_shift`` are exact.

    The arrays are stored as read-only float64 copies; ``radius`` may be given as a scalar.
    Equality compares all fields exactly. Use ``dataclasses.replace`` to derive a variant
    (for example with shifted centres).

    Attributes:
        x: Speckle centres, x (column) coordinate, shape ``(N,)``, px, reference configuration.
        y: Speckle centres, y (row) coordinate, shape ``(N,)``, px.
        radius: Per-speckle radius ``R``, shape ``(N,)``, px (Gaussian: ``1/e`` radius of the
            intensity; disc: geometric radius).
        peak: Per-speckle signed intensity ``I0`` added to the background, shape ``(N,)``,
            grey levels. Negative values give dark speckles.
        kind: ``"gaussian"`` or ``"disc"``.
        background: Grey level where no speckle contributes.
        period: ``(width, height)`` in px for a periodic pattern, or ``None``.
        cutoff: Truncation radius of Gaussian speckles in units of their radius (ignored for
            discs).
    """

    x: FloatArray
    y: FloatArray
    radius: FloatArray
    peak: FloatArray
    kind: SpeckleKind = "gaussian"
    background: float = 0.0
    period: tuple[float, float] | None = None
    cutoff: float = 4.0

    def __post_init__(self) -> None:
        x = _frozen_vector(self.x, None, "x")
        n = x.size
        object.__setattr__(self, "x", x)
        object.__setattr__(self, "y", _frozen_vector(self.y, n, "y"))
        object.__setattr__(self, "radius", _frozen_vector(self.radius, n, "radius"))
        object.__setattr__(self, "peak", _frozen_vector(self.peak, n, "peak"))
        object.__setattr__(self, "background", float(self.background))
        object.__setattr__(self, "cutoff", float(self.cutoff))
        if self.kind not in ("gaussian", "disc"):
            raise ValueError(f"unknown speckle kind {self.kind!r}")
        if n and not np.all(self.radius > 0.0):
            raise ValueError("speckle radii must be positive")
        if not all(np.isfinite(a).all() for a in (self.x, self.y, self.radius, self.peak)):
            raise ValueError("speckle parameters must be finite")
        if not self.cutoff > 0.0:
            raise ValueError("cutoff must be positive")
        if self.period is not None:
            w, h = (float(v) for v in self.period)
            if not (w > 0.0 and h > 0.0):
                raise ValueError("period must be positive")
            object.__setattr__(self, "period", (w, h))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, SpecklePattern):
            return NotImplemented
        return (
            self.kind == other.kind
            and self.background == other.background
            and self.period == other.period
            and self.cutoff == other.cutoff
            and all(
                np.array_equal(a, b)
                for a, b in (
                    (self.x, other.x),
                    (self.y, other.y),
                    (self.radius, other.radius),
                    (self.peak, other.peak),
                )
            )
        )

    __hash__ = None  # type: ignore[assignment]

    @property
    def count(self) -> int:
        """Number of speckles ``N`` (including those generated in the margin)."""
        return int(self.x.size)

    @cached_property
    def _index(self) -> _SpeckleIndex:
        return _build_index(self)

    def intensity(self, X: npt.ArrayLike, Y: npt.ArrayLike) -> FloatArray:
        """Evaluate the reference-configuration intensity at material points.

        Args:
            X: x (column) coordinates of the material points, px, any shape.
            Y: y (row) coordinates, px, broadcastable against ``X``.

        Returns:
            Grey levels, float64, of the broadcast shape of ``X`` and ``Y``. Points that are
            not finite give NaN.
        """
        Xb, Yb = np.broadcast_arrays(np.asarray(X, np.float64), np.asarray(Y, np.float64))
        shape = Xb.shape
        px = np.ascontiguousarray(Xb).reshape(-1)
        py = np.ascontiguousarray(Yb).reshape(-1)
        out = np.empty(px.size, np.float64)
        ix = self._index
        w, h = self.period if self.period is not None else (0.0, 0.0)
        _evaluate(
            px,
            py,
            out,
            ix.sx,
            ix.sy,
            ix.sinv,
            ix.scut,
            ix.sp,
            ix.cell_start,
            ix.gx0,
            ix.gy0,
            ix.cell,
            ix.ncx,
            ix.ncy,
            w,
            h,
            self.kind == "disc",
            self.background,
        )
        return out.reshape(shape)


def _scatter_centres(
    rng: np.random.Generator,
    width: int,
    height: int,
    count: int,
    ring_count: int,
    margin: float,
) -> tuple[FloatArray, FloatArray]:
    """``count`` uniform centres on the image domain, then ``ring_count`` in the margin ring."""
    x = _ORIGIN + rng.random(count) * width
    y = _ORIGIN + rng.random(count) * height
    if ring_count <= 0:
        return x, y
    mx, my = margin * width, margin * height
    ext_w, ext_h = width + 2.0 * mx, height + 2.0 * my
    ring_fraction = 1.0 - width * height / (ext_w * ext_h)
    rx: list[FloatArray] = []
    ry: list[FloatArray] = []
    have = 0
    while have < ring_count:
        batch = int(math.ceil((ring_count - have) / ring_fraction * 1.2)) + 16
        cx = _ORIGIN - mx + rng.random(batch) * ext_w
        cy = _ORIGIN - my + rng.random(batch) * ext_h
        outside = (cx < _ORIGIN) | (cx >= _ORIGIN + width) | (cy < _ORIGIN)
        outside |= cy >= _ORIGIN + height
        take = min(int(outside.sum()), ring_count - have)
        rx.append(cx[outside][:take])
        ry.append(cy[outside][:take])
        have += take
    return np.concatenate([x, *rx]), np.concatenate([y, *ry])


def _check_image_args(width: int, height: int, margin: float, levels: tuple[float, float]) -> None:
    if width < 1 or height < 1:
        raise ValueError("width and height must be positive")
    if margin < 0.0:
        raise ValueError("margin must be non-negative")
    if not levels[1] > levels[0]:
        raise ValueError("levels must be (dark, bright) with bright > dark")


def _ring_area_ratio(margin: float) -> float:
    return (1.0 + 2.0 * margin) ** 2 - 1.0


def gaussian_speckle(
    width: int,
    height: int,
    *,
    count: int,
    radius: float,
    seed: Seed,
    levels: tuple[float, float] = DEFAULT_LEVELS,
    peak_range: tuple[float, float] = (0.4, 0.8),
    periodic: bool = False,
    margin: float = 0.25,
    cutoff: float = 4.0,
) -> SpecklePattern:
    """Classic Gaussian speckle pattern (Zhang et al. 2016, Eq. 21; Zhou & Goodson).

    ``I(x, y) = sum_k I0_k * exp(-((x - x_k)**2 + (y - y_k)**2) / R**2)`` with ``N = count``
    centres uniformly distributed over the image domain ``[-0.5, width - 0.5) x [-0.5,
    height - 0.5)``, a common radius ``R`` and random peak intensities ``I0_k``. The paper's
    case is ``width = height = 700``, ``count = 1200``, ``radius = 4``.

    Grey-level scaling: bright speckles on a dark background. The background is
    ``levels[0]`` and ``I0_k`` is uniform in ``peak_range * (levels[1] - levels[0])``, so with
    the defaults an isolated speckle peaks at 106..192 grey levels and pairs of overlapping
    speckles fill the rest of the span. At the paper's density (about 12 % of the area within
    ``R`` of a centre) about 0.1 % of the pixels exceed ``levels[1]`` and 0.06 % exceed 255,
    so 8-bit quantisation barely clips.

    Margin: for a non-periodic pattern, speckles at the same density are added in a ring of
    width ``margin * width`` (left and right) and ``margin * height`` (top and bottom) around
    the image, ``round(count * ring_area / image_area)`` of them, so deformed images that show
    material from outside the reference image (translation, lateral contraction) stay
    speckled. Exactly ``count`` centres lie in the image domain.

    Args:
        width: Image width, px (number of columns).
        height: Image height, px (number of rows).
        count: Number ``N`` of speckles with centres in the image domain.
        radius: Speckle radius ``R``, px.
        seed: Seed or generator for ``numpy.random.default_rng``.
        levels: ``(dark, bright)`` grey-level span, see ``DEFAULT_LEVELS``.
        peak_range: Range of ``I0_k`` as fractions of ``levels[1] - levels[0]``.
        periodic: Make the pattern periodic on the image domain (speckles wrap across the
            edges; ``margin`` is then unused).
        margin: Width of the speckled margin ring as a fraction of the image size.
        cutoff: Truncation radius in units of ``R`` (see ``SpecklePattern``).

    Returns:
        A ``SpecklePattern`` of kind ``"gaussian"``.
    """
    _check_image_args(width, height, margin, levels)
    if count < 0 or not radius > 0.0:
        raise ValueError("count must be non-negative and radius positive")
    rng = np.random.default_rng(seed)
    ring = 0 if periodic else int(round(count * _ring_area_ratio(margin)))
    x, y = _scatter_centres(rng, width, height, count, ring, margin)
    span = levels[1] - levels[0]
    peak = span * rng.uniform(peak_range[0], peak_range[1], x.size)
    return SpecklePattern(
        x=x,
        y=y,
        radius=np.full(x.size, float(radius)),
        peak=peak,
        kind="gaussian",
        background=levels[0],
        period=(float(width), float(height)) if periodic else None,
        cutoff=cutoff,
    )


def dense_speckle(
    width: int,
    height: int,
    *,
    seed: Seed,
    radius: float = 2.0,
    density: float = 0.25,
    levels: tuple[float, float] = DEFAULT_LEVELS,
    clip_sigma: float = 3.0,
    periodic: bool = False,
    margin: float = 0.25,
    cutoff: float = 4.0,
) -> SpecklePattern:
    """Dense, high-gradient pattern of many small, heavily overlapping Gaussian speckles.

    Same model as ``gaussian_speckle`` (Eq. 21) but with ``density`` speckles per square
    pixel of radius ``R = radius`` and peaks of random sign and equal magnitude: dark and
    bright spots on a mid-grey background.

    Defaults and why: ``R = 2`` px gives spots about 3.3 px across at half maximum, in the
    3-5 px speckle size recommended for subset-based DIC, while the spectrum of a spot,
    ``exp(-(pi R f)**2)``, is only 5e-5 of its peak at the Nyquist frequency, so sampling at
    one pixel hardly aliases. ``density = 0.25`` puts on average ``density * pi * R**2 = pi``
    centres within one radius of any point: the field is then close to Gaussian (excess
    kurtosis ``1 / pi``), without flat background patches, and its mean intensity gradient,
    about ``sqrt(2) * sigma / R``, is roughly twice that of the paper's sparse pattern.

    Grey-level scaling (Campbell's theorem): with peaks ``+-a`` the field has mean
    ``background`` and variance ``density * a**2 * pi * R**2 / 2``. The background is the
    middle of ``levels`` and ``a`` is chosen so that ``+-clip_sigma`` standard deviations span
    ``levels``; with ``clip_sigma = 3`` about 0.5 % of the pixels fall outside the span
    (slightly more than the Gaussian 0.27 % because of the residual kurtosis) and 0.1 % outside
    0..255.

    Args:
        width: Image width, px.
        height: Image height, px.
        seed: Seed or generator for ``numpy.random.default_rng``.
        radius: Speckle radius ``R``, px.
        density: Speckle centres per square pixel.
        levels: ``(dark, bright)`` grey-level span, see ``DEFAULT_LEVELS``.
        clip_sigma: Number of standard deviations of the field mapped to each end of
            ``levels``.
        periodic: Make the pattern periodic on the image domain.
        margin: Width of the speckled margin ring as a fraction of the image size (see
            ``gaussian_speckle``).
        cutoff: Truncation radius in units of ``R``.

    Returns:
        A ``SpecklePattern`` of kind ``"gaussian"`` with ``round(density * width * height)``
        centres in the image domain.
    """
    _check_image_args(width, height, margin, levels)
    if not (radius > 0.0 and density > 0.0 and clip_sigma > 0.0):
        raise ValueError("radius, density and clip_sigma must be positive")
    rng = np.random.default_rng(seed)
    count = int(round(density * width * height))
    ring = 0 if periodic else int(round(count * _ring_area_ratio(margin)))
    x, y = _scatter_centres(rng, width, height, count, ring, margin)
    sigma = (levels[1] - levels[0]) / (2.0 * clip_sigma)
    amplitude = sigma / math.sqrt(density * math.pi * radius**2 / 2.0)
    peak = amplitude * np.where(rng.random(x.size) < 0.5, -1.0, 1.0)
    return SpecklePattern(
        x=x,
        y=y,
        radius=np.full(x.size, float(radius)),
        peak=peak,
        kind="gaussian",
        background=0.5 * (levels[0] + levels[1]),
        period=(float(width), float(height)) if periodic else None,
        cutoff=cutoff,
    )


def disc_speckle(
    width: int,
    height: int,
    *,
    seed: Seed,
    radius: float = 2.5,
    coverage: float = 0.5,
    levels: tuple[float, float] = DEFAULT_LEVELS,
    dark_on_bright: bool = True,
    periodic: bool = False,
    margin: float = 0.25,
) -> SpecklePattern:
    """Boolean-model speckle: the union of discs of radius ``R`` at Poisson positions.

    Centres form a homogeneous Poisson process of intensity
    ``lambda = -ln(1 - coverage) / (pi R**2)``, so the expected fraction of the area covered
    by the union of the discs is ``coverage`` (Boolean model). The union is ``levels[0]`` on a
    ``levels[1]`` background (``dark_on_bright``, like sprayed black paint on a white
    coat) or the reverse. Edges are sharp; ``render`` with ``oversample >= 3`` anti-aliases
    them by supersampling.

    Args:
        width: Image width, px.
        height: Image height, px.
        seed: Seed or generator for ``numpy.random.default_rng``.
        radius: Disc radius ``R``, px.
        coverage: Expected covered area fraction, in ``(0, 1)``.
        levels: ``(dark, bright)`` grey levels, see ``DEFAULT_LEVELS``.
        dark_on_bright: Dark discs on a bright background if true, bright on dark otherwise.
        periodic: Make the pattern periodic on the image domain.
        margin: Width of the margin ring (fraction of the image size) also filled with discs
            at the same intensity, for non-periodic patterns.

    Returns:
        A ``SpecklePattern`` of kind ``"disc"``.
    """
    _check_image_args(width, height, margin, levels)
    if not (radius > 0.0 and 0.0 < coverage < 1.0):
        raise ValueError("radius must be positive and coverage in (0, 1)")
    rng = np.random.default_rng(seed)
    lam = -math.log1p(-coverage) / (math.pi * radius**2)
    count = int(rng.poisson(lam * width * height))
    ring = 0 if periodic else int(rng.poisson(lam * width * height * _ring_area_ratio(margin)))
    x, y = _scatter_centres(rng, width, height, count, ring, margin)
    dark, bright = levels
    background, ink = (bright, dark) if dark_on_bright else (dark, bright)
    return SpecklePattern(
        x=x,
        y=y,
        radius=np.full(x.size, float(radius)),
        peak=np.full(x.size, ink - background),
        kind="disc",
        background=background,
        period=(float(width), float(height)) if periodic else None,
    )


# --------------------------------------------------------------------------------------------
# Mappings
# --------------------------------------------------------------------------------------------


class PointMapping(Protocol):
    """A mapping from reference (material) positions to deformed positions.

    Both methods are vectorised: they take float arrays of any common (broadcastable) shape, in
    px, and return a pair of float64 arrays of the broadcast shape.
    """

    def forward(self, X: npt.ArrayLike, Y: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Deformed position ``(x, y)`` of the material point at reference ``(X, Y)``."""
        ...

    def inverse(self, x: npt.ArrayLike, y: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Reference position ``(X, Y)`` of the material point now at ``(x, y)``."""
        ...


def _as_pair(a: npt.ArrayLike, b: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    A, B = np.broadcast_arrays(np.asarray(a, np.float64), np.asarray(b, np.float64))
    return A, B


@dataclass(frozen=True)
class AffineMapping:
    """Homogeneous (affine) deformation about a centre ``(xc, yc)``.

    ``x = X + u + ux (X - xc) + uy (Y - yc)``, ``y = Y + v + vx (X - xc) + vy (Y - yc)``:
    the first-order shape function of DIC, with ``(u, v)`` the displacement of the centre and
    ``ux = du/dX``, ``uy = du/dY``, ``vx = dv/dX``, ``vy = dv/dY`` the displacement gradients.
    The inverse is exact (closed-form 2x2 inverse of ``F = I + grad u``), which requires
    ``det F > 0``.

    Attributes:
        u: x displacement of the centre, px.
        v: y displacement of the centre, px.
        ux: du/dX, dimensionless.
        uy: du/dY, dimensionless.
        vx: dv/dX, dimensionless.
        vy: dv/dY, dimensionless.
        xc: x of the centre (reference), px.
        yc: y of the centre (reference), px.
    """

    u: float = 0.0
    v: float = 0.0
    ux: float = 0.0
    uy: float = 0.0
    vx: float = 0.0
    vy: float = 0.0
    xc: float = 0.0
    yc: float = 0.0

    def __post_init__(self) -> None:
        if not self.determinant > 0.0:
            raise ValueError("deformation gradient must have a positive determinant")

    @classmethod
    def translation(cls, dx: float, dy: float) -> AffineMapping:
        """Rigid translation by ``(dx, dy)`` px."""
        return cls(u=dx, v=dy)

    @property
    def determinant(self) -> float:
        """``det F = (1 + ux)(1 + vy) - uy vx``: local area ratio deformed/reference."""
        return (1.0 + self.ux) * (1.0 + self.vy) - self.uy * self.vx

    def forward(self, X: npt.ArrayLike, Y: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Deformed position ``(x, y)`` of reference points ``(X, Y)`` (px, arrays)."""
        X, Y = _as_pair(X, Y)
        dX = X - self.xc
        dY = Y - self.yc
        x = X + self.u + self.ux * dX + self.uy * dY
        y = Y + self.v + self.vx * dX + self.vy * dY
        return x, y

    def inverse(self, x: npt.ArrayLike, y: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Reference position ``(X, Y)`` of deformed points ``(x, y)`` (px, arrays)."""
        x, y = _as_pair(x, y)
        a, b = 1.0 + self.ux, self.uy
        c, d = self.vx, 1.0 + self.vy
        det = self.determinant
        rx = x - self.xc - self.u
        ry = y - self.yc - self.v
        X = self.xc + (d * rx - b * ry) / det
        Y = self.yc + (-c * rx + a * ry) / det
        return X, Y


@dataclass(frozen=True)
class UniaxialStretch:
    """Uniaxial stretch with lateral contraction about a centre ``(xc, yc)``.

    Stretch ``lambda = stretch`` along ``axis`` and lateral stretch ``lambda_t`` across it:

    * ``poisson_ratio is None``: ``lambda_t = lambda ** -0.5`` (incompressible, e.g. rubber:
      ``lambda * lambda_t**2 = 1``);
    * otherwise ``lambda_t = 1 - nu * (lambda - 1)`` (linear elasticity with Poisson's ratio
      ``nu``).

    For ``axis = "x"``: ``x = xc + lambda (X - xc)``, ``y = yc + lambda_t (Y - yc)``. The
    centre does not move; compose with a translation if it should.

    Attributes:
        stretch: Axial stretch ratio ``lambda`` (> 0; 1 + engineering strain).
        axis: ``"x"`` (along columns) or ``"y"`` (along rows).
        poisson_ratio: ``nu`` for linear lateral contraction, or ``None`` for incompressible.
        xc: x of the fixed centre, px.
        yc: y of the fixed centre, px.
    """

    stretch: float
    axis: Literal["x", "y"] = "x"
    poisson_ratio: float | None = None
    xc: float = 0.0
    yc: float = 0.0

    def __post_init__(self) -> None:
        if not self.stretch > 0.0:
            raise ValueError("stretch must be positive")
        if self.axis not in ("x", "y"):
            raise ValueError("axis must be 'x' or 'y'")
        if not self.lateral_stretch > 0.0:
            raise ValueError("lateral stretch must be positive")

    @property
    def lateral_stretch(self) -> float:
        """Lateral stretch ratio ``lambda_t`` (see class docstring)."""
        if self.poisson_ratio is None:
            return self.stretch**-0.5
        return 1.0 - self.poisson_ratio * (self.stretch - 1.0)

    @property
    def affine(self) -> AffineMapping:
        """The same deformation as an ``AffineMapping``."""
        ea, et = self.stretch - 1.0, self.lateral_stretch - 1.0
        ux, vy = (ea, et) if self.axis == "x" else (et, ea)
        return AffineMapping(ux=ux, vy=vy, xc=self.xc, yc=self.yc)

    def forward(self, X: npt.ArrayLike, Y: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Deformed position ``(x, y)`` of reference points ``(X, Y)`` (px, arrays)."""
        return self.affine.forward(X, Y)

    def inverse(self, x: npt.ArrayLike, y: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Reference position ``(X, Y)`` of deformed points ``(x, y)`` (px, arrays)."""
        return self.affine.inverse(x, y)


FieldFunction = Callable[[FloatArray, FloatArray], FloatArray]
GradientFunction = Callable[
    [FloatArray, FloatArray], tuple[FloatArray, FloatArray, FloatArray, FloatArray]
]


@dataclass(frozen=True)
class DisplacementField:
    """General non-uniform deformation ``x = X + u(X, Y)``, ``y = Y + v(X, Y)``.

    ``u`` and ``v`` are vectorised callables of reference coordinates (px in, px out). The
    inverse solves ``X + u(X, Y) = x``, ``Y + v(X, Y) = y`` by Newton iteration started from
    the fixed-point step ``X0 = x - u(x, y)``, until the residual of every point is at most
    ``tol`` px in both components. The Jacobian ``F = I + grad u`` comes from ``gradient``
    when given, otherwise from central differences with step ``fd_step``; the stopping test
    uses the exact residual, so either way the result is accurate to ``tol``. The mapping
    must be invertible (``det F > 0`` everywhere and one-to-one).

    Attributes:
        u: ``u(X, Y)``, x displacement at reference points, px.
        v: ``v(X, Y)``, y displacement at reference points, px.
        gradient: Optional ``(X, Y) -> (du/dX, du/dY, dv/dX, dv/dY)``.
        tol: Residual tolerance of the inverse, px.
        max_iter: Iteration limit of the inverse; exceeding it raises ``RuntimeError``.
        fd_step: Central-difference step for the Jacobian when ``gradient`` is absent, px.
    """

    u: FieldFunction
    v: FieldFunction
    gradient: GradientFunction | None = None
    tol: float = 1e-10
    max_iter: int = 50
    fd_step: float = 1e-4

    def displacement(self, X: npt.ArrayLike, Y: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """``(u, v)`` at reference points ``(X, Y)``, float64 arrays of the broadcast shape."""
        X, Y = _as_pair(X, Y)
        u = np.broadcast_to(np.asarray(self.u(X, Y), np.float64), X.shape)
        v = np.broadcast_to(np.asarray(self.v(X, Y), np.float64), X.shape)
        return u, v

    def forward(self, X: npt.ArrayLike, Y: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Deformed position ``(x, y)`` of reference points ``(X, Y)`` (px, arrays)."""
        X, Y = _as_pair(X, Y)
        u, v = self.displacement(X, Y)
        return X + u, Y + v

    def _jacobian(
        self, X: FloatArray, Y: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        if self.gradient is not None:
            g = self.gradient(X, Y)
            ux, uy, vx, vy = (np.broadcast_to(np.asarray(a, np.float64), X.shape) for a in g)
        else:
            h = self.fd_step
            up, vp = self.displacement(X + h, Y)
            um, vm = self.displacement(X - h, Y)
            ux, vx = (up - um) / (2.0 * h), (vp - vm) / (2.0 * h)
            up, vp = self.displacement(X, Y + h)
            um, vm = self.displacement(X, Y - h)
            uy, vy = (up - um) / (2.0 * h), (vp - vm) / (2.0 * h)
        return 1.0 + ux, uy, vx, 1.0 + vy

    def inverse(self, x: npt.ArrayLike, y: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Reference position ``(X, Y)`` of deformed points ``(x, y)``, to ``tol`` px.

        Raises:
            RuntimeError: if some point has not converged after ``max_iter`` iterations.
        """
        x, y = _as_pair(x, y)
        shape = x.shape
        xf, yf = x.reshape(-1), y.reshape(-1)
        u0, v0 = self.displacement(xf, yf)
        X = xf - u0
        Y = yf - v0
        active = np.arange(xf.size)
        for _ in range(self.max_iter + 1):
            Xa, Ya = X[active], Y[active]
            u, v = self.displacement(Xa, Ya)
            rx = Xa + u - xf[active]
            ry = Ya + v - yf[active]
            todo = (np.abs(rx) > self.tol) | (np.abs(ry) > self.tol)
            todo |= ~(np.isfinite(rx) & np.isfinite(ry))
            if not todo.any():
                break
            active = active[todo]
            Xa, Ya, rx, ry = Xa[todo], Ya[todo], rx[todo], ry[todo]
            a, b, c, d = self._jacobian(Xa, Ya)
            det = a * d - b * c
            X[active] = Xa - (d * rx - b * ry) / det
            Y[active] = Ya - (-c * rx + a * ry) / det
        else:
            raise RuntimeError(
                f"inverse mapping did not converge to {self.tol} px at {active.size} points"
            )
        return X.reshape(shape), Y.reshape(shape)


def sinusoidal_displacement(
    amplitude_u: float,
    amplitude_v: float,
    wavelength: float,
    *,
    angle_deg: float = 0.0,
    phase: float = 0.0,
) -> DisplacementField:
    """A plane sinusoidal displacement wave, with its analytic gradient.

    ``(u, v) = (amplitude_u, amplitude_v) * sin(k . (X, Y) + phase)`` with wave vector
    ``k = 2 pi / wavelength * (cos(angle), sin(angle))`` in image coordinates (angle from +x
    towards +y, i.e. clockwise on screen since y points down). ``angle_deg = 0`` and
    ``amplitude_v = 0`` is the usual test of DIC spatial resolution: ``u`` varying along x.

    The mapping is one-to-one iff ``|k . (amplitude_u, amplitude_v)| < 1``, which is checked.

    Args:
        amplitude_u: Amplitude of ``u``, px.
        amplitude_v: Amplitude of ``v``, px.
        wavelength: Wavelength along the wave vector, px.
        angle_deg: Direction of the wave vector, degrees.
        phase: Phase at the origin, radians.

    Returns:
        A ``DisplacementField`` with ``gradient`` set.
    """
    if not wavelength > 0.0:
        raise ValueError("wavelength must be positive")
    k = 2.0 * math.pi / wavelength
    kx = k * math.cos(math.radians(angle_deg))
    ky = k * math.sin(math.radians(angle_deg))
    if not abs(kx * amplitude_u + ky * amplitude_v) < 1.0:
        raise ValueError("sinusoidal field is not invertible: |k . amplitude| must be < 1")

    def u(X: FloatArray, Y: FloatArray) -> FloatArray:
        return amplitude_u * np.sin(kx * X + ky * Y + phase)

    def v(X: FloatArray, Y: FloatArray) -> FloatArray:
        return amplitude_v * np.sin(kx * X + ky * Y + phase)

    def gradient(
        X: FloatArray, Y: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        c = np.cos(kx * X + ky * Y + phase)
        cu, cv = amplitude_u * c, amplitude_v * c
        return cu * kx, cu * ky, cv * kx, cv * ky

    return DisplacementField(u=u, v=v, gradient=gradient)


def true_displacement(
    mapping: PointMapping, X: npt.ArrayLike, Y: npt.ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """Exact displacement ``(u, v) = forward(X, Y) - (X, Y)`` at reference points, px."""
    X, Y = _as_pair(X, Y)
    x, y = mapping.forward(X, Y)
    return x - X, y - Y


# --------------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------------


def render(
    pattern: SpecklePattern,
    height: int,
    width: int,
    mapping: PointMapping | None = None,
    *,
    oversample: int = 1,
) -> FloatArray:
    """Render the deformed pattern analytically.

    Pixel ``(r, c)`` is the reference intensity at ``mapping.inverse(c, r)``: the material
    point seen there, so speckles move and deform with the material and the mapping is the
    exact ground truth. With ``oversample = n > 1`` each pixel is the mean of ``n x n``
    samples at ``c + (i + 0.5) / n - 0.5``, ``r + (j + 0.5) / n - 0.5`` (box-filtered pixel
    area, which anti-aliases disc edges).

    Speckles are binned on a grid of cells in reference coordinates and a compiled kernel
    sums, for each sample, only the speckles of the neighbouring cells within the cut-off;
    the work is split into blocks of rows and runs on all cores.

    Args:
        pattern: The speckle pattern (reference configuration).
        height: Number of rows.
        width: Number of columns.
        mapping: Reference-to-deformed mapping; ``None`` renders the reference image.
        oversample: Sub-pixel samples per pixel along each axis, >= 1.

    Returns:
        float64 image of shape ``(height, width)``, grey levels (not clipped).
    """
    if height < 1 or width < 1:
        raise ValueError("height and width must be positive")
    n = int(oversample)
    if n < 1:
        raise ValueError("oversample must be >= 1")
    offsets = (np.arange(n) + 0.5) / n - 0.5
    xs = (np.arange(width)[:, None] + offsets[None, :]).reshape(-1)
    out = np.empty((height, width), np.float64)
    rows = max(1, _BLOCK_SAMPLES // (width * n * n))
    for r0 in range(0, height, rows):
        r1 = min(height, r0 + rows)
        ys = (np.arange(r0, r1)[:, None] + offsets[None, :]).reshape(-1)
        X, Y = np.meshgrid(xs, ys)
        if mapping is not None:
            X, Y = mapping.inverse(X, Y)
        values = pattern.intensity(X, Y)
        if n == 1:
            out[r0:r1] = values
        else:
            out[r0:r1] = values.reshape(r1 - r0, n, width, n).mean(axis=(1, 3))
    return out


def render_exposure(
    pattern: SpecklePattern,
    height: int,
    width: int,
    mapping_at: Callable[[float], PointMapping | None],
    *,
    start: float,
    stop: float,
    samples: int,
    oversample: int = 1,
) -> FloatArray:
    """Render an exposure integrated over time: motion blur along the real velocity field.

    The image is the mean of ``render(pattern, height, width, mapping_at(t_i), oversample=...)``
    at ``t_i = start + (i + 0.5) (stop - start) / samples``, ``i = 0 .. samples - 1``: the
    midpoint rule for the time average of the irradiance over the exposure ``[start, stop]``.
    For a constant-velocity translation this equals a line blur (``motion_blur``) whose length
    is the distance travelled during the exposure.

    Args:
        pattern: The speckle pattern.
        height: Number of rows.
        width: Number of columns.
        mapping_at: Mapping at time ``t`` (``None`` for the reference configuration).
        start: Start of the exposure, in the time unit of ``mapping_at``.
        stop: End of the exposure.
        samples: Number of time samples, >= 1.
        oversample: Sub-pixel samples per pixel along each axis (see ``render``).

    Returns:
        float64 image of shape ``(height, width)``, grey levels.
    """
    if samples < 1:
        raise ValueError("samples must be >= 1")
    acc = np.zeros((height, width), np.float64)
    dt = (stop - start) / samples
    for i in range(samples):
        mapping = mapping_at(start + (i + 0.5) * dt)
        acc += render(pattern, height, width, mapping, oversample=oversample)
    return acc / samples


# --------------------------------------------------------------------------------------------
# Image operations
# --------------------------------------------------------------------------------------------


def fourier_shift(image: npt.ArrayLike, dx: float, dy: float) -> FloatArray:
    """Shift image content by ``(+dx, +dy)`` px by the Fourier shift theorem.

    ``out(x, y) = in(x - dx, y - dy)`` with the image taken as one period of a periodic,
    band-limited function: the spectrum is multiplied by ``exp(-2 pi i (fx dx + fy dy))``
    and the real part of the inverse transform is returned (for an even size the Nyquist
    component is thus scaled by ``cos(pi d)``, the symmetric band-limited interpretation).
    Exact for a periodic image whose spectrum vanishes at the Nyquist frequency, such as a
    periodic Gaussian speckle pattern of radius >= 2 px; a non-periodic image wraps around
    and rings at its edges.

    Args:
        image: 2-D array, any real dtype.
        dx: Shift along x (columns), px; positive moves content to the right.
        dy: Shift along y (rows), px; positive moves content down.

    Returns:
        float64 image of the same shape.
    """
    img = np.asarray(image, np.float64)
    if img.ndim != 2:
        raise ValueError("image must be 2-D")
    fy = np.fft.fftfreq(img.shape[0])[:, None]
    fx = np.fft.fftfreq(img.shape[1])[None, :]
    phase = np.exp(-2j * np.pi * (fx * dx + fy * dy))
    return np.fft.ifft2(np.fft.fft2(img) * phase).real


def add_gaussian_noise(image: npt.ArrayLike, sigma: float, *, seed: Seed) -> FloatArray:
    """Add zero-mean white Gaussian noise of standard deviation ``sigma`` grey levels.

    Args:
        image: Array of grey levels, any shape.
        sigma: Noise standard deviation, grey levels (>= 0).
        seed: Seed or generator for ``numpy.random.default_rng``.

    Returns:
        float64 array of the same shape (not clipped; see ``quantize``).
    """
    if not sigma >= 0.0:
        raise ValueError("sigma must be non-negative")
    img = np.asarray(image, np.float64)
    rng = np.random.default_rng(seed)
    return img + rng.normal(0.0, sigma, img.shape) if sigma > 0.0 else img.copy()


def add_poisson_noise(
    image: npt.ArrayLike, gain: float, *, seed: Seed, black_level: float = 0.0
) -> FloatArray:
    """Apply photon shot noise with a conversion gain of ``gain`` electrons per grey level.

    The expected number of electrons of a pixel is ``(image - black_level) * gain`` (negative
    values count as 0); a Poisson sample of it is converted back to grey levels. The variance
    of the result is therefore ``(image - black_level) / gain`` grey levels squared and its
    mean is unchanged.

    Args:
        image: Array of expected grey levels, any shape.
        gain: Conversion gain, electrons per grey level (> 0).
        seed: Seed or generator for ``numpy.random.default_rng``.
        black_level: Grey level of zero signal (dark offset), not subject to shot noise.

    Returns:
        float64 array of the same shape (not clipped; see ``quantize``).
    """
    if not gain > 0.0:
        raise ValueError("gain must be positive")
    img = np.asarray(image, np.float64)
    rng = np.random.default_rng(seed)
    electrons = np.clip((img - black_level) * gain, 0.0, None)
    return black_level + rng.poisson(electrons) / gain


def quantize(image: npt.ArrayLike, bits: int = 8) -> npt.NDArray[np.unsignedinteger]:
    """Round to the nearest integer and clip to ``0 .. 2**bits - 1`` camera counts.

    Ties round to even (``numpy.rint``). 8-bit (and fewer) images are returned as ``uint8``,
    9- to 16-bit images (e.g. 12-bit, values 0..4095) as ``uint16``.

    Args:
        image: Array of grey levels on the target scale, any shape; must be finite.
        bits: Bit depth, 1..16.

    Returns:
        Unsigned integer array of the same shape.
    """
    if not 1 <= bits <= 16:
        raise ValueError("bits must be in 1..16")
    img = np.asarray(image, np.float64)
    if not np.isfinite(img).all():
        raise ValueError("image must be finite to quantise")
    dtype = np.uint8 if bits <= 8 else np.uint16
    return np.clip(np.rint(img), 0, (1 << bits) - 1).astype(dtype)
