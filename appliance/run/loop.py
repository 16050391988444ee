"""The measurement loop: acquisition, tracking and publishing on their own threads.

    camera.fetch --(frames queue)--> track + strain --(samples queue)--> sinks

* The acquisition thread fetches frames and reads the machine controller right after each one.
  When the frames queue is full it drops the frame and counts it (a real camera cannot wait),
  unless the loop is told to block (a simulation running as fast as possible, whose clock
  only moves when a frame is fetched).
* The tracking thread measures the frame (`appliance.measure.frame_measurer.FrameMeasurer`: marks,
  strain, validity, stop criteria and break detection), calls the *immediate* sinks (the
  Modbus registers and the watchdog, which must see the strain of this frame before the next
  one is measured; they must be fast and must not block) and hands the `StrainSample` on.
* The publishing thread calls the sinks (strain file, recording, viewer, progress display).
  Its queue never drops: every sample measured is published; a sink that cannot keep up
  slows the loop until the frames queue drops frames, which are counted. A sink that fails
  (a recording on a full disk) ends the test as a fault and gets no further samples; the
  other sinks still get every sample measured before the test ended.

Timestamps come from the device (`Frame.timestamp_ns`). Latency is wall time from the moment
the camera delivers a frame to the moment its strain sample is complete, so it measures this
program and nothing of the camera's transport.

Devices that go away (real hardware):

* A camera outage (`fetch` raising `HardwareConnectError` or `HardwareTimeout`) is waited
  through for up to `camera_outage_timeout_s` while the backend reconnects: no samples are
  measured, listeners hear `DeviceEvent`s (the Modbus registers clear data-valid), the loop
  stays in control (its liveness listeners are still called), and the run faults only when
  the outage outlasts the timeout. A camera that comes back with its frame counter or clock
  restarted is re-based: the device time continues from the last frame by the host time
  that passed (the original stamp stays in the frame's metadata as `device_timestamp_ns`).
* A controller that cannot be read leaves the sample's `machine` None (its force and
  crosshead are missing, and flagged) while the strain is still measured; listeners hear
  when the controller is lost and when it is back.
* A camera call that does not return (a `fetch` still blocked `hung_after_s` after it began:
  its timeout plus as long again plus 1 s; a hung driver) is not an outage the loop can wait
  through: the loop is no longer in control. Listeners hear a "hung" `DeviceEvent` (data-valid
  cleared), the run ends as a FAULT ("fetch did not return within N s"), the blocked thread
  is given up on so the outputs still close, and `LoopResult.hung_call` says so: only a new
  process can recover the driver.

Liveness: the thread that called `run` watches the others every `LIVENESS_PERIOD_S` and calls
the liveness listeners (the service's watchdog, the Modbus heartbeat) while the loop is in
control: no camera call blocked beyond `hung_after_s` and no frame in measurement for longer
than `TRACKING_BOUND_S`. A loop stuck in a call stops those calls, so the service manager's
watchdog restarts the service; a camera that answers without frames does not.

The run follows `appliance.run.state`: ARMED while the reference is taken, RUNNING while
measuring, STOPPING while the queues drain, then IDLE; ABORTED on an operator interrupt and
FAULT on an error of a device or of the measurement, each with its reason. Samples measured
before an abort or a fault are kept and published.
"""

from __future__ import annotations

import dataclasses
import queue
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

from appliance.errors import InputError
from appliance.measure.edge_width import EdgeWidthGauge
from appliance.measure.frame_measurer import (
    BreakDetection,
    FrameMeasurer,
    StopCriteria,
    StrainSample,
)
from appliance.measure.gauges import StrainGauges
from appliance.measure.tracking import MarkTracker
from appliance.run.state import ExitStatus, RunEvent, RunState, RunStateMachine
from hal.camera.base import Camera, Frame
from hal.errors import HardwareConnectError, HardwareError, HardwareTimeout
from hal.machine.base import MachineState, TestingMachine

