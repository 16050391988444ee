"""`extensometer verify`: ISO 9513 verification against a precision calibrator.

Two ways in, one computation (`appliance.run.verification`) and one report
(`appliance.run.verification_report`: `verification.json` and `report.html` in `--out`):

* `--sim`: a simulated calibrator (`appliance.sim.calibrator`) in the specimen plane of the
  simulated bench, seen through its camera, measured by the extensometer's own tracking
  (`appliance.run.calibrator_measurement`). The calibrator's own error is set with
  `--calibrator-error-percent` and `--calibrator-offset-um` (0 by default).
* `--readings FILE.csv`: a lab's readings of a real calibrator
  (`appliance.run.verification_readings`): the computation and the report alone.

Exit status 0 when the run met the requested class (`--class`, 0.5 by default), 1 when it did
not (the report and the printed findings say where), 2 for bad input.
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import shlex
import sys
from pathlib import Path
from typing import Any

from appliance import __version__
from appliance.cli import arguments
from appliance.config import Config
from appliance.errors import InputError
from appliance.run.iso9513 import CLASSES, class_named
from appliance.run.verification import (
    Verification,
    VerificationData,
    calibration_steps,
    series_directions,
    verify,
)

VERIFY_OPTIONS = (
    ("material", "sim", "material"),
    ("seed", "sim", "seed"),
    ("bench", "sim", "bench"),
)
"""(argument, table, key) of `verify`'s options that set configuration keys."""
DEFAULT_RANGE_UM = 1000.0
DEFAULT_LOWER_UM = 20.0
DEFAULT_REST_FRAMES = 10


def add_parser(commands: argparse._SubParsersAction) -> None:
    """The `verify` command."""
    parser = commands.add_parser(
        "verify",
        help="ISO 9513 verification against a calibrator (simulated with --sim)",
        description=(
            "Verify the extensometer to ISO 9513: bias error at every step of two or more "
            "series over the range, resolution and gauge length error, graded into the "
            "standard's classes. Writes verification.json and report.html to --out; exit "
            "status 0 when the requested class is met, 1 when it is not."
        ),
    )
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument(
        "--sim", action="store_true", help="measure a simulated calibrator on the simulated bench"
    )
    source.add_argument(
        "--readings",
        type=Path,
        metavar="FILE.csv",
        help="a real calibrator's readings: series, calibrator_um, reading_um[, gauge_length_mm]",
    )
    parser.add_argument("--config", type=Path, help="TOML configuration file (default: defaults)")
    parser.add_argument(
        "--out", type=arguments.output_directory, required=True, help="output directory"
    )
    parser.add_argument(
        "--class",
        dest="extensometer_class",
        default="0.5",
        choices=[c.name for c in CLASSES],
        help="the class to verify against (default 0.5)",
    )
    parser.add_argument(
        "--bench", choices=("ideal", "typical", "harsh"), help="simulated bench ([sim] bench)"
    )
    parser.add_argument("--material", choices=("rubber", "metal"), help="simulated preset's camera")
    parser.add_argument("--seed", type=arguments.non_negative_int, help="seed of the simulation")
    parser.add_argument(
        "--range-um",
        type=arguments.within(float, 1.0, 100_000.0),
        default=DEFAULT_RANGE_UM,
        help=f"upper limit of the calibrated range, um (default {DEFAULT_RANGE_UM:g})",
    )
    parser.add_argument(
        "--lower-um",
        type=arguments.positive_float,
        default=DEFAULT_LOWER_UM,
        help=f"lower limit of the calibrated range, um (default {DEFAULT_LOWER_UM:g})",
    )
    parser.add_argument(
        "--series",
        type=arguments.within(int, 1, 20),
        default=2,
        help="series of measurements, alternately increasing and decreasing (default 2)",
    )
    parser.add_argument(
        "--rest-frames",
        type=arguments.within(int, 2, 1000),
        default=DEFAULT_REST_FRAMES,
        help=f"frames read at rest for the resolution (default {DEFAULT_REST_FRAMES})",
    )
    parser.add_argument(
        "--calibrator-error-percent",
        type=arguments.within(float, -10.0, 10.0),
        default=0.0,
        help="the simulated calibrator's scale error, %% of its reading (default 0)",
    )
    parser.add_argument(
        "--calibrator-offset-um",
        type=arguments.within(float, -100.0, 100.0),
        default=0.0,
        help="the simulated calibrator's zero offset, um (default 0)",
    )
    parser.add_argument(
        "--gauge-length-mm",
        type=arguments.within(float, 0.1, 10_000.0),
        help="nominal gauge length, mm (default: [gauge] length_mm, or the simulated preset's)",
    )
    parser.add_argument(
        "--display-step-um",
        type=arguments.non_negative_float,
        default=0.0,
        help="the reading's display step, um (--readings; default 0: a continuous reading)",
    )
    parser.set_defaults(handler=run_verify)


