"""Chessboard corners refined by fitting the blurred-corner model: on drawn corners at any
sub-pixel phase, on a rendered ChArUco view through a distorting lens, and what it refuses."""

import math

import numpy as np
import pytest
from scipy.special import erf

from appliance.optics.calibration_target import CalibrationTarget
from appliance.optics.camera_model import CameraModel, LensDistortion
from appliance.optics.chessboard_corner_fit import fit_chessboard_corners
from appliance.sim.target import TargetLook, calibration_poses, render_target, target_pixels


def _corner_image(centre, normals_rad, blur_px, size=41, contrast=80.0, noise=0.0, seed=0):
    rows, columns = np.mgrid[0:size, 0:size].astype(np.float64)
    d = [
        math.cos(t) * (columns - centre[0]) + math.sin(t) * (rows - centre[1]) for t in normals_rad
    ]
    image = 120.0 + contrast * erf(d[0] / (math.sqrt(2) * blur_px[0])) * erf(
        d[1] / (math.sqrt(2) * blur_px[1])
    )
    return image + np.random.default_rng(seed).normal(0.0, noise, image.shape)


def _jacobian(normals_rad, px_per_mm=6.0):
    """Plane axes along the edges: X along edge 1 (normal t1), Y along edge 2."""
    along = [(-math.sin(t), math.cos(t)) for t in normals_rad]
    return px_per_mm * np.array([[along[0][0], along[1][0]], [along[0][1], along[1][1]]])


@pytest.mark.parametrize("phase", [(0.0, 0.0), (0.25, 0.5), (0.5, 0.75), (0.8, 0.1)])
def test_a_drawn_corner_is_found_at_any_sub_pixel_phase(phase):
    normals = (math.radians(10.0), math.radians(115.0))
    centre = (20.0 + phase[0], 20.0 + phase[1])
    image = _corner_image(centre, normals, (1.0, 1.4))
    start = np.array([[centre[0] + 0.4, centre[1] - 0.3]])
    corners, fitted = fit_chessboard_corners(image, start, _jacobian(normals)[None], 2.0)
    assert fitted.all()
    assert np.abs(corners[0] - centre).max() < 1e-3


def test_noise_moves_a_drawn_corner_by_a_few_thousandths_of_a_pixel():
    normals = (math.radians(-20.0), math.radians(60.0))
    errors = []
    for seed in range(10):
        centre = (20.3, 19.6)
        image = _corner_image(centre, normals, (1.0, 1.0), noise=1.0, seed=seed)
        corners, fitted = fit_chessboard_corners(
            image, np.array([[20.0, 20.0]]), _jacobian(normals)[None], 2.0
        )
        assert fitted.all()
        errors.append(corners[0] - centre)
    assert np.sqrt(np.mean(np.square(errors))) < 0.006


def test_a_tilted_charuco_view_through_a_distorting_lens_is_found_to_its_truth():
    camera = CameraModel.ideal(
        1024, 2048, 2638.0, distortion=LensDistortion(k1=-0.056, k2=0.014, p1=-1e-3, p2=7e-4)
    )
    target = CalibrationTarget("charuco", 9, 14, 12.0, 8.4)
    poses = calibration_poses(camera, target, 4, distance_mm=400.0, seed=1)
    errors = []
    for k, pose in enumerate(poses[1:]):
        assert pose.normal_tilt_deg > 30.0
        image = render_target(target, pose, camera, look=TargetLook(noise_grey=1.0), seed=k)
        detection = target.detect(image)
        assert detection is not None and len(detection) > 30
        errors.append(detection.image_px - target_pixels(target, pose, camera)[detection.ids])
    error = np.vstack(errors)
    assert np.sqrt(np.mean(error**2)) < 0.006
    assert np.abs(error).max() < 0.025


def test_a_tilted_chessboard_view_is_found_to_its_truth():
    camera = CameraModel.ideal(2048, 1024, 2545.0, distortion=LensDistortion(k1=-0.05))
    target = CalibrationTarget("chessboard", 9, 6, 12.0)
    pose = calibration_poses(camera, target, 4, distance_mm=400.0, seed=1)[3]
    assert pose.normal_tilt_deg > 30.0
    image = render_target(target, pose, camera, look=TargetLook(noise_grey=0.5), seed=3)
    detection = target.detect(image)
    assert detection is not None
    truth = target_pixels(target, pose, camera)
    if np.abs(detection.image_px - truth).max() > 5.0:
        truth = truth[::-1]
    error = detection.image_px - truth
    assert np.sqrt(np.mean(error**2)) < 0.005
    assert np.abs(error).max() < 0.02


def test_a_start_on_a_flat_patch_keeps_its_position_and_is_not_fitted():
    image = np.full((41, 41), 100.0) + np.random.default_rng(0).normal(0.0, 1.0, (41, 41))
    start = np.array([[20.2, 19.7]])
    corners, fitted = fit_chessboard_corners(image, start, _jacobian((0.0, 1.5))[None], 2.0)
    assert not fitted.any()
    np.testing.assert_array_equal(corners, start)


def test_a_window_too_small_keeps_the_start():
    normals = (0.0, math.pi / 2)
    image = _corner_image((20.0, 20.0), normals, (1.0, 1.0))
    start = np.array([[20.3, 20.3]])
    corners, fitted = fit_chessboard_corners(image, start, _jacobian(normals)[None], 0.1)
    assert not fitted.any()
    np.testing.assert_array_equal(corners, start)


@pytest.mark.parametrize(
    ("image", "corners", "jacobian", "radius", "message"),
    [
        (np.zeros(5), np.zeros((1, 2)), np.eye(2)[None], 1.0, "2-D"),
        (np.zeros((5, 5)), np.zeros((2, 2)), np.eye(2)[None], 1.0, "Jacobians"),
        (np.zeros((5, 5)), np.zeros((1, 2)), np.eye(2)[None], 0.0, "radius"),
    ],
)
def test_bad_inputs_are_refused(image, corners, jacobian, radius, message):
    with pytest.raises(ValueError, match=message):
        fit_chessboard_corners(image, corners, jacobian, radius)
