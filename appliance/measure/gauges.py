"""Gauges: from tracked point positions to gauge lengths, strains and elongation.

An extensometer measures between *marks*. Each mark here is a small cluster of tracked points
whose mean position is the mark's position, so one noisy or lost point does not move the mark
much, and a line of points across the specimen averages over its width. An axial gauge is two
marks along the loading axis; a transverse gauge two marks across it.

Strains are always referred to the original gauge length L0 (at the reference image), whatever
the tracker does in between (reference updates, re-acquisition):

    engineering strain   e = (L - L0) / L0
    true strain          eps = ln(1 + e)
    elongation           dL = (L - L0) * scale_mm_per_px
    Poisson's ratio      nu = -e_transverse / e_axial   (reported once |e_axial| >= 1e-4)

Calibration: by nominal scale, `scale_mm_per_px` from the optics (pixel size / magnification,
see `appliance.plan.optics`) or from a known distance in the image, lengths are measured in
pixels and scaled; or in the object plane, through a camera calibration's `PlaneProjection`
(`appliance.optics.calibration_file`): every point is mapped from its pixel position to mm on
the specimen plane (lens distortion removed, its ray intersected with the plane), each mark is
the mean of its points' plane positions, and L, L0, dL are the distances between marks there,
in mm. The strain is then free of the lens's distortion and of the plane's tilt, as far as the
calibration describes them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from appliance.optics.calibration_file import CameraCalibration
from appliance.optics.camera_model import PlaneProjection

POISSON_MIN_AXIAL_STRAIN = 1e-4


@dataclass(frozen=True)
class Calibration:
    """Pixels to millimetres of the object plane.

    Attributes:
        scale_mm_per_px: the scale, mm/px: the nominal scale, or with a projection the
            calibration's scale at the image centre (shown, and used nowhere else).
        projection: pixels to mm on the specimen plane; None = measure by nominal scale.
        camera: the camera calibration the projection comes from (recorded with the test);
            None when there is none or the projection was given directly.
        file: the calibration file it was read from ("" when none).
    """

    scale_mm_per_px: float
    projection: PlaneProjection | None = field(default=None, compare=False, repr=False)
    camera: CameraCalibration | None = field(default=None, repr=False)
    file: str = ""

    def __post_init__(self) -> None:
        if not (self.scale_mm_per_px > 0 and math.isfinite(self.scale_mm_per_px)):
            raise ValueError(f"scale_mm_per_px must be finite and > 0, got {self.scale_mm_per_px}")

    @classmethod
    def object_plane(cls, camera: CameraCalibration, file: str = "") -> Calibration:
        """Measure in the object plane of a camera calibration (read from `file`)."""
        return cls(camera.scale_mm_per_px, camera.projection(), camera, file)

    @property
    def in_object_plane(self) -> bool:
        """True when lengths are measured in mm on the specimen plane (a projection)."""
        return self.projection is not None

    @property
    def checksum(self) -> str:
        """The camera calibration's checksum ("sha256:<hex>"); "" without one."""
        return self.camera.checksum if self.camera is not None else ""

    @classmethod
    def from_known_distance(cls, distance_mm: float, distance_px: float) -> Calibration:
        """Scale from a distance known in mm and measured in px."""
        if not (distance_mm > 0 and distance_px > 0):
            raise ValueError("known distance must be > 0 in mm and in px")
        return cls(distance_mm / distance_px)

    @classmethod
    def from_optics(cls, pixel_size_um: float, magnification: float) -> Calibration:
        """Scale of a camera with the given pixel pitch and lateral magnification."""
        if not (pixel_size_um > 0 and magnification > 0):
            raise ValueError("pixel_size_um and magnification must be > 0")
        return cls(pixel_size_um * 1e-3 / magnification)


