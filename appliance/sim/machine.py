"""The simulated tensile machine: a crosshead pulling a specimen bar, read at any instant.

`MachineWithSpecimen` implements `hal.machine.sim.MachineModel`: the machine simulator asks it
for the state at a simulation time and passes commands on with their times. The camera simulator's
scene asks it for the specimen's shape at the instants it renders (`deformation_at`).

Everything is a function of the time and of the command history: the crosshead position is
piecewise-analytic in time (`appliance.sim.crosshead`), the force and shape follow from the
bar model (`appliance.sim.bar`) at that position and at the largest position reached before
it. The specimen breaks at the first instant the crosshead reaches the bar's breaking
displacement; from then on the force is 0.

Threads: commands (under a lock) replace an immutable snapshot of the plan and its break
time; readers take the snapshot without locking, so `state` and `deformation_at` may be called
from camera and machine threads while commands arrive from another.

What it does not model: machine and load-cell compliance, load-cell noise and filtering, an
automatic stop at break (the controller's job).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

from appliance.sim.bar import BarModel, BarState
from appliance.sim.crosshead import Crosshead, MotionPlan
from appliance.sim.deformation import AxialDeformation
from hal.machine.base import MachineState


@dataclass(frozen=True)
class _Snapshot:
    plan: MotionPlan
    broken_at_s: float | None


class MachineWithSpecimen:
    """A tensile machine with a specimen in its grips (implements `MachineModel`).

    Args:
        bar: the specimen as a bar model.
        crosshead: the crosshead kinematics (a fresh `Crosshead()` by default).
        encoder_counts_per_mm: crosshead encoder resolution, counts/mm; None for a
            controller without an encoder reading.
        speed_changes: the controller's speed program after every start: (seconds after
            the start, speed in mm/min), in increasing time (see `Crosshead.start`).
    """

    def __init__(
        self,
        bar: BarModel,
        crosshead: Crosshead | None = None,
        *,
        encoder_counts_per_mm: float | None = 1000.0,
        speed_changes: tuple[tuple[float, float], ...] = (),
    ) -> None:
        if encoder_counts_per_mm is not None and not encoder_counts_per_mm > 0:
            raise ValueError(f"encoder_counts_per_mm must be positive, got {encoder_counts_per_mm}")
        self.bar = bar
        self.crosshead = crosshead if crosshead is not None else Crosshead()
        self.encoder_counts_per_mm = encoder_counts_per_mm
        self.speed_changes = speed_changes
        self._lock = threading.Lock()
        self._snapshot = self._snapshot_of(self.crosshead.plan)

    def _snapshot_of(self, plan: MotionPlan) -> _Snapshot:
        return _Snapshot(plan, plan.first_time_at_or_beyond(self.bar.breaking_crosshead_mm))

    @property
    def broken_at(self) -> float | None:
        """Simulation time, s, at which the specimen breaks under the commands given so far.

        None if the present plan never reaches the breaking displacement. It may lie ahead of
        the present while the crosshead is still on its way; a later command can move it then.
        """
        return self._snapshot.broken_at_s

    def is_broken(self, t_s: float) -> bool:
        """Whether the specimen has broken by simulation time t_s."""
        broken_at = self._snapshot.broken_at_s
        return broken_at is not None and t_s >= broken_at

    def bar_state_at(self, t_s: float) -> BarState:
        """The specimen (force, phase, shape) at simulation time t_s, s."""
        return self._bar_state(self._snapshot, t_s)

    def _bar_state(self, snapshot: _Snapshot, t_s: float) -> BarState:
        position = float(snapshot.plan.position_mm_at(t_s))
        reached = float(snapshot.plan.max_position_mm_until(t_s))
        breaking = self.bar.breaking_crosshead_mm
        if snapshot.broken_at_s is not None and t_s >= snapshot.broken_at_s:
            reached = max(reached, math.nextafter(breaking, math.inf))
        else:
            reached = min(reached, breaking)
        return self.bar.deformation(position, max_crosshead_mm=max(reached, position))

    def deformation_at(self, t_s: float) -> AxialDeformation:
        """Shape of the specimen at simulation time t_s, s (for the camera's renderer)."""
        return self.bar_state_at(t_s).deformation

    def state(self, t_s: float) -> MachineState:
        """Controller state at simulation time t_s, s: crosshead, speed, force, encoder."""
        snapshot = self._snapshot
        position = float(snapshot.plan.position_mm_at(t_s))
        counts = (
            None
            if self.encoder_counts_per_mm is None
            else round(position * self.encoder_counts_per_mm)
        )
        return MachineState(
            crosshead_mm=position,
            speed_mm_min=60.0 * float(snapshot.plan.speed_mm_s_at(t_s)),
            force_n=self._bar_state(snapshot, t_s).force_n,
            running=bool(snapshot.plan.running_at(t_s)),
            timestamp_ns=round(t_s * 1e9),
            encoder_counts=counts,
        )

    def start(self, speed_mm_min: float, t_s: float) -> None:
        """Start the crosshead at `speed_mm_min` (positive = opening) at time t_s, followed
        by the speed program."""
        with self._lock:
            self._snapshot = self._snapshot_of(
                self.crosshead.start(speed_mm_min, t_s, self.speed_changes)
            )

    def stop(self, t_s: float) -> None:
        """Stop the crosshead (decelerating) at time t_s."""
        with self._lock:
            self._snapshot = self._snapshot_of(self.crosshead.stop(t_s))

    def return_to_start(self, speed_mm_min: float, t_s: float) -> None:
        """Drive back to the start position at |speed_mm_min| from time t_s."""
        with self._lock:
            self._snapshot = self._snapshot_of(self.crosshead.return_to_start(speed_mm_min, t_s))
