"""The simulated world refuses, in one line naming the key, a test no bench could run."""

import pytest

from appliance.config import config_from_table
from appliance.errors import InputError
from appliance.plan.optics import configured_optics
from appliance.sim.world import MAX_TEST_DURATION_S, PRESETS, SimWorld


def _world(table: dict) -> SimWorld:
    config = config_from_table(table)
    return SimWorld.from_config(
        config, configured_optics(config, PRESETS[config.sim.material].optics)
    )


def test_a_sensor_larger_than_a_camera_has_is_refused_at_load():
    with pytest.raises(InputError, match=r"\[sim\] sensor_width_px: must be <= 8192"):
        config_from_table({"sim": {"sensor_width_px": 16384}})


def test_a_sensor_of_too_many_pixels_is_refused_naming_both_keys():
    with pytest.raises(InputError) as refused:
        _world({"sim": {"sensor_width_px": 8192, "sensor_height_px": 8192}})
    assert str(refused.value) == (
        "[sim] sensor_width_px x sensor_height_px: 8192 x 8192 px is 67.1 MP, more than the "
        "simulated camera's 33.6 MP"
    )


def test_a_test_too_slow_to_end_within_a_day_is_refused_naming_the_speed():
    with pytest.raises(
        InputError,
        match=r"^\[run\] speed_mm_min: at 0.01 mm/min the simulated "
        r"test to the break \(6\) would last \d+ h",
    ):
        _world({"run": {"speed_mm_min": 0.01}})


def test_a_slow_test_with_a_near_end_strain_is_accepted_and_its_duration_known():
    world = _world({"run": {"speed_mm_min": 0.5, "until_strain": 0.01}})
    assert 0 < world.planned_duration_s < MAX_TEST_DURATION_S
    standard = _world({})
    assert standard.planned_duration_s == pytest.approx(
        standard.end_crosshead_mm / (standard.speed_mm_min / 60.0)
    )


def test_optics_that_magnify_the_specimen_beyond_what_the_simulator_renders_are_refused():
    with pytest.raises(InputError, match=r"^\[optics\]: at 0.001 mm/px the simulated specimen"):
        _world(
            {"optics": {"focal_length_mm": 1.0, "object_distance_mm": 2.0, "pixel_size_um": 1.0}}
        )


def test_optics_too_coarse_to_resolve_the_speckle_are_refused():
    with pytest.raises(InputError, match=r"^\[optics\]: at 9.6e\+03 mm/px the simulated speckle"):
        _world(
            {"optics": {"focal_length_mm": 1.0, "object_distance_mm": 1e5, "pixel_size_um": 96.0}}
        )
