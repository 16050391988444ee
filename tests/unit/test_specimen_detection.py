"""Specimen detection on rendered views: axis, centre and width against the view's truth, the
parallel length, the refusals (no specimen, two, one at the image's edge), and a parallel
length the image cuts, centred on its part in view."""

from __future__ import annotations

import numpy as np
import pytest

from appliance.measure.gauges import Calibration, place_marks
from appliance.measure.specimen_detection import (
    NothingStandsOut,
    SpecimenNotFound,
    detect_specimen,
)
from appliance.measure.specimen_gauge import marks_beyond_parallel_length
from appliance.sim.specimen import Specimen
from appliance.sim.specimen_view import render_specimen_view
from appliance.sim.world import PRESETS, SimWorld
from hal.camera.base import Region

SENSOR = (1024, 2048)
RUBBER_MM_PER_PX = PRESETS["rubber"].optics.scale_mm_per_px
METAL_MM_PER_PX = PRESETS["metal"].optics.scale_mm_per_px


def _view(shape: str, **options):
    specimen, scale = (
        (Specimen.iso37_type1(), RUBBER_MM_PER_PX)
        if shape == "iso37"
        else (Specimen.iso6892_flat(), METAL_MM_PER_PX)
    )
    return render_specimen_view(specimen, scale_mm_per_px=scale, sensor_size=SENSOR, **options)


def _axis_error_deg(measured: float, true: float) -> float:
    return abs((measured - true + 90.0) % 180.0 - 90.0)


@pytest.mark.parametrize(
    ("shape", "lighting", "rotation_deg", "offset_px", "grips"),
    [
        ("iso37", "front-dark", 3.0, (60.0, -80.0), True),
        ("iso37", "back-lit", -5.0, (-90.0, 40.0), True),
        ("iso37", "front-bright", 4.2, (30.0, 120.0), False),
        ("iso6892", "front-dark", -5.0, (-90.0, 40.0), True),
        ("iso6892", "back-lit", 3.0, (60.0, -80.0), False),
    ],
)
def test_the_axis_centre_and_width_of_a_rotated_off_centre_specimen_are_found(
    shape, lighting, rotation_deg, offset_px, grips
):
    centre = (511.5 + offset_px[0], 1023.5 + offset_px[1])
    image, truth = _view(
        shape,
        centre_px=centre,
        rotation_deg=rotation_deg,
        lighting=lighting,
        grips=grips,
        seed=5,
    )
    found = detect_specimen(image)
    assert _axis_error_deg(found.axis_deg, truth.axis_deg) < 0.1
    assert np.hypot(*np.subtract(found.centre_px, truth.centre_px)) < 2.0
    assert found.width_px == pytest.approx(truth.width_px, abs=0.2)
    assert found.dark_on_bright == (lighting != "front-dark")
    assert found.ends_in_view == (True, True)
    assert truth.parallel_length_px < found.parallel_length_px < 1.2 * truth.parallel_length_px
    ends = np.array(found.parallel_ends_px)
    assert np.allclose(ends.mean(axis=0), found.centre_px, atol=1.0)


def test_the_simulated_tests_reference_view_is_found_where_its_specimen_is():
    """The rubber test's view shows one tab and only the start of the other shoulder."""
    world = SimWorld(PRESETS["rubber"])
    scene = world.scene
    image, _ = scene.render(0.0, 0.0, Region(0, 0, scene.sensor_width, scene.sensor_height))
    found = detect_specimen(image)
    assert np.hypot(*np.subtract(found.centre_px, world.specimen_centre_px)) < 1.0
    assert found.axis_deg == pytest.approx(90.0, abs=0.1)
    width_px = world.specimen.parallel_width_mm / world.optics.scale_mm_per_px
    assert found.width_px == pytest.approx(width_px, abs=0.2)


def test_a_uniform_image_or_a_speckle_filling_the_view_stands_out_of_nothing():
    with pytest.raises(NothingStandsOut, match="uniform"):
        detect_specimen(np.full((600, 400), 90, np.uint8))
    rng = np.random.default_rng(0)
    with pytest.raises(NothingStandsOut, match="nothing stands out"):
        detect_specimen(rng.normal(128, 30, (600, 400)).clip(0, 255).astype(np.uint8))


