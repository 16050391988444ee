"""The simulated trigger microcontroller: camera trigger edges from a plan and the crosshead.

It stands where the real microcontroller (`firmware_bridge`) stands in a simulated test: it
is configured with a `appliance.plan.trigger_plan.TriggerPlan` and armed at a simulation time, and
answers the simulated camera's trigger input (`hal.camera.sim.TriggerLine`) with the time of
the next rising edge:

* period source: edges at arm time + k * period (the period in ticks at `tick_hz`, so the
  rounding to whole ticks is the real one);
* encoder source: an edge each time the crosshead encoder (the machine's position times its
  counts per mm, as the simulated machine reports it) has advanced by the divisor since the
  last edge, found exactly from the crosshead's motion plan.

Every edge is kept as a `SimTriggerEvent` (sequence number from 1, time, encoder position),
as the firmware reports TRIGGER events. `retime` changes the period or divisor of the armed
trigger from the last edge on, as the firmware's RETIME message does. What it does not
model: pulse width (the simulated camera takes the rising edge), jitter (edges are exact), a
dead-man, or reverse motion (the encoder source follows forward travel only, like the
firmware).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

from appliance.plan.trigger_plan import TriggerPlan
from appliance.sim.machine import MachineWithSpecimen


@dataclass(frozen=True)
class SimTriggerEvent:
    """One trigger edge: its number (1 = the first after arming), simulation time, s, and
    encoder counts."""

    trigger_seq: int
    time_s: float
    position_counts: int


class SimTriggerController:
    """Edges for the simulated camera's trigger input.

    Args:
        machine: the simulated machine (crosshead motion and encoder resolution).
        tick_hz: the simulated microcontroller's tick rate, Hz.
    """

    def __init__(self, machine: MachineWithSpecimen, *, tick_hz: float = 2_000_000.0) -> None:
        self.machine = machine
        self.tick_hz = tick_hz
        self.events: list[SimTriggerEvent] = []
        self._plan: TriggerPlan | None = None
        self._armed_at_s: float | None = None
        self._base: tuple[int, float, int] = (0, 0.0, 0)
        self._lock = threading.Lock()

    def configure(self, plan: TriggerPlan) -> None:
        """Set the plan (while disarmed). Raises ValueError for an encoder plan on a machine
        without an encoder."""
        if plan.source == "encoder" and self.machine.encoder_counts_per_mm is None:
            raise ValueError("encoder triggering needs a machine with an encoder")
        with self._lock:
            self._plan = plan

    def arm(self, t_s: float) -> None:
        """Start triggering at simulation time `t_s` (the first edge is at `t_s`)."""
        with self._lock:
            if self._plan is None:
                raise ValueError("arm before configure")
            self._armed_at_s = t_s
            self._base = (0, t_s, self._counts_at(t_s))
            self.events = []

    def disarm(self) -> None:
        """Stop triggering."""
        with self._lock:
            self._armed_at_s = None

    def retime(self, plan: TriggerPlan) -> None:
        """Change the spacing of the armed trigger, as the firmware's RETIME does: edges
        already fired stay, the next ones follow `plan`'s period (from the last edge) or
        divisor (from the last edge's encoder position). Sequence numbers continue. Raises
        ValueError for a plan of another source, or when disarmed."""
        with self._lock:
            current = self._plan
            if current is None or self._armed_at_s is None:
                raise ValueError("retime while disarmed")
            if plan.source != current.source:
                raise ValueError(f"retime from {current.source} to {plan.source} triggering")
            if self.events:
                last = self.events[-1]
                self._base = (len(self.events) - 1, last.time_s, last.position_counts)
            self._plan = plan

    def next_edge_s(self, after_s: float) -> float | None:
        """The first edge after `after_s` (the camera's trigger input asks). Period edges the
        camera was too late for are fired all the same (and kept as events), as a real
        microcontroller's would be."""
        with self._lock:
            plan, armed = self._plan, self._armed_at_s
            if plan is None or armed is None:
                return None
            tick_s = 1.0 / self.tick_hz
            base_index, base_s, base_counts = self._base
            while True:
                n = len(self.events)
                if plan.source == "period":
                    edge = base_s + (n - base_index) * plan.period_ticks * tick_s
                else:
                    target = base_counts + (n - base_index) * plan.encoder_divisor
                    edge = self._time_at_counts(target, max(armed, after_s + tick_s))
                    if edge is None:
                        return None
                self.events.append(SimTriggerEvent(n + 1, edge, self._counts_at(edge)))
                if edge > after_s:
                    return edge

    def _counts_at(self, t_s: float) -> int:
        per_mm = self.machine.encoder_counts_per_mm
        if per_mm is None:
            return 0
        return round(float(self.machine.crosshead.position_mm(t_s)) * per_mm)

    def _time_at_counts(self, counts: int, not_before_s: float) -> float | None:
        per_mm = self.machine.encoder_counts_per_mm
        assert per_mm is not None
        position = (counts - 0.5) / per_mm
        if position <= 0.0:
            return not_before_s
        reached = self.machine.crosshead.plan.first_time_at_or_beyond(position)
        if reached is None:
            return None
        return max(reached, not_before_s)
