"""A lost gauge mark is not a break where the force is read; a test without a valid sample fails.

The scene is a stretching speckle that turns to flat grey at `VANISH_S` (the marks are lost,
as when a specimen is hidden or leaves the view); the machine, when there is one, reads a
steady force, so nothing says the specimen broke.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any

import numpy as np

from appliance.dic import synthetic
from appliance.measure.frame_measurer import StopCriteria
from appliance.measure.gauges import Calibration, Gauge, StrainGauges
from appliance.measure.tracking import MarkTracker, TrackerSettings
from appliance.run.loop import MeasurementLoop
from hal.camera.base import Region, TriggerInfo, TriggerMode
from hal.camera.sim import SimCamera
from hal.clock import SimClock
from hal.machine.base import MachineState

HEIGHT, WIDTH = 400, 160
POINTS = np.array([[80.0, 120.0], [80.0, 128.0], [80.0, 240.0], [80.0, 248.0]])
VANISH_S = 0.55


class VanishingScene:
    """Speckle stretched along y, replaced by flat grey from `vanish_s` on."""

    sensor_width = WIDTH
    sensor_height = HEIGHT

    def __init__(self, vanish_s: float) -> None:
        self.pattern = synthetic.dense_speckle(WIDTH, HEIGHT, seed=5, radius=2.5)
        self.vanish_s = vanish_s

    def render(
        self, start_s: float, stop_s: float, region: Region
    ) -> tuple[np.ndarray, Mapping[str, Any]]:
        if start_s >= self.vanish_s:
            return np.full((HEIGHT, WIDTH), 128.0), {}
        stretch = synthetic.UniaxialStretch(1 + 0.05 * start_s, axis="y", xc=80.0, yc=120.0)
        return synthetic.render(self.pattern, HEIGHT, WIDTH, stretch), {}


class SteadyForce:
    """A machine whose load cell reads a steady 100 N."""

    url = "sim://steady-force"

    def read_state(self, timeout_s: float = 1.0) -> MachineState:
        return MachineState(1.0, 10.0, 100.0, True, time.monotonic_ns())


def _run(vanish_s: float, machine: SteadyForce | None):
    camera = SimCamera(
        "sim://camera",
        scene=VanishingScene(vanish_s),
        clock=SimClock(),
        read_noise=0.0,
        electrons_per_grey=0.0,
    )
    camera.open()
    camera.prepare(TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=10.0, exposure_us=100.0))

    def setup(frame):
        tracker = MarkTracker(frame.image, POINTS, [(0, 1), (2, 3)], TrackerSettings(subset_px=31))
        return tracker, StrainGauges(Gauge((0, 1), (2, 3)), POINTS, Calibration(0.1))

    samples = []
    loop = MeasurementLoop(camera, machine, setup, sinks=[samples.append], block_when_full=True)
    return loop.run(StopCriteria(until_break=True, max_frames=15)), samples


def test_lost_marks_with_a_steady_force_are_invalid_samples_not_a_break():
    result, samples = _run(VANISH_S, SteadyForce())
    assert result.exit_status == "completed" and "frame limit" in result.reason
    assert len(samples) == 15 and samples[0].data_valid
    lost = [s for s in samples if s.time_s >= VANISH_S]
    assert lost and not any(s.data_valid for s in lost) and all(s.points_lost for s in lost)


def test_without_force_readings_a_lost_mark_is_a_break_said_to_be_inferred():
    result, samples = _run(VANISH_S, None)
    assert result.exit_status == "break"
    assert result.reason.startswith("break inferred from a lost mark (no force reading)")
    assert len(samples) < 15 and result.valid_samples > 0


def test_a_test_that_never_measured_a_valid_sample_ends_in_a_fault():
    result, samples = _run(0.0, None)
    assert not any(s.data_valid for s in samples) and result.valid_samples == 0
    assert result.exit_status == "fault"
    assert result.reason.startswith("no valid sample was measured")
