"""Exposure planning: motion blur and frame-to-frame motion of a moving specimen.

During an exposure of T seconds a point of the specimen moving at V mm/s in the object plane
travels V T mm, and its image is smeared over a line on the sensor of (Zhang et al. 2016, Eq. 9,
with the magnification m = v / u = f / (u - f) of Eq. 7-8, see `appliance.plan.optics`)

    blur_um = V[mm/s] * T[s] * m * 1000                                   (Eq. 9)
    blur_px = blur_um / p                 p = pixel pitch, um

The same formula with the frame period in place of T gives the point's motion from one frame
to the next, which the integer search has to cover (its capture range, e.g. the search radius).

`plan_exposure` turns a crosshead speed into an exposure and a frame period:

- the exposure is the longest (most light, least noise) whose blur stays within a blur budget,
  clipped to what the camera can do;
- the frame period is the longest (fewest frames to process) whose frame-to-frame motion stays
  within the capture range, and never shorter than the exposure.

Speeds are given in mm/min, as tensile machines state them; times in seconds.

The blur length in px is what `Correlator(reference_blur=(blur_px, angle))` and
`extensometer track --blur-px` expect when the blur cannot be kept within budget.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np

from appliance.config import Config
from appliance.errors import InputError, ParameterError
from appliance.plan.optics import Optics

DEFAULT_MAX_PERIOD_S = 1.0
"""Frame period planned when nothing moves (speed 0), s."""


class BlurLength(NamedTuple):
    """Length of the motion-blur line on the sensor (float, or arrays of the broadcast shape).

    Attributes:
        um: blur length on the sensor, um.
        px: blur length on the sensor, px.
    """

    um: float | np.ndarray
    px: float | np.ndarray


def motion_blur_length(
    optics: Optics, speed_mm_min: float | np.ndarray, exposure_s: float | np.ndarray
) -> BlurLength:
    """Motion blur on the sensor of a point moving during one exposure (Eq. 9).

    Args:
        optics: lens and sensor (magnification m, pixel pitch p).
        speed_mm_min: speed of the point in the object plane, mm/min (>= 0); scalar or array.
        exposure_s: exposure time T, s (>= 0); scalar or array, broadcast against the speed.
            Any duration works: with a frame period it gives the motion between two frames.

    Returns:
        `BlurLength(um, px)`: blur_um = V/60 * T * m * 1000, blur_px = blur_um / p. Floats for
        scalar arguments, arrays of the broadcast shape otherwise.

    Raises:
        ValueError: a speed or exposure that is negative or not finite.
    """
    speed = np.asarray(speed_mm_min, dtype=np.float64)
    exposure = np.asarray(exposure_s, dtype=np.float64)
    if not np.all(np.isfinite(speed) & (speed >= 0)):
        raise ValueError(f"speed_mm_min must be finite and >= 0, got {speed_mm_min}")
    if not np.all(np.isfinite(exposure) & (exposure >= 0)):
        raise ValueError(f"exposure_s must be finite and >= 0, got {exposure_s}")
    travel_mm = speed / 60.0 * exposure
    blur_um = optics.image_um(travel_mm)
    blur_px = blur_um / optics.pixel_size_um
    if blur_um.ndim == 0:
        return BlurLength(float(blur_um), float(blur_px))
    return BlurLength(blur_um, blur_px)


@dataclass(frozen=True)
class ExposurePlan:
    """Exposure and frame period for one crosshead speed, and what they give.

    Attributes:
        speed_mm_min: crosshead speed, mm/min.
        point_speed_mm_min: speed of the fastest gauge point, mm/min (speed_fraction * speed).
        exposure_s: planned exposure time, s.
        frame_period_s: planned time from one frame to the next, s (>= exposure_s).
        blur_um: blur of the fastest point at the planned exposure, um on the sensor.
        blur_px: the same in px.
        motion_per_frame_px: frame-to-frame motion of the fastest point, px.
        budget_met: blur_px <= the blur budget. False only when even the shortest exposure
            blurs more than the budget; the exposure is then that shortest one, and the
            blur-tolerant search (LPQ) or a reference blurred to match (`blur_px`) must carry
            the blur.
        period_covers_exposure: the frame-to-frame motion stays within the capture range with
            a period no shorter than the exposure. When False the period is the exposure
            itself and `motion_per_frame_px` exceeds the capture range: lower the blur budget
            (a shorter exposure) or widen the capture range.
        exposure_limit: what set the exposure: "blur_budget", "max_exposure" (the budget
            allows longer) or "min_exposure" (the budget wants shorter, see `budget_met`).
        period_limit: what set the period: "capture_range", "max_period" (speed 0 or so
            slow that the capture range allows longer), "exposure" (see
            `period_covers_exposure`); after `paced`, also "min_frame_rate" (the rate the
            controller receives strain at) or "frame_rate" (a rate set outright).
    """

    speed_mm_min: float
    point_speed_mm_min: float
    exposure_s: float
    frame_period_s: float
    blur_um: float
    blur_px: float
    motion_per_frame_px: float
    budget_met: bool
    period_covers_exposure: bool
    exposure_limit: Literal["blur_budget", "max_exposure", "min_exposure"]
    period_limit: Literal["capture_range", "max_period", "exposure", "min_frame_rate", "frame_rate"]

    @property
    def frame_rate_hz(self) -> float:
        """Frame rate 1 / frame_period_s, Hz."""
        return 1.0 / self.frame_period_s


def _finite(name: str, value: float, *, positive: bool) -> float:
    """`value` as a float, or ValueError naming `name` unless finite and > 0 (>= 0)."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = math.nan
    if not (math.isfinite(number) and (number > 0 if positive else number >= 0)):
        bound = "> 0" if positive else ">= 0"
        raise ParameterError(name, f"must be a finite number {bound}, got {value!r}")
    return number


