"""The testing machine interface: what the appliance reads from and asks of the machine.

Reading the state works on every controller. Commands (start at a speed, stop, return to the
start position) work only on controllers configured to accept them; the others raise
`HardwareConfigError` naming the command. Every call takes a timeout.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable


@dataclass(frozen=True)
class MachineState:
    """A snapshot of the machine.

    Attributes:
        crosshead_mm: crosshead position from its start, mm (positive = opening the grips).
        speed_mm_min: crosshead speed, mm/min.
        force_n: force on the load cell, N.
        running: the crosshead is commanded to move.
        timestamp_ns: controller (or simulation) time of the reading, ns.
        encoder_counts: crosshead encoder position, counts, where the controller exposes it.
    """

    crosshead_mm: float
    speed_mm_min: float
    force_n: float
    running: bool
    timestamp_ns: int
    encoder_counts: int | None = None


@runtime_checkable
class TestingMachine(Protocol):
    """A tensile testing machine's controller as the appliance uses it."""

    url: str

    def open(self, timeout_s: float = 5.0) -> None:
        """Connect. Raises HardwareConnectError."""

    def close(self) -> None:
        """Disconnect; safe to call twice."""

    def read_state(self, timeout_s: float = 1.0) -> MachineState:
        """Current state. Raises HardwareTimeout or HardwareConnectError."""

    def start(self, speed_mm_min: float, timeout_s: float = 1.0) -> None:
        """Start moving the crosshead at a speed (positive = tension)."""

    def stop(self, timeout_s: float = 1.0) -> None:
        """Stop the crosshead."""

    def return_to_start(self, speed_mm_min: float, timeout_s: float = 1.0) -> None:
        """Drive the crosshead back to its start position."""

    def statistics(self) -> dict[str, Any]:
        """The client's counters since construction (reads, requests, failures), JSON-ready;
        {} for a backend that keeps none."""
