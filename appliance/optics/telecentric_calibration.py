"""Calibration of a telecentric (orthographic) camera from views of a planar target.

A telecentric lens images the object plane without perspective: a camera-frame point
(x, y, z) mm lands at (a, b) = (x, y) whatever its z, then Brown-Conrady distortion acts on
(a, b) in millimetres and the intrinsics scale them to pixels (`CameraModel` with
`telecentric=True`: fx, fy in px per mm of object). OpenCV has no such model, so it is fitted
here with `scipy.optimize.least_squares` (Levenberg-Marquardt, a central-difference
Jacobian that steps every view's pose at once):

- intrinsics: fx, fy (px/mm), k1, k2, p1, p2 (k3 = 0: the fourth-order radial term already
  fits a machine-vision telecentric lens to the detection noise, and a sixth-order term only
  trades off against k2). The distortion centre cx, cy is the image centre, not fitted: with
  no perspective to tie it, a free centre trades off against the decentring terms p1, p2 and
  the magnification (measured on the metal bench's simulated lens, 14 views, seeds 1..3: the
  free centre ran 57, 537 and 295 px from the image centre and fx, fy up to 0.74 % off, at
  the same RMS; the fixed centre: fx, fy within 0.005 %); a lens's decentring is carried by
  p1, p2. The coefficients are fitted in
  units of the field's half-diagonal L (mm at the object) so that they are of order one, and
  stored in millimetres: k1 / L^2, k2 / L^4, p / L.
- per view: the plane's rotation (Rodrigues, 3) and its in-plane translation (tx, ty). The
  distance tz is not observable through a telecentric lens (it moves nothing in the image):
  every view's tz is fixed at the nominal `object_distance_mm` (0 unless given), and the
  stored plane's tz is that nominal value.

Initialisation: an affine fit of every view's plane corners to its pixels,
``pixel = A (X, Y) + c``. For square pixels A = f R2 (R2 the rotation's upper-left 2x2 block,
whose singular values are 1 and cos(tilt)), so f is the median of the views' largest singular
values; R2 = A / f is completed to a rotation (its third row from the orthonormality of the
first two columns) and (c - image centre) / f is the in-plane translation.

Tilt sign: an orthographic view of a tilted plane cannot tell a tilt from its mirror image
(the rotation's third row changes sign, R2 does not): both poses project every point of the
plane to the same pixel, so both fit equally well and both measure the same millimetres on
the plane. The completion whose plane X axis points away from the camera (R[2, 0] >= 0) is
kept; nothing that the calibration measures on the plane depends on the choice.

Scale and its uncertainty: the scale at the image centre on the plane view's plane
(`PlaneProjection.scale_mm_per_px`); its standard uncertainty is propagated from the fit's
covariance ``s^2 (J^T J)^+`` (s^2 the residual variance per coordinate) through the scale's
gradient with respect to the intrinsics and the plane view's pose (central differences).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares

from appliance.optics.camera_model import CameraModel, LensDistortion, PlanePose, PlaneProjection
from appliance.optics.fit_uncertainty import fit_covariance, propagated_uncertainty

FloatArray = npt.NDArray[np.float64]

_INTRINSICS = 8
_CENTRE = [2, 3]
_PER_VIEW = 5
_TOLERANCE = 1e-12
_MAX_EVALUATIONS = 400


@dataclass(frozen=True)
class TelecentricFit:
    """A telecentric camera fitted to views of a planar target.

    Attributes:
        camera: the fitted camera (telecentric; fx, fy in px/mm; distortion in mm units).
        poses: each view's plane pose (tz the nominal distance).
        rms_px: RMS reprojection error over every corner of every view, px.
        view_errors_px: RMS reprojection error of each view, px.
        scale_mm_per_px: scale at the image centre on the plane view's plane, mm/px.
        scale_uncertainty_mm_per_px: its standard uncertainty from the fit, mm/px.
    """

    camera: CameraModel
    poses: tuple[PlanePose, ...]
    rms_px: float
    view_errors_px: tuple[float, ...]
    scale_mm_per_px: float
    scale_uncertainty_mm_per_px: float


def fit_telecentric(
    plane_points_mm: Sequence[npt.ArrayLike],
    image_points_px: Sequence[npt.ArrayLike],
    size_px: tuple[int, int],
    *,
    plane_index: int = 0,
    object_distance_mm: float = 0.0,
) -> TelecentricFit:
    """Fit a telecentric camera with Brown-Conrady distortion to views of a planar target.

    Args:
        plane_points_mm: per view, the target's corners (n, 2) in its plane, mm.
        image_points_px: per view, where they were found (n, 2), px.
        size_px: (width, height) of the images.
        plane_index: the view whose plane is the specimen plane (for the scale).
        object_distance_mm: the nominal tz of every view's plane (not observable).

    Raises:
        ValueError: a view with fewer than 4 corners, or a fit that does not converge to
            finite parameters.
    """
    objects = [np.asarray(p, np.float64).reshape(-1, 2) for p in plane_points_mm]
    images = [np.asarray(p, np.float64).reshape(-1, 2) for p in image_points_px]
    for k, (obj, img) in enumerate(zip(objects, images, strict=True)):
        if len(obj) < 4 or len(obj) != len(img):
            raise ValueError(f"view {k}: {len(obj)} corners, at least 4 needed")
    width, height = size_px
    centre = np.array([0.5 * (width - 1), 0.5 * (height - 1)])
    affines = [_affine(obj, img) for obj, img in zip(objects, images, strict=True)]
    focal = float(np.median([np.linalg.svd(a)[1][0] for a, _ in affines]))
    half_diagonal_mm = 0.5 * math.hypot(width, height) / focal
    start = [focal, focal, 0.0, 0.0, 0.0, 0.0]
    for matrix, offset in affines:
        rotation = _completed_rotation(matrix / focal)
        start.extend([*rotation, *((offset - centre) / focal)])
    observed = np.concatenate([img.ravel() for img in images])

    def full(free: FloatArray) -> FloatArray:
        return np.concatenate([free[:2], centre, free[2:]])

    def residuals(free: FloatArray) -> FloatArray:
        return _project_all(full(free), objects, half_diagonal_mm) - observed

    def jacobian(free: FloatArray) -> FloatArray:
        return np.delete(_jacobian(full(free), objects, half_diagonal_mm), _CENTRE, axis=1)

    result = least_squares(
        residuals,
        np.asarray(start, np.float64),
        jac=jacobian,
        method="lm",
        x_scale="jac",
        ftol=_TOLERANCE,
        xtol=_TOLERANCE,
        gtol=_TOLERANCE,
        max_nfev=_MAX_EVALUATIONS,
    )
    values = full(result.x)
    if not np.all(np.isfinite(values)) or values[0] <= 0 or values[1] <= 0:
        raise ValueError("the telecentric fit did not converge")
    camera = _camera(values, size_px, half_diagonal_mm)
    poses = tuple(
        _pose(values[_INTRINSICS + _PER_VIEW * k :][:_PER_VIEW], object_distance_mm)
        for k in range(len(objects))
    )
    residual = result.fun.reshape(-1, 2)
    squared = np.sum(residual**2, axis=1)
    rms = float(math.sqrt(squared.mean()))
    bounds = np.cumsum([0] + [len(obj) for obj in objects])
    view_errors = tuple(
        float(math.sqrt(squared[bounds[k] : bounds[k + 1]].mean())) for k in range(len(objects))
    )
    scale = PlaneProjection(camera, poses[plane_index]).scale_mm_per_px(tuple(centre))
    uncertainty = _scale_uncertainty(
        values,
        np.insert(np.asarray(result.jac), [_CENTRE[0]] * len(_CENTRE), 0.0, axis=1),
        result.fun,
        plane_index,
        size_px,
        half_diagonal_mm,
        tuple(centre),
    )
    return TelecentricFit(camera, poses, rms, view_errors, scale, uncertainty)


def telecentric_pose(
    camera: CameraModel,
    plane_points_mm: npt.ArrayLike,
    image_points_px: npt.ArrayLike,
    *,
    object_distance_mm: float = 0.0,
) -> PlanePose:
    """A planar target's pose under a telecentric camera's stored intrinsics: the corners are
    undistorted to millimetres, an affine fit of the plane to them starts a least-squares fit
    of the rotation and the in-plane translation to the pixels; tz is `object_distance_mm`.

    Raises:
        ValueError: fewer than 4 corners, or a camera that is not telecentric.
    """
    pose, _ = _fit_pose(camera, plane_points_mm, image_points_px, object_distance_mm, False)
    return pose


def telecentric_magnification(
    camera: CameraModel,
    plane_points_mm: npt.ArrayLike,
    image_points_px: npt.ArrayLike,
    *,
    object_distance_mm: float = 0.0,
) -> tuple[PlanePose, float]:
    """A planar target's pose and the camera's magnification now relative to the stored one
    (m: fx, fy now are m times the stored ones). A telecentric lens's scale does not change
    with the distance, so a field check must free the magnification to see it change: a
    tilt shrinks the image along one direction only, a magnification along both.

    Raises:
        ValueError: as `telecentric_pose`.
    """
    return _fit_pose(camera, plane_points_mm, image_points_px, object_distance_mm, True)


def _fit_pose(
    camera: CameraModel,
    plane_points_mm: npt.ArrayLike,
    image_points_px: npt.ArrayLike,
    object_distance_mm: float,
    free_magnification: bool,
) -> tuple[PlanePose, float]:
    if not camera.telecentric:
        raise ValueError("a telecentric pose needs a telecentric camera")
    objects = np.asarray(plane_points_mm, np.float64).reshape(-1, 2)
    pixels = np.asarray(image_points_px, np.float64).reshape(-1, 2)
    if len(objects) < 4 or len(objects) != len(pixels):
        raise ValueError(f"{len(objects)} corners, at least 4 needed")
    matrix, offset = _affine(objects, camera.normalised(pixels))
    magnification = float(np.linalg.svd(matrix)[1][0]) if free_magnification else 1.0
    start = [*_completed_rotation(matrix / magnification), *(offset / magnification)]
    if free_magnification:
        start.append(magnification)

    def model(values: FloatArray) -> CameraModel:
        if not free_magnification:
            return camera
        return dataclasses.replace(
            camera, fx_px=camera.fx_px * values[5], fy_px=camera.fy_px * values[5]
        )

    def residuals(values: FloatArray) -> FloatArray:
        pose = _pose(values, object_distance_mm)
        return (model(values).project(pose.to_camera(objects)) - pixels).ravel()

    result = least_squares(
        residuals, np.asarray(start), jac="3-point", method="lm", x_scale="jac", xtol=_TOLERANCE
    )
    return _pose(result.x, object_distance_mm), float(result.x[5]) if free_magnification else 1.0


def _affine(objects: FloatArray, images: FloatArray) -> tuple[FloatArray, FloatArray]:
    """A (2, 2) and c (2,) of the least-squares fit images = objects @ A.T + c."""
    design = np.column_stack([objects, np.ones(len(objects))])
    solution, *_ = np.linalg.lstsq(design, images, rcond=None)
    return solution[:2].T, solution[2]


def _completed_rotation(block: FloatArray) -> FloatArray:
    """The Rodrigues vector of the rotation whose upper-left 2x2 block is nearest `block`;
    of the two (mirror) completions, the one whose plane X axis points away from the camera
    (the tilt sign is not observable)."""
    first, second = block[:, 0], block[:, 1]
    z_first = math.sqrt(max(0.0, 1.0 - float(first @ first)))
    z_second = math.sqrt(max(0.0, 1.0 - float(second @ second)))
    if float(first @ second) > 0:
        z_second = -z_second
    columns = np.column_stack([[*first, z_first], [*second, z_second]])
    u, _, vt = np.linalg.svd(columns, full_matrices=False)
    orthonormal = u @ vt
    rotation = np.column_stack([orthonormal, np.cross(orthonormal[:, 0], orthonormal[:, 1])])
    return cv2.Rodrigues(rotation)[0].ravel()


def _pose(values: FloatArray, object_distance_mm: float) -> PlanePose:
    return PlanePose.from_arrays(values[:3], [values[3], values[4], object_distance_mm])


def _distortion(values: FloatArray, half_diagonal_mm: float) -> LensDistortion:
    length = half_diagonal_mm
    k1, k2, p1, p2 = values[4:8]
    return LensDistortion(k1 / length**2, k2 / length**4, p1 / length, p2 / length, 0.0)


def _camera(values: FloatArray, size_px: tuple[int, int], half_diagonal_mm: float) -> CameraModel:
    return CameraModel(
        int(size_px[0]),
        int(size_px[1]),
        float(values[0]),
        float(values[1]),
        float(values[2]),
        float(values[3]),
        _distortion(values, half_diagonal_mm),
        telecentric=True,
    )


def _project_all(
    values: FloatArray, objects: Sequence[FloatArray], half_diagonal_mm: float
) -> FloatArray:
    """Every view's corners projected (flattened x, y pairs), px."""
    fx, fy, cx, cy, k1, k2, p1, p2 = values[:_INTRINSICS]
    length = half_diagonal_mm
    out = []
    for k, points in enumerate(objects):
        view = values[_INTRINSICS + _PER_VIEW * k :][:_PER_VIEW]
        rotation = cv2.Rodrigues(np.asarray(view[:3], np.float64))[0]
        a = (points @ rotation[0, :2] + view[3]) / length
        b = (points @ rotation[1, :2] + view[4]) / length
        r2 = a * a + b * b
        radial = 1.0 + r2 * (k1 + r2 * k2)
        a_d = a * radial + 2.0 * p1 * a * b + p2 * (r2 + 2.0 * a * a)
        b_d = b * radial + p1 * (r2 + 2.0 * b * b) + 2.0 * p2 * a * b
        out.append(np.column_stack([fx * length * a_d + cx, fy * length * b_d + cy]).ravel())
    return np.concatenate(out)


