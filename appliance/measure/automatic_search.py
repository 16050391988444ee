"""The search the mark tracker picks by itself, from the blur and the stretch it measures.

With `[tracking] reacquire_search = "auto"` (or `search = "auto"`) `MarkTracker` picks that
stage's integer search through the decision function `extensometer track` uses
(`appliance.dic.search_choice.choose_search`, backed by the search benchmark's table), from
what the tracker knows of the frames and nothing else:

* the blur of each mark: its speed, px/s (its velocity from its positions in the last two
  frames, the velocity the tracker predicts with), times the frame's exposure, along the
  loading axis; no motion known (before the second frame) is no blur;
* the expected one-step stretch: the true strain rate along the loading axis between the two
  marks farthest apart along it, ((v_j - v_i) . a) / ((p_j - p_i) . a) in 1/s, over the time
  between frames, as an engineering strain exp(rate dt) - 1; untold (None) until both marks'
  velocities are measured, or with fewer than two marks.

The one-step stretch is handed to the decision in steps of `STRETCH_QUANTUM` (half the
pre-warps' strain step, `appliance.dic.stretch.STRETCH_STEP`: 2.5 %, which moves the ends of
a 41 px subset by half a pixel); the step in force changes when the measured stretch is more
than `STRETCH_HOLD` (three quarters) of a step from it, so a stretch that hovers about the
middle between two steps does not flip it. The decision is made again for a mark when its
blur has moved by more than `blur_tolerance_px` from the blur the last decision used, or the
stepped stretch changes; a decision that changes the search the tracker runs (the method, the
LPQ window or the pre-warps' stretch) is a `SearchChoiceChange` with the inputs it used, which
the tracker hands to its listeners (the run logs it) and keeps in order. A blur that varies
from frame to frame (vibration) thus does not make a line of every frame.

What the tracker takes from a choice: its method (LPQ at the window of the blur rule for the
mark's subset, `appliance.dic.lpq.window_for_blur`, or ZNCC) and its pre-warps over the
one-step stretch, applied about the mark's current deformation (the deformation since the
mark's reference, which the next frame stretches by one step more). The reference is blurred
to match by the tracker's own rule (its first reference by the mark's blur; a later reference
is a frame exposed at the same speed). The recovery of rejected points a choice names is
`extensometer track`'s; the tracker's own is the estimate of a failed point from the other
points of its mark.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from appliance.dic.search_choice import SearchChoice, choose_search
from appliance.dic.stretch import STRETCH_STEP

__all__ = [
    "AUTO",
    "AutomaticSearch",
    "SearchChoiceChange",
    "SearchInputs",
    "axial_strain_rate_per_s",
    "prewarps_about",
]

AUTO = "auto"
"""The setting that hands a stage's search to the automatic choice."""

STRETCH_QUANTUM = STRETCH_STEP / 2
"""Step in which the one-step stretch is handed to the decision."""

STRETCH_HOLD = 0.75
"""How far, in steps, the measured stretch must be from the step in force to change it."""

LARGEST_ONE_STEP_STRETCH = (-0.45, 3.0)
"""Range the one-step stretch is clipped to before pre-warps are made of it (their limits)."""

STAGE_NAMES = {"track": "every-frame search", "reacquire": "re-acquisition"}


@dataclass(frozen=True)
class SearchInputs:
    """What one automatic choice was made from, for one mark.

    Attributes:
        blur_px: the mark's expected motion blur, px (`speed_px_s` x `exposure_s`).
        speed_px_s: the mark's speed, px/s (0 until measured).
        exposure_s: the frame's exposure, s (0 = unknown: before the first frame).
        strain_rate_per_s: true strain rate along the loading axis, 1/s; None = not measured.
        frame_interval_s: time since the previous frame, s; None before the second frame.
    """

    blur_px: float
    speed_px_s: float
    exposure_s: float
    strain_rate_per_s: float | None
    frame_interval_s: float | None

    @property
    def one_step_stretch(self) -> float | None:
        """Engineering strain expected between this frame and the previous one, or None."""
        if self.strain_rate_per_s is None or not self.frame_interval_s:
            return None
        low, high = LARGEST_ONE_STEP_STRETCH
        return min(high, max(low, math.expm1(self.strain_rate_per_s * self.frame_interval_s)))

    def stretch_range(self) -> tuple[float, float] | None:
        """The one-step stretch as the range the pre-warps cover: from 0 (the mark's current
        deformation) to the expected step in whole `STRETCH_QUANTUM`s, or None when untold."""
        step = self.one_step_stretch
        if step is None:
            return None
        stepped = math.floor(step / STRETCH_QUANTUM + 0.5) * STRETCH_QUANTUM
        return (min(0.0, stepped), max(0.0, stepped))

    def describe(self) -> dict:
        """The inputs as JSON fields."""
        return {
            "blur_px": self.blur_px,
            "speed_px_s": self.speed_px_s,
            "exposure_s": self.exposure_s,
            "strain_rate_per_s": self.strain_rate_per_s,
            "frame_interval_s": self.frame_interval_s,
            "one_step_stretch": self.one_step_stretch,
        }


