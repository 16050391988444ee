"""What the simulated camera sees: a speckled specimen deforming in front of a dark backdrop.

`SpecimenScene` implements `hal.camera.base.Scene`. It owns the optics of the simulation (a
telecentric view: a fixed object-plane scale, no distortion) and the speckle coat painted on the
specimen; the specimen's shape over time comes from a function `deformation_at(t_s)` returning
an `AxialDeformation` (see `appliance.sim.deformation` for its coordinate frames).

View. The specimen axis is vertical in the image: material Y maps to image y (rows, downwards),
X to x (columns). With scale ``s`` mm/px, a ``W x H`` sensor and the object point ``(cx, cy)`` mm
imaged at the sensor centre, the centre of pixel column ``c`` and row ``r`` sees the
object-plane point

    x = cx + (c - (W - 1) / 2) * s,        y = cy + (r - (H - 1) / 2) * s      (mm).

Pixel conventions are the project's: pixel centres at integers, x = column, y = row.

Rendering. The coat is an analytic speckle pattern (`appliance.dic.synthetic`) in material
coordinates. At construction it is evaluated once on a texture of texel size ``s / oversample``
over the whole material extent that can come into view, and the texture's cubic B-spline
coefficients are kept in single precision (`appliance.dic.bspline`; the rounding is about
1e-5 grey levels, far below the interpolation error). A time sample of a frame maps every pixel
centre to the object plane, then to material coordinates through the deformation (separable:
the row gives Y, the column and lambda_t(Y) give X), and samples the texture there. Across the
specimen's edge the coat is blended with the backdrop by the fraction of the pixel the specimen
covers; rows whose material section lies outside the textured range show the backdrop.

Exposure. A frame is the mean of N time samples at the midpoints of N equal sub-intervals of
the exposure, with N chosen so that no visible material point moves more than
`max_sample_step_px` between successive samples (motion blur along the true velocity field).
`image_positions` averages material point positions over the same samples, which is where a
correlator finds a point under symmetric blur.

Painted marks. `PaintedMarks` (optional) paints two dots or two lines across the specimen over
the speckle, in material coordinates, into the same texture: they stretch with the material
(a round dot becomes an ellipse as the rubber stretches) and are blurred by the same motion.

Truth. `render` returns, with the image, a small mapping (times and sample count); gauge truth
is derived from `material_points` and `image_positions`.
"""

from __future__ import annotations

import collections
import math
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Literal

import numba
import numpy as np
import numpy.typing as npt

from appliance.dic.bspline import PAD, cubic_weights, spline_coefficients
from appliance.dic.synthetic import (
    DEFAULT_LEVELS,
    SpecklePattern,
    dense_speckle,
    gaussian_speckle,
    render,
)
from appliance.sim.deformation import AxialDeformation
from hal.camera.base import Region

FloatArray = npt.NDArray[np.float64]
CoatKind = Literal["dense", "gaussian"]

_GAUSSIAN_CENTRES_PER_RADIUS2 = 1200.0 / 700.0**2 * 4.0**2
"""Speckle centres per squared radius of Zhang et al.'s (2016) sparse Gaussian pattern."""

_ROUNDING = 1e-9
"""Slack on the motion in sample steps, so that an exact multiple of the step is not rounded up."""


TEXTURE_OVERSAMPLE = 2
"""Texels per pixel (each way) of the specimen's texture, by default."""

RECENT_EXPOSURES = 96
"""Exposures whose shapes a scene keeps (each frame's, and its start's and stop's instants):
the truth of a frame, computed on another thread a few frames after it was rendered, reuses
them instead of solving the specimen again."""


def _exposure_key(start_s: float, stop_s: float) -> tuple[int, int]:
    """An exposure to the nanosecond: a frame's timestamp (whole ns) names the exposure it
    was rendered for."""
    return round(start_s * 1e9), round(stop_s * 1e9)


