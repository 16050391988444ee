"""Simulated testing machine: the `TestingMachine` protocol over a `MachineModel` and a `SimClock`.

URL: `sim://machine`. Constructed by the registry as `SimMachine(url, machine=..., clock=...)`.
The machine model (crosshead kinematics, specimen force) lives with the simulated world in the
appliance; this backend only puts it behind the controller interface, reading the shared clock
for every state and command.

What it does not model: communication latency and errors, controller sampling and filtering
of force, load-cell noise, command rejection by a real controller's interlocks.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

from hal.clock import SimClock
from hal.errors import HardwareConfigError
from hal.machine.base import MachineState


@runtime_checkable
class MachineModel(Protocol):
    """The simulated machine: state as a function of simulation time, and commands."""

    def state(self, t_s: float) -> MachineState:
        """State at simulation time `t_s` (timestamp_ns set from `t_s`)."""

    def start(self, speed_mm_min: float, t_s: float) -> None:
        """Start the crosshead at `speed_mm_min` at time `t_s`."""

    def stop(self, t_s: float) -> None:
        """Stop the crosshead at time `t_s`."""

    def return_to_start(self, speed_mm_min: float, t_s: float) -> None:
        """Drive back to the start position from time `t_s`."""


class SimMachine:
    """A testing machine controller that answers from a simulated machine.

    Args:
        url: the device URL (kept for messages).
        machine: the simulated machine.
        clock: the shared simulation clock.
        accepts_commands: whether start/stop/return are allowed (as configured on a real
            controller).
    """

    def __init__(
        self,
        url: str,
        *,
        machine: MachineModel,
        clock: SimClock,
        accepts_commands: bool = True,
        **_: Any,
    ) -> None:
        self.url = url
        self._machine = machine
        self._clock = clock
        self._accepts_commands = accepts_commands
        self._open = False

    def open(self, timeout_s: float = 5.0) -> None:
        self._open = True

    def close(self) -> None:
        self._open = False

    def read_state(self, timeout_s: float = 1.0) -> MachineState:
        return self._machine.state(self._clock.now_s())

    def start(self, speed_mm_min: float, timeout_s: float = 1.0) -> None:
        self._command("start")
        self._machine.start(speed_mm_min, self._clock.now_s())

    def stop(self, timeout_s: float = 1.0) -> None:
        self._command("stop")
        self._machine.stop(self._clock.now_s())

    def return_to_start(self, speed_mm_min: float, timeout_s: float = 1.0) -> None:
        self._command("return")
        self._machine.return_to_start(speed_mm_min, self._clock.now_s())

    def statistics(self) -> dict[str, Any]:
        """{}: the simulator keeps no client counters."""
        return {}

    def _command(self, name: str) -> None:
        if not self._accepts_commands:
            raise HardwareConfigError(f"{self.url}: controller does not accept command {name}")