OUTAGE_RETRY_S = 0.05
"""Pause between fetch attempts while the camera is away (its backend paces reconnects)."""

OUTAGE_SETTLE_FRAMES = 3
"""A camera that goes away again before it has sent this many frames since it came back is
still in the outage it came back from (counted once): a camera resumed after a stall longer
than its heartbeat timeout, or restarted, may send a frame or two before the host learns it
no longer controls it and reconnects."""

LIVENESS_PERIOD_S = 0.1
"""How often the loop's threads are watched and the liveness listeners called."""

TRACKING_BOUND_S = 10.0
"""Longest measurement of one frame that still counts as progress (a frame takes ms)."""


@dataclass(frozen=True)
class DeviceEvent:
    """A device went away, is still away, or came back during a run.

    Attributes:
        device: "camera" or "machine" (its controller).
        url: the device's URL.
        kind: "lost" (first failure), "waiting" (each further failed attempt, camera only),
            "restored", or "hung" (a call that did not return: the run ends as a fault and
            the device cannot be used again in this process).
        text: one line: the error, or how long the device was away.
    """

    device: str
    url: str
    kind: str
    text: str

    @property
    def available(self) -> bool:
        """Whether the device is delivering again."""
        return self.kind == "restored"


@dataclass
class LoopResult:
    """How a run went.

    Attributes:
        exit_status: how the run ended.
        reason: why the run ended, one line.
        frames_processed: samples measured.
        valid_samples: samples with the data-valid flag.
        frames_dropped: frames lost: dropped on a full queue or missing from the camera's
            frame counter.
        latencies_s: per-sample latency, s.
        tracking_time_s: wall time spent tracking (the measurement's own cost).
        final_state: the run state at the end.
        camera_outages: times the camera went away during the run (a return of fewer than
            `OUTAGE_SETTLE_FRAMES` frames does not end an outage).
        camera_outage_s: total time without the camera, s (wall time).
        controller_outages: times the controller could not be read after it had been.
        samples_without_controller: frames acquired without the controller's state.
        hung_call: the device call that did not return and was given up on, one line; ""
            when none (a process with a hung call needs a restart to use the device again).
    """

    exit_status: ExitStatus = ExitStatus.COMPLETED
    reason: str = ""
    frames_processed: int = 0
    valid_samples: int = 0
    frames_dropped: int = 0
    latencies_s: list[float] = field(default_factory=list)
    tracking_time_s: float = 0.0
    final_state: RunState = RunState.IDLE
    camera_outages: int = 0
    camera_outage_s: float = 0.0
    controller_outages: int = 0
    samples_without_controller: int = 0
    hung_call: str = ""


Sink = Callable[[StrainSample], None]
_END = object()
_T = TypeVar("_T")

DEVICE_CALL_BOUND_S = 30.0
"""Longest a device call outside the measurement (open, disarm, close) counts as progress."""


def call_in_control(
    call: Callable[[], _T],
    liveness_listeners: Sequence[Callable[[], None]],
    bound_s: float = DEVICE_CALL_BOUND_S,
) -> _T:
    """`call()` on the caller's thread, while a thread of its own calls the liveness
    listeners every `LIVENESS_PERIOD_S` for up to `bound_s` (a device call that returns within
    its own timeouts is the loop in control; one that blocks longer stops the listeners, so
    the service manager's watchdog sees it). The call itself stays on the caller's thread:
    device libraries are used from the thread that opened them (Aravis' GLib objects, the
    trigger link's clock synchronisation). Returns what `call` returns, raises what it raises."""
    if not liveness_listeners:
        return call()
    finished = threading.Event()

    def keep_alive() -> None:
        deadline = time.monotonic() + bound_s
        while not finished.wait(LIVENESS_PERIOD_S) and time.monotonic() <= deadline:
            for listener in liveness_listeners:
                listener()

    pinger = threading.Thread(target=keep_alive, name="device-call-liveness", daemon=True)
    pinger.start()
    try:
        return call()
    finally:
        finished.set()
        pinger.join()


