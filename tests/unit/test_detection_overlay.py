"""The installer's saved frame: camera-check's last frame with the specimen's outline, axis,
parallel length's ends and the gauge marks drawn over it, or the refusal written on it."""

from __future__ import annotations

import cv2
import numpy as np

from appliance.cli.detection_overlay import BLUE, GREEN, RED, detection_overlay
from appliance.cli.device_checks import camera_for_check, check_camera
from appliance.config import config_from_table
from appliance.sim.world import PRESETS

OPTICS = PRESETS["rubber"].optics


def _config():
    return config_from_table(
        {
            "camera": {"url": "sim://camera"},
            "gauge": {"length_mm": 25.0},
            "optics": {
                "focal_length_mm": OPTICS.focal_length_mm,
                "object_distance_mm": OPTICS.object_distance_mm,
                "pixel_size_um": OPTICS.pixel_size_um,
            },
        }
    )


def _has(image: np.ndarray, colour: tuple[int, int, int]) -> bool:
    return bool(np.any(np.all(image == np.array(colour, np.uint8), axis=2)))


def test_camera_check_saves_its_last_frame_with_the_detection_and_the_gauge(tmp_path):
    config = _config()
    path = tmp_path / "view.png"
    report = check_camera(
        camera_for_check(config, "sim://camera"), config, frames=2, save_path=path
    )
    assert report["saved"] == str(path)
    saved = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert saved.shape == (report["height"], report["width"], 3)
    assert _has(saved, GREEN) and _has(saved, BLUE) and _has(saved, RED)


def test_a_frame_without_a_specimen_gets_the_refusal_written_on_it():
    blank = np.full((400, 300), 100, np.uint8)
    drawn = detection_overlay(blank, 255, _config())
    assert drawn.shape == (400, 300, 3)
    assert not _has(drawn, GREEN) and not _has(drawn, RED)
    assert np.any(drawn != 100)
