"""Trigger planning: the exposure plan turned into what the trigger microcontroller executes.

The exposure planner (`appliance.plan.exposure.plan_exposure`) gives, for a crosshead speed, the
longest exposure within the blur budget and the longest frame period within the tracker's
capture range. The trigger microcontroller fires the camera either

* at a fixed period in its clock ticks (`TriggerSource.PERIOD`): frame-to-frame motion then
  grows and shrinks with the speed, so the period must be re-planned when the speed changes;
* every N counts of the crosshead encoder (`TriggerSource.ENCODER`): frame-to-frame motion is
  fixed by the crosshead's displacement whatever the speed, so only the exposure (the blur)
  needs re-planning as the speed changes.

`plan_triggers` computes one `TriggerPlan` (source, pulse width, period in ticks or encoder
divisor, and the camera exposure); `TriggerReplanner` decides, from the controller's speed
readings, when a new plan is due: when the speed has moved by more than a relative
hysteresis from the speed the plan in force was made for (so a noisy speed reading does not
re-program the devices with every frame), at once when faster, after a dwell when slower.

The pulse width is the camera's trigger input width: cameras triggered on the rising edge
take their exposure time from their own setting, so the pulse only has to be long enough for
the input's debounce (60 us by default: well above the few us camera inputs need, and above
the firmware's 50 us minimum).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from appliance.config import TriggerConfig
from appliance.plan.exposure import ExposurePlan

DEFAULT_PULSE_WIDTH_US = 60.0


@dataclass(frozen=True)
class TriggerPlan:
    """What the trigger microcontroller and the camera are set to for one speed.

    Attributes:
        source: "period" or "encoder".
        speed_mm_min: the crosshead speed the plan was made for.
        exposure_us: camera exposure, us.
        pulse_width_ticks: trigger pulse width, MCU ticks.
        period_ticks: trigger period, MCU ticks (period source; 0 otherwise).
        encoder_divisor: encoder counts between triggers (encoder source; 0 otherwise).
        frame_period_s: time from one frame to the next at `speed_mm_min`, s.
        motion_per_frame_mm: crosshead travel from one frame to the next at that speed, mm.
    """

    source: str
    speed_mm_min: float
    exposure_us: float
    pulse_width_ticks: int
    period_ticks: int
    encoder_divisor: int
    frame_period_s: float
    motion_per_frame_mm: float


def plan_triggers(
    plan: ExposurePlan,
    *,
    tick_hz: float,
    counts_per_mm: float | None = None,
    pulse_width_us: float = DEFAULT_PULSE_WIDTH_US,
) -> TriggerPlan:
    """The trigger plan of an exposure plan.

    With `counts_per_mm` (the crosshead encoder's resolution) the triggers follow the
    encoder: the divisor is the planned frame-to-frame crosshead travel in counts, rounded
    down (at least 1), so the frame-to-frame motion never exceeds the planned one. Without it,
    or at speed 0 (an encoder that does not move gives no frames), the triggers follow the
    planned period, rounded down to whole ticks.

    Args:
        plan: the exposure plan for the current speed.
        tick_hz: the microcontroller's tick rate, Hz.
        counts_per_mm: encoder counts per mm of crosshead travel; None = no encoder.
        pulse_width_us: trigger pulse width, us (> 0, shorter than the period).

    Raises:
        ValueError: a non-positive tick rate, resolution or pulse width, or a pulse not
            shorter than the period.
    """
    if not (tick_hz > 0 and math.isfinite(tick_hz)):
        raise ValueError(f"tick_hz must be > 0, got {tick_hz}")
    if counts_per_mm is not None and not counts_per_mm > 0:
        raise ValueError(f"counts_per_mm must be > 0, got {counts_per_mm}")
    if not pulse_width_us > 0:
        raise ValueError(f"pulse_width_us must be > 0, got {pulse_width_us}")
    width = max(1, round(pulse_width_us * 1e-6 * tick_hz))
    speed_mm_s = plan.speed_mm_min / 60.0
    travel_mm = speed_mm_s * plan.frame_period_s
    if counts_per_mm is not None and speed_mm_s > 0:
        divisor = max(1, math.floor(travel_mm * counts_per_mm))
        travel_mm = divisor / counts_per_mm
        period_s = travel_mm / speed_mm_s
        if width >= period_s * tick_hz:
            raise ValueError(
                f"a pulse of {pulse_width_us:g} us does not fit one encoder step of "
                f"{period_s * 1e6:g} us at {plan.speed_mm_min:g} mm/min"
            )
        return TriggerPlan(
            "encoder",
            plan.speed_mm_min,
            plan.exposure_s * 1e6,
            width,
            0,
            divisor,
            period_s,
            travel_mm,
        )
    period_ticks = math.floor(plan.frame_period_s * tick_hz)
    if width >= period_ticks:
        raise ValueError(
            f"a pulse of {pulse_width_us:g} us does not fit the period of "
            f"{plan.frame_period_s * 1e6:g} us"
        )
    period_s = period_ticks / tick_hz
    return TriggerPlan(
        "period",
        plan.speed_mm_min,
        plan.exposure_s * 1e6,
        width,
        period_ticks,
        0,
        period_s,
        speed_mm_s * period_s,
    )


def configured_trigger_plan(
    trigger: TriggerConfig, exposure: ExposurePlan, tick_hz: float
) -> TriggerPlan:
    """The trigger plan of an exposure plan for `[trigger]` (period or encoder source: the
    encoder's resolution is used only with the encoder source).

    Raises:
        ValueError: the pulse does not fit (see `plan_triggers`).
    """
    encoder = trigger.source == "encoder"
    return plan_triggers(
        exposure,
        tick_hz=tick_hz,
        counts_per_mm=trigger.encoder_counts_per_mm if encoder else None,
        pulse_width_us=trigger.pulse_width_us,
    )


def free_running_plan(exposure: ExposurePlan) -> TriggerPlan:
    """The plan of a free-running camera (internal trigger source): no pulses, only the
    exposure and the frame period of `exposure`."""
    return TriggerPlan(
        "internal",
        exposure.speed_mm_min,
        exposure.exposure_s * 1e6,
        0,
        0,
        0,
        exposure.frame_period_s,
        exposure.speed_mm_min / 60.0 * exposure.frame_period_s,
    )


class TriggerReplanner:
    """Decides, from the controller's speed readings, when a new trigger plan is due.

    Being planned for a speed slower than the crosshead's is the dangerous side (blur and
    frame-to-frame motion beyond budget, tracking lost), being planned for a faster one only
    costs light and frames; so the decision is asymmetric:

    * faster: a speed more than `hysteresis` above the speed planned for is due at once;
    * slower: a speed more than `hysteresis` below it is due only once every reading for
      `slow_down_after_s` has been below it; the plan is then made for the fastest of those
      readings (a ramp or a noisy reading does not slow the frames down);
    * standing still: a speed below `min_speed_mm_min` never re-plans. The plan in force
      stays, so a crosshead that restarts is caught at the frame rate it had (a stop or a
      hold at the end of a test does not slow the frames down to one a second).

    Args:
        planned_for: the speed the plan in force was made for, mm/min (the test speed).
        hysteresis: relative speed change that calls for a new plan (0.1 = 10 %; > 0).
        slow_down_after_s: how long the speed must stay below the planned one, s (>= 0).
        min_speed_mm_min: speeds below this count as standing still.
    """

    def __init__(
        self,
        planned_for: float,
        *,
        hysteresis: float = 0.1,
        slow_down_after_s: float = 2.0,
        min_speed_mm_min: float = 0.01,
    ) -> None:
        if not hysteresis > 0:
            raise ValueError(f"hysteresis must be > 0, got {hysteresis}")
        if not slow_down_after_s >= 0:
            raise ValueError(f"slow_down_after_s must be >= 0, got {slow_down_after_s}")
        self.planned_for = abs(planned_for)
        self.hysteresis = hysteresis
        self.slow_down_after_s = slow_down_after_s
        self.min_speed_mm_min = min_speed_mm_min
        self._slower_since: float | None = None
        self._fastest_slower = 0.0

    def due(self, speed_mm_min: float, t_s: float) -> float | None:
        """The speed to plan for now, given a reading of `speed_mm_min` at time `t_s` (s, any
        monotonic clock); None while the plan in force still fits. A returned speed becomes
        the speed planned for."""
        speed = abs(speed_mm_min)
        if speed < self.min_speed_mm_min or not math.isfinite(speed):
            self._slower_since = None
            return None
        planned = self.planned_for
        if speed > planned * (1.0 + self.hysteresis) or planned < self.min_speed_mm_min:
            return self._accept(speed)
        if speed >= planned * (1.0 - self.hysteresis):
            self._slower_since = None
            return None
        if self._slower_since is None:
            self._slower_since, self._fastest_slower = t_s, speed
        else:
            self._fastest_slower = max(self._fastest_slower, speed)
        if t_s - self._slower_since >= self.slow_down_after_s:
            return self._accept(self._fastest_slower)
        return None

    def _accept(self, speed: float) -> float:
        self.planned_for = speed
        self._slower_since = None
        return speed