@dataclass(frozen=True)
class Gauge:
    """Two marks, each a list of indices into the tracked points.

    Attributes:
        first, second: point indices of each mark (non-empty, disjoint).
    """

    first: tuple[int, ...]
    second: tuple[int, ...]

    def __post_init__(self) -> None:
        if not self.first or not self.second:
            raise ValueError("each mark of a gauge needs at least one point")
        if set(self.first) & set(self.second):
            raise ValueError("the two marks of a gauge share points")

    def length_px(self, positions: np.ndarray, valid: np.ndarray | None = None) -> float:
        """Distance between the mark centroids, px; NaN when a mark has no valid point.

        Args:
            positions: (n, 2) current positions (x, y) of all tracked points.
            valid: (n,) mask of points that may be used; None = all.
        """
        indices = self._usable_points(valid)
        if indices is None:
            return math.nan
        first, second = (positions[index].mean(axis=0) for index in indices)
        return float(np.hypot(*(second - first)))

    def length_mm(
        self,
        positions: np.ndarray,
        projection: PlaneProjection,
        valid: np.ndarray | None = None,
    ) -> float:
        """Distance between the marks on the specimen plane, mm: each point mapped through
        `projection`, each mark the mean of its points' plane positions; NaN when a mark has
        no valid point (or a point that cannot be mapped).

        Args:
            positions: (n, 2) current positions (x, y) of all tracked points, px.
            projection: pixels to mm on the plane.
            valid: (n,) mask of points that may be used; None = all.
        """
        indices = self._usable_points(valid)
        if indices is None:
            return math.nan
        pixels = positions[np.concatenate(indices)]
        if not np.all(np.isfinite(pixels)):
            return math.nan
        try:
            plane = projection.to_plane_mm(pixels)
        except ValueError:
            return math.nan
        split = len(indices[0])
        first, second = plane[:split].mean(axis=0), plane[split:].mean(axis=0)
        return float(np.hypot(*(second - first)))

    def _usable_points(self, valid: np.ndarray | None) -> tuple[np.ndarray, np.ndarray] | None:
        """The indices of each mark's points that `valid` allows (all when None); None when a
        mark has none."""
        indices = []
        for mark in (self.first, self.second):
            index = np.asarray(mark)
            if valid is not None:
                index = index[valid[index]]
            if index.size == 0:
                return None
            indices.append(index)
        return indices[0], indices[1]


@dataclass(frozen=True)
class StrainReading:
    """Strain of one frame, all referred to the original gauge lengths."""

    axial_px: float
    engineering_strain: float
    true_strain: float
    elongation_mm: float
    gauge_length_mm: float
    transverse_strain: float
    poisson_ratio: float


class StrainGauges:
    """Axial (and optionally transverse) gauge on a set of tracked points.

    Args:
        axial: the axial gauge.
        reference_positions: (n, 2) positions of all points in the reference image, px;
            they define L0.
        calibration: px -> mm; with a projection every length is measured in mm on the
            specimen plane, otherwise in px and scaled.
        transverse: optional transverse gauge.
    """

    def __init__(
        self,
        axial: Gauge,
        reference_positions: np.ndarray,
        calibration: Calibration,
        transverse: Gauge | None = None,
    ) -> None:
        self.axial = axial
        self.transverse = transverse
        self.calibration = calibration
        self.axial_l0_px = axial.length_px(reference_positions)
        if not self.axial_l0_px > 0:
            raise ValueError("axial gauge has zero length in the reference image")
        self.transverse_l0_px = (
            transverse.length_px(reference_positions) if transverse is not None else math.nan
        )
        self.axial_l0_mm = math.nan
        self.transverse_l0_mm = math.nan
        if calibration.projection is not None:
            self._zero_in_plane(reference_positions)

    def _zero_in_plane(self, positions: np.ndarray) -> None:
        projection = self.calibration.projection
        assert projection is not None
        length = self.axial.length_mm(positions, projection)
        if not length > 0:
            raise ValueError("axial gauge has no length on the specimen plane")
        self.axial_l0_mm = length
        if self.transverse is not None:
            self.transverse_l0_mm = self.transverse.length_mm(positions, projection)

    def rezero(self, positions: np.ndarray) -> None:
        """Make the gauge lengths at `positions` (n, 2) the new L0 (strain zero from here).

        Raises:
            ValueError: the axial gauge has no length there (a mark without a point).
        """
        length = self.axial.length_px(positions)
        if not length > 0:
            raise ValueError("axial gauge has no length to zero on")
        if self.calibration.projection is not None:
            self._zero_in_plane(positions)
        self.axial_l0_px = length
        if self.transverse is not None:
            self.transverse_l0_px = self.transverse.length_px(positions)

    @property
    def gauge_length_mm(self) -> float:
        """Original axial gauge length L0, mm."""
        if self.calibration.projection is not None:
            return self.axial_l0_mm
        return self.axial_l0_px * self.calibration.scale_mm_per_px

    def read(self, positions: np.ndarray, valid: np.ndarray | None = None) -> StrainReading:
        """Strains for current positions (n, 2) px; NaN where a mark has no valid point."""
        if self.calibration.projection is not None:
            return self._read_in_plane(positions, valid, self.calibration.projection)
        length = self.axial.length_px(positions, valid)
        strain = (length - self.axial_l0_px) / self.axial_l0_px
        transverse = math.nan
        if self.transverse is not None:
            width = self.transverse.length_px(positions, valid)
            transverse = (width - self.transverse_l0_px) / self.transverse_l0_px
        poisson = (
            -transverse / strain
            if abs(strain) >= POISSON_MIN_AXIAL_STRAIN and math.isfinite(transverse)
            else math.nan
        )
        scale = self.calibration.scale_mm_per_px
        return StrainReading(
            axial_px=length,
            engineering_strain=strain,
            true_strain=math.log1p(strain) if strain > -1 else math.nan,
            elongation_mm=(length - self.axial_l0_px) * scale,
            gauge_length_mm=length * scale,
            transverse_strain=transverse,
            poisson_ratio=poisson,
        )

    def _read_in_plane(
        self, positions: np.ndarray, valid: np.ndarray | None, projection: PlaneProjection
    ) -> StrainReading:
        length = self.axial.length_mm(positions, projection, valid)
        strain = (length - self.axial_l0_mm) / self.axial_l0_mm
        transverse = math.nan
        if self.transverse is not None:
            width = self.transverse.length_mm(positions, projection, valid)
            transverse = (width - self.transverse_l0_mm) / self.transverse_l0_mm
        poisson = (
            -transverse / strain
            if abs(strain) >= POISSON_MIN_AXIAL_STRAIN and math.isfinite(transverse)
            else math.nan
        )
        return StrainReading(
            axial_px=self.axial.length_px(positions, valid),
            engineering_strain=strain,
            true_strain=math.log1p(strain) if strain > -1 else math.nan,
            elongation_mm=length - self.axial_l0_mm,
            gauge_length_mm=length,
            transverse_strain=transverse,
            poisson_ratio=poisson,
        )


