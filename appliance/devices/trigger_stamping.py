"""Frames of a camera triggered by the trigger microcontroller, stamped with their triggers.

A real camera on the trigger microcontroller's output exposes at every pulse; the firmware
reports every pulse as a TRIGGER event (number from 1 after ARM, tick of its rising edge,
encoder position), and the link's clock sync puts the tick on the host's clock. The frame's
own device timestamp is on the camera's clock, which nothing relates to the host's, and the
time the buffer reached the host carries the transport's delays. `TriggerStampedCamera` wraps
the camera and gives each frame the time of its trigger:

* arming arms the camera first, then the microcontroller (`McuTriggerLine.start`) with its
  first pulse `arm_lead_s` later, so no pulse falls on a camera still starting to acquire:
  the first frame is trigger 1;
* frames are matched to TRIGGER events by sequence: a frame `g` frame ids after the last
  one (g > 1: frames lost on the way) is trigger `last + g`. The match is checked against
  time: a frame's device time less its trigger's tick time is the camera's latency plus the
  two clocks' offset; its smallest value over the last frames is the baseline. The expected
  trigger and its neighbours are tried, and the one whose offset is nearest the baseline is
  taken, if it lies between one trigger spacing below the baseline and two thirds of a
  spacing above it (or `tolerance_s`, if larger). A camera that missed a pulse (still busy
  when it came), which shifts the numbering, is so re-synchronised (and counted). A frame
  earlier than the baseline means the baseline was set by a late frame (a camera slow to
  take its first trigger); the baseline is lowered by it rather than every later frame being
  paired with the trigger before its own. Not told apart: a first frame later than half a
  spacing followed at once by a missed pulse. After a few frames that fit no
  trigger (a camera back with a new clock) the baseline is dropped and the next frame is
  matched by frame ids alone;
* the frame is returned with `timestamp_ns` = the trigger's tick on the host clock (ns,
  monotonic) by the clock fit when the frame is matched (a fit that has seen round trips
  after the trigger, better than the one the event arrived with), and
  its metadata extended by `trigger` (sequence, tick, encoder position, clock-fit
  uncertainty) and `device_timestamp_ns`;
* a frame whose trigger does not arrive within `wait_s`, or fits no trigger in time, is
  dropped and counted, never stamped with another clock.

`statistics()` adds the matching counters to the camera's own.
"""

from __future__ import annotations

import collections
import dataclasses
import time
from typing import Any

from appliance.devices.mcu_trigger import McuTriggerLine
from appliance.plan.trigger_plan import TriggerPlan
from firmware_bridge.clocksync import ClockNotSynced
from firmware_bridge.link import FirmwareError, TriggerEvent
from hal.camera.base import Camera, CameraSettings, Frame, TriggerInfo
from hal.errors import HardwareTimeout

RESYNC_CANDIDATES = 4
"""Triggers tried after the expected one when the expected one does not fit in time."""

BASELINE_FRAMES = 64
"""Matched frames whose smallest pulse-to-frame offset is the latency baseline."""

REANCHOR_AFTER = 3
"""Consecutive frames without a fitting trigger after which the baseline is dropped and the
next frame is matched by frame ids alone (a camera that came back with a new clock)."""