@dataclass(frozen=True)
class SearchChoiceChange:
    """One automatic choice of a mark's search, with what it was made from.

    Attributes:
        time_s: time of the frame it was made for (the tracker's clock), s; None = made on
            the reference frame, before any frame was tracked.
        mark: index of the mark (the tracker's order of marks).
        stages: the stages that follow the choice: "track" (every frame), "reacquire".
        inputs: what the choice was made from.
        choice: the decision function's choice (its recovery of rejected points is
            `extensometer track`'s; the tracker estimates a failed point from its mark).
    """

    time_s: float | None
    mark: int
    stages: tuple[str, ...]
    inputs: SearchInputs
    choice: SearchChoice

    def describe(self) -> str:
        """One line: the choice and the inputs it used."""
        c, i = self.choice, self.inputs
        method = "LPQ" if c.method == "lpq" else "ZNCC"
        prewarps = 0 if c.prewarps is None else len(c.prewarps)
        step = i.one_step_stretch
        stretch = "untold" if step is None else f"{step * 100:.3g} % a step"
        rate = "" if i.strain_rate_per_s is None else f", strain rate {i.strain_rate_per_s:.4g}/s"
        stages = " and ".join(STAGE_NAMES[s] for s in self.stages)
        chosen = f"search choice, mark {self.mark} {stages}: {method}, {prewarps} pre-warps"
        if self.time_s is None:
            return f"{chosen}; on the reference frame, no motion known"
        return (
            f"{chosen}; at t {self.time_s:.3f} s from blur {i.blur_px:.3g} px "
            f"({i.speed_px_s:.4g} px/s x exposure {i.exposure_s * 1e3:.4g} ms), "
            f"one-step stretch {stretch}{rate}"
        )

    def to_json(self) -> dict:
        """The change as JSON fields (the summary's `search_choices`)."""
        return {
            "time_s": self.time_s,
            "mark": self.mark,
            "stages": list(self.stages),
            "inputs": self.inputs.describe(),
            "choice": self.choice.describe(),
        }


class AutomaticSearch:
    """One mark's automatic choice, made again when its inputs move (module docstring).

    Args:
        axis: loading axis, unit vector (x, y) in image coordinates (the blur's direction;
            the pre-warps stretch along the image axis nearer to it).
        blur_tolerance_px: change of the blur that makes the choice again, px.
    """

    def __init__(self, axis: tuple[float, float], blur_tolerance_px: float) -> None:
        self.axis_deg = math.degrees(math.atan2(axis[1], axis[0]))
        self.stretch_axis = "x" if abs(axis[0]) > abs(axis[1]) else "y"
        self.blur_tolerance_px = blur_tolerance_px
        self.inputs: SearchInputs | None = None
        self.choice: SearchChoice | None = None
        self.stretch: tuple[float, float] | None = None
        self.search_changed = False

    def update(self, inputs: SearchInputs, subset_px: int) -> bool:
        """Decide again if `inputs` moved beyond tolerance from the last decision's (or there
        is none yet); returns whether it decided again, and `search_changed` says whether
        the search the tracker runs changed with it."""
        stretch = self._stretch_for(inputs)
        if self.inputs is not None and not self._moved(inputs, stretch):
            return False
        before = self._search()
        self.inputs = inputs
        self.stretch = stretch
        self.choice = choose_search(
            blur_px=inputs.blur_px,
            blur_angle_deg=self.axis_deg,
            stretch=stretch,
            stretch_axis=self.stretch_axis,
            subset=subset_px,
        )
        self.search_changed = self._search() != before
        return True

    def _search(self) -> tuple | None:
        """What of the choice the tracker runs: method, LPQ window, the pre-warps' stretch."""
        c = self.choice
        return None if c is None else (c.method, c.lpq_window, c.stretch)

    def _stretch_for(self, inputs: SearchInputs) -> tuple[float, float] | None:
        """The stepped stretch range for `inputs`: the one in force while the measured step
        is within `STRETCH_HOLD` steps of it."""
        stepped = inputs.stretch_range()
        if stepped is None or self.stretch is None:
            return stepped
        held = self.stretch[0] + self.stretch[1]
        if abs(inputs.one_step_stretch - held) <= STRETCH_HOLD * STRETCH_QUANTUM:
            return self.stretch
        return stepped

    def _moved(self, inputs: SearchInputs, stretch: tuple[float, float] | None) -> bool:
        if abs(inputs.blur_px - self.inputs.blur_px) > self.blur_tolerance_px:
            return True
        return stretch != self.stretch


def axial_strain_rate_per_s(
    centres: np.ndarray, velocities: Sequence[np.ndarray | None], axis: tuple[float, float]
) -> float | None:
    """True strain rate along `axis` between the two marks farthest apart along it, 1/s.

    Args:
        centres: (k, 2) the marks' centres, px.
        velocities: each mark's velocity (x, y), px/s, or None where it is not measured.
        axis: loading axis, unit vector.

    Returns:
        ((v_j - v_i) . a) / ((p_j - p_i) . a) for the pair farthest apart along the axis, or
        None with fewer than two marks, a velocity of that pair not measured, or the pair less
        than a pixel apart along the axis.
    """
    if len(centres) < 2:
        return None
    along = np.asarray(centres, dtype=np.float64) @ np.asarray(axis, dtype=np.float64)
    first, last = int(np.argmin(along)), int(np.argmax(along))
    apart = float(along[last] - along[first])
    if apart < 1.0 or velocities[first] is None or velocities[last] is None:
        return None
    closing = float((velocities[last] - velocities[first]) @ np.asarray(axis))
    return closing / apart


def prewarps_about(gradient: np.ndarray, choice: SearchChoice) -> list[tuple[float, ...]]:
    """The pre-warps a stage searches over: the mark's current deformation `gradient`
    (ux, uy, vx, vy) alone, or with each of the choice's one-step pre-warps added to it."""
    if choice.prewarps is None:
        return [tuple(gradient)]
    return [tuple(row) for row in np.asarray(gradient) + choice.prewarps]
