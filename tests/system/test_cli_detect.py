"""`extensometer detect IMG`: the specimen's figures and the marks a test would place, as text
and JSON, placed as a test places them (configured without detection, detected, or on the
centre of a view the specimen fills); an image with more than one object, a specimen at the
image's side and a gauge longer than the parallel length are refused in one line with exit
status 2."""

from __future__ import annotations

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from appliance.cli import main
from appliance.sim.specimen import Specimen
from appliance.sim.specimen_view import render_specimen_view
from appliance.sim.world import PRESETS

OPTICS = PRESETS["rubber"].optics
CONFIG = (
    "[gauge]\nlength_mm = {length}\n{gauge}[optics]\n"
    f"focal_length_mm = {OPTICS.focal_length_mm}\nobject_distance_mm = "
    f"{OPTICS.object_distance_mm}\npixel_size_um = {OPTICS.pixel_size_um}\n"
)


def _image(tmp_path, name="view.png", **options):
    image, truth = render_specimen_view(
        Specimen.iso37_type1(),
        scale_mm_per_px=OPTICS.scale_mm_per_px,
        sensor_size=(1024, 2048),
        **options,
    )
    path = tmp_path / name
    cv2.imwrite(str(path), image)
    return path, image, truth


def _config(tmp_path, length_mm, gauge=""):
    path = tmp_path / f"gauge_{length_mm}.toml"
    path.write_text(CONFIG.format(length=length_mm, gauge=gauge))
    return path


def test_detect_prints_the_specimen_and_the_marks_it_would_place(tmp_path, capsys):
    image, _, truth = _image(
        tmp_path, centre_px=(540.0, 1000.0), rotation_deg=2.0, lighting="back-lit", grips=True
    )
    config = _config(tmp_path, 25.0)
    assert main(["detect", str(image), "--config", str(config), "--json"]) == 0
    document = json.loads(capsys.readouterr().out)
    assert document["centre_x_px"] == pytest.approx(truth.centre_px[0], abs=2.0)
    assert document["centre_y_px"] == pytest.approx(truth.centre_px[1], abs=2.0)
    assert document["axis_deg"] == pytest.approx(truth.axis_deg, abs=0.1)
    assert document["width_px"] == pytest.approx(truth.width_px, abs=0.2)
    assert len(document["parallel_ends_px"]) == 2
    gauge = document["gauge"]
    assert gauge["placement"] == "detected"
    assert gauge["achieved_length_mm"] == pytest.approx(25.0, rel=1e-9)
    first, second = np.array(gauge["marks_px"])
    assert np.hypot(*(second - first)) * OPTICS.scale_mm_per_px == pytest.approx(25.0)
    assert np.allclose((first + second) / 2, truth.centre_px, atol=2.0)
    assert main(["detect", str(image), "--config", str(config)]) == 0
    text = capsys.readouterr().out
    for key in ("centre_x_px", "centre_y_px", "axis_deg", "width_px", "parallel_ends_px"):
        assert key in text
    assert "ends_in_view               seen, seen" in text
    assert "gauge_placement            detected" in text and "mark_2_px" in text


def test_a_configured_centre_places_the_marks_there_without_detection(tmp_path, capsys):
    _, left, _ = _image(tmp_path, centre_px=(300.0, 1023.5), lighting="back-lit", seed=1)
    _, right, _ = _image(tmp_path, centre_px=(720.0, 1023.5), lighting="back-lit", seed=2)
    two = tmp_path / "two.png"
    cv2.imwrite(str(two), np.minimum(left, right))
    config = _config(tmp_path, 20.0, "centre_x_px = 300.0\ncentre_y_px = 1010.0\n")
    assert main(["detect", str(two), "--config", str(config), "--json"]) == 0
    document = json.loads(capsys.readouterr().out)
    assert "centre_x_px" not in document and document["gauge_placement"] == "configured"
    gauge = document["gauge"]
    assert gauge["placement"] == "configured" and gauge["centre_px"] == [300.0, 1010.0]
    assert main(["detect", str(two), "--config", str(config)]) == 0
    text = capsys.readouterr().out
    assert "gauge_placement            configured" in text and "nothing detected" in text


