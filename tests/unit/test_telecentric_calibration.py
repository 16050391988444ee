"""Calibration of a telecentric lens from simulated ChArUco views: 2048 x 1024 px at 20 px/mm
(a 102 x 51 mm field) with about 1 % distortion at the corners (12 px), in millimetre units as
a telecentric lens's coefficients are. What it recovers, how it measures on the plane, its file,
its field check and the command end to end."""

import dataclasses
import json
import math

import cv2
import numpy as np
import pytest

from appliance.cli import main
from appliance.errors import InputError
from appliance.optics.calibration_file import load_calibration, save_calibration
from appliance.optics.calibration_target import CalibrationTarget
from appliance.optics.camera_model import CameraModel, LensDistortion, PlanePose, PlaneProjection
from appliance.optics.target_calibration import calibrate, check_calibration, find_target
from appliance.optics.telecentric_calibration import fit_telecentric, telecentric_pose
from appliance.sim.target import TargetLook, calibration_poses, render_target

WIDTH, HEIGHT, PX_PER_MM = 2048, 1024, 20.0
HALF_DIAGONAL_MM = 0.5 * math.hypot(WIDTH, HEIGHT) / PX_PER_MM
DISTORTION = LensDistortion(
    -0.0133 / HALF_DIAGONAL_MM**2,
    0.0033 / HALF_DIAGONAL_MM**4,
    -0.0005 / HALF_DIAGONAL_MM,
    0.0003 / HALF_DIAGONAL_MM,
)
CAMERA = CameraModel.ideal(WIDTH, HEIGHT, PX_PER_MM, distortion=DISTORTION, telecentric=True)
TARGET = CalibrationTarget("charuco", 10, 6, 5.0)
OPTIONS = ("--target", "charuco", "--squares", "10x6", "--square-mm", "5")
LOOK = TargetLook(noise_grey=0.5)
CENTRE = ((WIDTH - 1) / 2, (HEIGHT - 1) / 2)
CORNERS = np.array(
    [[0.0, 0.0], [WIDTH - 1.0, 0.0], [0.0, HEIGHT - 1.0], [WIDTH - 1.0, HEIGHT - 1.0]]
)


def _image(pose, camera=CAMERA, seed=0):
    return render_target(TARGET, pose, camera, look=LOOK, seed=seed)


def _views(poses, camera=CAMERA, seed=0):
    return [find_target(TARGET, _image(p, camera, seed + k), f"v{k}") for k, p in enumerate(poses)]


def _lens_displacement(camera: CameraModel, pixels=CORNERS) -> np.ndarray:
    normalised = camera.normalised(pixels)
    return pixels - (normalised * [camera.fx_px, camera.fy_px] + [camera.cx_px, camera.cy_px])


@pytest.fixture(scope="module")
def telecentric():
    poses = calibration_poses(CAMERA, TARGET, 12, distance_mm=0.0, seed=1)
    views = _views(poses)
    calibration = calibrate(views, TARGET, telecentric=True, object_distance_mm=150.0)
    return poses, views, calibration


def test_a_telecentric_calibration_recovers_the_camera_the_lens_and_the_scale(telecentric):
    poses, _, calibration = telecentric
    camera = calibration.camera
    assert camera.telecentric
    assert camera.fx_px == pytest.approx(PX_PER_MM, rel=2e-4)
    assert camera.fy_px == pytest.approx(PX_PER_MM, rel=2e-4)
    assert (camera.cx_px, camera.cy_px) == CENTRE
    assert camera.distortion.k3 == 0.0
    rows, columns = np.mgrid[0:HEIGHT:64, 0:WIDTH:64]
    field = np.column_stack([columns.ravel(), rows.ravel()]).astype(float)
    field = np.vstack([field, CORNERS])
    true_px = _lens_displacement(CAMERA, field)
    assert np.hypot(*true_px.T).max() > 10.0
    error_px = np.hypot(*(_lens_displacement(camera, field) - true_px).T)
    assert error_px.max() < 0.1
    true_scale = PlaneProjection(CAMERA, poses[0]).scale_mm_per_px(CENTRE)
    assert calibration.scale_mm_per_px == pytest.approx(true_scale, rel=1e-4)
    assert 0 < calibration.scale_uncertainty_mm_per_px / true_scale < 5e-5
    assert calibration.rms_reprojection_px <= 0.05
    assert len(calibration.view_errors_px) == 12
    assert max(calibration.view_errors_px) < 0.08
    assert 0.5 < calibration.coverage_fraction <= 1.0
    assert calibration.plane.translation_mm[2] == 150.0
    assert calibration.target["plane_image"] == "v0"


def test_a_telecentric_file_measures_a_known_distance_on_the_plane(telecentric, tmp_path):
    poses, _, calibration = telecentric
    path = tmp_path / "telecentric.cal.json"
    save_calibration(calibration, path)
    assert json.loads(path.read_text())["camera"]["telecentric"] is True
    loaded = load_calibration(path, sensor_size=(WIDTH, HEIGHT))
    assert loaded.camera.telecentric and loaded.checksum == calibration.checksum
    ends_mm = np.array([[-15.0, 20.0], [25.0, 20.0], [5.0, 5.0], [5.0, 35.0]])
    seen_px = PlaneProjection(CAMERA, poses[0]).to_pixels(ends_mm)
    measured = loaded.projection().to_plane_mm(seen_px)
    assert np.hypot(*(measured[1] - measured[0])) == pytest.approx(40.0, rel=1e-4)
    assert np.hypot(*(measured[3] - measured[2])) == pytest.approx(30.0, rel=1e-4)
    assert np.abs(measured - ends_mm).max() < 0.01


