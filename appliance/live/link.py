"""The live connections of a running test: Modbus registers, viewer, watchdog and commands.

`LiveLink` ties a test run by `appliance.runner.run_test` to what watches and drives it from
outside, for `extensometer run` (one test) and `extensometer serve` (one test after another):

* the Modbus strain server (`appliance.live.modbus_server`): registers written on the measurement
  thread with every frame, the run state mirrored in the status bits, and the controller's
  commands (stop and zero act on the running test; start and the gauge length set point are
  the caller's to decide, through `on_start` and `on_gauge_length`);
* the viewer (`appliance.live.viewer`), an output of every test;
* the service manager's watchdog, pinged while the measurement loop is in control (its
  liveness calls, `RunHooks.on_alive`: frames coming, or a camera outage being waited
  through), never while one of its calls hangs; the Modbus heartbeat moves with it;
* device events (`appliance.run.loop.DeviceEvent`): a camera outage clears data-valid; a
  camera call that hung is kept in `hung_call` (the process cannot use the camera again);
* the test's results (`RunHooks.on_results`, the summary's `results` object): written to the
  Modbus result registers in the same update as the exit status when the test's outputs end
  (`appliance.live.result_registers`), and cleared when the next test is armed.

`hooks()` gives the `RunHooks` that connect a test run by `run_test` to the link.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Mapping
from typing import Any

from appliance.config import Config
from appliance.live.modbus_server import StrainRegisterServer
from appliance.live.result_registers import result_register_values
from appliance.live.sd_notify import ServiceNotifier
from appliance.live.viewer import RerunViewer
from appliance.measure.frame_measurer import StrainSample
from appliance.run.loop import DeviceEvent, LoopResult, MeasurementLoop
from appliance.run.outputs import RunFacts, RunHooks, RunOutput
from appliance.run.state import RunState, Transition


class LiveLink:
    """Connections shared by the tests of one process.

    Args:
        config: the configuration ([modbus] chooses the servers).
        notifier: the service manager's notifier (None = no watchdog).
        viewer: an output following every test (a Rerun viewer), or None.
        on_start: decides a start command (called on the Modbus thread); None = refused.
        on_gauge_length: takes a gauge length set point, mm; None = refused.
        on_transition: called at every change of the run state, after the registers.
    """

    def __init__(
        self,
        config: Config,
        *,
        notifier: ServiceNotifier | None = None,
        viewer: RerunViewer | None = None,
        on_start: Callable[[], bool] | None = None,
        on_gauge_length: Callable[[float], bool] | None = None,
        on_transition: Callable[[Transition], None] | None = None,
    ) -> None:
        self.notifier = notifier
        self.viewer = viewer
        self._on_start = on_start
        self._on_gauge_length = on_gauge_length
        self._on_transition = on_transition
        self._lock = threading.Lock()
        self._loop: MeasurementLoop | None = None
        self._facts: RunFacts | None = None
        self.state = RunState.IDLE
        self.hung_call = ""
        self._results: Mapping[str, float | int] | None = None
        self.modbus = StrainRegisterServer(
            config.modbus,
            self._on_command,
            gauge_length_setpoint_mm=config.gauge.length_mm or math.nan,
        )

    def start(self) -> None:
        """Start the servers (Modbus, the viewer's). Raises InputError naming the key."""
        self.modbus.start()
        if self.viewer is not None:
            self.viewer.start()

    def close(self) -> None:
        """Stop the servers; idempotent."""
        self.modbus.close()
        if self.viewer is not None:
            self.viewer.close()

    def request_stop(self, reason: str) -> bool:
        """Stop the running test, if any; whether one was running."""
        with self._lock:
            loop = self._loop
        if loop is None:
            return False
        loop.request_stop(reason)
        return True

    def hooks(self) -> RunHooks:
        """The hooks of `run_test` connecting a test to the link.

        `hung_call` is set once a test's camera call hung (a "hung" device event) and stays
        set: the caller decides what a process with a hung call does."""
        outputs: list[RunOutput] = [_FactsTap(self)]
        if self.viewer is not None:
            outputs.append(self.viewer)
        return RunHooks(
            outputs=outputs,
            immediate_sinks=[self._on_sample],
            on_transition=self._transition,
            on_loop=self._attach,
            device_listeners=[self._on_device_event],
            on_alive=self._on_alive,
            on_results=self._on_results,
        )

    def _attach(self, loop: MeasurementLoop) -> None:
        with self._lock:
            self._loop = loop

    def _detach(self) -> None:
        with self._lock:
            self._loop = None
            self._facts = None

    def _on_sample(self, sample: StrainSample) -> None:
        self.modbus.publish(sample, self._facts)

    def _on_results(self, results: Mapping[str, Any]) -> None:
        """The test's results, computed before its outputs end: kept for the registers,
        which take them with the exit status (`_FactsTap.end`), and shown in the viewer."""
        self._results = result_register_values(results)
        if self.viewer is not None:
            self.viewer.show_results(self._results)

    def _on_alive(self) -> None:
        self.modbus.tick()
        if self.notifier is not None and not self.hung_call:
            self.notifier.watchdog()

    def _on_device_event(self, event: DeviceEvent) -> None:
        if event.device == "camera":
            self.modbus.set_camera_lost(not event.available)
        if event.kind == "hung":
            self.hung_call = event.text

    def _transition(self, transition: Transition) -> None:
        with self._lock:
            self.state = transition.target
        if transition.target is RunState.ARMED:
            self._results = None
            self.modbus.set_exit_status(None)
        self.modbus.set_run_state(transition.target)
        if self._on_transition is not None:
            self._on_transition(transition)

    def _on_command(self, command: str, value: float | None) -> bool:
        with self._lock:
            loop, running = self._loop, self.state is RunState.RUNNING
        if command == "stop":
            if loop is None or not running:
                return False
            loop.request_stop("stop command")
            return True
        if command == "zero":
            if loop is None or not running:
                return False
            loop.request_zero()
            return True
        if command == "start":
            return self._on_start() if self._on_start is not None else False
        if command == "gauge_length" and value is not None and self._on_gauge_length:
            if not self._on_gauge_length(value):
                return False
            self.modbus.set_gauge_length_setpoint(value)
            return True
        return False


class _FactsTap:
    """The output that lets the link know the running test's facts (for register times)."""

    def __init__(self, link: LiveLink) -> None:
        self._link = link

    def begin(self, facts: RunFacts) -> None:
        self._link._facts = facts

    def __call__(self, sample: StrainSample) -> None:
        pass

    def end(self, result: LoopResult) -> None:
        link = self._link
        results, link._results = link._results, None
        link.modbus.set_exit_status(result.exit_status, results)
        link._detach()

    def stats(self) -> dict[str, Any]:
        return {}
