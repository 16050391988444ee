"""Simulated calibration targets: `render_plane` puts a texture where the camera model says,
and a target's detected corners sit on their geometric truth."""

import numpy as np
import pytest

from appliance.optics.calibration_target import CalibrationTarget
from appliance.optics.camera_model import CameraModel, LensDistortion, PlanePose, PlaneProjection
from appliance.sim.target import (
    TargetLook,
    calibration_poses,
    render_plane,
    render_target,
    target_pixels,
)

LENS = LensDistortion(k1=-0.05)


def _blob(size: int = 201, sigma: float = 10.0) -> np.ndarray:
    y, x = np.mgrid[0:size, 0:size] - size // 2
    return np.exp(-(x * x + y * y) / (2.0 * sigma * sigma))


def _centroid(image: np.ndarray) -> np.ndarray:
    rows, columns = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    return np.array([(image * columns).sum(), (image * rows).sum()]) / image.sum()


@pytest.mark.parametrize("telecentric", [False, True])
def test_a_small_blob_is_imaged_where_the_camera_model_projects_its_centre(telecentric):
    if telecentric:
        camera = CameraModel.ideal(
            320, 240, 6.0, distortion=LensDistortion(k1=-2e-5), telecentric=True
        )
        pose = PlanePose((0.4, -0.3, 0.2), (8.0, -5.0, 100.0))
    else:
        camera = CameraModel.ideal(320, 240, 400.0, distortion=LensDistortion(k1=-0.2))
        pose = PlanePose((0.4, -0.3, 0.2), (60.0, -40.0, 300.0))
    texel_mm = 0.01
    image = render_plane(_blob(), texel_mm, (-1.0, -1.0), pose, camera, 0.0)
    expected = PlaneProjection(camera, pose).to_pixels([[0.0, 0.0]])[0]
    assert np.hypot(*(_centroid(image) - expected)) < 0.01


def test_rays_that_miss_the_texture_see_the_background():
    camera = CameraModel.ideal(64, 48, 100.0)
    image = render_plane(np.ones((10, 10)), 0.1, (0.0, 0.0), PlanePose.facing(100.0), camera, 7.0)
    assert image[0, 0] == pytest.approx(7.0)
    assert image.shape == (48, 64)


def test_a_bad_texture_is_refused():
    camera = CameraModel.ideal(64, 48, 100.0)
    with pytest.raises(ValueError, match="texel_mm"):
        render_plane(np.ones((4, 4)), 0.0, (0.0, 0.0), PlanePose.facing(100.0), camera)
    with pytest.raises(ValueError, match="2-D"):
        render_plane(np.ones(4), 0.1, (0.0, 0.0), PlanePose.facing(100.0), camera)


@pytest.mark.parametrize(
    ("target", "tolerance_px"),
    [
        (CalibrationTarget("charuco", 10, 6, 15.0), 0.08),
        (CalibrationTarget("chessboard", 10, 6, 15.0), 0.08),
        (CalibrationTarget("circles", 9, 5, 15.0), 0.02),
    ],
)
def test_corners_detected_on_a_facing_target_sit_on_their_truth(target, tolerance_px):
    camera = CameraModel.ideal(2048, 1024, 2545.0, distortion=LENS)
    pose = calibration_poses(camera, target, 1, distance_mm=400.0)[0]
    image = render_target(target, pose, camera, look=TargetLook(noise_grey=0.5))
    assert image.dtype == np.uint8
    detection = target.detect(image)
    assert detection is not None
    assert len(detection) == len(target.object_points_mm)
    truth = target_pixels(target, pose, camera)[detection.ids]
    error = detection.image_px - truth
    if np.abs(error).max() > 5.0:
        error = detection.image_px[::-1] - truth
    assert np.abs(error).max() < tolerance_px


def test_calibration_views_tilt_the_board_and_spread_over_the_field():
    camera = CameraModel.ideal(2048, 1024, 2545.0, distortion=LENS)
    target = CalibrationTarget("charuco", 10, 6, 15.0)
    poses = calibration_poses(camera, target, 9, distance_mm=400.0, seed=4)
    assert poses[0].normal_tilt_deg == pytest.approx(0.0, abs=1e-9)
    tilts = [pose.normal_tilt_deg for pose in poses[1:]]
    assert min(tilts) >= 30.0 - 1e-9
    assert max(tilts) <= 45.0 + 1e-9
    centres = np.array([target_pixels(target, p, camera).mean(axis=0) for p in poses[1:]])
    assert centres[:, 0].min() < 600 and centres[:, 0].max() > 1450
    assert centres[:, 1].min() < 350 and centres[:, 1].max() > 670


def test_a_small_board_under_high_magnification_is_rendered_finely_enough_for_its_corners():
    camera = CameraModel.ideal(1024, 1024, 17.43, telecentric=True)
    target = CalibrationTarget("charuco", 9, 9, 4.5, 3.15)
    pose = calibration_poses(camera, target, 1, distance_mm=400.0)[0]
    image = render_target(target, pose, camera, look=TargetLook(noise_grey=0.0))
    detection = target.detect(image)
    assert detection is not None and len(detection) == 64
    error = detection.image_px - target_pixels(target, pose, camera)[detection.ids]
    assert np.sqrt(np.mean(error**2)) < 0.005