def test_two_specimens_are_refused_naming_where_they_are():
    left, _ = _view("iso37", centre_px=(300.0, 1023.5), lighting="back-lit", seed=1)
    right, _ = _view("iso37", centre_px=(720.0, 1023.5), lighting="back-lit", seed=2)
    both = np.minimum(left, right)
    with pytest.raises(SpecimenNotFound, match="2 objects stand out") as refused:
        detect_specimen(both)
    assert "(300, 1024)" in str(refused.value) and "(720, 1024)" in str(refused.value)


def test_a_specimen_cut_by_the_side_of_the_image_is_refused():
    image, _ = _view("iso6892", centre_px=(60.0, 1023.5), lighting="back-lit")
    with pytest.raises(SpecimenNotFound, match="touches the image's edge"):
        detect_specimen(image)


def test_a_parallel_length_cut_by_the_image_at_one_end_is_centred_on_its_part_in_view():
    image, truth = _view("iso6892", centre_px=(511.5, 1850.0), lighting="front-dark")
    found = detect_specimen(image)
    assert found.ends_in_view == (True, False)
    (_, top), (_, bottom) = found.parallel_ends_px
    assert top == pytest.approx(1850.0 - 0.5 * truth.parallel_length_px, abs=40.0)
    assert bottom > 2030.0
    assert found.centre_px[1] == pytest.approx(0.5 * (top + bottom), abs=0.5)
    assert found.width_px == pytest.approx(truth.width_px, abs=0.2)


def test_a_parallel_length_longer_than_the_view_is_centred_on_the_view():
    image, truth = _view("iso6892", centre_px=(511.5, 300.0), lighting="front-dark")
    found = detect_specimen(image[:600])
    assert found.ends_in_view == (False, False)
    assert found.centre_px[1] == pytest.approx(299.5, abs=8.0)
    assert found.width_px == pytest.approx(truth.width_px, abs=0.2)


def test_marks_beyond_the_parallel_length_are_named():
    image, _ = _view("iso37", lighting="back-lit")
    found = detect_specimen(image)
    calibration = Calibration(RUBBER_MM_PER_PX)
    fits, _ = place_marks(found.centre_px, 25.0, calibration, axis_deg=found.axis_deg)
    assert marks_beyond_parallel_length(fits, found) is None
    too_long, _ = place_marks(found.centre_px, 40.0, calibration, axis_deg=found.axis_deg)
    why = marks_beyond_parallel_length(too_long, found)
    assert why is not None and "more than its parallel length" in why


@pytest.mark.parametrize("shape", [(600, 400), (480, 640), (1200, 800)])
def test_a_bar_in_a_small_view_is_found_like_in_a_large_one(shape):
    """A plain 120 x 400 px bar in the middle of the view: its edges lie well inside the image
    whatever the image's size (no edge search reaches out of it)."""
    height, width = shape
    image = np.full(shape, 20, np.uint8)
    image[height // 2 - 200 : height // 2 + 200, width // 2 - 60 : width // 2 + 60] = 200
    found = detect_specimen(image)
    assert found.centre_px == pytest.approx(((width - 1) / 2, (height - 1) / 2), abs=0.5)
    assert found.width_px == pytest.approx(120.0, abs=0.1)
    assert found.axis_deg == pytest.approx(90.0, abs=0.01)
    assert found.ends_in_view == (False, False)


@pytest.mark.parametrize("sensor_size", [(640, 480), (480, 640), (800, 600)])
def test_a_specimen_in_a_small_view_is_found_with_its_ends(sensor_size):
    width, height = sensor_size
    image, truth = render_specimen_view(
        Specimen.iso6892_flat(),
        scale_mm_per_px=200.0 / (0.9 * height),
        sensor_size=sensor_size,
        lighting="front-dark",
        seed=3,
    )
    found = detect_specimen(image)
    assert found.ends_in_view == (True, True)
    assert np.hypot(*np.subtract(found.centre_px, truth.centre_px)) < 2.0
    assert found.width_px == pytest.approx(truth.width_px, abs=0.3)