@dataclass(frozen=True)
class StrainGaugesLayout:
    """Which tracked points form the axial gauge and the optional transverse gauge."""

    axial: Gauge
    transverse: Gauge | None

    @property
    def marks(self) -> tuple[tuple[int, ...], ...]:
        """The tracker's marks: the axial marks, then the transverse ones."""
        marks = [self.axial.first, self.axial.second]
        if self.transverse is not None:
            marks += [self.transverse.first, self.transverse.second]
        return tuple(tuple(m) for m in marks)


def place_marks(
    centre_px: tuple[float, float],
    gauge_length_mm: float,
    calibration: Calibration,
    *,
    axis_deg: float = 90.0,
    mark_width_px: float = 40.0,
    points_per_mark: int = 3,
    transverse_width_mm: float | None = None,
    along_axis: bool = False,
) -> tuple[np.ndarray, StrainGaugesLayout]:
    """Place gauge marks automatically, centred on the specimen.

    Each axial mark is a line of `points_per_mark` points, `mark_width_px` long, centred at
    +- L0/2 from the centre along the loading axis: across the specimen (the default, for
    wide specimens) or along the axis (`along_axis`, for narrow specimens whose width holds
    only one subset). The optional transverse marks are single points at +- width/2 across
    the axis through the centre.

    With a plane projection in `calibration` the distances are laid out on the specimen
    plane: the centre is mapped to the plane, the axis is the plane direction the image
    axis points along there, the mark centres lie L0/2 either side of the centre (and the
    transverse marks width/2 across) in mm, and are mapped back to pixels; each mark's line
    of points keeps its length in px. Without one, the distances are divided by the scale.

    Args:
        centre_px: specimen centre (x, y) in the reference image, px.
        gauge_length_mm: L0, mm.
        calibration: px -> mm.
        axis_deg: loading axis direction, degrees from +x towards +y (90 = along the image
            rows, specimen vertical).
        mark_width_px: length of each mark's line of points across the axis, px.
        points_per_mark: points per axial mark (>= 1).
        along_axis: lay each mark's line along the axis instead of across it.
        transverse_width_mm: spacing of the transverse marks, mm; None = no transverse gauge.

    Returns:
        (points (n, 2) px, layout naming which points form which mark).
    """
    if not gauge_length_mm > 0:
        raise ValueError(f"gauge_length_mm must be > 0, got {gauge_length_mm}")
    if points_per_mark < 1:
        raise ValueError(f"points_per_mark must be >= 1, got {points_per_mark}")
    theta = math.radians(axis_deg)
    along = np.array([math.cos(theta), math.sin(theta)])
    across = np.array([-along[1], along[0]])
    centre = np.asarray(centre_px, dtype=np.float64)
    if transverse_width_mm is not None and not transverse_width_mm > 0:
        raise ValueError(f"transverse_width_mm must be > 0, got {transverse_width_mm}")
    if calibration.projection is not None:
        return _place_on_plane(
            centre,
            along,
            gauge_length_mm,
            calibration.projection,
            mark_width_px=mark_width_px,
            points_per_mark=points_per_mark,
            transverse_width_mm=transverse_width_mm,
            along_axis=along_axis,
        )
    half = 0.5 * gauge_length_mm / calibration.scale_mm_per_px
    offsets = (
        np.linspace(-0.5, 0.5, points_per_mark) * mark_width_px if points_per_mark > 1 else [0]
    )
    spread = along if along_axis else across
    points = [centre + sign * half * along + o * spread for sign in (-1, 1) for o in offsets]
    first = tuple(range(points_per_mark))
    second = tuple(range(points_per_mark, 2 * points_per_mark))
    transverse = None
    if transverse_width_mm is not None:
        w = 0.5 * transverse_width_mm / calibration.scale_mm_per_px
        start = len(points)
        points += [centre - w * across, centre + w * across]
        transverse = Gauge((start,), (start + 1,))
    return np.array(points), StrainGaugesLayout(Gauge(first, second), transverse)


