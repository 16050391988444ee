"""`extensometer calibrate` end to end: simulated ChArUco images through a distorting lens
become a calibration file; `--check` passes a fresh view of the plane and fails a camera that
moved or changed its magnification; every bad input is one line and exit status 2."""

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from appliance.optics.calibration_file import load_calibration
from appliance.optics.calibration_target import CalibrationTarget
from appliance.optics.camera_model import CameraModel, LensDistortion, PlanePose, PlaneProjection
from appliance.sim.target import TargetLook, calibration_poses, render_target

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))
CAMERA = CameraModel.ideal(2048, 1024, 2545.0, distortion=LensDistortion(k1=-0.05))
TARGET = CalibrationTarget("charuco", 10, 6, 15.0)
OPTIONS = ("--target", "charuco", "--squares", "10x6", "--square-mm", "15")
LOOK = TargetLook(noise_grey=0.5)


def extensometer(*args) -> subprocess.CompletedProcess:
    return subprocess.run(
        [EXTENSOMETER, "calibrate", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )


def _write(path: Path, pose: PlanePose, camera: CameraModel = CAMERA, seed: int = 0) -> Path:
    cv2.imwrite(str(path), render_target(TARGET, pose, camera, look=LOOK, seed=seed))
    return path


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    folder = tmp_path_factory.mktemp("calibrate")
    poses = calibration_poses(CAMERA, TARGET, 10, distance_mm=400.0, seed=5)
    images = [_write(folder / f"view{k:02d}.png", p, seed=k) for k, p in enumerate(poses)]
    out = folder / "camera.cal.json"
    done = extensometer(*images, *OPTIONS, "--out", out)
    return folder, poses, images, out, done


def test_calibrate_writes_the_calibration_file(calibrated):
    _, poses, images, out, done = calibrated
    assert done.returncode == 0, done.stderr
    assert "RMS" in done.stdout and "mm/px at the image centre" in done.stdout
    calibration = load_calibration(out, sensor_size=(2048, 1024))
    assert calibration.camera.fx_px == pytest.approx(CAMERA.fx_px, rel=1e-3)
    truth = PlaneProjection(CAMERA, poses[0]).scale_mm_per_px((1023.5, 511.5))
    assert calibration.scale_mm_per_px == pytest.approx(truth, rel=2e-4)
    assert calibration.rms_reprojection_px < 0.05
    assert calibration.target["plane_image"] == str(images[0])
    assert len(calibration.view_errors_px) == 10
    assert calibration.software_version
    assert calibration.created_utc.endswith("+00:00")


def test_the_plane_option_picks_the_specimen_plane(calibrated):
    folder, poses, images, _, _ = calibrated
    out = folder / "plane.cal.json"
    done = extensometer(*images, *OPTIONS, "--plane", images[4], "--out", out, "--json")
    assert done.returncode == 0, done.stderr
    document = json.loads(done.stdout)
    assert document["target"]["plane_image"] == str(images[4])
    truth = PlaneProjection(CAMERA, poses[4]).scale_mm_per_px((1023.5, 511.5))
    assert document["scale_mm_per_px"] == pytest.approx(truth, rel=3e-4)


def test_check_passes_a_fresh_view_and_fails_a_moved_or_rescaled_camera(calibrated):
    folder, poses, _, out, _ = calibrated
    plane = poses[0]
    x_mm, y_mm, z_mm = plane.translation_mm
    fresh = _write(folder / "fresh.png", PlanePose(plane.rotation_vector, (x_mm - 15, y_mm, z_mm)))
    done = extensometer("--check", out, fresh)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "verdict: fit" in done.stdout
    moved = _write(folder / "moved.png", plane.moved_along_normal(-3.0), seed=7)
    zoomed = dataclasses.replace(CAMERA, fx_px=CAMERA.fx_px * 0.99, fy_px=CAMERA.fy_px * 0.99)
    rescaled = _write(folder / "rescaled.png", plane, camera=zoomed, seed=8)
    done = extensometer("--check", out, fresh, moved, rescaled, "--json")
    assert done.returncode == 1, done.stderr
    report = json.loads(done.stdout)
    assert [view["fit"] for view in report["views"]] == [True, False, False]
    assert report["views"][1]["scale_change"] == pytest.approx(-0.0075, rel=0.05)
    assert report["views"][2]["scale_change"] == pytest.approx(0.0101, rel=0.05)
    assert report["fit"] is False


def _refused(done: subprocess.CompletedProcess, message: str) -> None:
    assert done.returncode == 2
    assert done.stdout == ""
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith("extensometer: error: ")
    assert message in lines[0], lines[0]


def test_bad_input_is_refused_in_one_line(calibrated, tmp_path):
    _, _, images, _, _ = calibrated
    out = tmp_path / "x.json"
    _refused(extensometer(*images[:2], *OPTIONS, "--out", out), "at least 3 needed")
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((1024, 2048), 128, np.uint8))
    _refused(
        extensometer(*images[:4], blank, *OPTIONS, "--out", out),
        "blank.png: charuco target not found",
    )
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.full((512, 1024), 128, np.uint8))
    _refused(
        extensometer(*images[:4], small, *OPTIONS, "--out", out), "small.png: image is 1024x512 px"
    )
    broken = tmp_path / "broken.png"
    broken.write_bytes(b"not an image")
    _refused(
        extensometer(*images[:4], broken, *OPTIONS, "--out", out),
        "broken.png: not a readable image",
    )
    _refused(
        extensometer(*images[:4], *OPTIONS, "--out", out, "--min-coverage", "0.99"),
        "--min-coverage",
    )
    _refused(
        extensometer(*images, *OPTIONS, "--out", out, "--max-rms-px", "0.001"),
        "above the limit 0.001 px (--max-rms-px)",
    )
    _refused(
        extensometer(*images, *OPTIONS, "--out", out, "--telecentric"),
        "calibrate without --telecentric",
    )
    _refused(extensometer(*images[:4], "--squares", "10x6", "--out", out), "--target is required")
    _refused(
        extensometer(
            *images[:4], *OPTIONS[:2], "--squares", "10by6", "--square-mm", "15", "--out", out
        ),
        "COLSxROWS",
    )
    _refused(extensometer("--check", tmp_path / "none.json", images[0]), "no such calibration file")
    assert not out.exists()
