"""`extensometer track --calibration FILE`: object-plane positions and displacements in mm."""

import json

import cv2
import numpy as np
import pytest

from appliance.optics.calibration_file import CameraCalibration, save_calibration
from appliance.optics.camera_model import CameraModel, LensDistortion, PlanePose
from tests.system.test_cli_track import SHIFTS, SIZE, scene, track  # noqa: F401

POINTS = np.array([[80.0, 80.0], [160.0, 80.0], [120.0, 160.0]])


def _calibration(tmp_path, size=SIZE) -> tuple[CameraCalibration, object]:
    camera = CameraModel.ideal(size, size, 900.0, distortion=LensDistortion(k1=-0.3, p1=0.002))
    calibration = CameraCalibration(camera, PlanePose((0.05, -0.08, 0.01), (-3.0, 2.0, 180.0)), 0.2)
    path = tmp_path / "lens.cal.json"
    save_calibration(calibration, path)
    return calibration, path


def test_points_get_their_plane_position_and_displacement_in_mm(scene, tmp_path):  # noqa: F811
    _, reference, targets, points = scene
    calibration, path = _calibration(tmp_path)
    done = track(
        reference, *targets, "--points", points, "--subset", "31", "--json", "--calibration", path
    )
    assert done.returncode == 0, done.stderr
    document = json.loads(done.stdout)
    assert document["calibration"]["checksum"] == calibration.checksum
    projection = calibration.projection()
    start_mm = projection.to_plane_mm(POINTS)
    for image, (du, dv) in zip(document["images"], SHIFTS, strict=True):
        for k, point in enumerate(image["points"]):
            assert point["status"] == "converged"
            where = POINTS[k] + [point["u"], point["v"]]
            expected = projection.to_plane_mm(where[None, :])[0]
            assert point["X_mm"] == pytest.approx(expected[0], abs=1e-9)
            assert point["Y_mm"] == pytest.approx(expected[1], abs=1e-9)
            assert point["dX_mm"] == pytest.approx(expected[0] - start_mm[k, 0], abs=1e-9)
            assert point["dY_mm"] == pytest.approx(expected[1] - start_mm[k, 1], abs=1e-9)
            true_mm = projection.to_plane_mm((POINTS[k] + [du, dv])[None, :])[0]
            assert np.hypot(*(expected - true_mm)) < 0.05 * 0.2


def test_a_point_not_found_has_null_plane_fields(scene, tmp_path):  # noqa: F811
    _, reference, targets, _ = scene
    _, path = _calibration(tmp_path)
    flat = tmp_path / "flat.png"
    image = cv2.imread(str(reference), cv2.IMREAD_UNCHANGED)
    image[50:110, 50:110] = 128
    cv2.imwrite(str(flat), image)
    points = tmp_path / "points.csv"
    points.write_text("x,y\n80,80\n160,80\n")
    done = track(
        flat, targets[0], "--points", points, "--subset", "31", "--json", "--calibration", path
    )
    assert done.returncode == 0, done.stderr
    lost, found = json.loads(done.stdout)["images"][0]["points"]
    assert lost["status"] == "flat_subset"
    assert all(lost[key] is None for key in ("X_mm", "Y_mm", "dX_mm", "dY_mm"))
    assert all(isinstance(found[key], float) for key in ("X_mm", "Y_mm", "dX_mm", "dY_mm"))


def test_without_calibration_the_json_has_no_plane_fields(scene):  # noqa: F811
    _, reference, targets, points = scene
    done = track(reference, targets[0], "--points", points, "--subset", "31", "--json")
    document = json.loads(done.stdout)
    assert "calibration" not in document
    assert "X_mm" not in document["images"][0]["points"][0]


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda tmp: _calibration(tmp, size=SIZE * 2)[1], "calibration made for a 480x480 px"),
        (lambda tmp: tmp / "missing.json", "no such calibration file"),
        (lambda tmp: _altered(tmp), "checksum mismatch"),
    ],
)
def test_a_calibration_that_does_not_fit_is_refused_in_one_line(scene, tmp_path, make, message):  # noqa: F811
    _, reference, targets, points = scene
    path = make(tmp_path)
    done = track(reference, targets[0], "--points", points, "--calibration", path, "--json")
    assert done.returncode == 2
    assert done.stderr.startswith("extensometer: error: track: --calibration: ")
    assert message in done.stderr and len(done.stderr.strip().splitlines()) == 1
    assert done.stdout == ""


def _altered(tmp_path):
    _, path = _calibration(tmp_path)
    document = json.loads(path.read_text())
    document["camera"]["fx_px"] = 901.0
    path.write_text(json.dumps(document))
    return path
