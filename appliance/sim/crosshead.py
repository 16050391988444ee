"""Crosshead kinematics of a simulated testing machine: speed commands with acceleration limits.

The crosshead position is measured from its start, positive when the grips open (tension).
Commands arrive in time order, each with its time stamp: start at a speed (optionally with a
speed program that follows, as a controller's test program changes speed), stop, return to
the start position. Each replaces whatever motion the previous command had planned from its
time on. Between commands the motion is a sequence of constant-acceleration segments
(trapezoidal speed profiles with acceleration magnitude `max_acceleration_mm_s2`), so
position and speed are exact piecewise-quadratic and piecewise-linear functions of time, and
position is continuous with continuous speed.

What it does not model: jerk limits, servo lag and overshoot, backlash, machine compliance.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class MotionPlan:
    """An immutable motion history and plan: constant-acceleration segments.

    Segment i starts at `start_s[i]` with position `position_mm[i]`, speed `speed_mm_s[i]`
    and lasts, with acceleration `acceleration_mm_s2[i]`, until the next one starts; the last
    lasts forever with zero acceleration. Before the first segment the crosshead rests at 0.

    Attributes:
        start_s: (k,) segment start times, s, non-decreasing.
        position_mm: (k,) positions at the segment starts, mm.
        speed_mm_s: (k,) speeds at the segment starts, mm/s.
        acceleration_mm_s2: (k,) accelerations, mm/s^2.
        commanded: (k,) the crosshead is commanded to move during the segment (a start or
            a return under way; not a stop).
    """

    start_s: FloatArray
    position_mm: FloatArray
    speed_mm_s: FloatArray
    acceleration_mm_s2: FloatArray
    commanded: npt.NDArray[np.bool_]

    def _segment(self, t: FloatArray) -> tuple[npt.NDArray[np.intp], FloatArray]:
        index = np.clip(np.searchsorted(self.start_s, t, side="right") - 1, 0, None)
        return index, np.maximum(t - self.start_s[index], 0.0)

    def position_mm_at(self, t_s: npt.ArrayLike) -> FloatArray:
        """Crosshead position, mm, at times t_s (any shape)."""
        t = np.asarray(t_s, np.float64)
        index, dt = self._segment(t)
        return (
            self.position_mm[index]
            + self.speed_mm_s[index] * dt
            + 0.5 * self.acceleration_mm_s2[index] * dt * dt
        )

    def speed_mm_s_at(self, t_s: npt.ArrayLike) -> FloatArray:
        """Crosshead speed, mm/s, at times t_s (any shape)."""
        t = np.asarray(t_s, np.float64)
        index, dt = self._segment(t)
        return self.speed_mm_s[index] + self.acceleration_mm_s2[index] * dt

    def running_at(self, t_s: npt.ArrayLike) -> npt.NDArray[np.bool_]:
        """Whether the crosshead is commanded to move at times t_s."""
        index, _ = self._segment(np.asarray(t_s, np.float64))
        return self.commanded[index]

    def _durations(self) -> FloatArray:
        return np.append(np.diff(self.start_s), np.inf)

    def _segment_maxima(self) -> FloatArray:
        duration = self._durations()
        span = np.where(np.isfinite(duration), duration, 0.0)
        x0, v0, a = self.position_mm, self.speed_mm_s, self.acceleration_mm_s2
        end = x0 + v0 * span + 0.5 * a * span * span
        end = np.where(np.isfinite(duration), end, np.where(v0 > 0, np.inf, x0))
        turn = np.where(a < 0, np.clip(-v0 / np.where(a < 0, a, 1.0), 0.0, span), 0.0)
        at_turn = x0 + v0 * turn + 0.5 * a * turn * turn
        return np.maximum(np.maximum(x0, end), at_turn)

    def max_position_mm_until(self, t_s: npt.ArrayLike) -> FloatArray:
        """Largest position reached at or before t_s, mm (0 before any motion)."""
        t = np.asarray(t_s, np.float64)
        index, dt = self._segment(t)
        before = np.concatenate([[0.0], np.maximum.accumulate(self._segment_maxima())])[index]
        x0 = self.position_mm[index]
        v0 = self.speed_mm_s[index]
        a = self.acceleration_mm_s2[index]
        turn = np.where(a < 0, np.clip(-v0 / np.where(a < 0, a, 1.0), 0.0, dt), 0.0)
        now = x0 + v0 * dt + 0.5 * a * dt * dt
        inside = np.maximum(np.maximum(x0, now), x0 + v0 * turn + 0.5 * a * turn * turn)
        return np.maximum(np.maximum(before, inside), 0.0)

    def first_time_at_or_beyond(self, position_mm: float) -> float | None:
        """Earliest time, s, at which the position reaches `position_mm` (> 0), or None."""
        durations = self._durations()
        for k in range(self.start_s.size):
            x0 = float(self.position_mm[k])
            v0 = float(self.speed_mm_s[k])
            a = float(self.acceleration_mm_s2[k])
            distance = position_mm - x0
            if distance <= 0.0:
                return float(self.start_s[k])
            discriminant = v0 * v0 + 2.0 * a * distance
            if discriminant < 0.0:
                continue
            # Roots of a/2 tau^2 + v0 tau - distance = 0, in the cancellation-free form.
            q = -0.5 * (v0 + math.copysign(math.sqrt(discriminant), v0))
            roots = []
            if a != 0.0:
                roots.append(q / (0.5 * a))
            if q != 0.0:
                roots.append(-distance / q)
            reached = [tau for tau in roots if 0.0 <= tau <= durations[k]]
            if reached:
                return float(self.start_s[k]) + min(reached)
        return None


@dataclass(frozen=True)
class _Moves:
    phases: list[tuple[float, float]]
    end_speed_mm_s: float
    end_position_mm: float | None


def _rest_plan() -> MotionPlan:
    return MotionPlan(
        np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1, dtype=np.bool_)
    )


class Crosshead:
    """The crosshead's motion under speed commands, with an acceleration limit.

    Args:
        max_acceleration_mm_s2: magnitude of every acceleration and deceleration, mm/s^2
            (electromechanical frames reach test speed within tens of milliseconds).

    Thread safety: commands may come from one thread while others read; readers see either
    the plan before a command or after it, never a mixture.
    """

    def __init__(self, *, max_acceleration_mm_s2: float = 100.0) -> None:
        if not (math.isfinite(max_acceleration_mm_s2) and max_acceleration_mm_s2 > 0):
            raise ValueError(
                f"max_acceleration_mm_s2 must be positive, got {max_acceleration_mm_s2}"
            )
        self.max_acceleration_mm_s2 = float(max_acceleration_mm_s2)
        self._lock = threading.Lock()
        self._plan = _rest_plan()
        self._last_command_s = -math.inf

    @property
    def plan(self) -> MotionPlan:
        """The current motion plan (an immutable snapshot)."""
        return self._plan

    def position_mm(self, t_s: npt.ArrayLike) -> FloatArray:
        """Position from the start, mm, at times t_s."""
        return self._plan.position_mm_at(t_s)

    def speed_mm_min(self, t_s: npt.ArrayLike) -> FloatArray:
        """Speed, mm/min, at times t_s (positive = opening)."""
        return 60.0 * self._plan.speed_mm_s_at(t_s)

    def running(self, t_s: float) -> bool:
        """Whether the crosshead is commanded to move at time t_s."""
        return bool(self._plan.running_at(t_s))

    def start(
        self,
        speed_mm_min: float,
        t_s: float,
        speed_changes: Sequence[tuple[float, float]] = (),
    ) -> MotionPlan:
        """From t_s, ramp to `speed_mm_min` (signed; positive = opening) and hold it.

        Args:
            speed_mm_min: the speed to ramp to, mm/min.
            t_s: the command's time, s.
            speed_changes: a speed program that follows the start: (seconds after t_s,
                speed in mm/min), in increasing time, each ramping to its speed as a start
                would. The next command (a stop, say) replaces what is left of it.

        Returns:
            The new plan.
        """
        steps = [(0.0, speed_mm_min), *speed_changes]
        for index, (after_s, speed) in enumerate(steps):
            if not math.isfinite(speed):
                raise ValueError(f"speed_mm_min must be finite, got {speed}")
            if index and not (math.isfinite(after_s) and after_s > steps[index - 1][0]):
                raise ValueError(f"speed change times must increase, got {after_s} s")

        def ramp_to(target: float) -> Callable[[float, float], _Moves]:
            return lambda x, v: self._ramp(x, v, target)

        return self._command(
            t_s,
            [(t_s + after_s, ramp_to(speed / 60.0), speed != 0.0) for after_s, speed in steps],
        )

    def stop(self, t_s: float) -> MotionPlan:
        """From t_s, decelerate to rest. Returns the new plan."""
        return self._command(t_s, [(t_s, lambda x, v: self._ramp(x, v, 0.0), False)])

    def return_to_start(self, speed_mm_min: float, t_s: float) -> MotionPlan:
        """From t_s, drive to position 0 at up to |speed_mm_min| and stop there.

        A crosshead moving away from the start, or too fast to stop in time, first brakes
        to rest. Returns the new plan.
        """
        speed = abs(speed_mm_min) / 60.0
        if not (math.isfinite(speed) and speed > 0):
            raise ValueError(f"return speed must be non-zero and finite, got {speed_mm_min}")
        return self._command(t_s, [(t_s, lambda x, v: self._move_to(x, v, 0.0, speed), True)])

    def _ramp(self, position: float, speed: float, target: float) -> _Moves:
        if speed == target:
            return _Moves([], target, None)
        acceleration = math.copysign(self.max_acceleration_mm_s2, target - speed)
        return _Moves(
            [(abs(target - speed) / self.max_acceleration_mm_s2, acceleration)], target, None
        )

    def _move_to(self, position: float, speed: float, target: float, cruise: float) -> _Moves:
        a = self.max_acceleration_mm_s2
        phases: list[tuple[float, float]] = []
        distance = target - position
        overshoots = speed * speed / (2.0 * a) > abs(distance)
        if speed != 0.0 and (speed * distance <= 0.0 or overshoots):
            phases.append((abs(speed) / a, -math.copysign(a, speed)))
            position += speed * abs(speed) / (2.0 * a)
            speed = 0.0
            distance = target - position
        direction = math.copysign(1.0, distance)
        length, u = abs(distance), abs(speed)
        if length == 0.0:
            return _Moves(phases, 0.0, target)
        if u > cruise:
            coast = (length - u * u / (2.0 * a)) / cruise
            phases += [
                ((u - cruise) / a, -direction * a),
                (coast, 0.0),
                (cruise / a, -direction * a),
            ]
            return _Moves(phases, 0.0, target)
        peak = math.sqrt(a * length + 0.5 * u * u)
        if peak <= cruise:
            phases += [((peak - u) / a, direction * a), (peak / a, -direction * a)]
            return _Moves(phases, 0.0, target)
        coast = (length - (2.0 * cruise * cruise - u * u) / (2.0 * a)) / cruise
        phases += [((cruise - u) / a, direction * a), (coast, 0.0), (cruise / a, -direction * a)]
        return _Moves(phases, 0.0, target)

    def _command(
        self,
        t_s: float,
        steps: Sequence[tuple[float, Callable[[float, float], _Moves], bool]],
    ) -> MotionPlan:
        """Apply a command at t_s: its steps (time, planner, commanded), in time order, each
        replacing the motion planned from its time on; one new plan for readers."""
        t_s = float(t_s)
        if not math.isfinite(t_s):
            raise ValueError(f"command time must be finite, got {t_s}")
        with self._lock:
            if t_s < self._last_command_s:
                raise ValueError(
                    f"command at {t_s} s precedes the previous command at {self._last_command_s} s"
                )
            plan = self._plan
            for step_s, planner, commanded in steps:
                plan = _replanned(plan, float(step_s), planner, commanded)
            self._plan = plan
            self._last_command_s = t_s
            return self._plan


def _replanned(
    plan: MotionPlan, t_s: float, planner: Callable[[float, float], _Moves], commanded: bool
) -> MotionPlan:
    """`plan` up to t_s, then the moves `planner` gives from the position and speed there."""
    position = float(plan.position_mm_at(t_s))
    speed = float(plan.speed_mm_s_at(t_s))
    keep = plan.start_s < t_s
    starts = list(plan.start_s[keep])
    positions = list(plan.position_mm[keep])
    speeds = list(plan.speed_mm_s[keep])
    accelerations = list(plan.acceleration_mm_s2[keep])
    flags = list(plan.commanded[keep])
    moves = planner(position, speed)
    time = t_s
    for duration, acceleration in moves.phases:
        if duration <= 0.0:
            continue
        starts.append(time)
        positions.append(position)
        speeds.append(speed)
        accelerations.append(acceleration)
        flags.append(commanded)
        position += speed * duration + 0.5 * acceleration * duration * duration
        speed += acceleration * duration
        time += duration
    starts.append(time)
    positions.append(position if moves.end_position_mm is None else moves.end_position_mm)
    speeds.append(moves.end_speed_mm_s)
    accelerations.append(0.0)
    flags.append(commanded and moves.end_speed_mm_s != 0.0)
    return MotionPlan(
        np.array(starts, np.float64),
        np.array(positions, np.float64),
        np.array(speeds, np.float64),
        np.array(accelerations, np.float64),
        np.array(flags, np.bool_),
    )
