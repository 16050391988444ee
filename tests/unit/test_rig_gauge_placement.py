"""The rig places the gauge from the reference frame's pixels, never from the simulated world's
truth: a frame whose specimen has moved moves the gauge; a configured centre wins; a frame
with two specimens is refused in one line naming them."""

from __future__ import annotations

import numpy as np
import pytest

from appliance.config import Config, config_from_table
from appliance.errors import InputError
from appliance.rig import gauge_centre_for, rig_for
from appliance.sim.world import PRESETS, SimWorld
from hal.camera.base import Frame, Region


def _config(**gauge) -> Config:
    return config_from_table({"sim": {"material": "rubber"}, "gauge": gauge})


def _reference(world: SimWorld) -> np.ndarray:
    scene = world.scene
    image, _ = scene.render(0.0, 0.0, Region(0, 0, scene.sensor_width, scene.sensor_height))
    return image


def _frame(image: np.ndarray) -> Frame:
    return Frame(image=image, frame_id=0, timestamp_ns=0, exposure_us=1000.0)


def test_the_simulated_rig_centres_the_gauge_on_the_specimen_in_the_frame():
    rig = rig_for(_config(), simulate=True)
    assert rig.world is not None
    image = _reference(rig.world)
    centre = rig.gauge_centre(_frame(image))
    assert centre.placement == "detected" and centre.detection is not None
    assert np.hypot(*np.subtract(centre.centre_px, rig.world.specimen_centre_px)) < 1.0
    assert centre.axis_deg == pytest.approx(90.0, abs=0.1)
    shifted = np.full_like(image, image[0, 0])
    shifted[:-40, 25:] = image[40:, :-25]
    moved = rig.gauge_centre(_frame(shifted))
    assert np.subtract(moved.centre_px, centre.centre_px) == pytest.approx([25.0, -40.0], abs=0.5)


def test_a_configured_centre_wins_along_the_configured_axis():
    rig = rig_for(_config(centre_x_px=480.0, centre_y_px=1500.0, axis_deg=88.0), simulate=True)
    assert rig.world is not None
    centre = rig.gauge_centre(_frame(_reference(rig.world)))
    assert (centre.placement, centre.centre_px, centre.axis_deg) == (
        "configured",
        (480.0, 1500.0),
        88.0,
    )


def test_half_a_configured_centre_is_refused():
    with pytest.raises(InputError, match=r"\[gauge\] centre_x_px, centre_y_px: set both"):
        gauge_centre_for(_config(centre_x_px=480.0))


def test_a_frame_with_two_specimens_is_refused_naming_them():
    world = SimWorld.from_config(_config(), PRESETS["rubber"].optics)
    image = _reference(world)
    two = np.maximum(image, np.roll(image, 300, axis=1))
    with pytest.raises(InputError, match=r"^reference frame: 2 objects stand out"):
        gauge_centre_for(_config())(_frame(two))


def test_a_frame_showing_only_speckle_centres_the_gauge_on_the_image():
    rng = np.random.default_rng(1)
    speckle = rng.normal(128.0, 40.0, (512, 640)).clip(0, 255)
    centre = gauge_centre_for(_config(axis_deg=90.0))(_frame(speckle))
    assert centre.placement == "image centre" and centre.centre_px == (319.5, 255.5)
