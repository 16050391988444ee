"""Camera calibration from simulated target images through a lens with about 1 % distortion
at the corners (k1 = -0.05, 2048 x 1024 px of 5.5 um behind a 14 mm lens at 400 mm:
fx ~ 2545 px): what it recovers, what it refuses, and the field check."""

import dataclasses

import numpy as np
import pytest

from appliance.errors import InputError
from appliance.optics.calibration_target import CalibrationTarget
from appliance.optics.camera_model import CameraModel, LensDistortion, PlanePose, PlaneProjection
from appliance.optics.target_calibration import (
    CalibrationLimits,
    View,
    calibrate,
    check_calibration,
    coverage_fraction,
    find_target,
)
from appliance.sim.target import TargetLook, calibration_poses, render_target

CAMERA = CameraModel.ideal(2048, 1024, 2545.0, distortion=LensDistortion(k1=-0.05))
CHARUCO = CalibrationTarget("charuco", 10, 6, 15.0)
LOOK = TargetLook(noise_grey=0.5)
DISTANCE_MM = 400.0
CENTRE = ((CAMERA.width_px - 1) / 2, (CAMERA.height_px - 1) / 2)
CORNERS = np.array([[0.0, 0.0], [2047.0, 0.0], [0.0, 1023.0], [2047.0, 1023.0]])


def _views(target, poses, camera=CAMERA, seed=0):
    return [
        find_target(target, render_target(target, p, camera, look=LOOK, seed=seed + k), f"v{k}")
        for k, p in enumerate(poses)
    ]


def _lens_displacement(camera: CameraModel) -> np.ndarray:
    normalised = camera.normalised(CORNERS)
    ideal = normalised * [camera.fx_px, camera.fy_px] + [camera.cx_px, camera.cy_px]
    return CORNERS - ideal


@pytest.fixture(scope="module")
def charuco():
    poses = calibration_poses(CAMERA, CHARUCO, 12, distance_mm=DISTANCE_MM, seed=1)
    views = _views(CHARUCO, poses)
    return poses, views, calibrate(views, CHARUCO, software_version="t", created_utc="now")


def test_a_charuco_calibration_recovers_the_camera_and_the_scale(charuco):
    poses, _, calibration = charuco
    camera = calibration.camera
    assert camera.fx_px == pytest.approx(CAMERA.fx_px, rel=1e-3)
    assert camera.fy_px == pytest.approx(CAMERA.fy_px, rel=1e-3)
    assert camera.cx_px == pytest.approx(CAMERA.cx_px, abs=2.0)
    assert camera.cy_px == pytest.approx(CAMERA.cy_px, abs=2.0)
    assert np.hypot(*_lens_displacement(CAMERA).T).max() > 10.0
    error_px = np.hypot(*(_lens_displacement(camera) - _lens_displacement(CAMERA)).T)
    assert error_px.max() < 0.3
    true_scale = PlaneProjection(CAMERA, poses[0]).scale_mm_per_px(CENTRE)
    scale_error = calibration.scale_mm_per_px / true_scale - 1.0
    assert abs(scale_error) < 2e-4
    assert 0 < calibration.scale_uncertainty_mm_per_px / true_scale < 1e-4
    assert calibration.rms_reprojection_px < 0.05
    assert len(calibration.view_errors_px) == 12
    assert max(calibration.view_errors_px) < 0.05
    assert 0.5 < calibration.coverage_fraction < 1.0
    assert calibration.target["kind"] == "charuco"
    assert calibration.target["plane_image"] == "v0"
    assert calibration.software_version == "t"


def test_the_plane_is_the_target_in_the_plane_view(charuco):
    poses, views, _ = charuco
    calibration = calibrate(views, CHARUCO, plane_index=3)
    truth = PlaneProjection(CAMERA, poses[3]).scale_mm_per_px(CENTRE)
    assert calibration.scale_mm_per_px == pytest.approx(truth, rel=3e-4)
    assert calibration.plane.normal_tilt_deg == pytest.approx(poses[3].normal_tilt_deg, abs=0.1)