def run_verify(args: argparse.Namespace) -> int:
    """Run `verify`; 0 when the requested class is met, 1 when not."""
    from appliance.run.object_plane import resolved_calibration_path
    from appliance.run.verification_report import write_verification

    config = resolved_calibration_path(
        arguments.configuration(
            args.config, args, arguments.option_overrides(args, VERIFY_OPTIONS)
        ),
        args.config,
    )
    _check_options(args)
    requested = class_named(args.extensometer_class)
    facts: dict[str, Any] = {
        "software_version": __version__,
        "command": "extensometer " + shlex.join(sys.argv[1:]),
        "created_utc": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "calibration_file": config.optics.calibration or None,
        "calibration_checksum": None,
    }
    if args.sim:
        data = _simulated(config, args, facts)
    else:
        data = _from_readings(config, args, facts)
    verification = verify(data, requested)
    json_path, html_path = write_verification(verification, args.out, facts)
    _print(verification, json_path, html_path)
    return 0 if verification.met else 1


SIM_ONLY = ("bench", "material", "seed", "calibrator_error_percent", "calibrator_offset_um")
"""Options of the simulated calibrator, refused with --readings."""


def _check_options(args: argparse.Namespace) -> None:
    """Refuse an option that has no meaning for the source chosen, naming it."""
    if args.sim:
        if args.display_step_um:
            raise InputError("verify: --display-step-um applies to --readings only")
        return
    for name in SIM_ONLY:
        if getattr(args, name) not in (None, 0.0):
            raise InputError(f"verify: --{name.replace('_', '-')} applies to --sim only")


def _nominal_gauge_length(config: Config, args: argparse.Namespace) -> float | None:
    if args.gauge_length_mm is not None:
        return float(args.gauge_length_mm)
    return config.gauge.length_mm


def _from_readings(
    config: Config, args: argparse.Namespace, facts: dict[str, Any]
) -> VerificationData:
    from appliance.run.object_plane import calibration_file
    from appliance.run.verification_readings import read_readings

    calibration = calibration_file(config)
    if calibration is not None:
        facts["calibration_checksum"] = calibration.checksum
    points, rest = read_readings(args.readings)
    facts["readings_file"] = str(args.readings)
    facts["readings_sha256"] = hashlib.sha256(args.readings.read_bytes()).hexdigest()
    return VerificationData(
        points=points,
        rest_readings_um=rest,
        display_step_um=args.display_step_um,
        nominal_gauge_length_mm=_nominal_gauge_length(config, args),
        source=f"readings of a calibrator: {args.readings}",
    )


