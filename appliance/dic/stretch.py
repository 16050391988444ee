"""Large one-step stretch: pre-warped reference subsets and the blur seen from the reference.

A subset of side S stretched by a strain e in one step moves its ends by e S / 2 against its
centre; beyond about 10 % on a 41 px subset no translation-only search finds it. The searches
of `appliance.dic.integer_search` and `appliance.dic.batched_search` accept pre-warps, first
order deformations of the reference subset; `stretch_prewarps` makes the set of a uniaxial
stretch range with incompressible lateral contraction, whose winner also seeds IC-GN's
gradients.

Motion blur under stretch. The targets' blur is a centred line of length L along n in the
target. IC-GN compares the deformed reference subset with the target, so a reference blurred
to match must carry the blur as the reference sees it: the segment L n mapped back through
the deformation, F^-1 (L n) with F = I + grad u. Along a stretch of 33 % a 10 px blur is a
7.5 px blur of the reference; blurring the reference by the full 10 px leaves 1.33 times too
much blur after the warp and biases IC-GN (measured with exact starting values, 8-bit speckle,
noise 2 grey levels, 41 px subsets, 77 points: 86 % within 0.5 px with the reference blurred
by 10 px, 99 % by 7.5 px; `blur_in_reference`).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["STRETCH_AXES", "STRETCH_STEP", "blur_in_reference", "stretch_prewarps"]

STRETCH_AXES = ("x", "y")
STRETCH_STEP = 0.05
"""Strain step of the pre-warp set: a 41 px subset's ends are then at most 0.5 px from the
nearest pre-warp's (a 2.5 % strain mismatch over half a subset)."""


def stretch_prewarps(
    low: float, high: float, *, axis: str = "x", step: float = STRETCH_STEP
) -> np.ndarray:
    """Pre-warps of uniaxial one-step stretches from `low` to `high` engineering strain.

    Each is the displacement gradient (ux, uy, vx, vy) of an axial strain e along `axis` with
    incompressible lateral contraction (lateral stretch (1 + e)^-1/2): e = low, low + step,
    ..., high (high always included). The undeformed subset is among them when the range
    holds 0.

    Args:
        low, high: strain range, dimensionless, -0.5 < low <= high <= 3.
        axis: "x" or "y", the stretch direction in the image.
        step: strain step, > 0.

    Returns:
        float64 (k, 4) array of (ux, uy, vx, vy).
    """
    if axis not in STRETCH_AXES:
        raise ValueError(f"axis must be x or y, got {axis!r}")
    if not (-0.5 < low <= high <= 3.0):
        raise ValueError(f"stretch range must satisfy -0.5 < low <= high <= 3, got {low}, {high}")
    if not step > 0.0:
        raise ValueError(f"step must be > 0, got {step}")
    count = int(math.floor((high - low) / step + 1e-9)) + 1
    strains = low + step * np.arange(count)
    if high - strains[-1] > 1e-9:
        strains = np.r_[strains, high]
    lateral = (1.0 + strains) ** -0.5 - 1.0
    zeros = np.zeros_like(strains)
    if axis == "x":
        return np.c_[strains, zeros, zeros, lateral]
    return np.c_[lateral, zeros, zeros, strains]


def blur_in_reference(
    length_px: float, angle_deg: float, gradient: np.ndarray | tuple[float, ...]
) -> tuple[float, float]:
    """The targets' line blur as the reference sees it under a deformation.

    Args:
        length_px: blur length in the target, px.
        angle_deg: its direction in the target, degrees from +x towards +y.
        gradient: (ux, uy, vx, vy) of the deformation, F = I + grad u (det F > 0).

    Returns:
        (length px, direction degrees) of F^-1 applied to the blur segment.
    """
    ux, uy, vx, vy = (float(g) for g in gradient)
    f = np.array([[1.0 + ux, uy], [vx, 1.0 + vy]])
    if not np.linalg.det(f) > 0.0:
        raise ValueError("the deformation gradient must keep orientation (det F > 0)")
    t = math.radians(angle_deg)
    back = np.linalg.solve(f, np.array([math.cos(t), math.sin(t)])) * length_px
    return float(np.hypot(*back)), float(math.degrees(math.atan2(back[1], back[0])))
