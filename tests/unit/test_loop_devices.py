"""Devices that go away during a run: camera outages waited through, controller gaps flagged.

The camera is the simulator, whose scene fails inside a window of simulated time (an outage
as the backend reports it: `HardwareConnectError` from `fetch`); the controller is a small
`TestingMachine` whose reads fail for a stretch of calls. `PolledMachine` runs over the
same controller.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Mapping
from typing import Any

import numpy as np
import pytest

from appliance.devices.polled_machine import PolledMachine
from appliance.measure.frame_measurer import StopCriteria
from appliance.run.loop import DeviceEvent, MeasurementLoop
from appliance.run.state import RunState
from hal.camera.base import Frame, Region
from hal.errors import HardwareConnectError, HardwareTimeout
from hal.machine.base import MachineState
from tests.unit.test_loop import StretchingScene, _camera, _setup


class ScheduledOutageScene(StretchingScene):
    """The stretching scene, unreachable between `away_from_s` and `back_at_s`."""

    def __init__(self, away_from_s: float, back_at_s: float) -> None:
        super().__init__()
        self.away_from_s, self.back_at_s = away_from_s, back_at_s

    def render(
        self, start_s: float, stop_s: float, region: Region
    ) -> tuple[np.ndarray, Mapping[str, Any]]:
        if self.away_from_s <= start_s < self.back_at_s:
            raise HardwareConnectError("sim://camera: control lost")
        return super().render(start_s, stop_s, region)


class TwoOutagesScene(StretchingScene):
    """The stretching scene, unreachable in two windows of simulated time."""

    def __init__(self, windows: list[tuple[float, float]]) -> None:
        super().__init__()
        self.windows = windows

    def render(
        self, start_s: float, stop_s: float, region: Region
    ) -> tuple[np.ndarray, Mapping[str, Any]]:
        if any(first <= start_s < last for first, last in self.windows):
            raise HardwareConnectError("sim://camera: control lost")
        return super().render(start_s, stop_s, region)


class RestartedCamera:
    """A camera that comes back from its outage rebooted: frame counter and clock at zero."""

    def __init__(self, camera, back_at_s: float) -> None:
        self.camera, self.back_at_s = camera, back_at_s
        self.url = camera.url

    def __getattr__(self, name: str):
        return getattr(self.camera, name)

    def fetch(self, timeout_s: float) -> Frame:
        frame = self.camera.fetch(timeout_s)
        if frame.timestamp_ns < self.back_at_s * 1e9:
            return frame
        return dataclasses.replace(
            frame,
            frame_id=frame.frame_id - 1000,
            timestamp_ns=frame.timestamp_ns - int(self.back_at_s * 1e9),
        )


class FlakyController:
    """A controller whose reads `first_failure` .. `last_failure` (by call) fail."""

    url = "modbus-tcp://127.0.0.1:1"

    def __init__(self, first_failure: int, last_failure: int) -> None:
        self.calls = 0
        self.first_failure, self.last_failure = first_failure, last_failure
        self.fail = threading.Event()

    def open(self, timeout_s: float = 5.0) -> None:
        pass

    def close(self) -> None:
        pass

    def read_state(self, timeout_s: float = 1.0) -> MachineState:
        self.calls += 1
        if self.first_failure <= self.calls <= self.last_failure or self.fail.is_set():
            raise HardwareTimeout(f"{self.url}: no reply within {timeout_s:g} s")
        return MachineState(1.0, 10.0, 5.0, True, time.monotonic_ns())

    def start(self, speed_mm_min: float, timeout_s: float = 1.0) -> None:
        pass

    def stop(self, timeout_s: float = 1.0) -> None:
        pass

    def return_to_start(self, speed_mm_min: float, timeout_s: float = 1.0) -> None:
        pass


def _run(camera, machine=None, *, outage_timeout_s: float, frames: int = 20):
    samples, events = [], []
    loop = MeasurementLoop(
        camera,
        machine,
        _setup,
        sinks=[samples.append],
        block_when_full=True,
        camera_outage_timeout_s=outage_timeout_s,
        device_listeners=[events.append],
    )
    result = loop.run(StopCriteria(until_break=False, max_frames=frames))
    return result, samples, events


def test_a_camera_gone_again_just_after_it_came_back_is_one_outage():
    """Back for one frame, then away again (a camera that resumes and only then is found to
    have dropped this host's control): one outage, both stretches of its time counted."""
    scene = TwoOutagesScene([(0.45, 1.05), (1.15, 1.55)])
    result, samples, events = _run(_camera(scene), outage_timeout_s=30.0)
    assert result.exit_status == "completed" and result.frames_processed == 20
    assert result.camera_outages == 1
    kinds = [e.kind for e in events if e.kind != "waiting"]
    assert kinds == ["lost", "restored", "lost", "restored"]
    times = [round(sample.time_s, 3) for sample in samples]
    assert 1.1 in times and 1.2 not in times and 1.6 in times


def test_a_camera_back_for_a_few_frames_starts_a_new_outage_when_it_goes_again():
    scene = TwoOutagesScene([(0.45, 1.05), (1.35, 1.85)])
    result, _, _ = _run(_camera(scene), outage_timeout_s=30.0, frames=30)
    assert result.exit_status == "completed"
    assert result.camera_outages == 2


def test_a_camera_outage_is_waited_through_and_reported():
    result, samples, events = _run(_camera(ScheduledOutageScene(0.45, 1.05)), outage_timeout_s=30.0)
    assert result.exit_status == "completed" and result.final_state is RunState.IDLE
    assert result.frames_processed == len(samples) == 20
    assert result.camera_outages == 1 and result.camera_outage_s > 0
    kinds = [e.kind for e in events]
    assert kinds[0] == "lost" and kinds[-1] == "restored"
    assert set(kinds[1:-1]) == {"waiting"} and len(kinds) == 2 + 5
    assert all(e.device == "camera" and e.url == "sim://camera" for e in events)
    assert not events[0].available and events[-1].available
    times = [round(s.time_s, 3) for s in samples]
    assert 0.5 not in times and 1.0 not in times and 1.1 in times
    for sample in samples:
        assert sample.reading.engineering_strain == pytest.approx(
            sample.metadata["truth"]["strain"], abs=3e-4
        )


def test_an_outage_longer_than_its_timeout_faults_and_no_tolerance_faults_at_once():
    result, samples, events = _run(
        _camera(ScheduledOutageScene(0.45, 1e9)), outage_timeout_s=0.3, frames=100
    )
    assert result.exit_status == "fault" and "camera away for" in result.reason
    assert "outage timeout 0.3 s" in result.reason and len(samples) == 4
    assert events[0].kind == "lost" and events[-1].kind == "waiting"
    result, samples, events = _run(
        _camera(ScheduledOutageScene(0.45, 1e9)), outage_timeout_s=0.0, frames=100
    )
    assert result.exit_status == "fault" and "control lost" in result.reason
    assert events == [] and len(samples) == 4


def test_a_camera_restarted_during_the_outage_is_re_based_onto_the_run_clock():
    camera = RestartedCamera(_camera(ScheduledOutageScene(0.45, 1.05)), back_at_s=1.05)
    result, samples, _ = _run(camera, outage_timeout_s=30.0)
    assert result.exit_status == "completed" and result.frames_dropped == 0
    stamps = np.array([s.timestamp_ns for s in samples])
    assert np.all(np.diff(stamps) > 0)
    after = [s for s in samples if "device_timestamp_ns" in s.metadata]
    assert after and after[0].metadata["device_timestamp_ns"] < 1e8
    assert after[0].time_s > samples[len(samples) - len(after) - 1].time_s


def test_controller_gaps_leave_samples_without_machine_state_and_are_reported():
    controller = FlakyController(first_failure=4, last_failure=8)
    result, samples, events = _run(_camera(StretchingScene()), controller, outage_timeout_s=0)
    assert result.exit_status == "completed" and len(samples) == 20
    missing = [s.index for s in samples if s.machine is None]
    assert missing == [3, 4, 5, 6, 7]
    assert all(s.data_valid for s in samples)
    assert result.controller_outages == 1 and result.samples_without_controller == 5
    assert [(e.device, e.kind) for e in events] == [("machine", "lost"), ("machine", "restored")]
    assert "no reply" in events[0].text


def test_polled_machine_hands_out_fresh_readings_and_refuses_stale_ones():
    controller = FlakyController(first_failure=0, last_failure=-1)
    polled = PolledMachine(controller, rate_hz=200.0, max_age_s=0.2)
    polled.open()
    try:
        state = polled.read_state()
        assert state.force_n == 5.0 and polled.url == controller.url
        calls = controller.calls
        time.sleep(0.1)
        assert controller.calls > calls
        controller.fail.set()
        deadline = time.monotonic() + 5.0
        while True:
            try:
                polled.read_state()
            except HardwareConnectError as exc:
                assert "no fresh controller reading" in str(exc) and "no reply" in str(exc)
                break
            assert time.monotonic() < deadline, "a stale reading was still handed out"
            time.sleep(0.02)
        controller.fail.clear()
        deadline = time.monotonic() + 5.0
        while True:
            try:
                polled.read_state()
                break
            except HardwareConnectError:
                assert time.monotonic() < deadline, "readings did not come back"
                time.sleep(0.02)
        stats = polled.poll_statistics()
        assert stats.reads > 2 and stats.failures > 0 and stats.p99_ms >= stats.p50_ms
    finally:
        polled.close()
    polled.close()


def test_polled_machine_events_reach_the_loop_as_controller_gaps():
    controller = FlakyController(first_failure=0, last_failure=-1)
    polled = PolledMachine(controller, rate_hz=100.0, max_age_s=0.1)
    polled.open()
    controller.fail.set()
    time.sleep(0.3)
    try:
        result, samples, events = _run(_camera(StretchingScene()), polled, outage_timeout_s=0)
    finally:
        polled.close()
    assert all(s.machine is None for s in samples) and result.controller_outages == 1
    assert [e.kind for e in events] == ["lost"]
    assert isinstance(events[0], DeviceEvent) and events[0].device == "machine"
