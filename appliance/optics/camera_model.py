"""A camera's geometry: pinhole or telecentric projection with Brown-Conrady lens distortion,
and the mapping between image pixels and millimetres on a plane in front of it.

Frames and conventions (OpenCV's, so that `cv2.calibrateCamera` results drop in unchanged):

- Camera frame: x to the right of the image, y down the image, z along the optical axis away
  from the lens, mm.
- Pixels: column x, row y, pixel centres at integers (the project's convention).
- A plane (the specimen's surface, a calibration target) has its own frame: X, Y in the plane,
  Z along its normal, mm. Its pose (R, t) maps plane points to the camera frame,
  ``P_camera = R @ (X, Y, 0) + t``.

Projection of a camera-frame point (x, y, z):

    entocentric (pinhole)   a = x / z,  b = y / z        (dimensionless)
    telecentric             a = x,      b = y            (mm; no perspective)

then Brown-Conrady distortion with r^2 = a^2 + b^2 (OpenCV's 5-coefficient model),

    a' = a (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 a b + p2 (r^2 + 2 a^2)
    b' = b (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 b^2) + 2 p2 a b

and the intrinsic matrix: column = fx a' + cx, row = fy b' + cy. For an entocentric lens fx, fy
are the focal length in pixels; for a telecentric lens they are pixels per millimetre of the
object (the magnification over the pixel pitch), and the distortion coefficients act on
millimetres.

Going back from a pixel to the plane undistorts it (an iterative inversion, converged to
1e-12 in normalised units) and intersects its ray with the plane: for the pinhole, the ray
through the centre of projection; for the telecentric lens, the ray parallel to the optical
axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

_UNDISTORT_ITERATIONS = 100
_UNDISTORT_TOLERANCE = 1e-12


@dataclass(frozen=True)
class LensDistortion:
    """Brown-Conrady distortion coefficients in OpenCV's order (k1, k2, p1, p2, k3).

    Attributes:
        k1, k2, k3: radial coefficients (of r^2, r^4, r^6).
        p1, p2: tangential (decentring) coefficients.
    """

    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0

    def __post_init__(self) -> None:
        for name in ("k1", "k2", "p1", "p2", "k3"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"distortion coefficient {name} must be finite")

    @property
    def coefficients(self) -> FloatArray:
        """The five coefficients as OpenCV takes them, float64 (5,)."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3], np.float64)

    @property
    def is_zero(self) -> bool:
        """True when the lens does not distort."""
        return not np.any(self.coefficients)

    @classmethod
    def from_coefficients(cls, coefficients: npt.ArrayLike) -> LensDistortion:
        """From OpenCV's coefficient vector (4, 5 or more values; terms past k3 must be 0)."""
        values = np.asarray(coefficients, np.float64).ravel()
        if values.size < 4:
            raise ValueError(f"distortion needs at least 4 coefficients, got {values.size}")
        if values.size > 5 and np.any(values[5:]):
            raise ValueError("only the 5-coefficient Brown-Conrady model is supported")
        k3 = float(values[4]) if values.size > 4 else 0.0
        return cls(float(values[0]), float(values[1]), float(values[2]), float(values[3]), k3)

    def apply(self, a: FloatArray, b: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Distorted coordinates (a', b') of undistorted normalised coordinates (a, b)."""
        r2 = a * a + b * b
        radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        a_d = a * radial + 2.0 * self.p1 * a * b + self.p2 * (r2 + 2.0 * a * a)
        b_d = b * radial + self.p1 * (r2 + 2.0 * b * b) + 2.0 * self.p2 * a * b
        return a_d, b_d

    def remove(self, a_d: FloatArray, b_d: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Undistorted coordinates (a, b) whose distorted coordinates are (a_d, b_d).

        Newton's method on the distortion map, from (a_d, b_d); converges to 1e-12 for every
        lens whose distortion map is invertible over the field.

        Raises:
            ValueError: a point did not converge (the distortion folds over there).
        """
        a = np.array(a_d, np.float64, copy=True)
        b = np.array(b_d, np.float64, copy=True)
        if self.is_zero:
            return a, b
        k1, k2, k3, p1, p2 = self.k1, self.k2, self.k3, self.p1, self.p2
        for _ in range(_UNDISTORT_ITERATIONS):
            r2 = a * a + b * b
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            d_radial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
            fa = a * radial + 2.0 * p1 * a * b + p2 * (r2 + 2.0 * a * a) - a_d
            fb = b * radial + p1 * (r2 + 2.0 * b * b) + 2.0 * p2 * a * b - b_d
            j11 = radial + 2.0 * a * a * d_radial + 2.0 * p1 * b + 6.0 * p2 * a
            j12 = 2.0 * a * b * d_radial + 2.0 * p1 * a + 2.0 * p2 * b
            j21 = 2.0 * a * b * d_radial + 2.0 * p1 * a + 2.0 * p2 * b
            j22 = radial + 2.0 * b * b * d_radial + 6.0 * p1 * b + 2.0 * p2 * a
            determinant = j11 * j22 - j12 * j21
            step_a = (j22 * fa - j12 * fb) / determinant
            step_b = (j11 * fb - j21 * fa) / determinant
            a -= step_a
            b -= step_b
            if np.all(np.abs(step_a) + np.abs(step_b) < _UNDISTORT_TOLERANCE):
                break
        residual_a, residual_b = self.apply(a, b)
        error = np.abs(residual_a - a_d) + np.abs(residual_b - b_d)
        if not np.all(error < 1e-9):
            raise ValueError("lens distortion could not be inverted at a point of the field")
        return a, b


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics of a camera: sensor size, projection, principal point and lens distortion.

    Attributes:
        width_px, height_px: sensor size, px.
        fx_px, fy_px: entocentric: focal length, px; telecentric: px per mm of object.
        cx_px, cy_px: principal point, px (column, row).
        distortion: the lens's Brown-Conrady coefficients.
        telecentric: True for a telecentric lens (orthographic projection).
    """

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    distortion: LensDistortion = field(default_factory=LensDistortion)
    telecentric: bool = False

    def __post_init__(self) -> None:
        if self.width_px < 1 or self.height_px < 1:
            raise ValueError(f"sensor size must be positive, got {self.width_px}x{self.height_px}")
        for name in ("fx_px", "fy_px"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be finite and > 0, got {value}")
        for name in ("cx_px", "cy_px"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"{name} must be finite")

    @classmethod
    def ideal(
        cls,
        width_px: int,
        height_px: int,
        focal_px: float,
        *,
        distortion: LensDistortion | None = None,
        telecentric: bool = False,
    ) -> CameraModel:
        """Square pixels, the principal point at the sensor centre."""
        return cls(
            int(width_px),
            int(height_px),
            float(focal_px),
            float(focal_px),
            0.5 * (width_px - 1),
            0.5 * (height_px - 1),
            distortion or LensDistortion(),
            telecentric,
        )

    @property
    def matrix(self) -> FloatArray:
        """The 3x3 intrinsic matrix K as OpenCV takes it."""
        return np.array(
            [[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]]
        )

    @property
    def sensor_size(self) -> tuple[int, int]:
        """(width, height), px."""
        return (self.width_px, self.height_px)

    def normalised(self, pixels: npt.ArrayLike) -> FloatArray:
        """Undistorted normalised coordinates (a, b) of pixel positions (n, 2)."""
        points = _as_points(pixels)
        a_d = (points[:, 0] - self.cx_px) / self.fx_px
        b_d = (points[:, 1] - self.cy_px) / self.fy_px
        a, b = self.distortion.remove(a_d, b_d)
        return np.column_stack([a, b])

    def pixels(self, normalised: npt.ArrayLike) -> FloatArray:
        """Pixel positions (n, 2) of undistorted normalised coordinates (a, b)."""
        points = _as_points(normalised)
        a_d, b_d = self.distortion.apply(points[:, 0], points[:, 1])
        return np.column_stack([self.fx_px * a_d + self.cx_px, self.fy_px * b_d + self.cy_px])

    def project(self, points_camera_mm: npt.ArrayLike) -> FloatArray:
        """Pixel positions (n, 2) of camera-frame points (n, 3), mm.

        Raises:
            ValueError: an entocentric camera asked for a point at or behind the lens.
        """
        points = np.asarray(points_camera_mm, np.float64).reshape(-1, 3)
        if self.telecentric:
            return self.pixels(points[:, :2])
        if np.any(points[:, 2] <= 0):
            raise ValueError("a point lies at or behind the lens")
        return self.pixels(points[:, :2] / points[:, 2:3])

    def distortion_px(self, pixels: npt.ArrayLike) -> FloatArray:
        """How far (n,) px the lens moves each pixel position from where a distortion-free lens
        with the same intrinsics would image its ray."""
        points = _as_points(pixels)
        normalised = self.normalised(points)
        ideal = np.column_stack(
            [
                self.fx_px * normalised[:, 0] + self.cx_px,
                self.fy_px * normalised[:, 1] + self.cy_px,
            ]
        )
        return np.hypot(*(points - ideal).T)

    def with_distortion(self, distortion: LensDistortion) -> CameraModel:
        """The same camera with another lens distortion."""
        return CameraModel(
            self.width_px,
            self.height_px,
            self.fx_px,
            self.fy_px,
            self.cx_px,
            self.cy_px,
            distortion,
            self.telecentric,
        )


@dataclass(frozen=True)
class PlanePose:
    """Where a plane lies in the camera frame: ``P_camera = R @ (X, Y, 0) + t``.

    Attributes:
        rotation_vector: Rodrigues vector of R (3,), rad.
        translation_mm: t (3,), mm: the plane origin in the camera frame.
    """

    rotation_vector: tuple[float, float, float]
    translation_mm: tuple[float, float, float]

    def __post_init__(self) -> None:
        if len(self.rotation_vector) != 3 or len(self.translation_mm) != 3:
            raise ValueError("a plane pose needs a 3-vector rotation and a 3-vector translation")
        values = (*self.rotation_vector, *self.translation_mm)
        if not all(math.isfinite(v) for v in values):
            raise ValueError("a plane pose must be finite")

    @classmethod
    def facing(cls, distance_mm: float, centre_mm: tuple[float, float] = (0.0, 0.0)) -> PlanePose:
        """A plane square to the optical axis at `distance_mm`, its axes along the image's,
        with plane point `centre_mm` on the optical axis."""
        return cls((0.0, 0.0, 0.0), (-float(centre_mm[0]), -float(centre_mm[1]), distance_mm))

    @classmethod
    def from_arrays(cls, rotation_vector: npt.ArrayLike, translation: npt.ArrayLike) -> PlanePose:
        """From OpenCV's rvec and tvec."""
        r = np.asarray(rotation_vector, np.float64).ravel()
        t = np.asarray(translation, np.float64).ravel()
        return cls((float(r[0]), float(r[1]), float(r[2])), (float(t[0]), float(t[1]), float(t[2])))

    @property
    def rotation(self) -> FloatArray:
        """R, 3x3."""
        matrix, _ = cv2.Rodrigues(np.asarray(self.rotation_vector, np.float64))
        return np.asarray(matrix, np.float64)

    @property
    def translation(self) -> FloatArray:
        """t (3,), mm."""
        return np.asarray(self.translation_mm, np.float64)

    @property
    def normal_tilt_deg(self) -> float:
        """Angle between the plane's normal and the optical axis, degrees."""
        return math.degrees(math.acos(min(1.0, abs(float(self.rotation[2, 2])))))

    def to_camera(self, points_mm: npt.ArrayLike) -> FloatArray:
        """Camera-frame points (n, 3), mm, of plane points (n, 2), mm."""
        points = _as_points(points_mm)
        rotation = self.rotation
        return points @ rotation[:, :2].T + self.translation

    def moved_along_normal(self, offset_mm: float) -> PlanePose:
        """The same plane moved by `offset_mm` along its normal (positive away from the
        camera when the normal points along +z)."""
        t = self.translation + offset_mm * self.rotation[:, 2]
        return PlanePose(self.rotation_vector, (float(t[0]), float(t[1]), float(t[2])))


class PlaneProjection:
    """Pixels to millimetres on a plane and back, through a camera model.

    Args:
        camera: the camera's intrinsics and distortion.
        pose: the plane's pose in the camera frame.

    Raises:
        ValueError: the plane is seen edge-on, or lies behind an entocentric camera.
    """

    def __init__(self, camera: CameraModel, pose: PlanePose) -> None:
        self.camera = camera
        self.pose = pose
        rotation = pose.rotation
        self._rotation = rotation
        self._translation = pose.translation
        if camera.telecentric:
            in_plane = rotation[:2, :2]
            if abs(np.linalg.det(in_plane)) < 1e-9:
                raise ValueError("the plane is seen edge-on")
            self._inverse = np.linalg.inv(in_plane)
        else:
            basis = np.column_stack([rotation[:, 0], rotation[:, 1], self._translation])
            if abs(np.linalg.det(basis)) < 1e-12 or self._translation[2] <= 0:
                raise ValueError("the plane is seen edge-on or lies behind the lens")
            self._inverse = np.linalg.inv(basis)

    def to_plane_mm(self, pixels: npt.ArrayLike) -> FloatArray:
        """Plane points (X, Y) (n, 2), mm, seen at pixel positions (n, 2). A pixel whose ray
        meets the plane behind the lens or never (a tilted plane's horizon) gives NaN: it sees
        no point of the plane."""
        normalised = self.camera.normalised(pixels)
        if self.camera.telecentric:
            return (normalised - self._translation[:2]) @ self._inverse.T
        rays = np.column_stack([normalised, np.ones(len(normalised))])
        homogeneous = rays @ self._inverse.T
        with np.errstate(divide="ignore", invalid="ignore"):
            points = homogeneous[:, :2] / homogeneous[:, 2:3]
        points[homogeneous[:, 2] <= 0.0] = np.nan
        return points

    def to_pixels(self, points_mm: npt.ArrayLike) -> FloatArray:
        """Pixel positions (n, 2) of plane points (X, Y) (n, 2), mm."""
        return self.camera.project(self.pose.to_camera(points_mm))

    def scale_mm_per_px(self, pixel: tuple[float, float], step_px: float = 0.5) -> float:
        """Local scale at a pixel: the square root of the area in mm^2 that one pixel covers
        on the plane there (a central difference over `step_px`)."""
        x, y = float(pixel[0]), float(pixel[1])
        points = np.array([[x - step_px, y], [x + step_px, y], [x, y - step_px], [x, y + step_px]])
        plane = self.to_plane_mm(points)
        along_x = (plane[1] - plane[0]) / (2.0 * step_px)
        along_y = (plane[3] - plane[2]) / (2.0 * step_px)
        return math.sqrt(abs(along_x[0] * along_y[1] - along_x[1] * along_y[0]))


def _as_points(values: npt.ArrayLike) -> FloatArray:
    points = np.asarray(values, np.float64)
    if points.ndim == 1:
        points = points.reshape(-1, 2)
    if points.ndim != 2 or points.shape[1] != 2:
        raise ValueError(f"expected (n, 2) points, got shape {points.shape}")
    return points