class TriggerStampedCamera:
    """A camera whose frames carry the time and number of the trigger that exposed them.

    Args:
        camera: the camera, configured and prepared for EXTERNAL triggering.
        line: the trigger microcontroller (connected; configured and armed by `arm`).
        plan: the trigger plan to arm with.
        wait_s: longest wait for a frame's TRIGGER event after the frame arrived.
        tolerance_s: smallest half-width of the latency window a match must fall in, s (a
            third of the trigger spacing when that is larger).
        arm_lead_s: time from arming the camera to the first pulse, s.
    """

    def __init__(
        self,
        camera: Camera,
        line: McuTriggerLine,
        plan: TriggerPlan,
        *,
        wait_s: float = 0.5,
        tolerance_s: float = 0.005,
        arm_lead_s: float = 0.2,
    ) -> None:
        self.camera = camera
        self.line = line
        self.plan = plan
        self.wait_s = wait_s
        self.tolerance_s = tolerance_s
        self.arm_lead_s = arm_lead_s
        self.url = camera.url
        self.matched = 0
        self.unmatched = 0
        self.resyncs = 0
        self._events: dict[int, TriggerEvent] = {}
        self._last: tuple[TriggerEvent, int] | None = None
        self._offsets: collections.deque[float] = collections.deque(maxlen=BASELINE_FRAMES)
        self._misses = 0

    def open(self, timeout_s: float = 5.0) -> None:
        self.camera.open(timeout_s)

    def close(self) -> None:
        self.camera.close()

    def configure(self, settings: CameraSettings) -> CameraSettings:
        return self.camera.configure(settings)

    def prepare(self, trigger: TriggerInfo) -> None:
        self.camera.prepare(trigger)

    def set_exposure(self, exposure_us: float) -> float:
        return self.camera.set_exposure(exposure_us)

    def trigger(self) -> None:
        self.camera.trigger()

    def arm(self) -> None:
        """Arm the camera, then the trigger microcontroller with the plan."""
        self.camera.arm()
        self._events.clear()
        self._last = None
        self._offsets.clear()
        self._misses = 0
        link = self.line.link
        link.drain_events()
        start_tick = link.tick_at(time.monotonic_ns() + round(self.arm_lead_s * 1e9))
        self.line.start(self.plan, start_tick=start_tick)

    def disarm(self) -> None:
        """Disarm the trigger microcontroller (a link already gone is ignored), then the
        camera."""
        try:
            self.line.stop()
        except FirmwareError:
            pass
        self.camera.disarm()

    def fetch(self, timeout_s: float) -> Frame:
        """The next frame, stamped with its trigger. Raises HardwareTimeout when no frame
        with a trigger arrives within `timeout_s` (frames without one are dropped)."""
        deadline = time.monotonic() + timeout_s
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise HardwareTimeout(f"{self.url}: no triggered frame within {timeout_s:g} s")
            frame = self.camera.fetch(remaining)
            event = self._match(frame)
            stamp = self._host_time_ns(event) if event is not None else None
            if event is None or stamp is None:
                self.unmatched += 1
                continue
            self.matched += 1
            return dataclasses.replace(
                frame,
                timestamp_ns=stamp,
                metadata={
                    **frame.metadata,
                    "device_timestamp_ns": frame.timestamp_ns,
                    "trigger": {
                        "sequence": event.trigger_seq,
                        "tick": event.tick,
                        "position": event.position,
                        "uncertainty_ns": self._uncertainty_ns(event),
                    },
                },
            )

    def statistics(self) -> dict[str, Any]:
        """The camera's statistics and the matching counters."""
        own = dict(self.camera.statistics())
        return {
            **own,
            "frames_matched_to_triggers": self.matched,
            "frames_without_trigger": self.unmatched,
            "trigger_resyncs": self.resyncs,
        }

    def _host_time_ns(self, event: TriggerEvent) -> int | None:
        try:
            return int(self.line.link.host_time_ns(event.tick))
        except ClockNotSynced:
            return event.host_time_ns

    def _uncertainty_ns(self, event: TriggerEvent) -> float | None:
        estimate = self.line.link.clock_estimate()
        if estimate is None:
            return event.uncertainty_ns
        return float(estimate.uncertainty_ns(event.tick))

    def _match(self, frame: Frame) -> TriggerEvent | None:
        last = self._last
        expected = 1 if last is None else last[0].trigger_seq + max(1, frame.frame_id - last[1])
        event = self._event(expected, time.monotonic() + self.wait_s)
        if self._offsets and last is not None:
            best = self._best_in_time(frame, expected)
            if best is not None and best is not event:
                self.resyncs += 1
            event = best
        if event is None:
            self._misses += 1
            if self._misses >= REANCHOR_AFTER:
                self._offsets.clear()
            return None
        self._misses = 0
        self._last = (event, frame.frame_id)
        self._offsets.append(self._offset_s(frame, event))
        for seq in [s for s in self._events if s <= event.trigger_seq]:
            del self._events[seq]
        return event

    def _offset_s(self, frame: Frame, event: TriggerEvent) -> float:
        """Device time of the frame less the trigger's tick time, s (latency + clock offset)."""
        return frame.timestamp_ns * 1e-9 - event.tick / float(self.line.link.firmware.tick_hz)

    def _best_in_time(self, frame: Frame, expected: int) -> TriggerEvent | None:
        baseline = min(self._offsets)
        tick_hz = float(self.line.link.firmware.tick_hz)
        assert self._last is not None
        previous = self._last[0]

        def latency_s(candidate: TriggerEvent) -> float:
            return self._offset_s(frame, candidate) - baseline

        def fits(candidate: TriggerEvent) -> bool:
            steps = max(1, candidate.trigger_seq - previous.trigger_seq)
            spacing_s = (candidate.tick - previous.tick) / tick_hz / steps
            late = max(self.tolerance_s, spacing_s * 2.0 / 3.0)
            return -max(self.tolerance_s, spacing_s) < latency_s(candidate) < late

        self._collect()
        candidates = [
            self._events[seq]
            for seq in range(expected - 1, expected + 1 + RESYNC_CANDIDATES)
            if seq in self._events and seq > previous.trigger_seq
        ]
        fitting = [c for c in candidates if fits(c)]
        return min(fitting, key=lambda c: abs(latency_s(c))) if fitting else None

    def _event(self, seq: int, deadline: float) -> TriggerEvent | None:
        while seq not in self._events:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            event = self.line.link.next_event(remaining)
            if self.line.reset_under_test(event):
                raise self.line.restarted(event)
            if isinstance(event, TriggerEvent):
                self._events[event.trigger_seq] = event
        return self._events[seq]

    def _collect(self) -> None:
        for event in self.line.link.drain_events():
            if self.line.reset_under_test(event):
                raise self.line.restarted(event)
            if isinstance(event, TriggerEvent):
                self._events[event.trigger_seq] = event
