"""Calibration files: written with a checksum, read back equal, refused in one line."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from appliance.errors import InputError
from appliance.optics.calibration_file import (
    CameraCalibration,
    load_calibration,
    save_calibration,
)
from appliance.optics.camera_model import CameraModel, LensDistortion, PlanePose

CALIBRATION = CameraCalibration(
    camera=CameraModel.ideal(640, 480, 1000.0, distortion=LensDistortion(-0.05, 0.01)),
    plane=PlanePose((0.01, 0.0, 0.0), (1.0, 2.0, 200.0)),
    scale_mm_per_px=0.2,
    scale_uncertainty_mm_per_px=1e-5,
    rms_reprojection_px=0.03,
    view_errors_px=(0.02, 0.04),
    coverage_fraction=0.8,
    target={"kind": "charuco", "squares": [12, 9]},
    software_version="0.1.0",
    created_utc="2026-12-02T00:00:00Z",
)


def test_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "camera.json"
    save_calibration(CALIBRATION, path)
    loaded = load_calibration(path, sensor_size=(640, 480))
    assert loaded == CALIBRATION
    assert json.loads(path.read_text())["checksum"] == CALIBRATION.checksum


def _altered(tmp_path: Path, change) -> Path:
    document = json.loads(CALIBRATION.to_json())
    change(document)
    path = tmp_path / "altered.json"
    path.write_text(json.dumps(document))
    return path


@pytest.mark.parametrize(
    ("change", "reason"),
    [
        (lambda d: d.__setitem__("scale_mm_per_px", 0.21), "checksum mismatch"),
        (lambda d: d.__setitem__("format", "something-else"), "not a calibration file"),
        (lambda d: d.__setitem__("format_version", 9), "format version 9"),
    ],
)
def test_altered_or_foreign_file_is_refused(tmp_path: Path, change, reason: str) -> None:
    path = _altered(tmp_path, change)
    with pytest.raises(InputError, match=reason) as error:
        load_calibration(path)
    assert str(path) in str(error.value)
    assert "\n" not in str(error.value)


def test_missing_key_with_a_valid_checksum_is_named(tmp_path: Path) -> None:
    from appliance.optics.calibration_file import checksum

    document = json.loads(CALIBRATION.to_json())
    del document["plane"]
    document["checksum"] = checksum(document)
    path = tmp_path / "no-plane.json"
    path.write_text(json.dumps(document))
    with pytest.raises(InputError, match="lacks the key plane"):
        load_calibration(path)


def test_other_sensor_size_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "camera.json"
    save_calibration(CALIBRATION, path)
    with pytest.raises(InputError, match="640x480 px sensor, the images are 1024x768"):
        load_calibration(path, sensor_size=(1024, 768))


@pytest.mark.parametrize("content", [b"", b"\xff\xfe", b"{not json", b"[]"])
def test_unreadable_files_are_refused(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "bad.json"
    path.write_bytes(content)
    with pytest.raises(InputError, match=str(path)):
        load_calibration(path)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no such calibration file"):
        load_calibration(tmp_path / "absent.json")