@pytest.mark.parametrize(
    ("target", "max_rms_px", "max_scale_error"),
    [
        (CalibrationTarget("chessboard", 9, 6, 12.0), 0.06, 3e-4),
        (CalibrationTarget("circles", 9, 5, 14.0), 0.15, 1e-3),
    ],
)
def test_chessboard_and_circle_grid_calibrate(target, max_rms_px, max_scale_error):
    tilt = (30.0, 40.0) if target.kind == "circles" else (30.0, 45.0)
    poses = calibration_poses(CAMERA, target, 8, distance_mm=DISTANCE_MM, seed=2, tilt_deg=tilt)
    calibration = calibrate(_views(target, poses), target)
    assert calibration.rms_reprojection_px < max_rms_px
    assert calibration.camera.fx_px == pytest.approx(CAMERA.fx_px, rel=3e-3)
    true_scale = PlaneProjection(CAMERA, poses[0]).scale_mm_per_px(CENTRE)
    assert calibration.scale_mm_per_px == pytest.approx(true_scale, rel=max_scale_error)


def test_too_few_views_are_refused(charuco):
    _, views, _ = charuco
    with pytest.raises(InputError, match="2 view.*at least 3"):
        calibrate(views[:2], CHARUCO)


def test_a_target_not_found_is_refused_naming_the_image():
    blank = np.full((1024, 2048), 128, np.uint8)
    with pytest.raises(InputError, match="blank.png: charuco target not found"):
        find_target(CHARUCO, blank, "blank.png")


def test_images_of_different_sizes_are_refused(charuco):
    _, views, _ = charuco
    other = dataclasses.replace(views[2], size_px=(1024, 512))
    with pytest.raises(InputError, match="v2: image is 1024x512 px, v0 is 2048x1024"):
        calibrate([*views[:2], other, *views[3:]], CHARUCO)


def test_a_poorly_covered_field_is_refused(charuco):
    _, views, _ = charuco
    covered = coverage_fraction(views, (2048, 1024))
    with pytest.raises(InputError, match=r"cover \d+% of the field, at least 95% .*--min-coverage"):
        calibrate(views, CHARUCO, limits=CalibrationLimits(min_coverage=0.95))
    assert covered < 0.95


def test_an_rms_error_above_the_limit_is_refused(charuco):
    _, views, _ = charuco
    with pytest.raises(InputError, match=r"RMS reprojection error .* above the limit 0.001 px"):
        calibrate(views, CHARUCO, limits=CalibrationLimits(max_rms_px=0.001))


def test_a_view_with_mislabelled_corners_is_caught_by_the_rms_limit(charuco):
    _, views, _ = charuco
    detection = views[1].detection
    reversed_ids = dataclasses.replace(detection, ids=detection.ids[::-1])
    mislabelled = View("v1", views[1].size_px, reversed_ids)
    with pytest.raises(InputError, match="RMS reprojection error"):
        calibrate([views[0], mislabelled, *views[2:]], CHARUCO)


def test_views_through_a_lens_with_perspective_are_refused_as_telecentric(charuco):
    _, views, _ = charuco
    with pytest.raises(InputError, match="calibrate without --telecentric"):
        calibrate(views, CHARUCO, telecentric=True)


def test_the_field_check_passes_a_fresh_view_and_fails_a_moved_or_rescaled_camera(charuco):
    poses, _, calibration = charuco
    plane = poses[0]
    shifted = PlanePose(
        plane.rotation_vector, (plane.translation_mm[0] + 20.0,) + plane.translation_mm[1:]
    )
    fresh = _views(CHARUCO, [shifted], seed=100)
    [result] = check_calibration(calibration, CHARUCO, fresh)
    assert result.fit
    assert abs(result.scale_change) < 2e-4
    assert result.rms_px < 0.05
    moved = _views(CHARUCO, [plane.moved_along_normal(2.0)], seed=101)
    [result] = check_calibration(calibration, CHARUCO, moved)
    assert not result.fit
    assert result.scale_change == pytest.approx(0.005, rel=0.05)
    zoomed = dataclasses.replace(CAMERA, fx_px=CAMERA.fx_px * 1.01, fy_px=CAMERA.fy_px * 1.01)
    rescaled = _views(CHARUCO, [plane], camera=zoomed, seed=102)
    [result] = check_calibration(calibration, CHARUCO, rescaled)
    assert not result.fit
    assert result.scale_change == pytest.approx(-0.0099, rel=0.05)


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (("grid", 5, 5, 10.0), "target kind"),
        (("chessboard", 2, 5, 10.0), "at least 3x3"),
        (("chessboard", 5, 5, 0.0), "square size"),
        (("charuco", 5, 5, 10.0, 10.0), "marker size"),
        (("charuco", 5, 5, 10.0, 7.0, "DICT_NOPE"), "dictionary"),
        (("charuco", 20, 20, 10.0, 7.0, "DICT_4X4_50"), "needs 200 markers"),
    ],
)
def test_a_bad_target_is_refused(arguments, message):
    with pytest.raises(ValueError, match=message):
        CalibrationTarget(*arguments)