def test_a_view_the_specimen_fills_centres_the_gauge_on_the_image_and_says_so(tmp_path, capsys):
    speckle = np.random.default_rng(0).normal(120, 30, (1200, 900)).clip(0, 255)
    path = tmp_path / "speckle.png"
    cv2.imwrite(str(path), speckle.astype(np.uint8))
    config = _config(tmp_path, 20.0)
    assert main(["detect", str(path), "--config", str(config), "--json"]) == 0
    document = json.loads(capsys.readouterr().out)
    assert document["gauge_placement"] == "image centre"
    assert document["gauge_centre_px"] == [449.5, 599.5]
    assert document["gauge"]["centre_px"] == [449.5, 599.5]
    assert main(["detect", str(path)]) == 0
    text = capsys.readouterr().out
    assert "gauge_placement            image centre" in text
    assert "nothing stands out from the background" in text


def test_a_plain_bar_in_a_small_image_says_its_ends_were_not_seen(tmp_path, capsys):
    bar = np.full((600, 400), 20, np.uint8)
    bar[100:500, 140:260] = 200
    path = tmp_path / "bar.png"
    cv2.imwrite(str(path), bar)
    assert main(["detect", str(path)]) == 0
    text = capsys.readouterr().out
    assert "ends_in_view               not seen, not seen" in text
    assert "gauge_centre_px            (199.50, 299.50)" in text


def test_without_a_gauge_length_only_the_specimen_is_printed(tmp_path, capsys):
    image, _, _ = _image(tmp_path, lighting="front-bright")
    assert main(["detect", str(image), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["gauge"] is None


@pytest.mark.parametrize(
    ("case", "expected"),
    [
        ("two", "2 objects stand out from the background"),
        ("edge", "touches the image's edge"),
        ("long gauge", "[gauge] length_mm: the marks span"),
    ],
)
def test_bad_input_is_refused_in_one_line(tmp_path, case, expected):
    config = _config(tmp_path, 40.0 if case == "long gauge" else 25.0)
    if case == "two":
        _, left, _ = _image(tmp_path, centre_px=(300.0, 1023.5), lighting="back-lit", seed=1)
        _, right, _ = _image(tmp_path, centre_px=(720.0, 1023.5), lighting="back-lit", seed=2)
        path = tmp_path / "two.png"
        cv2.imwrite(str(path), np.minimum(left, right))
    elif case == "edge":
        path, _, _ = _image(tmp_path, centre_px=(12.0, 1023.5), lighting="back-lit")
    else:
        path, _, _ = _image(tmp_path, lighting="back-lit")
    assert expected in _refusal(path, config)


def _refusal(path, config) -> str:
    """The one-line refusal of `detect` on `path`, checked to be one line, exit 2, no output."""
    done = subprocess.run(
        [sys.executable, "-m", "appliance.cli", "detect", str(path), "--config", str(config)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2, done.stderr
    assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr
    assert done.stdout == ""
    return done.stderr


def _painted_view(tmp_path, painted: str) -> tuple[object, np.ndarray]:
    """A simulated rubber reference frame with `painted` marks ("dots" or "none"), saved, and
    the true image positions of the two gauge ends."""
    from appliance.sim.world import SimWorld
    from hal.camera.base import Region

    world = SimWorld(PRESETS["rubber"], painted_marks=painted, sensor_size=(512, 1024), seed=4)
    scene = world.scene
    image, _ = scene.render(0.0, 0.0, Region(0, 0, scene.sensor_width, scene.sensor_height))
    path = tmp_path / f"painted_{painted}.png"
    cv2.imwrite(str(path), np.clip(np.rint(image), 0, 255).astype(np.uint8))
    half = 0.5 * world.gauge_length_mm
    return path, scene.image_positions(np.array([[0.0, -half], [0.0, half]]), 0.0, 0.0)


def test_detect_finds_the_painted_dots_a_test_would_track(tmp_path, capsys):
    path, truth = _painted_view(tmp_path, "dots")
    config = _config(tmp_path, 25.0, gauge='marks = "dots"\n')
    assert main(["detect", str(path), "--config", str(config), "--json"]) == 0
    document = json.loads(capsys.readouterr().out)
    assert document["gauge_placement"] == "painted dots"
    gauge = document["gauge"]
    assert np.abs(np.array(gauge["marks_px"]) - truth).max() < 0.5
    assert gauge["achieved_length_mm"] == pytest.approx(25.0, rel=0.01)
    assert document["gauge_axis_deg"] == pytest.approx(90.0, abs=0.5)


def test_detect_refuses_painted_marks_that_are_not_there(tmp_path):
    path, _ = _painted_view(tmp_path, "none")
    config = _config(tmp_path, 25.0, gauge='marks = "dots"\n')
    assert f"{path}: no painted dot found" in _refusal(path, config)