def _longest_within(
    optics: Optics, speed_mm_min: float, limit_px: float, low_s: float, high_s: float
) -> float:
    """Longest duration in [low_s, high_s] whose image travel is <= limit_px (low_s if none).

    `speed_mm_min` must be > 0.
    """
    rate_px_s = motion_blur_length(optics, speed_mm_min, 1.0).px
    if rate_px_s == 0:  # a speed so small that its travel underflows
        return high_s
    duration = min(max(limit_px / rate_px_s, low_s), high_s)
    # Rounding in limit / rate can put the travel a few ulps above the limit: step back.
    while duration > low_s and motion_blur_length(optics, speed_mm_min, duration).px > limit_px:
        duration = max(math.nextafter(duration, 0.0), low_s)
    return duration


def plan_exposure(
    optics: Optics,
    speed_mm_min: float,
    *,
    blur_budget_px: float = 1.0,
    capture_range_px: float = 20.0,
    min_exposure_s: float = 50e-6,
    max_exposure_s: float = 20e-3,
    max_period_s: float = DEFAULT_MAX_PERIOD_S,
    speed_fraction: float = 1.0,
) -> ExposurePlan:
    """Longest exposure within a blur budget, longest frame period within a capture range.

    The fastest gauge point moves at `speed_fraction * speed_mm_min`. In a tensile test one
    grip stands still and the crosshead carries the other; every material point between them
    moves no faster than the crosshead, so `speed_fraction = 1` is a safe bound wherever the
    gauge sits. A smaller fraction (e.g. the gauge's share of the free length for a uniform
    specimen) plans longer exposures but is only safe when the strain stays uniform (no
    necking outside the gauge); a fraction above 1 adds a margin, e.g. for speed overshoot.

    Exposure: the longest T in [min_exposure_s, max_exposure_s] with blur_px(T) <= budget,
    i.e. T = budget / (image speed, px/s), clipped. When even min_exposure_s blurs more than the
    budget the plan takes min_exposure_s and reports `budget_met=False` with the blur there:
    the blur is then carried by the blur-tolerant LPQ search or a reference blurred to match.

    Frame period: the longest P <= max_period_s with motion_per_frame_px(P) <= capture_range_px,
    and P >= T (a frame cannot be shorter than its exposure). When the capture range would
    need P < T, the plan takes P = T and reports `period_covers_exposure=False`.

    Speed 0: nothing moves, so the exposure is max_exposure_s, the period max_period_s, and
    blur and motion are 0.

    Args:
        optics: lens and sensor.
        speed_mm_min: crosshead speed, mm/min (>= 0).
        blur_budget_px: largest acceptable blur of the fastest point, px (> 0).
        capture_range_px: largest frame-to-frame motion the integer search covers, px (> 0),
            e.g. its search radius.
        min_exposure_s: shortest exposure the camera (or the light) allows, s (> 0).
        max_exposure_s: longest exposure wanted, s (>= min_exposure_s).
        max_period_s: longest frame period wanted, s (>= max_exposure_s); the period at
            speed 0.
        speed_fraction: fastest gauge point speed / crosshead speed (> 0; 1 is safe).

    Returns:
        The `ExposurePlan`.

    Raises:
        ParameterError: an argument out of range (a ValueError naming it).
    """
    speed_mm_min = _finite("speed_mm_min", speed_mm_min, positive=False)
    blur_budget_px = _finite("blur_budget_px", blur_budget_px, positive=True)
    capture_range_px = _finite("capture_range_px", capture_range_px, positive=True)
    min_exposure_s = _finite("min_exposure_s", min_exposure_s, positive=True)
    max_exposure_s = _finite("max_exposure_s", max_exposure_s, positive=True)
    max_period_s = _finite("max_period_s", max_period_s, positive=True)
    speed_fraction = _finite("speed_fraction", speed_fraction, positive=True)
    if min_exposure_s > max_exposure_s:
        raise ParameterError(
            "min_exposure_s",
            f"({min_exposure_s:g} s) must not exceed max_exposure_s ({max_exposure_s:g} s)",
        )
    if max_period_s < max_exposure_s:
        raise ParameterError(
            "max_period_s",
            f"({max_period_s:g} s) must be >= max_exposure_s ({max_exposure_s:g} s)",
        )

    point_speed = speed_fraction * speed_mm_min
    if point_speed == 0:
        exposure, exposure_limit = max_exposure_s, "max_exposure"
        period, period_limit = max_period_s, "max_period"
    else:
        exposure = _longest_within(
            optics, point_speed, blur_budget_px, min_exposure_s, max_exposure_s
        )
        if motion_blur_length(optics, point_speed, exposure).px > blur_budget_px:
            exposure_limit = "min_exposure"
        elif exposure == max_exposure_s:
            exposure_limit = "max_exposure"
        else:
            exposure_limit = "blur_budget"
        period = _longest_within(optics, point_speed, capture_range_px, exposure, max_period_s)
        if motion_blur_length(optics, point_speed, period).px > capture_range_px:
            period_limit = "exposure"
        elif period == max_period_s:
            period_limit = "max_period"
        else:
            period_limit = "capture_range"
    blur = motion_blur_length(optics, point_speed, exposure)
    motion = motion_blur_length(optics, point_speed, period)
    return ExposurePlan(
        speed_mm_min=speed_mm_min,
        point_speed_mm_min=point_speed,
        exposure_s=exposure,
        frame_period_s=period,
        blur_um=blur.um,
        blur_px=blur.px,
        motion_per_frame_px=motion.px,
        budget_met=blur.px <= blur_budget_px,
        period_covers_exposure=motion.px <= capture_range_px,
        exposure_limit=exposure_limit,
        period_limit=period_limit,
    )