@dataclass(frozen=True)
class SpeckleCoat:
    """The speckle pattern painted on the specimen, in material coordinates.

    Attributes:
        radius_mm: speckle radius R (1/e radius of a Gaussian spot), mm.
        kind: "dense" (many heavily overlapping dark and bright spots on mid grey, see
            `appliance.dic.synthetic.dense_speckle`) or "gaussian" (sparse bright spots on a
            dark coat, `gaussian_speckle`).
        density_per_mm2: speckle centres per mm^2; None = the kind's default: 1 / R^2 for
            "dense" (pi centres within one radius of any point), 0.039 / R^2 for "gaussian"
            (the density of Zhang et al. 2016).
        levels: (dark, bright) grey-level span of the coat on the 8-bit scale.
        seed: seed of the pattern; the same coat and extent give the same pattern.
    """

    radius_mm: float
    kind: CoatKind = "dense"
    density_per_mm2: float | None = None
    levels: tuple[float, float] = DEFAULT_LEVELS
    seed: int = 0

    def __post_init__(self) -> None:
        if not self.radius_mm > 0:
            raise ValueError(f"radius_mm must be > 0, got {self.radius_mm}")
        if self.kind not in ("dense", "gaussian"):
            raise ValueError(f"kind must be 'dense' or 'gaussian', got {self.kind!r}")
        if self.density_per_mm2 is not None and not self.density_per_mm2 > 0:
            raise ValueError(f"density_per_mm2 must be > 0, got {self.density_per_mm2}")

    @property
    def density(self) -> float:
        """Speckle centres per mm^2 in force (the kind's default when none was given)."""
        if self.density_per_mm2 is not None:
            return self.density_per_mm2
        per_radius2 = 1.0 if self.kind == "dense" else _GAUSSIAN_CENTRES_PER_RADIUS2
        return per_radius2 / self.radius_mm**2

    def pattern(self, width: int, height: int, texel_mm: float) -> SpecklePattern:
        """The coat as a pattern on a ``width x height`` texture of texel size `texel_mm`.

        Speckle centres are spread over the texture only (no margin ring): keep the part of
        the texture that is used at least 4 radii from its edges.
        """
        radius = self.radius_mm / texel_mm
        density = self.density * texel_mm**2
        if self.kind == "dense":
            return dense_speckle(
                width,
                height,
                seed=self.seed,
                radius=radius,
                density=density,
                levels=self.levels,
                margin=0.0,
            )
        return gaussian_speckle(
            width,
            height,
            count=int(round(density * width * height)),
            radius=radius,
            seed=self.seed,
            levels=self.levels,
            margin=0.0,
        )


PaintedKind = Literal["dots", "lines"]


@dataclass(frozen=True)
class PaintedMarks:
    """Two contrasting marks painted over the speckle coat, in material coordinates.

    Attributes:
        kind: "dots" (discs of radius `size_mm`) or "lines" (bands `2 * size_mm` wide across
            the whole specimen).
        centres_y_mm: material Y of each mark's centre, mm (on the specimen's axis, X = 0).
        size_mm: radius of a dot, or half-width of a line, mm.
        level: grey level of the paint, 8-bit scale.
        edge_mm: width of the paint's edge (a linear ramp from paint to coat), mm.
    """

    kind: PaintedKind
    centres_y_mm: tuple[float, ...]
    size_mm: float
    level: float = 250.0
    edge_mm: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in ("dots", "lines"):
            raise ValueError(f"kind must be 'dots' or 'lines', got {self.kind!r}")
        if not self.size_mm > 0:
            raise ValueError(f"size_mm must be > 0, got {self.size_mm}")

    def coverage(self, X_mm: FloatArray, Y_mm: FloatArray, edge_mm: float) -> FloatArray:
        """Fraction of paint (0..1) at material points (X, Y), mm: 1 inside a mark, 0 outside,
        a linear ramp `edge_mm` wide across its outline (`edge_mm` > 0)."""
        cover = np.zeros(np.broadcast(X_mm, Y_mm).shape)
        for centre in self.centres_y_mm:
            if self.kind == "dots":
                distance = np.hypot(X_mm, Y_mm - centre)
            else:
                distance = np.abs(Y_mm - centre) + 0.0 * X_mm
            inside = np.clip(0.5 + (self.size_mm - distance) / edge_mm, 0.0, 1.0)
            cover = np.maximum(cover, inside)
        return cover

    def paint(self, texture: FloatArray, origin_mm: tuple[float, float], texel_mm: float) -> None:
        """Paint the marks into `texture` (rows = material Y, columns = X; texel (0, 0) at
        material `origin_mm`), in place."""
        edge = self.edge_mm if self.edge_mm > 0 else 2.0 * texel_mm
        rows, columns = texture.shape
        X = origin_mm[0] + np.arange(columns) * texel_mm
        Y = origin_mm[1] + np.arange(rows) * texel_mm
        cover = self.coverage(X[np.newaxis, :], Y[:, np.newaxis], edge)
        texture += cover * (self.level - texture)


