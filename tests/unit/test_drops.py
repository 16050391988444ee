"""Frames dropped during a test reach every sample and the warning."""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any

import numpy as np

from appliance.dic import synthetic
from appliance.measure.frame_measurer import StopCriteria
from appliance.measure.gauges import Calibration, Gauge, StrainGauges
from appliance.measure.tracking import MarkTracker, TrackerSettings
from appliance.run.drops import DropWarning
from appliance.run.loop import MeasurementLoop
from hal.camera.base import Region, TriggerInfo, TriggerMode
from hal.camera.sim import SimCamera
from hal.clock import Pace, SimClock

HEIGHT, WIDTH = 400, 160
POINTS = np.array([[80.0, 120.0], [80.0, 128.0], [80.0, 240.0], [80.0, 248.0]])


class StillSpeckle:
    sensor_width = WIDTH
    sensor_height = HEIGHT

    def __init__(self) -> None:
        pattern = synthetic.dense_speckle(WIDTH, HEIGHT, seed=5, radius=2.5)
        self.image = synthetic.render(pattern, HEIGHT, WIDTH)

    def render(
        self, start_s: float, stop_s: float, region: Region
    ) -> tuple[np.ndarray, Mapping[str, Any]]:
        return self.image, {}


def _setup(frame):
    tracker = MarkTracker(frame.image, POINTS, [(0, 1), (2, 3)], TrackerSettings(subset_px=31))
    return tracker, StrainGauges(Gauge((0, 1), (2, 3)), POINTS, Calibration(0.1))


def test_a_measurement_slower_than_the_camera_drops_frames_every_sample_counts():
    camera = SimCamera(
        "sim://camera",
        scene=StillSpeckle(),
        clock=SimClock(Pace.REAL_TIME),
        read_noise=0.0,
        electrons_per_grey=0.0,
    )
    camera.open()
    camera.prepare(TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=50.0, exposure_us=100.0))
    warnings: list[str] = []
    drops = DropWarning(50.0, warnings.append, interval_s=0.3)
    samples = []

    def slow(sample) -> None:
        time.sleep(0.05)

    loop = MeasurementLoop(
        camera,
        None,
        _setup,
        sinks=[samples.append, drops],
        immediate_sinks=[slow],
        queue_size=1,
    )
    result = loop.run(StopCriteria(until_break=False, max_time_s=1.5))
    assert result.frames_dropped > 0
    counts = [s.frames_dropped for s in samples]
    assert counts == sorted(counts) and counts[-1] <= result.frames_dropped
    assert warnings and drops.warnings == len(warnings)
    assert "camera frames dropped in" in warnings[0] and "of 50.0 frames/s planned" in warnings[0]


def test_no_drop_no_warning():
    warnings: list[str] = []
    drops = DropWarning(20.0, warnings.append, interval_s=0.1)

    class Sample:
        def __init__(self, index: int) -> None:
            self.index, self.time_s, self.frames_dropped = index, 0.05 * index, 0

    for index in range(100):
        drops(Sample(index))
    assert warnings == []