def _place_on_plane(
    centre_px: np.ndarray,
    along_px: np.ndarray,
    gauge_length_mm: float,
    projection: PlaneProjection,
    *,
    mark_width_px: float,
    points_per_mark: int,
    transverse_width_mm: float | None,
    along_axis: bool,
) -> tuple[np.ndarray, StrainGaugesLayout]:
    """`place_marks` with its distances laid out in mm on the plane of `projection`."""
    try:
        ends = projection.to_plane_mm(np.array([centre_px, centre_px + along_px]))
    except ValueError as exc:
        raise ValueError(
            f"the gauge centre cannot be mapped to the specimen plane ({exc})"
        ) from None
    centre_mm = ends[0]
    axis_mm = ends[1] - ends[0]
    axis_mm = axis_mm / np.hypot(*axis_mm)
    across_mm = np.array([-axis_mm[1], axis_mm[0]])
    half = 0.5 * gauge_length_mm
    targets = [centre_mm - half * axis_mm, centre_mm + half * axis_mm]
    if transverse_width_mm is not None:
        w = 0.5 * transverse_width_mm
        targets += [centre_mm - w * across_mm, centre_mm + w * across_mm]
    try:
        mark_centres = projection.to_pixels(np.array(targets))
    except ValueError as exc:
        raise ValueError(f"a gauge mark lies outside the camera's view ({exc})") from None
    offsets = (
        np.linspace(-0.5, 0.5, points_per_mark) * mark_width_px if points_per_mark > 1 else [0]
    )
    points = []
    for mark_centre in mark_centres[:2]:
        local = projection.to_plane_mm(np.array([mark_centre]))[0] + axis_mm
        direction = projection.to_pixels(np.array([local]))[0] - mark_centre
        direction = direction / np.hypot(*direction)
        spread = direction if along_axis else np.array([-direction[1], direction[0]])
        points += [mark_centre + o * spread for o in offsets]
    first = tuple(range(points_per_mark))
    second = tuple(range(points_per_mark, 2 * points_per_mark))
    transverse = None
    if transverse_width_mm is not None:
        start = len(points)
        points += [mark_centres[2], mark_centres[3]]
        transverse = Gauge((start,), (start + 1,))
    return np.array(points), StrainGaugesLayout(Gauge(first, second), transverse)


def marks_outside(points: np.ndarray, shape: tuple[int, ...], subset_px: int) -> str | None:
    """Why marks at `points` cannot be tracked in an image of `shape` with subsets of at least
    `subset_px` (a gauge too long for the field of view, or a centre off the image), as one
    line; None when every point has room for its subset."""
    height, width = shape[:2]
    half = subset_px // 2
    x, y = points[:, 0], points[:, 1]
    if (
        x.min() >= half
        and y.min() >= half
        and x.max() <= width - 1 - half
        and y.max() <= height - 1 - half
    ):
        return None
    return (
        f"the marks span x {x.min():.0f}..{x.max():.0f}, y {y.min():.0f}..{y.max():.0f} px, "
        f"outside the {width}x{height} image less half the smallest subset ({half} px)"
    )
