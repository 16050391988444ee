"""Exposure pacing: the camera's exposure and the trigger spacing follow the crosshead speed.

The exposure plan of a test is made for its configured speed. When the speed changes during
the test (a two-speed test program, an operator's override) the blur of an exposure and the
motion from one frame to the next change with it. `ExposurePacer` watches the speed the machine's
controller reports with every frame and, when `appliance.plan.trigger_plan.TriggerReplanner` says
a new plan is due, makes one for the new speed and applies it while acquiring:

* the camera's exposure (`Camera.set_exposure`), so the blur stays within budget;
* the trigger's spacing (`TriggerTimer.retime`: the firmware's RETIME over the serial link,
  or the simulated trigger microcontroller): the period for period triggering, the encoder
  divisor for encoder triggering. A free-running camera (internal trigger source) keeps its
  frame rate; only its exposure follows.

A new plan is made for the top of the hysteresis band around the speed read,
`speed * (1 + hysteresis)`: the next re-planning is due only when the speed leaves the band,
so the blur and the frame-to-frame motion stay within budget all the while (a frame or so of
latency apart), at the cost of exposures up to that fraction shorter than needed.

A plan that cannot be made or applied (a pulse that no longer fits the period, a device that
refuses) leaves the plan in force in place: the test goes on, the failure is kept in
`replans` with its reason and counted, and the caller is told (`on_replan`) so it can log it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from appliance.plan.trigger_plan import TriggerPlan, TriggerReplanner
from hal.camera.base import Camera
from hal.errors import HardwareError
from hal.machine.base import MachineState


class TriggerTimer(Protocol):
    """What spaces the camera's triggers while armed."""

    def retime(self, plan: TriggerPlan) -> None:
        """Apply `plan`'s period or encoder divisor from the next trigger on."""


@dataclass(frozen=True)
class Replan:
    """One re-planning during a test.

    Attributes:
        time_s: time of the frame whose controller reading called for it, s since the
            reference (the strain file's time axis).
        speed_mm_min: the speed read that called for it, mm/min (the plan is made for the
            top of the hysteresis band above it).
        exposure_us: the exposure in force afterwards, us.
        period_ticks: trigger period in ticks (period triggering; 0 otherwise).
        encoder_divisor: encoder counts per trigger (encoder triggering; 0 otherwise).
        frame_period_s: frame period at that speed, s.
        error: why the plan was not applied; "" when it was.
    """

    time_s: float
    speed_mm_min: float
    exposure_us: float
    period_ticks: int
    encoder_divisor: int
    frame_period_s: float
    error: str = ""

    def describe(self) -> str:
        """One line for the log."""
        spacing = (
            f"encoder divisor {self.encoder_divisor}"
            if self.encoder_divisor
            else f"period {self.frame_period_s * 1e3:.3f} ms"
        )
        head = f"re-planned for {self.speed_mm_min:g} mm/min at {self.time_s:.3f} s"
        if self.error:
            return f"{head} failed, plan in force kept: {self.error}"
        return f"{head}: exposure {self.exposure_us:g} us, {spacing}"


class ExposurePacer:
    """Re-plans exposure and trigger spacing from the controller's speed readings.

    Args:
        make_plan: the trigger plan for a speed, mm/min (raises ValueError when none fits).
        replanner: decides when a new plan is due; starts at the test speed.
        camera: the armed camera whose exposure follows.
        timer: what spaces the triggers; None for a free-running camera.
        exposure_us: the exposure in force at the start, us.
        on_replan: called with every `Replan` (on the calling thread).
    """

    def __init__(
        self,
        make_plan: Callable[[float], TriggerPlan],
        replanner: TriggerReplanner,
        camera: Camera,
        timer: TriggerTimer | None,
        *,
        exposure_us: float,
        on_replan: Callable[[Replan], None] | None = None,
    ) -> None:
        self.make_plan = make_plan
        self.replanner = replanner
        self.camera = camera
        self.timer = timer
        self.exposure_us = exposure_us
        self.on_replan = on_replan
        self.replans: list[Replan] = []

    @property
    def failures(self) -> int:
        """Re-plannings that could not be applied."""
        return sum(1 for replan in self.replans if replan.error)

    def follow(self, time_s: float, state: MachineState | None) -> None:
        """Look at the controller reading taken with the frame of `time_s` (s since the
        reference; None = no reading this frame) and re-plan if due.

        Called on the acquisition thread after each frame; it blocks for the device writes
        (a serial round trip and a camera register write) only when a plan is applied.
        """
        if state is None or not math.isfinite(state.speed_mm_min):
            return
        speed = self.replanner.due(state.speed_mm_min, time_s)
        if speed is None:
            return
        try:
            plan = self.make_plan(speed * (1.0 + self.replanner.hysteresis))
        except ValueError as exc:
            self._note(Replan(time_s, speed, self.exposure_us, 0, 0, math.nan, str(exc)))
            return
        error = ""
        try:
            if self.timer is not None:
                self.timer.retime(plan)
            if not math.isclose(plan.exposure_us, self.exposure_us, rel_tol=1e-9):
                self.exposure_us = self.camera.set_exposure(plan.exposure_us)
        except (HardwareError, ValueError, OSError) as exc:
            error = f"{type(exc).__name__}: {exc}"
        self._note(
            Replan(
                time_s,
                speed,
                self.exposure_us,
                plan.period_ticks,
                plan.encoder_divisor,
                plan.frame_period_s,
                error,
            )
        )

    def _note(self, replan: Replan) -> None:
        self.replans.append(replan)
        if self.on_replan is not None:
            self.on_replan(replan)