def _simulated(config: Config, args: argparse.Namespace, facts: dict[str, Any]) -> VerificationData:
    """Measure the simulated calibrator: every series, the readings at rest, the gauge length."""
    from appliance.plan.optics import configured_optics
    from appliance.run.calibrator_measurement import Setup, measure_series
    from appliance.run.object_plane import configured_calibration
    from appliance.sim.bench import bench_errors
    from appliance.sim.calibrator import SimCalibrator, calibrator_bench
    from appliance.sim.world import PRESETS

    preset = PRESETS[config.sim.material]
    optics = configured_optics(config, preset.optics)
    width = config.sim.sensor_width_px or preset.sensor_size[0]
    height = config.sim.sensor_height_px or preset.sensor_size[1]
    nominal = _nominal_gauge_length(config, args) or preset.specimen().gauge_length_mm
    calibration = configured_calibration(config, optics, (width, height))
    facts["calibration_checksum"] = calibration.checksum or None
    scale = optics.scale_mm_per_px
    bench = calibrator_bench(
        bench_errors(config.sim, (width, height), optics.object_distance_mm / scale),
        scale_mm_per_px=scale,
        object_distance_mm=optics.object_distance_mm,
        sensor_size=(width, height),
        seed=config.sim.seed,
    )
    try:
        bench.check_field()
    except ValueError as exc:
        raise InputError(f"[sim] lens_k1, lens_k2, lens_p1, lens_p2: {exc}") from None
    block_mm = min(10.0, 0.5 * nominal)
    try:
        calibrator = SimCalibrator(
            gauge_length_mm=nominal,
            bench=bench,
            speckle_radius_mm=preset.speckle_radius_mm,
            block_mm=block_mm,
            travel_mm=1.2 * args.range_um * 1e-3,
            scale_error=args.calibrator_error_percent / 100.0,
            offset_error_um=args.calibrator_offset_um,
            seed=config.sim.seed,
            read_noise=config.sim.read_noise_grey,
            electrons_per_grey=config.sim.electrons_per_grey,
        )
    except ValueError as exc:
        raise InputError(f"verify --sim: {exc}") from None
    g = config.gauge
    centre = (
        g.centre_x_px if g.centre_x_px is not None else 0.5 * (width - 1),
        g.centre_y_px if g.centre_y_px is not None else 0.5 * (height - 1),
    )
    setup = Setup(nominal, centre, calibration, config.gauge, config.tracking)
    try:
        steps = calibration_steps(args.range_um, args.lower_um)
    except ValueError as exc:
        raise InputError(f"--lower-um: {exc}") from None
    points = []
    rest: tuple[float, ...] = ()
    directions = {}
    for index, direction in enumerate(series_directions(args.series)):
        name = str(index + 1)
        directions[name] = direction
        readings = measure_series(
            calibrator,
            setup,
            name,
            direction,
            steps,
            rest_frames=args.rest_frames if index == 0 else 0,
        )
        points += readings.points
        rest = rest or readings.rest_um
    facts.update(
        {
            "bench": config.sim.bench,
            "material": config.sim.material,
            "scale_mm_per_px": calibration.scale_mm_per_px,
            "object_plane": calibration.in_object_plane,
            "sensor_px": f"{width}x{height}",
            "calibrator_error_percent": args.calibrator_error_percent,
            "calibrator_offset_um": args.calibrator_offset_um,
            "seed": config.sim.seed,
        }
    )
    return VerificationData(
        points=tuple(points),
        rest_readings_um=rest,
        nominal_gauge_length_mm=nominal,
        directions=directions,
        source=f"simulated calibrator on the {config.sim.bench} bench",
    )


def _print(verification: Verification, json_path: Path, html_path: Path) -> None:
    v = verification
    lines = [
        ("requested_class", v.requested.name),
        ("achieved_class", v.achieved or "none"),
        ("met", "yes" if v.met else "no"),
    ]
    for name, criterion in v.criteria.items():
        lines.append(
            (
                f"{name}_class",
                (criterion.best_class or "none") if criterion.assessed else "not assessed",
            )
        )
    worst = v.worst_bias
    if worst is not None:
        lines.append(("worst_bias", worst.describe_bias()))
    if v.resolution_um is not None:
        lines.append(("resolution_um", f"{v.resolution_um:.4g}"))
    if v.gauge_length_error_percent is not None:
        lines.append(("gauge_length_error_percent", f"{v.gauge_length_error_percent:+.4f}"))
    lines += [("verification", str(json_path)), ("report", str(html_path))]
    width = max(len(key) for key, _ in lines)
    for key, value in lines:
        print(f"{key:<{width}}  {value}")
    for finding in v.findings:
        print(f"finding: {finding}")
