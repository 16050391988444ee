"""The threaded measurement loop on the simulated camera: samples, stop criteria, faults."""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping
from typing import Any

import numpy as np
import pytest

from appliance.dic import synthetic
from appliance.measure.frame_measurer import StopCriteria
from appliance.measure.gauges import Calibration, Gauge, StrainGauges
from appliance.measure.tracking import MarkTracker, TrackerSettings
from appliance.run.loop import MeasurementLoop
from appliance.run.state import RunEvent, RunState
from hal.camera.base import Region, TriggerInfo, TriggerMode
from hal.camera.sim import SimCamera
from hal.clock import SimClock
from hal.errors import HardwareFault

HEIGHT, WIDTH = 400, 160
POINTS = np.array([[80.0, 120.0], [80.0, 128.0], [80.0, 240.0], [80.0, 248.0]])
STRAIN_RATE = 0.05
"""Engineering strain per second of the scene."""


class StretchingScene:
    """A speckle image stretched along y about row 120 at a constant strain rate."""

    sensor_width = WIDTH
    sensor_height = HEIGHT

    def __init__(self, fail_after_s: float | None = None) -> None:
        self.pattern = synthetic.dense_speckle(WIDTH, HEIGHT, seed=5, radius=2.5)
        self.fail_after_s = fail_after_s

    def mapping(self, t: float) -> synthetic.UniaxialStretch:
        return synthetic.UniaxialStretch(1 + STRAIN_RATE * t, axis="y", xc=80.0, yc=120.0)

    def render(
        self, start_s: float, stop_s: float, region: Region
    ) -> tuple[np.ndarray, Mapping[str, Any]]:
        if self.fail_after_s is not None and start_s > self.fail_after_s:
            raise HardwareFault("sim://camera: sensor failure")
        mid = 0.5 * (start_s + stop_s)
        image = synthetic.render(self.pattern, HEIGHT, WIDTH, self.mapping(mid))
        return image, {"strain": STRAIN_RATE * mid}


def _camera(scene: StretchingScene) -> SimCamera:
    camera = SimCamera(
        "sim://camera", scene=scene, clock=SimClock(), read_noise=0.0, electrons_per_grey=0.0
    )
    camera.open()
    camera.prepare(TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=10.0, exposure_us=100.0))
    return camera


def _setup(frame):
    tracker = MarkTracker(frame.image, POINTS, [(0, 1), (2, 3)], TrackerSettings(subset_px=31))
    gauges = StrainGauges(Gauge((0, 1), (2, 3)), POINTS, Calibration(0.1))
    return tracker, gauges


def test_loop_measures_until_the_strain_limit_in_order_without_loss():
    samples = []
    loop = MeasurementLoop(
        _camera(StretchingScene()),
        None,
        _setup,
        sinks=[samples.append],
        block_when_full=True,
        queue_size=2,
    )
    result = loop.run(StopCriteria(until_strain=0.05, until_break=False))
    assert result.exit_status == "completed" and "strain" in result.reason
    assert result.final_state is RunState.IDLE
    assert [e.event for e in loop.state.history] == [
        RunEvent.ARM,
        RunEvent.START,
        RunEvent.STOP,
        RunEvent.FINISH,
    ]
    assert result.frames_dropped == 0
    assert len(samples) == result.frames_processed == len(result.latencies_s)
    assert [s.index for s in samples] == list(range(len(samples)))
    assert samples[-1].reading.engineering_strain >= 0.05
    assert samples[-2].reading.engineering_strain < 0.05
    for sample in samples:
        assert sample.data_valid
        assert sample.reading.engineering_strain == pytest.approx(
            sample.metadata["truth"]["strain"], abs=2e-4
        )
    assert np.diff([s.timestamp_ns for s in samples]).tolist() == [100_000_000] * (len(samples) - 1)


def test_device_fault_ends_in_fault_and_keeps_every_sample_measured():
    samples = []
    loop = MeasurementLoop(
        _camera(StretchingScene(fail_after_s=0.55)),
        None,
        _setup,
        sinks=[samples.append],
        block_when_full=True,
    )
    result = loop.run(StopCriteria(until_break=False))
    assert result.exit_status == "fault"
    assert "acquisition" in result.reason and "sensor failure" in result.reason
    assert result.final_state is RunState.FAULT
    assert len(samples) == result.frames_processed == 5


def test_frame_limit_and_sink_failure():
    def broken_sink(sample):
        raise OSError("disk full")

    loop = MeasurementLoop(
        _camera(StretchingScene()), None, _setup, sinks=[broken_sink], block_when_full=True
    )
    result = loop.run(StopCriteria(until_break=False, max_frames=50))
    assert result.exit_status == "fault" and "disk full" in result.reason
    loop = MeasurementLoop(_camera(StretchingScene()), None, _setup, block_when_full=True)
    result = loop.run(StopCriteria(until_break=False, max_frames=3))
    assert result.exit_status == "completed" and result.frames_processed == 3


def test_a_failing_sink_ends_the_run_as_a_fault_and_the_others_get_every_sample_measured():
    kept, recorded = [], []

    def recording_fails_at_the_fourth_sample(sample):
        if len(recorded) == 3:
            raise OSError(28, "No space left on device")
        recorded.append(sample.index)

    loop = MeasurementLoop(
        _camera(StretchingScene()),
        None,
        _setup,
        sinks=[recording_fails_at_the_fourth_sample, kept.append],
        block_when_full=True,
        queue_size=4,
    )
    result = loop.run(StopCriteria(until_break=False))
    assert result.exit_status == "fault" and result.final_state is RunState.FAULT
    assert result.reason == "output: OSError: [Errno 28] No space left on device"
    assert recorded == [0, 1, 2]
    assert [s.index for s in kept] == list(range(result.frames_processed))
    assert result.frames_processed >= 4


def test_a_fault_requested_from_outside_ends_the_run_with_its_reason():
    samples = []
    loop = MeasurementLoop(
        _camera(StretchingScene()), None, _setup, sinks=[samples.append], block_when_full=True
    )

    def fault_at_the_third_sample(sample):
        if sample.index == 2:
            loop.request_fault("strain file", OSError(28, "No space left on device"))

    loop.immediate_sinks.append(fault_at_the_third_sample)
    result = loop.run(StopCriteria(until_break=False))
    assert result.exit_status == "fault"
    assert result.reason == "strain file: OSError: [Errno 28] No space left on device"
    assert [s.index for s in samples] == list(range(result.frames_processed))
    assert 3 <= result.frames_processed < 20


def test_a_hung_camera_stops_the_samples_and_a_stop_still_ends_the_run():
    camera = SimCamera(
        "sim://camera",
        scene=StretchingScene(),
        clock=SimClock(),
        read_noise=0.0,
        electrons_per_grey=0.0,
        hang_after_s=0.45,
    )
    camera.open()
    camera.prepare(TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=10.0, exposure_us=100.0))
    samples = []
    loop = MeasurementLoop(
        camera,
        None,
        _setup,
        sinks=[samples.append],
        block_when_full=True,
        fetch_timeout_s=0.2,
    )

    def stop_once_hung() -> None:
        deadline = time.monotonic() + 60.0
        while len(samples) < 4 and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.6)
        loop.request_stop("operator stop")

    stopper = threading.Thread(target=stop_once_hung)
    stopper.start()
    result = loop.run(StopCriteria(until_break=False))
    stopper.join()
    assert len(samples) == result.frames_processed == 4
    assert result.exit_status == "fault" and result.final_state is RunState.FAULT
    assert "fetch did not return" in result.reason
