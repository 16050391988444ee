"""`extensometer plan`: the motion blur of an exposure, and the exposure plan for a speed.

Thin-lens optics (`appliance.plan.optics`) and the exposure planner
(`appliance.plan.exposure`): the blur of the given exposure at the given crosshead speed,
then the longest exposure within the blur budget and the longest frame period within the
search's capture range. The domain refuses impossible values (`ParameterError`); this
command names the option that carried them.

It also states the false strain an out-of-plane motion of the specimen surface causes
(`appliance.run.object_plane`): dz / Z at the stand-off Z of an entocentric lens, 0 for a
telecentric one, with the ISO 9513 class that bias allows at 1 % strain over the gauge length.
Z is the calibrated plane's distance with `--calibration FILE`, else `--object-distance-mm`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from appliance.cli import arguments
from appliance.config import CameraConfig, OpticsConfig
from appliance.errors import InputError, ParameterError
from appliance.measure.gauges import Calibration
from appliance.optics.calibration_file import load_calibration
from appliance.plan.exposure import (
    DEFAULT_MAX_PERIOD_S,
    motion_blur_length,
    paced,
    plan_exposure,
)
from appliance.plan.optics import Optics
from appliance.run.object_plane import OUT_OF_PLANE_MM, out_of_plane_bound

OPTIONS = {
    "focal_length_mm": "--focal-length-mm",
    "object_distance_mm": "--object-distance-mm",
    "pixel_size_um": "--pixel-size-um",
    "speed_mm_min": "--speed-mm-min",
    "exposure_s": "--exposure-s",
    "speed_fraction": "--speed-fraction",
    "blur_budget_px": "--blur-budget-px",
    "capture_range_px": "--capture-range-px",
    "min_exposure_s": "--min-exposure-us",
    "max_exposure_s": "--max-exposure-us",
    "max_period_s": "--max-period-s",
}
"""The planner's parameter -> the option that sets it."""


def add_parser(commands: argparse._SubParsersAction) -> None:
    """The `plan` command."""
    plan = commands.add_parser(
        "plan",
        help="motion blur of an exposure; exposure and frame period for a blur budget",
        description=(
            "Thin-lens optics (Zhang et al. 2016, Eq. 7-8) and motion blur (Eq. 9) of the "
            "fastest gauge point at the given crosshead speed and exposure, then the longest "
            "exposure whose blur stays within the blur budget and the longest frame period "
            "whose frame-to-frame motion stays within the capture range."
        ),
    )
    plan.add_argument(
        "--focal-length-mm",
        type=arguments.like_key(OpticsConfig, "focal_length_mm"),
        required=True,
        help="focal length f, mm",
    )
    plan.add_argument(
        "--object-distance-mm",
        type=arguments.like_key(OpticsConfig, "object_distance_mm"),
        required=True,
        help="specimen-to-lens distance u, mm (> f)",
    )
    plan.add_argument(
        "--pixel-size-um",
        type=arguments.like_key(OpticsConfig, "pixel_size_um"),
        required=True,
        help="sensor pixel pitch p, um",
    )
    plan.add_argument(
        "--exposure-s",
        type=arguments.within(float, 0.0, 10.0, above=True),
        required=True,
        help="exposure T, s",
    )
    plan.add_argument(
        "--speed-mm-min",
        type=arguments.within(float, 0.0, 10000.0),
        required=True,
        help="crosshead speed, mm/min",
    )
    plan.add_argument(
        "--speed-fraction",
        type=arguments.within(float, 0.0, 1.0, above=True),
        default=1.0,
        help="fastest gauge point speed / crosshead speed (1, a safe bound)",
    )
    plan.add_argument(
        "--blur-budget-px",
        type=arguments.within(float, 0.0, 100.0, above=True),
        default=1.0,
        help="largest blur wanted, px (1)",
    )
    plan.add_argument(
        "--capture-range-px",
        type=arguments.within(float, 0.0, 1000.0, above=True),
        default=20.0,
        help="largest frame-to-frame motion the search covers, px (20)",
    )
    plan.add_argument(
        "--min-exposure-us",
        type=arguments.like_key(CameraConfig, "min_exposure_us"),
        default=50.0,
        help="shortest exposure the camera allows, us (50)",
    )
    plan.add_argument(
        "--max-exposure-us",
        type=arguments.like_key(CameraConfig, "max_exposure_us"),
        default=20000.0,
        help="longest exposure wanted, us (20000)",
    )
    plan.add_argument(
        "--max-period-s",
        type=arguments.within(float, 0.0, 3600.0, above=True),
        default=DEFAULT_MAX_PERIOD_S,
        help=f"longest frame period wanted, s ({DEFAULT_MAX_PERIOD_S:g}; the period at speed 0)",
    )
    plan.add_argument(
        "--min-frame-rate-hz",
        type=arguments.like_key(CameraConfig, "min_frame_rate_hz"),
        default=CameraConfig.min_frame_rate_hz,
        help=f"lowest frame rate, the rate the controller gets strain at, Hz "
        f"({CameraConfig.min_frame_rate_hz:g}; as [camera] min_frame_rate_hz in a test)",
    )
    plan.add_argument(
        "--out-of-plane-mm",
        type=arguments.within(float, 0.0, 100.0),
        default=OUT_OF_PLANE_MM,
        help=f"out-of-plane motion of the specimen surface to state the false strain of, mm "
        f"({OUT_OF_PLANE_MM:g})",
    )
    plan.add_argument(
        "--gauge-length-mm",
        type=arguments.within(float, 0.0, 10000.0, above=True),
        default=50.0,
        help="gauge length L0 for the ISO 9513 class of that false strain, mm (50)",
    )
    plan.add_argument(
        "--calibration",
        type=Path,
        metavar="FILE",
        help="camera calibration (extensometer calibrate): the stand-off Z is its plane's",
    )
    plan.add_argument("--json", action="store_true", help="print JSON on stdout")
    plan.set_defaults(handler=plan_exposure_for_speed)


