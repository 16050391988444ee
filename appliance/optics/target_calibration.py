"""Camera calibration from images of a planar target, and the field check of a calibration.

Calibration (`calibrate`):

1. The target's corners are found in every image (`CalibrationTarget.detect`); a view in
   which it is not found is refused by name, as are images of different sizes.
2. `cv2.calibrateCameraExtended` fits fx, fy, cx, cy and the five Brown-Conrady coefficients
   (k1, k2, p1, p2, k3) with flags 0: OpenCV's default model, the one `CameraModel` holds.
   Skew is fixed at zero by OpenCV; the aspect ratio and the principal point are free (a
   sensor's pixels need not be square nor its lens centred); the rational and thin-prism
   terms are not fitted, as a machine-vision lens does not need them and they would fit the
   detection noise at the field's edges.
3. The specimen plane is the target's surface in the plane view (`plane_index`, by default the
   first image): its pose is solved with `cv2.solvePnP` (iterative, from the calibration's
   pose of that view) under the fitted intrinsics. The board's thickness is taken as zero.
4. The scale at that plane at the image centre is `PlaneProjection.scale_mm_per_px`. Its
   standard uncertainty is propagated from the fit: the Jacobian of every corner's
   reprojection with respect to the intrinsics and every view's pose (`cv2.projectPoints`)
   gives the parameters' covariance ``s^2 (J^T J)^-1`` (s^2 the residual variance per
   coordinate), and the scale's gradient with respect to the intrinsics and the plane view's
   pose (central differences) carries it to the scale, correlations included. It covers the
   corners' detection noise, not the target's own tolerance (add the certificate's relative
   uncertainty of the square size in quadrature).
5. Coverage: the fraction of the image inside the union of the views' convex hulls of their
   detected corners (rasterised on an 8 px grid).

Refusals (`InputError`, one line): fewer than `MIN_VIEWS` views, a target not found, images of
different sizes, a coverage below `CalibrationLimits.min_coverage`, an RMS reprojection error
above `CalibrationLimits.max_rms_px`.

Telecentric lens (`telecentric=True`): the same checks, then steps 2 to 4 are
`appliance.optics.telecentric_calibration.fit_telecentric` (an orthographic camera with
Brown-Conrady distortion fitted with scipy, as OpenCV has none); every plane's distance is the
nominal `object_distance_mm` (not observable through a telecentric lens). The field check
solves a telecentric camera's poses with `telecentric_pose`.

Field check (`check_calibration`): the target's pose in each image is solved under the stored
intrinsics; the reprojection RMS now and the scale at the image centre now, against the stored
scale, decide whether the calibration still fits the camera. A telecentric lens's scale does
not change with the distance: its scale now is taken with the magnification freed.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from appliance.errors import InputError
from appliance.optics.calibration_file import CameraCalibration
from appliance.optics.calibration_target import CalibrationTarget, Detection
from appliance.optics.camera_model import CameraModel, LensDistortion, PlanePose, PlaneProjection
from appliance.optics.fit_uncertainty import fit_covariance, propagated_uncertainty
from appliance.optics.telecentric_calibration import (
    fit_telecentric,
    telecentric_magnification,
    telecentric_pose,
)

FloatArray = npt.NDArray[np.float64]

MIN_VIEWS = 3
"""Zhang's method: each view of a plane gives two constraints on the camera matrix, so three
views in general position are the fewest that determine fx, fy, cx, cy with the distortion;
ten or more tilted views spread over the field give a calibration worth its name."""

CALIBRATION_FLAGS = 0
_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
_COVERAGE_CELL_PX = 8


@dataclass(frozen=True)
class CalibrationLimits:
    """What a calibration must achieve to be written.

    Attributes:
        max_rms_px: largest RMS reprojection error over every corner, px.
        min_coverage: least fraction of the field the target's corners must cover (0..1).
    """

    max_rms_px: float = 0.5
    min_coverage: float = 0.5


@dataclass(frozen=True)
class CheckLimits:
    """When a calibration still fits the camera.

    Attributes:
        max_rms_px: largest RMS reprojection error of a check view under the stored
            intrinsics, px.
        max_scale_change: largest relative change of the scale at the image centre.
    """

    max_rms_px: float = 0.5
    max_scale_change: float = 0.001


@dataclass(frozen=True)
class View:
    """One image's detection.

    Attributes:
        name: the image's name (its file), for messages.
        size_px: (width, height) of the image.
        detection: the target's corners found in it.
    """

    name: str
    size_px: tuple[int, int]
    detection: Detection


def find_target(target: CalibrationTarget, image: npt.NDArray[np.uint8], name: str) -> View:
    """The target's corners in one 8-bit image.

    Raises:
        InputError: the target is not found (names the image).
    """
    detection = target.detect(image)
    if detection is None:
        raise InputError(f"{name}: {target.kind} target not found ({target.describe()})")
    return View(name, (int(image.shape[1]), int(image.shape[0])), detection)


def calibrate(
    views: Sequence[View],
    target: CalibrationTarget,
    *,
    plane_index: int = 0,
    limits: CalibrationLimits | None = None,
    software_version: str = "",
    created_utc: str = "",
    telecentric: bool = False,
    object_distance_mm: float = 0.0,
) -> CameraCalibration:
    """Calibrate the camera from views of a planar target.

    Args:
        views: the detections, one per image.
        target: the target they show.
        plane_index: the view whose target pose is the specimen plane.
        limits: what the calibration must achieve.
        software_version, created_utc: recorded in the calibration.
        telecentric: a telecentric lens (`fit_telecentric`).
        object_distance_mm: a telecentric lens: the nominal distance of the planes (their
            tz, not observable), mm.

    Raises:
        InputError: too few views, images of different sizes, poor coverage, or an RMS error
            above the limit.
    """
    limits = limits or CalibrationLimits()
    if len(views) < MIN_VIEWS:
        raise InputError(
            f"{len(views)} view(s) of the target, at least {MIN_VIEWS} needed (each view of a "
            "plane gives two constraints on the camera matrix; ten or more tilted views over "
            "the field are recommended)"
        )
    size = views[0].size_px
    for view in views[1:]:
        if view.size_px != size:
            raise InputError(
                f"{view.name}: image is {view.size_px[0]}x{view.size_px[1]} px, "
                f"{views[0].name} is {size[0]}x{size[1]} px (one camera, one size)"
            )
    coverage = coverage_fraction(views, size)
    if coverage < limits.min_coverage:
        raise InputError(
            f"the target's corners cover {coverage:.0%} of the field, at least "
            f"{limits.min_coverage:.0%} needed (--min-coverage): add views near the edges "
            "and corners"
        )
    if telecentric:
        return _calibrate_telecentric(
            views,
            target,
            plane_index,
            limits,
            object_distance_mm,
            coverage,
            software_version,
            created_utc,
        )
    objects = [_object_points(target, view.detection) for view in views]
    images = [view.detection.image_px.astype(np.float32).reshape(-1, 1, 2) for view in views]
    rms, matrix, distortion, rvecs, tvecs, _, _, view_errors = cv2.calibrateCameraExtended(
        objects, images, size, None, None, flags=CALIBRATION_FLAGS, criteria=_CRITERIA
    )
    _check_rms(rms, limits)
    camera = CameraModel(
        size[0],
        size[1],
        float(matrix[0, 0]),
        float(matrix[1, 1]),
        float(matrix[0, 2]),
        float(matrix[1, 2]),
        LensDistortion.from_coefficients(distortion),
    )
    plane_view = views[plane_index]
    plane = solve_pose(
        camera, target, plane_view.detection, (rvecs[plane_index], tvecs[plane_index])
    )
    centre = (0.5 * (size[0] - 1), 0.5 * (size[1] - 1))
    scale = PlaneProjection(camera, plane).scale_mm_per_px(centre)
    uncertainty = _scale_uncertainty(
        camera, target, views, list(rvecs), list(tvecs), plane_index, plane, centre
    )
    document = target.to_document()
    document["plane_image"] = plane_view.name
    return CameraCalibration(
        camera=camera,
        plane=plane,
        scale_mm_per_px=scale,
        scale_uncertainty_mm_per_px=uncertainty,
        rms_reprojection_px=float(rms),
        view_errors_px=tuple(float(v) for v in np.ravel(view_errors)),
        coverage_fraction=coverage,
        target=document,
        software_version=software_version,
        created_utc=created_utc,
    )


def _check_rms(rms: float, limits: CalibrationLimits, *, telecentric: bool = False) -> None:
    if not (math.isfinite(rms) and rms <= limits.max_rms_px):
        hint = " (or the lens has perspective: calibrate without --telecentric)"
        raise InputError(
            f"RMS reprojection error {rms:.3f} px, above the limit {limits.max_rms_px:g} px "
            "(--max-rms-px): check the target's size, focus and that the views are sharp"
            + (hint if telecentric else "")
        )


def _calibrate_telecentric(
    views: Sequence[View],
    target: CalibrationTarget,
    plane_index: int,
    limits: CalibrationLimits,
    object_distance_mm: float,
    coverage: float,
    software_version: str,
    created_utc: str,
) -> CameraCalibration:
    try:
        fit = fit_telecentric(
            [target.object_points_mm[view.detection.ids] for view in views],
            [view.detection.image_px for view in views],
            views[0].size_px,
            plane_index=plane_index,
            object_distance_mm=object_distance_mm,
        )
    except ValueError as exc:
        raise InputError(f"telecentric calibration failed: {exc}") from None
    _check_rms(fit.rms_px, limits, telecentric=True)
    document = target.to_document()
    document["plane_image"] = views[plane_index].name
    return CameraCalibration(
        camera=fit.camera,
        plane=fit.poses[plane_index],
        scale_mm_per_px=fit.scale_mm_per_px,
        scale_uncertainty_mm_per_px=fit.scale_uncertainty_mm_per_px,
        rms_reprojection_px=fit.rms_px,
        view_errors_px=fit.view_errors_px,
        coverage_fraction=coverage,
        target=document,
        software_version=software_version,
        created_utc=created_utc,
    )


def solve_pose(
    camera: CameraModel,
    target: CalibrationTarget,
    detection: Detection,
    guess: tuple[npt.ArrayLike, npt.ArrayLike] | None = None,
) -> PlanePose:
    """The target's pose under `camera`'s intrinsics (`cv2.solvePnP`, iterative; a
    telecentric camera: `telecentric_pose`, the distance from `guess` or 0)."""
    if camera.telecentric:
        distance_mm = 0.0 if guess is None else float(np.ravel(guess[1])[2])
        try:
            return telecentric_pose(
                camera,
                target.object_points_mm[detection.ids],
                detection.image_px,
                object_distance_mm=distance_mm,
            )
        except ValueError as exc:
            raise InputError(f"the target's pose could not be solved ({exc})") from None
    objects = _object_points(target, detection).astype(np.float64)
    images = detection.image_px.reshape(-1, 1, 2)
    distortion = camera.distortion.coefficients
    if guess is None:
        rvec = np.zeros((3, 1))
        tvec = np.zeros((3, 1))
        use_guess = False
    else:
        rvec = np.asarray(guess[0], np.float64).reshape(3, 1).copy()
        tvec = np.asarray(guess[1], np.float64).reshape(3, 1).copy()
        use_guess = True
    ok, rvec, tvec = cv2.solvePnP(
        objects,
        images,
        camera.matrix,
        distortion,
        rvec,
        tvec,
        useExtrinsicGuess=use_guess,
        flags=cv2.SOLVEPNP_ITERATIVE,
    )
    if not ok:
        raise InputError("the target's pose could not be solved")
    if not use_guess:
        rvec, tvec = cv2.solvePnPRefineLM(
            objects, images, camera.matrix, distortion, rvec, tvec, _CRITERIA
        )
    return PlanePose.from_arrays(rvec, tvec)


def reprojection_rms_px(
    camera: CameraModel, target: CalibrationTarget, detection: Detection, pose: PlanePose
) -> float:
    """RMS distance (px) between the detected corners and the corners projected from `pose`."""
    projected = PlaneProjection(camera, pose).to_pixels(target.object_points_mm[detection.ids])
    return float(np.sqrt(np.mean(np.sum((projected - detection.image_px) ** 2, axis=1))))


def coverage_fraction(views: Sequence[View], size_px: tuple[int, int]) -> float:
    """Fraction of the image inside the union of the views' convex hulls of their corners."""
    cell = _COVERAGE_CELL_PX
    mask = np.zeros((math.ceil(size_px[1] / cell), math.ceil(size_px[0] / cell)), np.uint8)
    for view in views:
        points = np.rint(view.detection.image_px / cell).astype(np.int32)
        hull = cv2.convexHull(points.reshape(-1, 1, 2))
        cv2.fillConvexPoly(mask, hull, 1)
    return float(mask.mean())


