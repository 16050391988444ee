"""The camera model against OpenCV's projection, and pixels to the plane and back."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.optics.camera_model import CameraModel, LensDistortion, PlanePose, PlaneProjection

LENS = LensDistortion(-0.08, 0.05, 0.001, -0.0005, 0.01)
CAMERA = CameraModel(2048, 1024, 3000.0, 3010.0, 1020.0, 515.0, LENS)
POSE = PlanePose((0.05, -0.03, 0.02), (5.0, -3.0, 250.0))


def test_projection_matches_opencv() -> None:
    points = np.random.default_rng(1).uniform(-40, 40, (200, 2))
    ours = PlaneProjection(CAMERA, POSE).to_pixels(points)
    theirs, _ = cv2.projectPoints(
        np.column_stack([points, np.zeros(len(points))]),
        np.array(POSE.rotation_vector).reshape(3, 1),
        np.array(POSE.translation_mm).reshape(3, 1),
        CAMERA.matrix,
        LENS.coefficients,
    )
    assert np.abs(theirs.reshape(-1, 2) - ours).max() < 1e-9


@settings(max_examples=50, deadline=None)
@given(
    x=st.floats(0, 2047),
    y=st.floats(0, 1023),
    telecentric=st.booleans(),
)
def test_pixel_to_plane_and_back(x: float, y: float, telecentric: bool) -> None:
    if telecentric:
        camera = CameraModel.ideal(
            2048, 1024, 12.0, distortion=LensDistortion(2e-5), telecentric=True
        )
        pose = PlanePose((0.1, 0.05, 0.0), (1.0, 2.0, 100.0))
    else:
        camera, pose = CAMERA, POSE
    projection = PlaneProjection(camera, pose)
    plane = projection.to_plane_mm([[x, y]])
    assert np.abs(projection.to_pixels(plane) - [[x, y]]).max() < 1e-8


def test_facing_plane_scale_is_distance_over_focal_length() -> None:
    camera = CameraModel.ideal(1024, 1024, 2000.0)
    projection = PlaneProjection(camera, PlanePose.facing(300.0))
    assert projection.scale_mm_per_px((511.5, 511.5)) == pytest.approx(0.15, rel=1e-9)
    assert projection.to_plane_mm([[511.5, 511.5]]) == pytest.approx(np.zeros((1, 2)), abs=1e-12)


def test_barrel_distortion_moves_corners_inwards() -> None:
    camera = CameraModel.ideal(2048, 2048, 2500.0, distortion=LensDistortion(-0.1))
    ideal = CameraModel.ideal(2048, 2048, 2500.0)
    corner = ideal.pixels(ideal.normalised([[0.0, 0.0]]))
    seen = camera.pixels(ideal.normalised(corner))
    assert np.all(seen > corner)
    assert camera.distortion_px([[1023.5, 1023.5]])[0] == pytest.approx(0.0, abs=1e-9)


def test_moving_the_plane_away_shrinks_the_image() -> None:
    camera = CameraModel.ideal(1024, 1024, 2000.0)
    near = PlaneProjection(camera, PlanePose.facing(200.0)).to_pixels([[10.0, 0.0]])
    far = PlaneProjection(camera, PlanePose.facing(200.0).moved_along_normal(0.2)).to_pixels(
        [[10.0, 0.0]]
    )
    shift_near = near[0, 0] - 511.5
    shift_far = far[0, 0] - 511.5
    assert shift_far / shift_near == pytest.approx(200.0 / 200.2, rel=1e-12)


def test_edge_on_plane_is_refused() -> None:
    with pytest.raises(ValueError, match="edge-on"):
        PlaneProjection(CAMERA, PlanePose((np.pi / 2, 0.0, 0.0), (0.0, 0.0, 0.0)))


def test_a_pixel_that_sees_no_point_of_a_tilted_plane_gives_nan() -> None:
    """A plane tilted 85 degrees about x: the image rows on one side of its horizon look at
    the plane behind the lens, and have no plane point; those on the other side do."""
    camera = CameraModel(2048, 1024, 3000.0, 3000.0, 1024.0, 512.0, LensDistortion())
    projection = PlaneProjection(camera, PlanePose((np.radians(85.0), 0.0, 0.0), (0.0, 0.0, 250.0)))
    pixels = np.array([[1024.0, 0.0], [1024.0, 1023.0]])
    plane = projection.to_plane_mm(pixels)
    seen = np.isfinite(plane).all(axis=1)
    assert seen.sum() == 1
    assert np.allclose(projection.to_pixels(plane[seen]), pixels[seen], atol=1e-6)