_CONFIGURED_BY = {
    "speed_mm_min": "[run] speed_mm_min",
    "blur_budget_px": "[camera] blur_budget_px",
    "capture_range_px": "[tracking] search_radius_px",
    "min_exposure_s": "[camera] min_exposure_us",
    "max_exposure_s": "[camera] max_exposure_us",
}
"""The planner's parameter -> the configuration key that sets it."""


def exposure_for(config: Config, optics: Optics, speed_mm_min: float) -> ExposurePlan:
    """The exposure plan of a test at a crosshead speed: the planner's for the configuration's
    blur budget, exposure bounds and search radius, with `[camera] exposure_us` and
    `frame_rate_hz` taking precedence where given, and the frame rate no lower than
    `min_frame_rate_hz` unless the exposure does not allow it.

    Raises:
        InputError: an exposure longer than the frame period, or a value the planner refuses
            (names the key).
    """
    camera = config.camera
    try:
        plan = plan_exposure(
            optics,
            speed_mm_min,
            blur_budget_px=camera.blur_budget_px,
            capture_range_px=float(config.tracking.search_radius_px),
            min_exposure_s=camera.min_exposure_us * 1e-6,
            max_exposure_s=camera.max_exposure_us * 1e-6,
        )
    except ParameterError as exc:
        raise InputError(f"{_CONFIGURED_BY[exc.parameter]}: {exc}") from None
    exposure_s = plan.exposure_s if camera.exposure_us is None else camera.exposure_us * 1e-6
    paced_plan = paced(
        plan,
        optics,
        exposure_s=exposure_s,
        min_frame_rate_hz=camera.min_frame_rate_hz,
        blur_budget_px=camera.blur_budget_px,
        frame_rate_hz=camera.frame_rate_hz,
    )
    if exposure_s > paced_plan.frame_period_s:
        raise InputError(
            f"[camera] exposure_us: {exposure_s * 1e6:g} exceeds the frame period "
            f"{paced_plan.frame_period_s * 1e6:g} us"
        )
    return paced_plan


def paced(
    plan: ExposurePlan,
    optics: Optics,
    *,
    exposure_s: float,
    min_frame_rate_hz: float,
    blur_budget_px: float,
    frame_rate_hz: float | None = None,
) -> ExposurePlan:
    """`plan` with the exposure in use and the frame period in use, and what they give.

    The period is `frame_rate_hz`'s when it is given (the caller refuses one shorter than the
    exposure); otherwise the plan's, shortened to 1 / `min_frame_rate_hz` (the rate the
    controller receives strain at) but never below the exposure. `extensometer plan` and a
    test (`exposure_for`) pace their plans with this one rule.
    """
    if frame_rate_hz is not None:
        period_s, period_limit = 1.0 / frame_rate_hz, "frame_rate"
    else:
        period_s, period_limit = plan.frame_period_s, plan.period_limit
        if period_s > 1.0 / min_frame_rate_hz:
            period_s, period_limit = 1.0 / min_frame_rate_hz, "min_frame_rate"
        if period_s < exposure_s:
            period_s, period_limit = exposure_s, "exposure"
    speed = plan.point_speed_mm_min
    blur = motion_blur_length(optics, speed, exposure_s)
    motion = motion_blur_length(optics, speed, period_s).px
    return dataclasses.replace(
        plan,
        exposure_s=exposure_s,
        frame_period_s=period_s,
        blur_um=blur.um,
        blur_px=blur.px,
        motion_per_frame_px=motion,
        budget_met=bool(blur.px <= blur_budget_px),
        period_limit=period_limit,
    )