EDGE_SEARCH_MARGIN_PX = 2
"""Columns beyond a row's computed edge still evaluated pixel by pixel, against rounding."""


@numba.njit(parallel=True, nogil=True, cache=True)
def integrate_exposure(
    out: FloatArray,
    weight: float,
    coefficients: np.ndarray,
    row_ty: FloatArray,
    row_inv_stretch: FloatArray,
    row_half_width_mm: FloatArray,
    row_textured: npt.NDArray[np.bool_],
    row_pixel_mm: FloatArray,
    col_offset_px: FloatArray,
    x_centre_mm: float,
    x_origin_texels: float,
    inv_texel_mm: float,
    background: float,
) -> None:
    """``out = sum over the time samples s of weight * (sample s of the view)``, in parallel by
    row, without the GIL.

    Sample s: pixel (r, c) sees the object-plane point x = x_centre + offset[s, c] *
    size[s, r] (mm) across the specimen, on the material section of row r (texel row
    `row_ty[s, r]`), and covers `size[s, r]` mm of it (the edge blend). The plain scene's size
    is its scale on every row; a bench's varies by row with the surface's distance. The
    per-sample arrays are (samples, rows) and (samples, columns).

    Each pixel is the sum, in sample order from 0, of weight times its value in each sample.
    Only the columns that some sample's specimen covers (with `EDGE_SEARCH_MARGIN_PX` to
    spare) are evaluated per pixel; the rest of the row is the backdrop's sum. The coat's
    spline is interpolated along the texel row of a row's sample first (one line of the four
    rows' weighted sum per row and sample, over the columns the specimen covers), then across
    it per pixel: the bicubic B-spline interpolation of `appliance.dic.bspline.interpolate`
    summed in the other order (equal to it within rounding, about 1e-13 grey levels).
    """
    samples, rows = row_ty.shape
    cols = out.shape[1]
    tx_max = coefficients.shape[1] - 2 * PAD - 1.0
    ty_max = coefficients.shape[0] - 2 * PAD - 1.0
    for r in numba.prange(rows):
        backdrop = 0.0
        for _ in range(samples):
            backdrop += weight * background
        first = cols
        last = 0
        for s in range(samples):
            if not row_textured[s, r]:
                continue
            size = row_pixel_mm[s, r]
            reach = row_half_width_mm[s, r] / size + 0.5
            centre = x_centre_mm / size
            offset0 = col_offset_px[s, 0]
            low = math.floor(-reach - centre - offset0) - EDGE_SEARCH_MARGIN_PX
            high = math.ceil(reach - centre - offset0) + EDGE_SEARCH_MARGIN_PX + 1
            first = min(first, max(low, 0))
            last = max(last, min(high, cols))
        for c in range(min(first, cols)):
            out[r, c] = backdrop
        for c in range(max(last, first), cols):
            out[r, c] = backdrop
        if first >= last:
            continue
        total = np.zeros(last - first)
        line = np.empty(coefficients.shape[1])
        for s in range(samples):
            if not row_textured[s, r]:
                for c in range(last - first):
                    total[c] += weight * background
                continue
            ty = min(max(row_ty[s, r], 0.0), ty_max)
            iy = int(np.floor(ty))
            wy0, wy1, wy2, wy3 = cubic_weights(ty - iy)
            texel_row = iy + PAD - 1
            size = row_pixel_mm[s, r]
            inv_size = 1.0 / size
            half_width = row_half_width_mm[s, r]
            to_texels = row_inv_stretch[s, r] * inv_texel_mm
            x_first = x_centre_mm + col_offset_px[s, first] * size
            x_last = x_centre_mm + col_offset_px[s, last - 1] * size
            tx_first = min(max(x_first * to_texels - x_origin_texels, 0.0), tx_max)
            tx_last = min(max(x_last * to_texels - x_origin_texels, 0.0), tx_max)
            for k in range(int(np.floor(tx_first)) + PAD - 1, int(np.floor(tx_last)) + PAD + 3):
                line[k] = (
                    wy0 * coefficients[texel_row, k]
                    + wy1 * coefficients[texel_row + 1, k]
                    + wy2 * coefficients[texel_row + 2, k]
                    + wy3 * coefficients[texel_row + 3, k]
                )
            for c in range(first, last):
                x = x_centre_mm + col_offset_px[s, c] * size
                cover = 0.5 + (half_width - abs(x)) * inv_size
                if cover <= 0.0:
                    value = background
                else:
                    tx = min(max(x * to_texels - x_origin_texels, 0.0), tx_max)
                    ix = int(np.floor(tx))
                    wx0, wx1, wx2, wx3 = cubic_weights(tx - ix)
                    k = ix + PAD - 1
                    coat = wx0 * line[k] + wx1 * line[k + 1] + wx2 * line[k + 2] + wx3 * line[k + 3]
                    value = coat if cover >= 1.0 else background + cover * (coat - background)
                total[c - first] += weight * value
        for c in range(first, last):
            out[r, c] = total[c - first]