def _jacobian(
    values: FloatArray, objects: Sequence[FloatArray], half_diagonal_mm: float
) -> FloatArray:
    """Central-difference Jacobian of `_project_all`. A view's residuals depend on its own
    pose only, so the same pose parameter of every view is stepped at once: 2 x (8 + 5)
    projections, whatever the number of views."""
    n_views = len(objects)
    bounds = 2 * np.cumsum([0] + [len(points) for points in objects])
    out = np.zeros((bounds[-1], len(values)))
    steps = 1e-6 * np.maximum(1.0, np.abs(values))
    for i in range(_INTRINSICS):
        up, down = values.copy(), values.copy()
        up[i] += steps[i]
        down[i] -= steps[i]
        difference = _project_all(up, objects, half_diagonal_mm)
        difference -= _project_all(down, objects, half_diagonal_mm)
        out[:, i] = difference / (2.0 * steps[i])
    for j in range(_PER_VIEW):
        columns = _INTRINSICS + _PER_VIEW * np.arange(n_views) + j
        up, down = values.copy(), values.copy()
        up[columns] += steps[columns]
        down[columns] -= steps[columns]
        difference = _project_all(up, objects, half_diagonal_mm)
        difference -= _project_all(down, objects, half_diagonal_mm)
        for k, column in enumerate(columns):
            rows = slice(bounds[k], bounds[k + 1])
            out[rows, column] = difference[rows] / (2.0 * steps[column])
    return out


def _scale_uncertainty(
    values: FloatArray,
    jacobian: FloatArray,
    residual: FloatArray,
    plane_index: int,
    size_px: tuple[int, int],
    half_diagonal_mm: float,
    centre: tuple[float, float],
) -> float:
    """Standard uncertainty of the scale at `centre`, propagated from the fit's covariance."""
    covariance = fit_covariance(jacobian, residual)
    first = _INTRINSICS + _PER_VIEW * plane_index
    columns = list(range(_INTRINSICS)) + list(range(first, first + _PER_VIEW))

    def scale_of(parameters: FloatArray) -> float:
        camera = _camera(parameters, size_px, half_diagonal_mm)
        pose = _pose(parameters[first : first + _PER_VIEW], 0.0)
        return PlaneProjection(camera, pose).scale_mm_per_px(centre)

    def scale_of_fitted(fitted: FloatArray) -> float:
        parameters = values.copy()
        parameters[columns] = fitted
        return scale_of(parameters)

    return propagated_uncertainty(
        scale_of_fitted, values[columns], covariance[np.ix_(columns, columns)]
    )