@dataclass(frozen=True)
class CheckedView:
    """One check image's result.

    Attributes:
        name: the image.
        rms_px: RMS reprojection error under the stored intrinsics, px.
        scale_mm_per_px: scale at the image centre on the target's plane now, mm/px.
        scale_change: relative difference from the stored scale (now / stored - 1).
        fit: both within the limits.
    """

    name: str
    rms_px: float
    scale_mm_per_px: float
    scale_change: float
    fit: bool


def check_calibration(
    calibration: CameraCalibration,
    target: CalibrationTarget,
    views: Sequence[View],
    limits: CheckLimits | None = None,
) -> list[CheckedView]:
    """Whether a calibration still fits the camera: for each view of the target (placed at the
    specimen plane), the reprojection RMS and the scale at the image centre now."""
    limits = limits or CheckLimits()
    camera = calibration.camera
    centre = (0.5 * (camera.width_px - 1), 0.5 * (camera.height_px - 1))
    results = []
    for view in views:
        if view.size_px != camera.sensor_size:
            raise InputError(
                f"{view.name}: image is {view.size_px[0]}x{view.size_px[1]} px, the "
                f"calibration is for {camera.width_px}x{camera.height_px} px"
            )
        pose = solve_pose(camera, target, view.detection)
        rms = reprojection_rms_px(camera, target, view.detection, pose)
        scale = _scale_now(camera, target, view.detection, pose, centre)
        change = scale / calibration.scale_mm_per_px - 1.0
        fit = rms <= limits.max_rms_px and abs(change) <= limits.max_scale_change
        results.append(CheckedView(view.name, rms, scale, change, fit))
    return results