class SpecimenScene:
    """A camera's view of a deforming, speckled specimen: the `Scene` of the simulated camera.

    Args:
        deformation_at: specimen shape at simulation time t_s (s): a function of time alone,
            called a few times per frame (exposure start and stop, every time sample). The
            shapes of the latest `RECENT_EXPOSURES` exposures are kept and reused when the
            same exposure (to the nanosecond) is asked for again (by `render`,
            `image_positions` or `time_samples`, from any thread).
        scale_mm_per_px: object-plane size of one pixel, mm/px (> 0).
        sensor_width: sensor width, px (columns).
        sensor_height: sensor height, px (rows).
        material_y_range_mm: (Y_min, Y_max) of the material sections to texture, mm: every
            section that can come into view during the simulation. Rows seeing material
            outside it show the backdrop.
        half_width_mm: largest undeformed half-width of the specimen, mm (at least the largest
            `AxialDeformation.half_width_mm` the deformation will report).
        centre_mm: object-plane point (x, y), mm, imaged at the sensor centre.
        coat: the speckle coat; None = a dense coat of 2 px radius at this scale.
        marks: marks painted over the coat; None = none.
        background: grey level of the backdrop around the specimen, 8-bit scale.
        oversample: texels per pixel along each axis (texel size = scale / oversample).
        max_time_samples: largest number of time samples per exposure (>= 1).
        max_sample_step_px: largest motion of a visible material point between successive
            time samples, px (> 0).

    Attributes:
        sensor_width, sensor_height: sensor size, px.
        scale_mm_per_px: object-plane pixel size, mm/px.
        centre_mm: object point at the sensor centre, mm.
        coat: the speckle coat in force.
        marks: the painted marks (None: none).
        background: backdrop grey level.
        texel_mm: texture sampling step, mm.
        texture_shape: (rows, columns) of the texture, texels.
        texture_origin_mm: material (X, Y), mm, of texel (0, 0) (column 0, row 0).
        material_y_range_mm, half_width_mm, max_time_samples, max_sample_step_px: as given.
    """

    def __init__(
        self,
        deformation_at: Callable[[float], AxialDeformation],
        *,
        scale_mm_per_px: float,
        sensor_width: int,
        sensor_height: int,
        material_y_range_mm: tuple[float, float],
        half_width_mm: float,
        centre_mm: tuple[float, float] = (0.0, 0.0),
        coat: SpeckleCoat | None = None,
        marks: PaintedMarks | None = None,
        background: float = 20.0,
        oversample: int = TEXTURE_OVERSAMPLE,
        max_time_samples: int = 64,
        max_sample_step_px: float = 0.25,
    ) -> None:
        if not scale_mm_per_px > 0:
            raise ValueError(f"scale_mm_per_px must be > 0, got {scale_mm_per_px}")
        if sensor_width < 1 or sensor_height < 1:
            raise ValueError(f"sensor size must be positive, got {sensor_width}x{sensor_height}")
        y_min, y_max = (float(v) for v in material_y_range_mm)
        if not y_max > y_min:
            raise ValueError(f"material_y_range_mm must be increasing, got {material_y_range_mm}")
        if not half_width_mm > 0:
            raise ValueError(f"half_width_mm must be > 0, got {half_width_mm}")
        if oversample < 1 or max_time_samples < 1:
            raise ValueError("oversample and max_time_samples must be >= 1")
        if not max_sample_step_px > 0:
            raise ValueError(f"max_sample_step_px must be > 0, got {max_sample_step_px}")
        self._deformation_at = deformation_at
        self.scale_mm_per_px = float(scale_mm_per_px)
        self.sensor_width = int(sensor_width)
        self.sensor_height = int(sensor_height)
        self.centre_mm = (float(centre_mm[0]), float(centre_mm[1]))
        self.coat = coat if coat is not None else SpeckleCoat(radius_mm=2.0 * scale_mm_per_px)
        self.marks = marks
        self.background = float(background)
        self.max_time_samples = int(max_time_samples)
        self.max_sample_step_px = float(max_sample_step_px)
        self.material_y_range_mm = (y_min, y_max)
        self.half_width_mm = float(half_width_mm)

        self.texel_mm = self.scale_mm_per_px / int(oversample)
        # Speckles reach 4 radii; the margin keeps the used texels clear of the texture's
        # unspeckled surroundings, and 2 px more covers the edge blend and the spline support.
        pad_mm = 4.0 * self.coat.radius_mm + 2.0 * self.scale_mm_per_px
        columns = int(math.ceil(2.0 * (self.half_width_mm + pad_mm) / self.texel_mm)) + 1
        rows = int(math.ceil((y_max - y_min + 2.0 * pad_mm) / self.texel_mm)) + 1
        self.texture_shape = (rows, columns)
        self.texture_origin_mm = (-0.5 * (columns - 1) * self.texel_mm, y_min - pad_mm)
        texture = render(self.coat.pattern(columns, rows, self.texel_mm), rows, columns)
        if marks is not None:
            marks.paint(texture, self.texture_origin_mm, self.texel_mm)
        self._coefficients = np.ascontiguousarray(spline_coefficients(texture), np.float32)
        self._recent_exposures: collections.OrderedDict[
            tuple[float, float], tuple[list[float], list[AxialDeformation]]
        ] = collections.OrderedDict()
        self._recent_lock = threading.Lock()

    @cached_property
    def pattern(self) -> SpecklePattern:
        """The coat as an analytic pattern in texel coordinates (see `texture_coordinates`).

        Regenerated from the coat's seed when first asked for, then kept (it holds a few
        arrays of the size of the speckle count; construction does not keep it).
        """
        rows, columns = self.texture_shape
        return self.coat.pattern(columns, rows, self.texel_mm)

    @property
    def texture_bytes(self) -> int:
        """Memory held by the texture's spline coefficients, bytes."""
        return int(self._coefficients.nbytes)

    def texture_coordinates(
        self, X_mm: npt.ArrayLike, Y_mm: npt.ArrayLike
    ) -> tuple[FloatArray, FloatArray]:
        """Texel coordinates (column, row) of material points (X, Y), mm."""
        X0, Y0 = self.texture_origin_mm
        X = np.asarray(X_mm, np.float64)
        Y = np.asarray(Y_mm, np.float64)
        return (X - X0) / self.texel_mm, (Y - Y0) / self.texel_mm

    def coat_intensity(self, X_mm: npt.ArrayLike, Y_mm: npt.ArrayLike) -> FloatArray:
        """Exact grey level of the speckle coat at material points (X, Y), mm (analytic pattern;
        painted marks not included)."""
        tx, ty = self.texture_coordinates(X_mm, Y_mm)
        return self.pattern.intensity(tx, ty)

    def object_of(self, col: npt.ArrayLike, row: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Object-plane point (x, y), mm, seen by sensor position (col, row), px."""
        cx, cy = self.centre_mm
        s = self.scale_mm_per_px
        col = np.asarray(col, np.float64)
        row = np.asarray(row, np.float64)
        return (
            cx + (col - 0.5 * (self.sensor_width - 1)) * s,
            cy + (row - 0.5 * (self.sensor_height - 1)) * s,
        )

    def pixel_of(self, x_mm: npt.ArrayLike, y_mm: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Sensor position (col, row), px, of object-plane point (x, y), mm."""
        cx, cy = self.centre_mm
        s = self.scale_mm_per_px
        x_mm = np.asarray(x_mm, np.float64)
        y_mm = np.asarray(y_mm, np.float64)
        return (
            (x_mm - cx) / s + 0.5 * (self.sensor_width - 1),
            (y_mm - cy) / s + 0.5 * (self.sensor_height - 1),
        )

    def time_samples(self, start_s: float, stop_s: float) -> list[float]:
        """Times, s, of the samples averaged into an exposure over [start_s, stop_s].

        The midpoints of N equal sub-intervals. N = 1 for a zero-length exposure; otherwise the
        smallest N that keeps the largest motion of any material point seen by the sensor
        between successive samples at or below `max_sample_step_px` (from the deformations at
        start and stop: the motion is taken as uniform over the exposure), at most
        `max_time_samples`. N depends on the whole sensor, not on the region read out.
        """
        return self._exposure(start_s, stop_s)[0]

    def render(
        self, start_s: float, stop_s: float, region: Region
    ) -> tuple[FloatArray, Mapping[str, Any]]:
        """Noise-free view of the region integrated over the exposure [start_s, stop_s].

        Each pixel is the coat's grey level at the material point its centre sees (texture
        interpolation of the analytic pattern: speckles are smooth enough that no pixel-area
        filter is needed), blended with the backdrop by the pixel's coverage across the
        specimen's edges, averaged over the exposure's time samples.

        Args:
            start_s: start of the exposure, s (simulation time).
            stop_s: end of the exposure, s (>= start_s).
            region: sensor region to render.

        Returns:
            (image, truth): float64 (region.height, region.width) grey levels on the 8-bit
            scale; truth has "time_s" (mid-exposure, s), "start_s", "stop_s",
            "time_samples" (N) and "sample_times_s" (tuple of the N times, s).
        """
        if region.x + region.width > self.sensor_width:
            raise ValueError(f"region {region} exceeds the sensor width {self.sensor_width}")
        if region.y + region.height > self.sensor_height:
            raise ValueError(f"region {region} exceeds the sensor height {self.sensor_height}")
        times, deformations = self._exposure(start_s, stop_s)
        cols = np.arange(region.x, region.x + region.width, dtype=np.float64)
        rows = np.arange(region.y, region.y + region.height, dtype=np.float64)
        _, row_y = self.object_of(0.0, rows)
        col_offset_px = cols - 0.5 * (self.sensor_width - 1)
        weight = 1.0 / len(times)
        x_origin_texels = self.texture_origin_mm[0] / self.texel_mm
        y_min, y_max = self.material_y_range_mm
        samples = len(deformations)
        row_ty = np.empty((samples, len(rows)))
        row_inv_stretch = np.empty((samples, len(rows)))
        row_half_width = np.empty((samples, len(rows)))
        row_textured = np.empty((samples, len(rows)), np.bool_)
        for s, deformation in enumerate(deformations):
            Y = deformation.material_y(row_y)
            stretch = deformation.lateral_stretch_at(Y)
            row_ty[s] = (Y - self.texture_origin_mm[1]) / self.texel_mm
            row_inv_stretch[s] = 1.0 / stretch
            row_half_width[s] = deformation.half_width_at(Y) * stretch
            row_textured[s] = (Y >= y_min) & (Y <= y_max)
        image = np.empty((region.height, region.width), np.float64)
        integrate_exposure(
            image,
            weight,
            self._coefficients,
            row_ty,
            row_inv_stretch,
            row_half_width,
            row_textured,
            np.full((samples, len(rows)), self.scale_mm_per_px),
            np.ascontiguousarray(np.broadcast_to(col_offset_px, (samples, len(cols)))),
            self.centre_mm[0],
            x_origin_texels,
            1.0 / self.texel_mm,
            self.background,
        )
        truth = {
            "time_s": 0.5 * (start_s + stop_s),
            "start_s": float(start_s),
            "stop_s": float(stop_s),
            "time_samples": len(times),
            "sample_times_s": tuple(times),
        }
        return image, truth

    def image_positions(
        self, material_points_mm: npt.ArrayLike, start_s: float, stop_s: float
    ) -> FloatArray:
        """Exposure-averaged sensor positions of material points.

        Args:
            material_points_mm: (n, 2) material points (X, Y), mm.
            start_s: start of the exposure, s.
            stop_s: end of the exposure, s.

        Returns:
            (n, 2) float64 positions (col, row), px: the mean over the time samples that
            `render` uses for this exposure. A correlator tracking a point in a frame with
            symmetric blur finds it there.
        """
        points = np.asarray(material_points_mm, np.float64).reshape(-1, 2)
        _, deformations = self._exposure(start_s, stop_s)
        total = np.zeros_like(points)
        for deformation in deformations:
            x, y = deformation.forward(points[:, 0], points[:, 1])
            col, row = self.pixel_of(x, y)
            total[:, 0] += col
            total[:, 1] += row
        return total / len(deformations)

    def material_points(self, image_points_px: npt.ArrayLike, t_s: float) -> FloatArray:
        """Material points seen at sensor positions at one instant.

        Args:
            image_points_px: (n, 2) sensor positions (col, row), px.
            t_s: the instant, s.

        Returns:
            (n, 2) float64 material points (X, Y), mm.
        """
        points = np.asarray(image_points_px, np.float64).reshape(-1, 2)
        x, y = self.object_of(points[:, 0], points[:, 1])
        X, Y = self._deformation_at(t_s).inverse(x, y)
        return np.column_stack([X, Y])

    def _exposure(
        self, start_s: float, stop_s: float
    ) -> tuple[list[float], list[AxialDeformation]]:
        start_s, stop_s = float(start_s), float(stop_s)
        if not stop_s >= start_s:
            raise ValueError(f"exposure must have stop_s >= start_s, got {start_s}, {stop_s}")
        with self._recent_lock:
            recent = self._recent_exposures.get(_exposure_key(start_s, stop_s))
        if recent is not None:
            return recent
        count = 1
        if stop_s > start_s:
            first = self._deformation_at(start_s)
            last = self._deformation_at(stop_s)
            self._remember_exposure(start_s, start_s, [start_s], [first])
            self._remember_exposure(stop_s, stop_s, [stop_s], [last])
            motion = self._largest_motion_px(first, last)
            steps = math.ceil(motion / self.max_sample_step_px - _ROUNDING)
            count = min(self.max_time_samples, max(1, steps))
        step = (stop_s - start_s) / count
        times = [start_s + (i + 0.5) * step for i in range(count)]
        deformations = [self._deformation_at(t) for t in times]
        self._remember_exposure(start_s, stop_s, times, deformations)
        return times, deformations

    def _remember_exposure(
        self,
        start_s: float,
        stop_s: float,
        times: list[float],
        deformations: list[AxialDeformation],
    ) -> None:
        """Keep an exposure's samples for the next `RECENT_EXPOSURES` exposures asked for."""
        with self._recent_lock:
            self._recent_exposures[_exposure_key(start_s, stop_s)] = (times, deformations)
            while len(self._recent_exposures) > RECENT_EXPOSURES:
                self._recent_exposures.popitem(last=False)

    def _largest_motion_px(self, first: AxialDeformation, second: AxialDeformation) -> float:
        rows = np.arange(self.sensor_height, dtype=np.float64)
        _, y = self.object_of(0.0, rows)
        Y = first.material_y(y)
        axial = second.spatial_y(Y) - y
        stretch = first.lateral_stretch_at(Y)
        widest = abs(self.centre_mm[0]) + 0.5 * (self.sensor_width - 1) * self.scale_mm_per_px
        X = np.minimum(first.half_width_at(Y), widest / stretch)
        lateral = X * (second.lateral_stretch_at(Y) - stretch)
        return float(np.max(np.hypot(axial, lateral))) / self.scale_mm_per_px