def test_the_tilt_sign_is_unobservable_and_changes_nothing_on_the_plane():
    rotation = cv2.Rodrigues(np.array([0.5, 0.3, 0.1]))[0]
    mirrored = np.diag([1.0, 1.0, -1.0]) @ rotation @ np.diag([1.0, 1.0, -1.0])
    pose = PlanePose.from_arrays(cv2.Rodrigues(rotation)[0], [3.0, -2.0, 0.0])
    mirror = PlanePose.from_arrays(cv2.Rodrigues(mirrored)[0], [3.0, -2.0, 0.0])
    assert pose.rotation[2, 0] == pytest.approx(-mirror.rotation[2, 0])
    points = np.array([[0.0, 0.0], [20.0, 5.0], [-7.0, 30.0]])
    np.testing.assert_allclose(
        PlaneProjection(CAMERA, pose).to_pixels(points),
        PlaneProjection(CAMERA, mirror).to_pixels(points),
        atol=1e-9,
    )


def test_a_noise_free_fit_is_exact():
    poses = calibration_poses(CAMERA, TARGET, 6, distance_mm=0.0, seed=3)
    objects = [TARGET.object_points_mm] * len(poses)
    pixels = [PlaneProjection(CAMERA, pose).to_pixels(TARGET.object_points_mm) for pose in poses]
    fit = fit_telecentric(objects, pixels, (WIDTH, HEIGHT), plane_index=2)
    assert fit.rms_px < 1e-6
    assert fit.camera.fx_px == pytest.approx(PX_PER_MM, rel=1e-9)
    assert fit.camera.cx_px == pytest.approx(CAMERA.cx_px, abs=1e-5)
    assert fit.camera.distortion.k1 == pytest.approx(DISTORTION.k1, rel=1e-6)
    assert fit.scale_mm_per_px == pytest.approx(
        PlaneProjection(CAMERA, poses[2]).scale_mm_per_px(CENTRE), rel=1e-9
    )
    pose = telecentric_pose(CAMERA, TARGET.object_points_mm, pixels[4], object_distance_mm=7.0)
    np.testing.assert_allclose(pose.rotation[:2, :2], poses[4].rotation[:2, :2], atol=1e-9)
    assert pose.translation_mm[2] == 7.0
    with pytest.raises(ValueError, match="at least 4"):
        fit_telecentric([objects[0][:3]] * 3, [pixels[0][:3]] * 3, (WIDTH, HEIGHT))


def test_views_through_a_lens_with_perspective_are_refused_as_telecentric():
    pinhole = CameraModel.ideal(WIDTH, HEIGHT, 2545.0, distortion=LensDistortion(k1=-0.05))
    target = CalibrationTarget("charuco", 10, 6, 15.0)
    poses = calibration_poses(pinhole, target, 9, distance_mm=400.0, seed=1)
    views = [
        find_target(target, render_target(target, p, pinhole, look=LOOK, seed=k), f"v{k}")
        for k, p in enumerate(poses)
    ]
    with pytest.raises(InputError, match=r"RMS reprojection error .* without --telecentric"):
        calibrate(views, target, telecentric=True)


def test_the_field_check_passes_a_fresh_view_and_fails_a_changed_magnification(telecentric):
    poses, _, calibration = telecentric
    plane = poses[0]
    shifted = PlanePose(
        plane.rotation_vector, (plane.translation_mm[0] + 8.0,) + plane.translation_mm[1:]
    )
    [result] = check_calibration(calibration, TARGET, _views([shifted], seed=100))
    assert result.fit
    assert result.rms_px < 0.05
    assert abs(result.scale_change) < 2e-4
    [result] = check_calibration(calibration, TARGET, _views([plane.moved_along_normal(5.0)]))
    assert result.fit, "a telecentric lens's scale does not change with distance"
    zoomed = dataclasses.replace(CAMERA, fx_px=PX_PER_MM * 1.01, fy_px=PX_PER_MM * 1.01)
    [result] = check_calibration(calibration, TARGET, _views([plane], camera=zoomed, seed=102))
    assert not result.fit
    assert result.scale_change == pytest.approx(-0.0099, rel=0.05)


def test_calibrate_telecentric_end_to_end(telecentric, tmp_path, capsys):
    poses, _, _ = telecentric
    images = []
    for k, pose in enumerate(poses[:8]):
        images.append(str(tmp_path / f"view{k}.png"))
        cv2.imwrite(images[-1], _image(pose, seed=50 + k))
    out = tmp_path / "camera.cal.json"
    arguments = ["calibrate", *images, *OPTIONS, "--telecentric", "--out", str(out)]
    assert main([*arguments, "--object-distance-mm", "120"]) == 0
    printed = capsys.readouterr().out
    assert "telecentric, fx" in printed and "px/mm" in printed and "(nominal)" in printed
    calibration = load_calibration(out)
    assert calibration.camera.telecentric
    assert calibration.camera.fx_px == pytest.approx(PX_PER_MM, rel=5e-4)
    assert calibration.plane.translation_mm[2] == 120.0
    fresh = str(tmp_path / "fresh.png")
    cv2.imwrite(fresh, _image(poses[0], seed=99))
    assert main(["calibrate", "--check", str(out), fresh]) == 0
    assert "verdict: fit" in capsys.readouterr().out
