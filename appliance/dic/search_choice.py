"""The integer search the product picks for a known blur and an expected one-step stretch.

`choose_search` turns what the appliance knows (the motion blur of the targets, from the
planned exposure and the speed at the point or given, and the expected one-step stretch
range, if any) into the search `extensometer track` runs: ZNCC against a reference blurred
to match, with pre-warps over the expected stretch when one is given, and with the recovery
of rejected points (`appliance.dic.seeded_recovery`) always on: it costs nothing when every
point is accepted. The search benchmark's table backs it (`extensometer bench search`,
`appliance/bench/results/search.md`: 34 cases of blur 0 ... 15 px, one-step stretch 0 ... 45 %,
noise of sigma 0 ... 5 grey levels, illumination gain 0.7 with offset +20, subsets of 21 ... 61
px): LPQ at its rule's window (`appliance.dic.lpq.window_for_blur`) never found more points
than this choice (97.4 % on average against LPQ's 60.7 %), and beat blur-matched ZNCC without
recovery only in 5 cases of 10 ... 15 px blur with a 25 % stretch; telling the stretch
(`stretch`) found 97.8 % at about 3.6 times the time per point, so recovery, not pre-warping
every point, is the default.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from appliance.dic.lpq import window_for_blur
from appliance.dic.stretch import stretch_prewarps

__all__ = ["UNTOLD_STRETCH", "SearchChoice", "choose_search", "untold_scale_prewarps"]

UNTOLD_STRETCH = (0.0, 0.5)
"""Strain range the seeds of a recovery are searched over when no stretch is expected."""


@dataclass(frozen=True)
class SearchChoice:
    """A search configuration and why it was chosen.

    Attributes:
        method: "zncc" or "lpq".
        lpq_window: LPQ window, px (the rule's for the blur), or None for ZNCC.
        reference_blur_px: blur the reference is given to match the targets, px (0 = none).
        stretch: expected one-step strain range (low, high), or None.
        stretch_axis: "x" or "y".
        prewarps: (k, 4) pre-warps every point is searched over, or None (translation only).
        recover: whether rejected points are recovered (seeds, then neighbour waves).
        reason: one line saying what decided it.
    """

    method: str
    lpq_window: int | None
    reference_blur_px: float
    stretch: tuple[float, float] | None
    stretch_axis: str
    prewarps: np.ndarray | None
    recover: bool
    reason: str

    def scale_prewarps(self) -> np.ndarray:
        """Pre-warps the recovery's seeds are searched over: the expected stretch along its
        axis, or `UNTOLD_STRETCH` along x and along y."""
        return scale_prewarps_for(self.stretch, self.stretch_axis)

    def describe(self) -> dict:
        """The choice as JSON fields."""
        return {
            "method": self.method,
            "lpq_window": self.lpq_window,
            "reference_blur_px": self.reference_blur_px,
            "stretch": None if self.stretch is None else list(self.stretch),
            "stretch_axis": self.stretch_axis,
            "prewarps": 0 if self.prewarps is None else int(len(self.prewarps)),
            "recover": self.recover,
            "reason": self.reason,
        }


def scale_prewarps_for(stretch: tuple[float, float] | None, axis: str) -> np.ndarray:
    """The recovery's seed pre-warps for an expected stretch (see `SearchChoice`)."""
    if stretch is not None:
        return stretch_prewarps(*stretch, axis=axis)
    return untold_scale_prewarps()


def untold_scale_prewarps() -> np.ndarray:
    """`UNTOLD_STRETCH` along x and along y (the undeformed subset once)."""
    along_x = stretch_prewarps(*UNTOLD_STRETCH, axis="x")
    along_y = stretch_prewarps(*UNTOLD_STRETCH, axis="y")
    return np.r_[along_x, along_y[1:]]


def choose_search(
    *,
    blur_px: float,
    blur_angle_deg: float = 0.0,
    stretch: tuple[float, float] | None = None,
    stretch_axis: str = "x",
    subset: int = 41,
) -> SearchChoice:
    """The search for a known blur and an expected stretch (see the module docstring).

    Args:
        blur_px: the targets' known motion blur, px (0 = sharp or unknown).
        blur_angle_deg: its direction, degrees; the choice does not depend on it (ZNCC against
            a reference blurred to match is chosen at any angle), taken for the same call as
            `explicit_search`.
        stretch: expected one-step strain range (low, high), or None (untold).
        stretch_axis: "x" or "y".
        subset: subset side, px; the choice does not depend on it either (as `blur_angle_deg`).

    Returns:
        `SearchChoice` with method "zncc".
    """
    prewarps = None if stretch is None else stretch_prewarps(*stretch, axis=stretch_axis)
    parts = [f"ZNCC, reference blurred {blur_px:g} px to match" if blur_px > 0 else "ZNCC, no blur"]
    if stretch is not None:
        parts.append(f"{len(prewarps)} pre-warps over the expected stretch")
    else:
        parts.append("rejected points recovered from scale-searched seeds")
    return SearchChoice(
        method="zncc",
        lpq_window=None,
        reference_blur_px=float(blur_px),
        stretch=stretch,
        stretch_axis=stretch_axis,
        prewarps=prewarps,
        recover=True,
        reason="; ".join(parts),
    )


def explicit_search(
    method: str,
    *,
    blur_px: float,
    blur_angle_deg: float = 0.0,
    lpq_window: int | None = None,
    stretch: tuple[float, float] | None = None,
    stretch_axis: str = "x",
    subset: int = 41,
) -> SearchChoice:
    """The search a user named: `method` as asked, LPQ at the given window or the rule's for
    the blur (`window_for_blur`), pre-warps over the expected stretch, recovery only when a
    stretch is expected."""
    window = None
    if method == "lpq":
        window = lpq_window or window_for_blur(blur_px, blur_angle_deg, subset=subset)
    prewarps = None if stretch is None else stretch_prewarps(*stretch, axis=stretch_axis)
    how = "given" if lpq_window else f"the rule's for {blur_px:g} px of blur"
    reason = f"--search {method}" + (f", LPQ window {window} px ({how})" if window else "")
    return SearchChoice(
        method=method,
        lpq_window=window,
        reference_blur_px=float(blur_px),
        stretch=stretch,
        stretch_axis=stretch_axis,
        prewarps=prewarps,
        recover=stretch is not None,
        reason=reason,
    )
