"""The installer's saved frame: camera-check's last frame with the specimen's outline, axis,
parallel length's ends and the gauge marks drawn over it, or the refusal written on it; the
gauge placed as a test places it (configured, detected, or on the centre of a view the
specimen fills)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from appliance.cli.detection_overlay import (
    BLUE,
    GREEN,
    RED,
    detection_overlay,
    gauge_overlay,
    overlay_quality,
)
from appliance.cli.device_checks import camera_for_check, check_camera
from appliance.config import config_from_table
from appliance.sim.world import PRESETS

OPTICS = PRESETS["rubber"].optics


def _config(**gauge):
    return config_from_table(
        {
            "camera": {"url": "sim://camera"},
            "gauge": {"length_mm": 25.0, **gauge},
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
    subsets = report["subsets"]
    assert subsets["subsets"] == 6 and subsets["subset_px"] == 41
    assert 2.0 < subsets["speckle_size_px"] < 8.0 and subsets["sssig"] > 0


def test_a_refused_frame_has_no_subset_figures():
    two = np.full((400, 300), 20, np.uint8)
    two[50:350, 40:100] = 200
    two[50:350, 200:260] = 200
    overlay = gauge_overlay(two, _config())
    assert overlay.refused and overlay.centre_px is None
    quality = overlay_quality(two, 255, _config(), overlay)
    assert quality.subsets is None and quality.focus_gradient >= 0


def test_a_frame_with_two_objects_gets_the_refusal_written_on_it():
    two = np.full((400, 300), 20, np.uint8)
    two[50:350, 40:100] = 200
    two[50:350, 200:260] = 200
    drawn = detection_overlay(two, 255, _config())
    assert drawn.shape == (400, 300, 3)
    assert not _has(drawn, GREEN) and not _has(drawn, RED)
    assert np.any(drawn[:60] != drawn[-1, -1])


def test_a_frame_in_which_nothing_stands_out_gets_the_gauge_on_its_centre_as_a_test_does():
    speckle = np.random.default_rng(0).normal(120, 30, (1200, 900)).clip(0, 255).astype(np.uint8)
    drawn = detection_overlay(speckle, 255, _config())
    assert not _has(drawn, GREEN) and _has(drawn, RED)
    red_rows, red_cols = np.nonzero(np.all(drawn == np.array(RED, np.uint8), axis=2))
    assert red_cols.mean() == pytest.approx(449.5, abs=3.0)
    assert red_rows.mean() == pytest.approx(599.5, abs=3.0)


def test_a_configured_centre_places_the_marks_there_without_detection():
    two = np.full((1200, 900), 20, np.uint8)
    two[100:1100, 200:300] = 200
    two[100:1100, 600:700] = 200
    config = _config(centre_x_px=250.0, centre_y_px=600.0)
    drawn = detection_overlay(two, 255, config)
    assert not _has(drawn, GREEN) and _has(drawn, RED)
    red_rows, red_cols = np.nonzero(np.all(drawn == np.array(RED, np.uint8), axis=2))
    assert red_cols.mean() == pytest.approx(250.0, abs=3.0)
    assert red_rows.mean() == pytest.approx(600.0, abs=3.0)