def _scale_now(
    camera: CameraModel,
    target: CalibrationTarget,
    detection: Detection,
    pose: PlanePose,
    centre: tuple[float, float],
) -> float:
    """The scale at the image centre on the check view's plane; a telecentric camera's with
    its magnification freed (`telecentric_magnification`)."""
    if not camera.telecentric:
        return PlaneProjection(camera, pose).scale_mm_per_px(centre)
    try:
        pose, magnification = telecentric_magnification(
            camera, target.object_points_mm[detection.ids], detection.image_px
        )
    except ValueError as exc:
        raise InputError(f"the target's pose could not be solved ({exc})") from None
    now = dataclasses.replace(
        camera, fx_px=camera.fx_px * magnification, fy_px=camera.fy_px * magnification
    )
    return PlaneProjection(now, pose).scale_mm_per_px(centre)


def target_from_document(document: object, source: str) -> CalibrationTarget:
    """The target a calibration file records (for its field check).

    Raises:
        InputError: the calibration records no usable target.
    """
    try:
        assert isinstance(document, dict)
        return CalibrationTarget(
            str(document["kind"]),
            int(document["columns"]),
            int(document["rows"]),
            float(document["square_mm"]),
            float(document.get("marker_mm", 0.0)),
            str(document.get("dictionary", "DICT_5X5_100")),
        )
    except (AssertionError, KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{source}: calibration records no usable target ({exc})") from None


def _object_points(target: CalibrationTarget, detection: Detection) -> npt.NDArray[np.float32]:
    plane = target.object_points_mm[detection.ids]
    points = np.column_stack([plane, np.zeros(len(plane))])
    return points.astype(np.float32).reshape(-1, 1, 3)


def _scale_uncertainty(
    camera: CameraModel,
    target: CalibrationTarget,
    views: Sequence[View],
    rvecs: list[FloatArray],
    tvecs: list[FloatArray],
    plane_index: int,
    plane: PlanePose,
    centre: tuple[float, float],
) -> float:
    """Standard uncertainty of the scale at `centre`, propagated from the fit's covariance."""
    n_views = len(views)
    n_params = 9 + 6 * n_views
    blocks, residuals = [], []
    distortion = camera.distortion.coefficients
    for k, view in enumerate(views):
        objects = _object_points(target, view.detection).astype(np.float64)
        projected, jacobian = cv2.projectPoints(
            objects, rvecs[k], tvecs[k], camera.matrix, distortion
        )
        residuals.append((projected.reshape(-1, 2) - view.detection.image_px).ravel())
        block = np.zeros((jacobian.shape[0], n_params))
        block[:, 0:9] = jacobian[:, 6:15]
        block[:, 9 + 6 * k : 15 + 6 * k] = jacobian[:, 0:6]
        blocks.append(block)
    jacobian = np.vstack(blocks)
    residual = np.concatenate(residuals)
    covariance = fit_covariance(jacobian, residual)
    parameters = np.concatenate(
        [
            [camera.fx_px, camera.fy_px, camera.cx_px, camera.cy_px],
            distortion,
            plane.rotation_vector,
            plane.translation_mm,
        ]
    )
    columns = list(range(9)) + list(range(9 + 6 * plane_index, 15 + 6 * plane_index))

    def scale_of(values: FloatArray) -> float:
        model = CameraModel(
            camera.width_px,
            camera.height_px,
            values[0],
            values[1],
            values[2],
            values[3],
            LensDistortion.from_coefficients(values[4:9]),
        )
        pose = PlanePose.from_arrays(values[9:12], values[12:15])
        return PlaneProjection(model, pose).scale_mm_per_px(centre)

    return propagated_uncertainty(scale_of, parameters, covariance[np.ix_(columns, columns)])