class MeasurementLoop:
    """Runs one test on a camera and a machine controller.

    Args:
        camera: an opened, configured and prepared camera (not armed).
        machine: an opened testing machine, or None.
        setup: called with the reference frame; returns the tracker and the strain gauges
            (this is where the marks are placed), and optionally a third item, the width
            gauge (`appliance.measure.edge_width.EdgeWidthGauge`, or None).
        sinks: called in order with every sample, on the publishing thread.
        immediate_sinks: called in order with every sample on the tracking thread, as soon
            as it is measured (fast, non-blocking work only).
        state: the run state machine (IDLE at the start).
        block_when_full: wait for room in the frames queue instead of dropping frames.
        queue_size: capacity of each queue.
        start_speed_mm_min: if set and the controller accepts commands, start the crosshead
            at this speed when the run starts and stop it at the end.
        fetch_timeout_s: timeout of every frame fetch.
        break_detection: how a break is recognised.
        camera_outage_timeout_s: how long a camera outage is waited through before the run
            faults; 0 = the first connection loss or timeout is a fault.
        device_listeners: called with every `DeviceEvent` (on the acquisition thread; a
            "hung" event on the thread that called `run`; fast, non-blocking work only).
        liveness_listeners: called every `LIVENESS_PERIOD_S` on the thread that called `run`
            while the loop is in control (the reference frame included), never while a call
            hangs (fast, non-blocking work only: the service's watchdog).
        machine_listeners: called with the time of every frame after the reference (s since
            the reference, as `StrainSample.time_s`) and the controller reading taken with it
            (None when there is none), on the acquisition thread before the frame is queued
            (the exposure pacing, `appliance.plan.pacing`).
        wall: wall clock, s (injected for tests).
    """

    def __init__(
        self,
        camera: Camera,
        machine: TestingMachine | None,
        setup: Callable[[Frame], tuple[Any, ...]],
        *,
        sinks: Sequence[Sink] = (),
        immediate_sinks: Sequence[Sink] = (),
        state: RunStateMachine | None = None,
        block_when_full: bool = False,
        queue_size: int = 8,
        start_speed_mm_min: float | None = None,
        fetch_timeout_s: float = 2.0,
        break_detection: BreakDetection | None = None,
        camera_outage_timeout_s: float = 0.0,
        device_listeners: Sequence[Callable[[DeviceEvent], None]] = (),
        liveness_listeners: Sequence[Callable[[], None]] = (),
        machine_listeners: Sequence[Callable[[float, MachineState | None], None]] = (),
        wall: Callable[[], float] = time.perf_counter,
    ) -> None:
        self.camera = camera
        self.machine = machine
        self.setup = setup
        self.sinks = list(sinks)
        self.immediate_sinks = list(immediate_sinks)
        self.state = state or RunStateMachine()
        self.block_when_full = block_when_full
        self.start_speed_mm_min = start_speed_mm_min
        self.fetch_timeout_s = fetch_timeout_s
        self.break_detection = break_detection or BreakDetection()
        self.camera_outage_timeout_s = camera_outage_timeout_s
        self.device_listeners = list(device_listeners)
        self.liveness_listeners = list(liveness_listeners)
        self.hung_after_s = 2 * fetch_timeout_s + 1.0
        self.machine_listeners = list(machine_listeners)
        self._wall = wall
        self._outage_since: float | None = None
        self._frames_since_return: int | None = None
        self._controller_lost = False
        self._time_offset_ns = 0
        self._last_timestamp_ns = 0
        self._last_delivered_s = 0.0
        self._frames: queue.Queue = queue.Queue(maxsize=queue_size)
        self._samples: queue.Queue = queue.Queue(maxsize=queue_size)
        self._stop = threading.Event()
        self._finished = threading.Event()
        self._zero_requested = threading.Event()
        self._result = LoopResult()
        self._errors: list[tuple[str, BaseException]] = []
        self._publishing_failed = False
        self._lock = threading.Lock()
        self._fetch_since: float | None = None
        self._tracking_since: float | None = None

    def request_stop(self, reason: str = "operator stop") -> None:
        """Stop the run before its criterion; it ends STOPPED with `reason` (thread-safe)."""
        self._finish(ExitStatus.STOPPED, reason)

    def request_fault(self, where: str, error: BaseException) -> None:
        """End the run as a FAULT because of `error` outside the loop's threads (an output
        that can no longer keep up with the test, a disk that is full); thread-safe. The
        reason is "`where`: `ErrorType`: `error`"; the first fault wins."""
        self._fail(where, error)

    def request_zero(self) -> None:
        """Zero the strain at the next measured frame (thread-safe); see
        `appliance.measure.frame_measurer.FrameMeasurer.zero`."""
        self._zero_requested.set()

    def run(self, criteria: StopCriteria) -> LoopResult:
        """Take the reference, measure until a stop criterion, a break, an abort or a fault.

        Raises:
            InputError: the set-up refused the reference frame (marks that do not fit, a
                speckle that cannot be tracked): the run goes back to IDLE, nothing measured.
        """
        self.state.handle(RunEvent.ARM, "reference")
        call_in_control(self.camera.arm, self.liveness_listeners)
        try:
            reference = self._reference_frame()
            self._reference_time_ns = reference.timestamp_ns
            self._last_frame_id = reference.frame_id
            self._last_timestamp_ns = reference.timestamp_ns
            self._last_delivered_s = time.monotonic()
            tracker, gauges, *width_gauge = call_in_control(
                lambda: self.setup(reference), self.liveness_listeners
            )
        except InputError as exc:
            self.state.handle(RunEvent.DISARM, f"refused: {exc}")
            self.camera.disarm()
            raise
        except Exception as exc:  # noqa: BLE001 - a failed start is a FAULT with its reason
            return self._fail_before_start(exc)
        if self._stop.is_set():
            return self._fail_before_start(None)
        self.state.handle(RunEvent.START, "measuring")
        if self.start_speed_mm_min is not None and self.machine is not None:
            self.machine.start(self.start_speed_mm_min)
        threads = [
            threading.Thread(target=self._guard, args=("acquisition", self._acquire), daemon=True),
            threading.Thread(
                target=self._guard,
                args=("tracking", self._track, tracker, gauges, criteria, *width_gauge),
                daemon=True,
            ),
            threading.Thread(target=self._guard, args=("publishing", self._publish), daemon=True),
        ]
        for thread in threads:
            thread.start()
        try:
            self._wait(threads)
        except KeyboardInterrupt:
            self._finish(ExitStatus.ABORTED, "interrupted by the operator")
            self._wait(threads)
        self._shut_down()
        return self._result

    def _reference_frame(self) -> Frame:
        """The first frame, fetched on a thread of its own so that a fetch that does not
        return is given up on (`hung_after_s`) and the liveness listeners hear the loop while
        it waits. A camera that delivers no frame is an outage here too, waited through for
        up to `camera_outage_timeout_s` unless the run is stopped meanwhile."""
        box: list[Frame | BaseException] = []

        def fetch() -> None:
            try:
                box.append(self._first_frame())
            except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
                box.append(exc)

        fetcher = threading.Thread(target=fetch, name="reference-fetch", daemon=True)
        fetcher.start()
        while fetcher.is_alive():
            fetcher.join(LIVENESS_PERIOD_S)
            hung = self._hung_fetch() if fetcher.is_alive() else None
            if hung is not None:
                raise self._hang(hung)
            self._alive()
        outcome = box[0]
        if isinstance(outcome, BaseException):
            raise outcome
        return outcome

    def _first_frame(self) -> Frame:
        while True:
            self._fetch_since = time.monotonic()
            try:
                frame = self.camera.fetch(self.fetch_timeout_s)
            except (HardwareConnectError, HardwareTimeout) as exc:
                self._fetch_since = None
                if self._stop.is_set():
                    raise
                self._camera_away(exc)
                continue
            self._fetch_since = None
            if self._outage_since is not None:
                away_s = time.monotonic() - self._outage_since
                self._result.camera_outage_s += away_s
                self._outage_since = None
                self._frames_since_return = 0
                self._emit(
                    DeviceEvent("camera", self.camera.url, "restored", f"back after {away_s:.1f} s")
                )
            return frame

    def _wait(self, threads: list[threading.Thread]) -> None:
        """Wait for the threads, calling the liveness listeners while the loop is in control;
        give up on an acquisition thread whose fetch does not return (a hung driver), so the
        test still ends and its outputs close."""
        while any(t.is_alive() for t in threads):
            for thread in threads:
                thread.join(timeout=LIVENESS_PERIOD_S / len(threads))
            hung = self._hung_fetch() if threads[0].is_alive() else None
            if hung is None:
                if not self._tracking_stuck():
                    self._alive()
                continue
            self._errors.insert(0, ("acquisition", self._hang(hung)))
            self._stop.set()
            self._put(self._frames, _END, force=True)
            for thread in threads[1:]:
                thread.join()
            return

    def _alive(self) -> None:
        for listener in self.liveness_listeners:
            listener()

    def _hung_fetch(self) -> str | None:
        """How long the camera's current fetch has been blocked, when beyond `hung_after_s`."""
        since = self._fetch_since
        if since is None:
            return None
        blocked_s = time.monotonic() - since
        if blocked_s <= self.hung_after_s:
            return None
        return f"{self.camera.url}: fetch did not return within {self.hung_after_s:g} s"

    def _tracking_stuck(self) -> bool:
        since = self._tracking_since
        return since is not None and time.monotonic() - since > TRACKING_BOUND_S

    def _hang(self, text: str) -> HardwareTimeout:
        """A camera call that does not return: said to the listeners, kept in the result."""
        self._result.hung_call = text
        self._emit(DeviceEvent("camera", self.camera.url, "hung", text))
        return HardwareTimeout(text)

    def _fail_before_start(self, exc: BaseException | None) -> LoopResult:
        """The run ends before its first frame is measured: the reference frame failed
        (`exc`), or a stop came while it was taken (None; the machine is not started)."""
        self._result.exit_status = ExitStatus.FAULT
        if exc is None or self._finished.is_set():
            ended = self._result.reason + (f"; reference frame: {exc}" if exc else "")
            self._result.reason = f"no valid sample was measured (the test ended: {ended})"
        else:
            where = "" if isinstance(exc, HardwareError) else f"{type(exc).__name__}: "
            self._result.reason = f"reference frame: {where}{exc}"
        self.state.handle(RunEvent.FAULT, self._result.reason)
        call_in_control(self.camera.disarm, self.liveness_listeners)
        self._result.final_state = self.state.state
        return self._result

    def _shut_down(self) -> None:
        call_in_control(self.camera.disarm, self.liveness_listeners)
        if self.start_speed_mm_min is not None and self.machine is not None:
            try:
                call_in_control(self.machine.stop, self.liveness_listeners)
            except HardwareError as exc:
                if not self._errors:
                    self._errors.append(("machine", exc))
        result = self._result
        if self._errors:
            where, exc = self._errors[0]
            result.exit_status = ExitStatus.FAULT
            result.reason = f"{where}: {type(exc).__name__}: {exc}"
        elif result.exit_status.ended_normally and result.valid_samples == 0:
            result.exit_status = ExitStatus.FAULT
            result.reason = f"no valid sample was measured (the test ended: {result.reason})"
        current = self.state.state
        if result.exit_status is ExitStatus.FAULT:
            self.state.handle(RunEvent.FAULT, result.reason)
        elif result.exit_status is ExitStatus.ABORTED:
            self.state.handle(RunEvent.ABORT, result.reason)
        else:
            if current is RunState.RUNNING:
                self.state.handle(RunEvent.STOP, result.reason)
            self.state.handle(RunEvent.FINISH, result.reason)
        result.final_state = self.state.state

    def _finish(self, status: ExitStatus, reason: str) -> None:
        with self._lock:
            if self._stop.is_set():
                return
            self._result.exit_status = status
            self._result.reason = reason
            self._finished.set()
            self._stop.set()
        if status.ended_normally and self.state.state is RunState.RUNNING:
            self.state.handle(RunEvent.STOP, reason)

    def _guard(self, name: str, body: Callable[..., None], *args: Any) -> None:
        try:
            body(*args)
        except BaseException as exc:  # noqa: BLE001 - every thread failure becomes a FAULT
            if name == "publishing":
                self._publishing_failed = True
            self._fail(name, exc)

    def _fail(self, where: str, error: BaseException) -> None:
        """Record a fault and end the run: no frame is acquired after it (the frames already
        acquired are still measured and published)."""
        with self._lock:
            self._errors.append((where, error))
            self._stop.set()
        self._put(self._frames, _END, force=True)

    def _put(self, q: queue.Queue, item: object, *, force: bool = False) -> bool:
        while True:
            try:
                q.put(item, timeout=0.05)
                return True
            except queue.Full:
                if force:
                    try:
                        q.get_nowait()
                    except queue.Empty:
                        pass
                elif self._stop.is_set():
                    return False

    def _acquire(self) -> None:
        try:
            while not self._stop.is_set():
                self._fetch_since = time.monotonic()
                try:
                    frame = self.camera.fetch(self.fetch_timeout_s)
                except (HardwareConnectError, HardwareTimeout) as exc:
                    self._fetch_since = None
                    self._camera_away(exc)
                    continue
                self._fetch_since = None
                delivered = self._wall()
                if self._outage_since is not None:
                    frame = self._camera_back(frame)
                elif self._time_offset_ns:
                    frame = self._rebased(frame, self._time_offset_ns)
                machine = self._read_machine()
                if self.machine_listeners:
                    time_s = (frame.timestamp_ns - self._reference_time_ns) * 1e-9
                    for listener in self.machine_listeners:
                        listener(time_s, machine)
                gap = frame.frame_id - self._last_frame_id - 1
                self._last_frame_id = frame.frame_id
                self._last_timestamp_ns = frame.timestamp_ns
                self._last_delivered_s = time.monotonic()
                if self._frames_since_return is not None:
                    self._frames_since_return += 1
                if gap > 0:
                    self._result.frames_dropped += gap
                item = (frame, machine, delivered)
                if self.block_when_full:
                    self._put(self._frames, item)
                else:
                    try:
                        self._frames.put_nowait(item)
                    except queue.Full:
                        self._result.frames_dropped += 1
        finally:
            if self._outage_since is not None:
                self._result.camera_outage_s += time.monotonic() - self._outage_since
                self._outage_since = None
            self._put(self._frames, _END, force=True)

    def _emit(self, event: DeviceEvent) -> None:
        for listener in self.device_listeners:
            listener(event)

    def _camera_away(self, exc: HardwareError) -> None:
        """A fetch failed: wait the outage through, or fault when it has lasted too long."""
        now = time.monotonic()
        if self.camera_outage_timeout_s <= 0:
            raise exc
        first = self._outage_since is None
        if first:
            self._outage_since = now
            returned = self._frames_since_return
            if returned is None or returned >= OUTAGE_SETTLE_FRAMES:
                self._result.camera_outages += 1
        away_s = now - self._outage_since
        if away_s > self.camera_outage_timeout_s:
            raise HardwareConnectError(
                f"{self.camera.url}: camera away for {away_s:.1f} s "
                f"(outage timeout {self.camera_outage_timeout_s:g} s): {exc}"
            )
        self._emit(DeviceEvent("camera", self.camera.url, "lost" if first else "waiting", str(exc)))
        self._stop.wait(OUTAGE_RETRY_S)

    def _camera_back(self, frame: Frame) -> Frame:
        """The first frame after an outage: end the outage, re-base a restarted camera."""
        away_s = time.monotonic() - self._outage_since
        self._result.camera_outage_s += away_s
        self._outage_since = None
        self._frames_since_return = 0
        if frame.frame_id <= self._last_frame_id:
            self._last_frame_id = frame.frame_id - 1
        host_elapsed_ns = int((time.monotonic() - self._last_delivered_s) * 1e9)
        expected_ns = self._last_timestamp_ns + host_elapsed_ns
        stamped = frame.timestamp_ns + self._time_offset_ns
        if stamped <= self._last_timestamp_ns or abs(stamped - expected_ns) > 1_000_000_000:
            self._time_offset_ns = expected_ns - frame.timestamp_ns
        self._emit(DeviceEvent("camera", self.camera.url, "restored", f"back after {away_s:.1f} s"))
        return self._rebased(frame, self._time_offset_ns) if self._time_offset_ns else frame

    @staticmethod
    def _rebased(frame: Frame, offset_ns: int) -> Frame:
        metadata = {**frame.metadata, "device_timestamp_ns": frame.timestamp_ns}
        return dataclasses.replace(
            frame, timestamp_ns=frame.timestamp_ns + offset_ns, metadata=metadata
        )

    def _read_machine(self) -> MachineState | None:
        """The controller's state for this frame; None (and an event) when it cannot be read."""
        if self.machine is None:
            return None
        try:
            state = self.machine.read_state()
        except HardwareError as exc:
            self._result.samples_without_controller += 1
            if not self._controller_lost:
                self._controller_lost = True
                self._result.controller_outages += 1
                self._emit(DeviceEvent("machine", self.machine.url, "lost", str(exc)))
            return None
        if self._controller_lost:
            self._controller_lost = False
            self._emit(DeviceEvent("machine", self.machine.url, "restored", "readings again"))
        return state

    def _track(
        self,
        tracker: MarkTracker,
        gauges: StrainGauges,
        criteria: StopCriteria,
        widths: EdgeWidthGauge | None = None,
    ) -> None:
        measurer = FrameMeasurer(
            tracker,
            gauges,
            self._reference_time_ns,
            break_detection=self.break_detection,
            wall=self._wall,
            widths=widths,
        )
        try:
            while True:
                item = self._frames.get()
                if item is _END:
                    break
                if self._finished.is_set():
                    continue
                frame, machine, delivered = item
                started = self._wall()
                self._tracking_since = time.monotonic()
                if self._zero_requested.is_set():
                    self._zero_requested.clear()
                    measurer.zero()
                sample = measurer.measure(frame, machine, delivered, self._result.frames_dropped)
                self._tracking_since = None
                for sink in self.immediate_sinks:
                    sink(sample)
                self._result.tracking_time_s += self._wall() - started
                self._result.frames_processed = measurer.samples
                self._result.valid_samples = measurer.valid_samples
                self._result.latencies_s.append(sample.latency_s)
                self._publish_sample(sample)
                ending = measurer.ending(criteria)
                if ending is not None:
                    status = ExitStatus.BREAK if ending.broke else ExitStatus.COMPLETED
                    self._finish(status, ending.reason)
        finally:
            self._stop.set()
            self._publish_sample(_END)

    def _publish_sample(self, sample: object) -> None:
        """Queue a sample for the sinks; waits for room (samples are never dropped)."""
        while True:
            try:
                self._samples.put(sample, timeout=0.05)
                return
            except queue.Full:
                if self._publishing_failed:
                    return

    def _publish(self) -> None:
        sinks = list(self.sinks)
        while True:
            sample = self._samples.get()
            if sample is _END:
                return
            for sink in tuple(sinks):
                try:
                    sink(sample)
                except Exception as exc:  # noqa: BLE001 - one failing sink must not starve the others
                    sinks.remove(sink)
                    self._fail("output", exc)
