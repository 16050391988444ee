"""Command line `extensometer`.

Subcommands:
    track   correlate points of interest between a reference image and target images.
    bench   accuracy and speed benchmarks of the measurement core (reports with figures).
    plan    motion blur of an exposure, and the exposure and frame period for a blur budget.
    run     a tensile test: measure strain until a strain limit or the break (`--sim`: the
            simulated test, with its ground truth and errors in the summary).
    serve   run as a service: a test per start command, Modbus, Rerun, systemd watchdog.
    replay  measure a recorded test again from its recorded pixels.
    info    summarise a recording and check its integrity.
    camera-check  grab frames from a camera and report size, format, rate and losses.
    machine-check   read the machine controller's state and report it, with read rate and latency.
    trigger-check handshake with the trigger microcontroller, time its link, fit its clock.

Bad input ends with one line `extensometer: error: ...` naming the culprit and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from appliance.errors import InputError

EXIT_USAGE = 2


class _Parser(argparse.ArgumentParser):
    """Argument parser whose errors are one line, like every other error of the tool."""

    def error(self, message: str) -> None:  # type: ignore[override]
        command = self.prog.removeprefix("extensometer").strip()
        raise InputError(f"{command}: {message}" if command else message)


def _number(parse, accept, requirement: str):
    """An argparse type: `parse` the text, then keep the value only if `accept` says so."""

    def convert(text: str):
        try:
            value = parse(text)
        except ValueError:
            kind = "an integer" if parse is int else "a number"
            raise argparse.ArgumentTypeError(f"{text!r} is not {kind}") from None
        if not (math.isfinite(value) and accept(value)):
            raise argparse.ArgumentTypeError(f"{value} {requirement}")
        return value

    return convert


_subset_size = _number(int, lambda v: v >= 5 and v % 2 == 1, "must be an odd size >= 5")
_window_size = _number(int, lambda v: v >= 3 and v % 2 == 1, "must be an odd size >= 3")
_non_negative_int = _number(int, lambda v: v >= 0, "must be >= 0")
_non_negative_float = _number(float, lambda v: v >= 0, "must be a finite number >= 0")
_finite_float = _number(float, lambda v: True, "is not finite")
_positive_float = _number(float, lambda v: v > 0, "must be a finite number > 0")
_frame_count = _number(int, lambda v: v >= 2, "must be >= 2")
_read_count = _number(int, lambda v: v >= 1, "must be >= 1")


def build_parser() -> argparse.ArgumentParser:
    """The `extensometer` argument parser."""
    from appliance.dic.correlation import DEFAULT_PREFILTER_SIGMA, SEARCH_METHODS

    parser = _Parser(prog="extensometer", description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    track = commands.add_parser(
        "track",
        help="correlate points between a reference and target images",
        description=(
            "Measure the displacement of each point of interest from REF to every IMG: "
            "integer search, then IC-GN subpixel refinement with a first-order shape "
            "function. Each image is measured against REF; the result of the previous "
            "image seeds the next one (the points file's u0,v0 seed the first)."
        ),
    )
    track.add_argument("reference", metavar="REF", help="reference image (TIFF, PNG, BMP)")
    track.add_argument("images", metavar="IMG", nargs="+", help="target images")
    track.add_argument(
        "--points", required=True, metavar="FILE", help="CSV with header x,y[,u0,v0]"
    )
    track.add_argument("--subset", type=_subset_size, default=41, help="subset size, px (41)")
    track.add_argument(
        "--search", choices=SEARCH_METHODS, default="zncc", help="integer search method (zncc)"
    )
    track.add_argument(
        "--search-radius", type=_non_negative_int, default=50, help="search half-width, px (50)"
    )
    track.add_argument(
        "--prefilter-sigma",
        type=_non_negative_float,
        default=DEFAULT_PREFILTER_SIGMA,
        help=f"Gaussian pre-filter of both images before IC-GN, px ({DEFAULT_PREFILTER_SIGMA}; "
        "0 = off)",
    )
    track.add_argument(
        "--blur-px",
        type=_non_negative_float,
        default=0.0,
        help="known motion blur of the targets, px: the reference is blurred to match (0)",
    )
    track.add_argument(
        "--blur-angle-deg",
        type=_finite_float,
        default=0.0,
        help="direction of that motion, degrees from +x towards +y (0)",
    )
    track.add_argument("--lpq-window", type=_window_size, default=None, help="LPQ window M, px (7)")
    output = track.add_mutually_exclusive_group()
    output.add_argument("--json", action="store_true", help="print JSON on stdout")
    output.add_argument("--out", metavar="FILE", help="write JSON to FILE")

    bench = commands.add_parser("bench", help="benchmarks of the measurement core")
    benches = bench.add_subparsers(dest="bench", required=True, parser_class=_Parser)
    accuracy = benches.add_parser(
        "accuracy",
        help="reproduce the paper's accuracy experiments; writes report.md, plots, results.json",
    )
    accuracy.add_argument("--out", required=True, metavar="DIR", help="report directory")
    accuracy.add_argument(
        "--quick", action="store_true", help="fewer cases and points, for a fast look"
    )
    speed = benches.add_parser("speed", help="IC-GN and integer-search throughput")
    speed.add_argument("--json", action="store_true", help="print JSON instead of a table")
    speed.add_argument("--out", metavar="FILE", help="also write the JSON to FILE")
    simulated = benches.add_parser(
        "sim", help="whole simulated tensile tests against their ground truth"
    )
    simulated.add_argument("--out", required=True, metavar="DIR", help="report directory")
    simulated.add_argument("--quick", action="store_true", help="shortened tests")
    modbus = benches.add_parser(
        "modbus", help="latency from frame delivery to Modbus register update (10 points)"
    )
    modbus.add_argument("--json", action="store_true", help="print JSON instead of a table")
    modbus.add_argument("--out", metavar="FILE", help="also write the JSON to FILE")
    camera = benches.add_parser(
        "camera",
        help="GigE Vision acquisition rate and loss (the Aravis fake camera on loopback)",
    )
    camera.add_argument("--camera", metavar="URL", help="a camera instead of the fake one")
    camera.add_argument("--frames", type=_frame_count, default=600, help="frames per setting")
    camera.add_argument("--json", action="store_true", help="print JSON instead of a table")
    camera.add_argument("--out", metavar="FILE", help="also write the JSON to FILE")
    machine = benches.add_parser(
        "machine", help="machine controller state reads over Modbus TCP: rate and latency"
    )
    machine.add_argument(
        "--machine", metavar="URL", help="a controller instead of the simulated one"
    )
    machine.add_argument(
        "--duration", type=_positive_float, default=5.0, help="seconds per measurement (5)"
    )
    machine.add_argument("--json", action="store_true", help="print JSON instead of a table")
    machine.add_argument("--out", metavar="FILE", help="also write the JSON to FILE")
    for name, text in (
        ("trigger-jitter", "trigger pulse timing of the real firmware under simavr"),
        ("clock-sync", "host timestamp error after clock sync, firmware under simavr"),
    ):
        firmware = benches.add_parser(name, help=text)
        firmware.add_argument("--json", action="store_true", help="print JSON, not a table")
        firmware.add_argument("--out", metavar="FILE", help="also write the JSON to FILE")

    _add_plan_parser(commands)
    _add_run_parser(commands)
    return parser


def _add_run_parser(commands) -> None:
    run = commands.add_parser(
        "run",
        help="run a tensile test (simulated with --sim)",
        description=(
            "Run a tensile test: take the reference image, place the gauge marks, start the "
            "crosshead and measure strain until the strain limit or the break. Writes "
            "strain.csv and summary.json to --out and prints the summary."
        ),
    )
    run.add_argument("--config", type=Path, help="TOML configuration file (default: defaults)")
    run.add_argument("--sim", action="store_true", help="use the simulated machine and camera")
    run.add_argument("--material", choices=("rubber", "metal"), help="simulated material")
    run.add_argument("--speed-mm-min", type=_positive_float, help="crosshead speed, mm/min")
    run.add_argument("--exposure-us", type=_positive_float, help="exposure (default: planned)")
    run.add_argument("--frame-rate-hz", type=_positive_float, help="frame rate (default: planned)")
    run.add_argument("--seed", type=_non_negative_int, help="seed of the simulated world")
    until = run.add_mutually_exclusive_group()
    until.add_argument(
        "--until-strain", type=_positive_float, help="stop at this engineering strain"
    )
    until.add_argument("--until-break", action="store_true", help="run to the break (default)")
    pace = run.add_mutually_exclusive_group()
    pace.add_argument("--realtime", action="store_true", help="simulate in real time")
    pace.add_argument("--fast", action="store_true", help="simulate as fast as possible")
    run.add_argument("--out", type=Path, help="output directory for strain.csv, summary.json")
    run.add_argument(
        "--record", type=Path, metavar="FILE.mcap", help="record the test to a new MCAP file"
    )
    _add_modbus_options(run)
    _add_rerun_options(run)
    run.add_argument("--json", action="store_true", help="print the summary as JSON, quietly")

    serve = commands.add_parser(
        "serve",
        help="run as a service: tests on the controller's command, Modbus, Rerun, watchdog",
        description=(
            "Run the appliance as a long-running service (systemd Type=notify): start the "
            "Modbus strain server and the Rerun server, then run one test per start command "
            '(or one at once with [service] start = "auto"), recording each to a new MCAP '
            "file in the state directory. SIGTERM ends the running test cleanly."
        ),
    )
    serve.add_argument("--config", type=Path, help="TOML configuration file (default: defaults)")
    serve.add_argument(
        "--record",
        type=Path,
        metavar="FILE.mcap",
        help="the first test's recording (later ones: FILE-2.mcap, ...; default: "
        "timestamped files in the state directory)",
    )
    _add_modbus_options(serve)
    _add_rerun_options(serve)

    replay = commands.add_parser(
        "replay",
        help="measure a recorded test again from its recorded pixels",
        description=(
            "Re-run the tracker on the pixels recorded in FILE.mcap with the recorded "
            "configuration: the strain series is reproduced bit for bit "
            "(max_abs_diff_to_recorded = 0.0). With --config, the tables and keys of that "
            "file replace the recorded ones and the test is measured again. A damaged file "
            "is replayed up to the damage, which is reported."
        ),
    )
    replay.add_argument("recording", metavar="FILE.mcap", type=Path, help="a recording")
    replay.add_argument(
        "--config", type=Path, metavar="OVERRIDE", help="TOML tables replacing recorded keys"
    )
    _add_rerun_options(replay)
    replay.add_argument("--json", action="store_true", help="print the summary as JSON, quietly")

    info = commands.add_parser(
        "info",
        help="summarise a recording and check its integrity",
        description=(
            "Read FILE.mcap front to back, checking every CRC, and print what it holds: the "
            "test, its channels and message counts, how the run ended, and any damage."
        ),
    )
    info.add_argument("recording", metavar="FILE.mcap", type=Path, help="a recording")
    info.add_argument("--json", action="store_true", help="print JSON on stdout")

    camera_check = commands.add_parser(
        "camera-check",
        help="grab frames from a camera and report what arrived",
        description=(
            "Open the camera, free-run it, grab N frames and report image size, pixel "
            "format, the frame rate achieved, lost frames, device timestamps and grey "
            "levels. The first command to run on a new installation. Exit status 1 when "
            "the camera cannot be opened or sends nothing, or frames were lost; 2 for a "
            "bad URL or setting."
        ),
    )
    camera_check.add_argument("--camera", metavar="URL", help="camera URL ([camera] url)")
    camera_check.add_argument("--config", type=Path, help="TOML configuration ([camera] table)")
    camera_check.add_argument("--frames", type=_frame_count, default=100, help="frames (100)")
    camera_check.add_argument(
        "--rate", type=_positive_float, default=30.0, help="frame rate asked for, Hz (30)"
    )
    camera_check.add_argument("--exposure-us", type=_positive_float, help="exposure, us")
    camera_check.add_argument("--json", action="store_true", help="print JSON on stdout")

    machine_check = commands.add_parser(
        "machine-check",
        help="read the machine controller's state and report it",
        description=(
            "Open the controller, read its state N times (nothing is written) and print "
            "crosshead position, speed, force and running, with the read rate and latency. "
            "Exit status 1 when the controller cannot be reached or answers with an error; "
            "2 for a bad URL or register map."
        ),
    )
    machine_check.add_argument("--machine", metavar="URL", help="controller URL ([machine] url)")
    machine_check.add_argument(
        "--config", type=Path, help="TOML configuration ([machine] table, register map)"
    )
    machine_check.add_argument("--reads", type=_read_count, default=50, help="reads (50)")
    machine_check.add_argument("--json", action="store_true", help="print JSON on stdout")

    trigger_check = commands.add_parser(
        "trigger-check",
        help="handshake with the trigger microcontroller and time its link",
        description=(
            "Open the trigger microcontroller's serial port, check that its firmware speaks "
            "this host's protocol and message table, time N round trips and fit its clock, "
            "and read the encoder position. Nothing is triggered. Exit status 1 when it "
            "does not answer or runs other firmware (both versions and hashes named)."
        ),
    )
    trigger_check.add_argument(
        "--port", required=True, metavar="URL", help="serial device or pyserial URL"
    )
    trigger_check.add_argument("--pings", type=_read_count, default=50, help="round trips (50)")
    trigger_check.add_argument("--json", action="store_true", help="print JSON on stdout")


def _add_modbus_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--modbus-tcp", metavar="HOST:PORT", help="serve strain on Modbus TCP ([modbus] tcp)"
    )
    parser.add_argument(
        "--modbus-rtu", metavar="DEVICE", help="serve strain on Modbus RTU ([modbus] rtu_device)"
    )


def _add_rerun_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--rerun-serve", metavar="HOST:PORT", help="gRPC server for Rerun viewers ([rerun] serve)"
    )
    parser.add_argument(
        "--rerun-connect", metavar="URL", help="push to a Rerun viewer at URL ([rerun] connect)"
    )
    parser.add_argument("--rerun-save", metavar="FILE.rrd", help="save an .rrd ([rerun] save)")


def _with_live_options(config, args: argparse.Namespace):
    """`config` with the --modbus-* and --rerun-* options applied (validated like the file)."""
    from appliance.config import config_from_table, config_to_table, merge_tables

    table = config_to_table(config)
    for option, section, key in (
        ("modbus_tcp", "modbus", "tcp"),
        ("modbus_rtu", "modbus", "rtu_device"),
        ("rerun_serve", "rerun", "serve"),
        ("rerun_connect", "rerun", "connect"),
        ("rerun_save", "rerun", "save"),
    ):
        value = getattr(args, option, None)
        if value is None:
            continue
        table = merge_tables(table, {section: {key: value}})
        where = f"[{section}] {key}: "
        try:
            config = config_from_table(table, "--" + option.replace("_", "-"))
        except InputError as error:
            raise InputError(str(error).replace(where, "", 1)) from None
    return config


def _viewer(config):
    """The Rerun viewer the configuration asks for, or None."""
    from appliance.live.viewer import RerunViewer, has_sinks

    return RerunViewer(config.rerun) if has_sinks(config.rerun) else None


def _run_config(args: argparse.Namespace):
    import dataclasses

    from appliance.config import Config, load_config

    config = load_config(args.config) if args.config else Config()
    config = _with_live_options(config, args)
    run_table = config.run
    if args.speed_mm_min is not None:
        run_table = dataclasses.replace(run_table, speed_mm_min=args.speed_mm_min)
    if args.until_strain is not None:
        run_table = dataclasses.replace(run_table, until_strain=args.until_strain)
    if args.until_break:
        run_table = dataclasses.replace(run_table, until_strain=0.0, until_break=True)
    camera = config.camera
    if args.exposure_us is not None:
        camera = dataclasses.replace(camera, exposure_us=args.exposure_us)
    if args.frame_rate_hz is not None:
        camera = dataclasses.replace(camera, frame_rate_hz=args.frame_rate_hz)
    sim = config.sim
    if args.material is not None:
        sim = dataclasses.replace(sim, material=args.material)
    if args.seed is not None:
        sim = dataclasses.replace(sim, seed=args.seed)
    if args.realtime or args.fast:
        sim = dataclasses.replace(sim, realtime=bool(args.realtime))
    return dataclasses.replace(config, run=run_table, camera=camera, sim=sim)


def _run(args: argparse.Namespace) -> int:
    from appliance.live.link import LiveLink
    from appliance.runner import run_test
    from hal.errors import HardwareError

    config = _run_config(args)
    progress = None if args.json or not sys.stderr.isatty() else sys.stderr
    link = LiveLink(config, viewer=_viewer(config))
    try:
        link.start()
        outcome = run_test(
            config,
            simulate=args.sim,
            out_dir=args.out,
            progress=progress,
            record_path=args.record,
            hooks=link.hooks(),
        )
    except HardwareError as error:
        raise InputError(f"run: {error}") from None
    except OSError as error:
        raise InputError(f"run: {error.filename or ''}: {error.strerror}") from None
    finally:
        link.close()
    if args.json:
        print(outcome.to_json())
    else:
        print_summary(outcome)
    return 0 if outcome.summary.exit_status.ended_normally else 1


def _serve(args: argparse.Namespace) -> int:
    from appliance.config import Config, load_config
    from appliance.live.sd_notify import ServiceNotifier
    from appliance.service import Service

    config = load_config(args.config) if args.config else Config()
    config = _with_live_options(config, args)
    with ServiceNotifier() as notifier:
        return Service(
            config, record_path=args.record, notifier=notifier, viewer=_viewer(config)
        ).run()


def _replay(args: argparse.Namespace) -> int:
    from appliance.config import Config
    from appliance.replay import is_exact, replay_recording

    progress = None if args.json or not sys.stderr.isatty() else sys.stderr
    viewer = _viewer(_with_live_options(Config(), args))
    outputs = [viewer] if viewer is not None else []
    for output in outputs:
        output.start()
    try:
        outcome = replay_recording(
            args.recording, override=args.config, outputs=outputs, progress=progress
        )
    finally:
        for output in outputs:
            output.close()
    if args.json:
        print(outcome.to_json())
    else:
        print_summary(outcome)
    damage = outcome.extra.get("damage")
    if damage:
        print(f"extensometer: {args.recording}: {damage}", file=sys.stderr)
        return 1
    if args.config is None and not is_exact(outcome):
        print(
            f"extensometer: {args.recording}: {outcome.extra['samples_differing']} samples "
            "differ from the recording",
            file=sys.stderr,
        )
        return 1
    return 0


def print_summary(outcome, stream=sys.stdout) -> None:
    """The summary as aligned human-readable lines."""
    for key, value in outcome.as_dict().items():
        if isinstance(value, float):
            value = f"{value:.6g}"
        stream.write(f"{key:38s} {value}\n")


def _info(args: argparse.Namespace) -> int:
    from appliance.recording.info import print_info, recording_info

    info = recording_info(args.recording)
    if args.json:
        json.dump(info, sys.stdout, indent=1)
        sys.stdout.write("\n")
    else:
        print_info(info, sys.stdout)
    if info["damage"]:
        print(f"extensometer: {args.recording}: {info['damage']}", file=sys.stderr)
        return 1
    return 0


def _add_plan_parser(commands) -> None:
    from appliance.plan.exposure import DEFAULT_MAX_PERIOD_S

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
        "--focal-length-mm", type=_positive_float, required=True, help="focal length f, mm"
    )
    plan.add_argument(
        "--object-distance-mm",
        type=_positive_float,
        required=True,
        help="specimen-to-lens distance u, mm (> f)",
    )
    plan.add_argument(
        "--pixel-size-um", type=_positive_float, required=True, help="sensor pixel pitch p, um"
    )
    plan.add_argument("--exposure-s", type=_positive_float, required=True, help="exposure T, s")
    plan.add_argument(
        "--speed-mm-min", type=_non_negative_float, required=True, help="crosshead speed, mm/min"
    )
    plan.add_argument(
        "--speed-fraction",
        type=_positive_float,
        default=1.0,
        help="fastest gauge point speed / crosshead speed (1, a safe bound)",
    )
    plan.add_argument(
        "--blur-budget-px", type=_positive_float, default=1.0, help="largest blur wanted, px (1)"
    )
    plan.add_argument(
        "--capture-range-px",
        type=_positive_float,
        default=20.0,
        help="largest frame-to-frame motion the search covers, px (20)",
    )
    plan.add_argument(
        "--min-exposure-us",
        type=_positive_float,
        default=50.0,
        help="shortest exposure the camera allows, us (50)",
    )
    plan.add_argument(
        "--max-exposure-us",
        type=_positive_float,
        default=20000.0,
        help="longest exposure wanted, us (20000)",
    )
    plan.add_argument(
        "--max-period-s",
        type=_positive_float,
        default=DEFAULT_MAX_PERIOD_S,
        help=f"longest frame period wanted, s ({DEFAULT_MAX_PERIOD_S:g}; the period at speed 0)",
    )
    plan.add_argument("--json", action="store_true", help="print JSON on stdout")


def _track(args: argparse.Namespace) -> int:
    from appliance.cli.image_files import read_grey
    from appliance.cli.points_file import read_points
    from appliance.dic.correlation import Correlator, PointStatus

    points = read_points(args.points)
    reference = read_grey(args.reference)
    height, width = reference.shape
    half = args.subset // 2
    for (x, y), line in zip(points.xy, points.lines, strict=True):
        if x - half < 0 or y - half < 0 or x + half > width - 1 or y + half > height - 1:
            raise InputError(
                f"{args.points}:{line}: subset {args.subset}x{args.subset} at ({x:g}, {y:g}) "
                f"reaches outside the {width}x{height} reference image {args.reference}"
            )
    if args.lpq_window is not None and args.lpq_window > args.subset:
        raise InputError(f"track: --lpq-window {args.lpq_window} exceeds --subset {args.subset}")
    correlator = Correlator(
        subset=args.subset,
        search=args.search,
        search_radius=args.search_radius,
        prefilter_sigma=args.prefilter_sigma,
        reference_blur=(args.blur_px, args.blur_angle_deg) if args.blur_px > 0 else None,
        lpq_window=args.lpq_window,
    )
    correlator.prepare(reference.astype(np.float64), points.xy)
    guess = np.zeros((len(points.xy), 2)) if points.guess is None else points.guess.copy()
    measured: list[dict] = []
    try:
        for path in args.images:
            image = read_grey(path)
            if image.shape != reference.shape:
                raise InputError(
                    f"{path}: size {image.shape[1]}x{image.shape[0]} differs from the "
                    f"reference {args.reference} ({width}x{height})"
                )
            result = correlator.measure(image.astype(np.float64), guess).refinement
            converged = result.status == PointStatus.CONVERGED
            guess[converged, 0] = result.u[converged]
            guess[converged, 1] = result.v[converged]
            measured.append(_image_record(path, points.xy, result))
    except InputError as error:
        _emit(args, measured)
        raise error
    _emit(args, measured)
    return 0


def _finite_or_none(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def _image_record(path: str, xy: np.ndarray, result) -> dict:
    from appliance.dic.icgn import PointStatus

    records = []
    for k in range(len(xy)):
        records.append(
            {
                "x": float(xy[k, 0]),
                "y": float(xy[k, 1]),
                "u": _finite_or_none(result.u[k]),
                "v": _finite_or_none(result.v[k]),
                "ux": _finite_or_none(result.ux[k]),
                "uy": _finite_or_none(result.uy[k]),
                "vx": _finite_or_none(result.vx[k]),
                "vy": _finite_or_none(result.vy[k]),
                "zncc": _finite_or_none(result.zncc[k]),
                "iterations": int(result.iterations[k]),
                "status": PointStatus(int(result.status[k])).name.lower(),
            }
        )
    return {"path": str(path), "points": records}


def _emit(args: argparse.Namespace, measured: list[dict]) -> None:
    document = {"images": measured}
    if args.out:
        try:
            Path(args.out).write_text(json.dumps(document, indent=1) + "\n", encoding="utf-8")
        except OSError as exc:
            raise InputError(f"{args.out}: cannot write output ({exc.strerror})") from None
    elif args.json:
        json.dump(document, sys.stdout, indent=1)
        sys.stdout.write("\n")
    else:
        for image in measured:
            print(image["path"])
            print(f"{'x':>9} {'y':>9} {'u':>10} {'v':>10} {'zncc':>8} {'it':>3}  status")
            for p in image["points"]:
                u = "-" if p["u"] is None else f"{p['u']:10.4f}"
                v = "-" if p["v"] is None else f"{p['v']:10.4f}"
                zncc = "-" if p["zncc"] is None else f"{p['zncc']:8.5f}"
                print(
                    f"{p['x']:9.2f} {p['y']:9.2f} {u:>10} {v:>10} {zncc:>8} "
                    f"{p['iterations']:3d}  {p['status']}"
                )


def _plan(args: argparse.Namespace) -> int:
    from appliance.plan.exposure import motion_blur_length, plan_exposure
    from appliance.plan.optics import Optics

    if not args.object_distance_mm > args.focal_length_mm:
        raise InputError(
            f"plan: --object-distance-mm {args.object_distance_mm:g} must exceed "
            f"--focal-length-mm {args.focal_length_mm:g} for a real image"
        )
    if args.min_exposure_us > args.max_exposure_us:
        raise InputError(
            f"plan: --min-exposure-us {args.min_exposure_us:g} exceeds "
            f"--max-exposure-us {args.max_exposure_us:g}"
        )
    if args.max_exposure_us * 1e-6 > args.max_period_s:
        raise InputError(
            f"plan: --max-period-s {args.max_period_s:g} is shorter than "
            f"--max-exposure-us {args.max_exposure_us:g}"
        )
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
    ]
    width = max(len(label) for label, _ in rows) + 2
    for label, value in rows:
        print(f"{label:<{width}}{value}")
    return 0


def _device_check(args: argparse.Namespace) -> int:
    from appliance import device_check
    from appliance.config import Config, load_config
    from hal.errors import HardwareConfigError, HardwareError

    if args.command == "trigger-check":
        from firmware_bridge.link import FirmwareError

        try:
            report = device_check.check_trigger(args.port, pings=args.pings)
        except FirmwareError as error:
            print(f"extensometer: trigger-check: {args.port}: {error}", file=sys.stderr)
            return 1
        text = device_check.trigger_report_lines(report)
        print(json.dumps(report, indent=2) if args.json else "\n".join(text))
        return 0
    config = load_config(args.config) if args.config else Config()
    try:
        if args.command == "camera-check":
            camera = device_check.camera_for_check(config, args.camera or config.camera.url)
            report = device_check.check_camera(
                camera,
                config,
                frames=args.frames,
                rate_hz=args.rate,
                exposure_us=args.exposure_us,
            )
            lines = device_check.camera_report_lines(report)
            failed = report["lost"] > 0
        else:
            machine = device_check.machine_for_check(config, args.machine or config.machine.url)
            report = device_check.check_machine(machine, reads=args.reads)
            lines = device_check.machine_report_lines(report)
            failed = False
    except HardwareConfigError as error:
        raise InputError(f"{args.command}: {error}") from None
    except HardwareError as error:
        print(f"extensometer: {args.command}: {error}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print("\n".join(lines))
    return 1 if failed else 0


def _bench(args: argparse.Namespace) -> int:
    if args.bench == "accuracy":
        from appliance.bench.accuracy import run_accuracy_benchmark

        return run_accuracy_benchmark(Path(args.out), quick=args.quick)
    if args.bench == "modbus":
        from appliance.bench.modbus import run_modbus_benchmark

        return run_modbus_benchmark(Path(args.out) if args.out else None, args.json)
    if args.bench == "camera":
        from appliance.bench.camera import run_camera_benchmark

        return run_camera_benchmark(
            Path(args.out) if args.out else None, args.json, url=args.camera, frames=args.frames
        )
    if args.bench == "machine":
        from appliance.bench.machine_client import run_machine_benchmark

        return run_machine_benchmark(
            Path(args.out) if args.out else None,
            args.json,
            url=args.machine,
            duration_s=args.duration,
        )
    if args.bench == "trigger-jitter":
        from appliance.bench.trigger_jitter import run_trigger_jitter_benchmark

        return run_trigger_jitter_benchmark(Path(args.out) if args.out else None, args.json)
    if args.bench == "clock-sync":
        from appliance.bench.clock_sync import run_clock_sync_benchmark

        return run_clock_sync_benchmark(Path(args.out) if args.out else None, args.json)
    if args.bench == "sim":
        from appliance.bench.simulated import run_simulated_benchmark

        return run_simulated_benchmark(Path(args.out), quick=args.quick)
    from appliance.bench.speed import run_speed_benchmark

    return run_speed_benchmark(as_json=args.json, out=Path(args.out) if args.out else None)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the `extensometer` command line; returns the process exit status."""
    # Device failures are reported by the appliance, once each; pymodbus would log every
    # failed request of a controller outage on stderr.
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    try:
        args = build_parser().parse_args(argv)
        if args.command == "track":
            return _track(args)
        if args.command == "plan":
            return _plan(args)
        if args.command == "run":
            return _run(args)
        if args.command == "replay":
            return _replay(args)
        if args.command == "serve":
            return _serve(args)
        if args.command == "info":
            return _info(args)
        if args.command in ("camera-check", "machine-check", "trigger-check"):
            return _device_check(args)
        return _bench(args)
    except InputError as error:
        print(f"extensometer: error: {error}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("extensometer: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