def plan_exposure_for_speed(args: argparse.Namespace) -> int:
    """Run `plan`; returns the exit status."""
    try:
        return _plan(args)
    except ParameterError as exc:
        raise InputError(f"plan: {OPTIONS[exc.parameter]}: {exc}") from None


def _plan(args: argparse.Namespace) -> int:
    optics = Optics(args.focal_length_mm, args.object_distance_mm, args.pixel_size_um)
    point_speed = args.speed_fraction * args.speed_mm_min
    blur = motion_blur_length(optics, point_speed, args.exposure_s)
    plan = plan_exposure(
        optics,
        args.speed_mm_min,
        blur_budget_px=args.blur_budget_px,
        capture_range_px=args.capture_range_px,
        min_exposure_s=args.min_exposure_us * 1e-6,
        max_exposure_s=args.max_exposure_us * 1e-6,
        max_period_s=args.max_period_s,
        speed_fraction=args.speed_fraction,
    )
    plan = paced(
        plan,
        optics,
        exposure_s=plan.exposure_s,
        min_frame_rate_hz=args.min_frame_rate_hz,
        blur_budget_px=args.blur_budget_px,
    )
    calibration = Calibration(optics.scale_mm_per_px)
    if args.calibration is not None:
        try:
            calibration = Calibration.object_plane(
                load_calibration(args.calibration), str(args.calibration)
            )
        except InputError as exc:
            raise InputError(f"plan: --calibration: {exc}") from None
    bound = out_of_plane_bound(
        calibration,
        optics.object_distance_mm,
        args.gauge_length_mm,
        args.out_of_plane_mm,
        object_distance_from="--object-distance-mm",
    )
    document = {
        "image_distance_mm": optics.image_distance_mm,
        "magnification": optics.magnification,
        "scale_mm_per_px": optics.scale_mm_per_px,
        "speed_mm_min": args.speed_mm_min,
        "point_speed_mm_min": point_speed,
        "exposure_s": args.exposure_s,
        "blur_um": blur.um,
        "blur_px": blur.px,
        "blur_budget_px": args.blur_budget_px,
        "capture_range_px": args.capture_range_px,
        "planned_exposure_s": plan.exposure_s,
        "planned_frame_period_s": plan.frame_period_s,
        "planned_frame_rate_hz": plan.frame_rate_hz,
        "planned_blur_um": plan.blur_um,
        "planned_blur_px": plan.blur_px,
        "planned_motion_per_frame_px": plan.motion_per_frame_px,
        "budget_met": plan.budget_met,
        "period_covers_exposure": plan.period_covers_exposure,
        "exposure_limit": plan.exposure_limit,
        "period_limit": plan.period_limit,
        "gauge_length_mm": args.gauge_length_mm,
        **bound.facts(),
    }
    if args.json:
        json.dump(document, sys.stdout, indent=1)
        sys.stdout.write("\n")
        return 0
    budget = "met" if plan.budget_met else "NOT met: let LPQ or track --blur-px carry the blur"
    capture = "" if plan.period_covers_exposure else ", exceeded: period = exposure"
    rows = [
        ("image distance", f"{optics.image_distance_mm:.4f} mm"),
        ("magnification", f"{optics.magnification:.6f}"),
        ("scale", f"{optics.scale_mm_per_px * 1e3:.4f} um/px (object plane)"),
        ("point speed", f"{point_speed:g} mm/min"),
        (f"blur at {args.exposure_s * 1e3:g} ms", f"{blur.um:.3f} um = {blur.px:.3f} px"),
        ("planned exposure", f"{plan.exposure_s * 1e3:.4f} ms (set by {plan.exposure_limit})"),
        (
            "planned blur",
            f"{plan.blur_um:.3f} um = {plan.blur_px:.3f} px "
            f"(budget {args.blur_budget_px:g} px {budget})",
        ),
        (
            "planned period",
            f"{plan.frame_period_s * 1e3:.4f} ms = {plan.frame_rate_hz:.3f} Hz "
            f"(set by {plan.period_limit})",
        ),
        (
            "motion per frame",
            f"{plan.motion_per_frame_px:.3f} px (capture range {args.capture_range_px:g} px"
            f"{capture})",
        ),
        ("out of plane", bound.describe()),
    ]
    width = max(len(label) for label, _ in rows) + 2
    for label, value in rows:
        print(f"{label:<{width}}{value}")
    return 0
