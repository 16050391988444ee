"""`extensometer bench NAME`: the benchmarks, programs that measure and report figures.

Every benchmark prints its figures (a table, or JSON with `--json` where offered) and, with
`--out DIR`, writes its report and figures into DIR and refreshes DIR's index
(`appliance.bench.results`); the repository keeps the reference host's reports in
`appliance/bench/results/`. Targets are judged in the reports, never by the exit status: 0
means measured, met or not.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from appliance.cli import arguments
from appliance.errors import InputError


def add_parser(commands: argparse._SubParsersAction) -> None:
    """The `bench` command and its benchmarks."""
    bench = commands.add_parser("bench", help="benchmarks: programs that measure and report")
    benches = bench.add_subparsers(dest="bench", required=True, parser_class=arguments.Parser)

    accuracy = benches.add_parser(
        "accuracy",
        help="reproduce the paper's accuracy experiments: subpixel error, blur, stretch, subset",
    )
    accuracy.add_argument(
        "--quick", action="store_true", help="fewer cases and points, for a fast look"
    )
    _add_out(accuracy, required=True)
    accuracy.set_defaults(handler=_accuracy)

    search = benches.add_parser(
        "search",
        help="integer searches (ZNCC, blur-matched ZNCC, LPQ, the automatic choice) under blur, "
        "one-step stretch, noise and illumination change: success and time per point",
    )
    search.add_argument(
        "--full", action="store_true", help="every combination (675 cases) instead of 34"
    )
    _add_out(search, required=True)
    search.set_defaults(handler=_search)

    speed = benches.add_parser("speed", help="IC-GN and integer-search throughput")
    _add_json_and_out(speed)
    speed.set_defaults(handler=_speed)

    simulated = benches.add_parser(
        "sim", help="whole simulated tensile tests against their ground truth"
    )
    simulated.add_argument("--quick", action="store_true", help="shortened tests")
    _add_out(simulated, required=True)
    simulated.set_defaults(handler=_simulated)

    results = benches.add_parser(
        "results",
        help="a test's results (Rp0.2, Rm, E; rubber's TS, Eb, S100..S300) against the "
        "simulated materials' values",
    )
    results.add_argument("--quick", action="store_true", help="one steel test, rubber to 350 %%")
    _add_out(results, required=True)
    results.set_defaults(handler=_results)

    transverse = benches.add_parser(
        "transverse",
        help="the specimen's width at its edges and r (ISO 10113) against the simulated sheet",
    )
    transverse.add_argument("--quick", action="store_true", help="one seed")
    _add_out(transverse, required=True)
    transverse.set_defaults(handler=_transverse)

    realtime = benches.add_parser(
        "realtime",
        help="the simulated test in real time, recording and Modbus served: drops and CPU time",
    )
    realtime.add_argument(
        "--runs", type=arguments.within(int, 1, 100), default=1, help="tests (default 1)"
    )
    realtime.add_argument(
        "--until-strain",
        type=arguments.within(float, 0.0, 100.0, above=True),
        help="end each test at this strain (default: the break)",
    )
    realtime.add_argument(
        "--material", choices=("rubber", "metal"), default="rubber", help="(default rubber)"
    )
    _add_json_and_out(realtime)
    realtime.set_defaults(handler=_realtime)

    modbus = benches.add_parser(
        "modbus", help="latency from frame delivery to Modbus register update (10 points)"
    )
    _add_json_and_out(modbus)
    modbus.set_defaults(handler=_modbus)

    camera = benches.add_parser(
        "camera",
        help="GigE Vision acquisition rate and loss (the Aravis fake camera on loopback)",
    )
    camera.add_argument("--camera", metavar="URL", help="a camera instead of the fake one")
    camera.add_argument(
        "--frames", type=arguments.frame_count, default=600, help="frames per setting"
    )
    _add_json_and_out(camera)
    camera.set_defaults(handler=_camera)

    machine = benches.add_parser(
        "machine", help="the machine's state read over Modbus TCP: rate and latency"
    )
    machine.add_argument(
        "--machine", metavar="URL", help="a controller instead of the simulated one"
    )
    machine.add_argument(
        "--duration",
        type=arguments.within(float, 0.0, 3600.0, above=True),
        default=5.0,
        help="seconds per measurement (5)",
    )
    _add_json_and_out(machine)
    machine.set_defaults(handler=_machine)

    jitter = benches.add_parser(
        "trigger-jitter", help="trigger pulse timing of the real firmware under simavr"
    )
    _add_json_and_out(jitter)
    jitter.set_defaults(handler=_trigger_jitter)

    clock = benches.add_parser(
        "clock-sync", help="host timestamp error after clock sync, firmware under simavr"
    )
    _add_json_and_out(clock)
    clock.set_defaults(handler=_clock_sync)

    _add_soak(benches)
    _add_optics(benches)
    _add_detection(benches)
    _add_gige(benches)


def _add_gige(benches: argparse._SubParsersAction) -> None:
    gige = benches.add_parser(
        "gige",
        help="a GigE Vision camera at full rate through the whole appliance (recording on, "
        "Modbus polled): frames dropped, delivery -> register update latency",
    )
    gige.add_argument(
        "--duration-s",
        type=arguments.within(float, 1.0, 3600.0),
        default=60.0,
        help="seconds of test after its first sample (default 60)",
    )
    gige.add_argument(
        "--width-px", type=arguments.within(int, 128, 4096), default=1024, help="(default 1024)"
    )
    gige.add_argument(
        "--height-px", type=arguments.within(int, 128, 4096), default=1024, help="(default 1024)"
    )
    gige.add_argument(
        "--frame-rate-hz",
        type=arguments.within(float, 1.0, 1000.0),
        default=200.0,
        help="the camera's frame rate asked for (default 200)",
    )
    _add_json_and_out(gige)
    gige.set_defaults(handler=_gige)


def _gige(args: argparse.Namespace) -> int:
    from appliance.bench.gige_rate import run_gige_benchmark

    return run_gige_benchmark(
        args.out,
        args.json,
        duration_s=args.duration_s,
        width=args.width_px,
        height=args.height_px,
        frame_rate_hz=args.frame_rate_hz,
    )


def _add_detection(benches: argparse._SubParsersAction) -> None:
    detection = benches.add_parser(
        "detection",
        help="specimen detection's axis, centre and width against simulated views' truth",
    )
    detection.add_argument("--quick", action="store_true", help="one seed, three poses")
    _add_out(detection)
    detection.set_defaults(handler=_detection)


def _detection(args: argparse.Namespace) -> int:
    from appliance.bench.detection import run_detection_benchmark

    return run_detection_benchmark(args.out, quick=args.quick)


def _add_optics(benches: argparse._SubParsersAction) -> None:
    optics = benches.add_parser(
        "optics",
        help="camera calibration, measuring in the object plane and ISO 9513 classes on the "
        "simulated benches",
    )
    optics.add_argument(
        "--quick", action="store_true", help="fewer calibrations, shorter tests, one bench"
    )
    optics.add_argument(
        "--only",
        choices=("calibration", "rubber", "metal", "verify"),
        help="measure this section again into the report already in --out, keeping the rest",
    )
    _add_out(optics, required=True)
    optics.set_defaults(handler=_optics)


def _optics(args: argparse.Namespace) -> int:
    from appliance.bench.optics import run_optics_benchmark

    return run_optics_benchmark(args.out, quick=args.quick, only=args.only)


def _add_soak(benches: argparse._SubParsersAction) -> None:
    from appliance.bench.soak import SHIPPED_CONFIGURATION, WARM_UP_TESTS

    soak = benches.add_parser(
        "soak",
        help="serve back-to-back simulated tests: memory, files and threads per test",
    )
    soak.add_argument(
        "--config",
        type=Path,
        default=SHIPPED_CONFIGURATION,
        help="the service's configuration (default: the shipped systemd/extensometer.toml)",
    )
    soak.add_argument(
        "--duration-s",
        type=arguments.within(float, 1.0, 86400.0),
        default=600.0,
        help="how long to keep starting tests (default 600)",
    )
    soak.add_argument(
        "--test-s",
        type=arguments.within(float, 0.5, 3600.0),
        default=5.0,
        help="how long each test measures before the stop command (default 5)",
    )
    soak.add_argument(
        "--warm-up-tests",
        type=arguments.within(int, 0, 100000),
        default=WARM_UP_TESTS,
        help=f"tests left out of the slopes (default {WARM_UP_TESTS}: kernels, caches, the "
        "viewer's history filling up)",
    )
    soak.add_argument("--no-viewer", action="store_true", help="without the Rerun server")
    soak.add_argument(
        "--heap-diff",
        nargs=2,
        type=arguments.within(int, 1, 100000),
        metavar=("FIRST", "LAST"),
        help="trace the service's Python allocations and report what grew from the end of "
        "test FIRST to the end of test LAST, by allocation site (slows the service)",
    )
    _add_json_and_out(soak)
    soak.set_defaults(handler=_soak)


def _add_out(parser: argparse.ArgumentParser, *, required: bool = False) -> None:
    parser.add_argument(
        "--out",
        type=arguments.output_directory,
        required=required,
        metavar="DIR",
        help="results directory: the report, the figures as JSON, and the directory's index",
    )


def _add_json_and_out(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    _add_out(parser)


def _soak(args: argparse.Namespace) -> int:
    from appliance.bench.soak import run_soak_benchmark

    if args.heap_diff and args.heap_diff[0] >= args.heap_diff[1]:
        raise InputError("bench soak: --heap-diff: FIRST must be below LAST")
    return run_soak_benchmark(
        args.out,
        args.json,
        config=args.config,
        duration_s=args.duration_s,
        test_s=args.test_s,
        viewer=not args.no_viewer,
        warm_up_tests=args.warm_up_tests,
        heap_diff_tests=tuple(args.heap_diff) if args.heap_diff else None,
    )


def _accuracy(args: argparse.Namespace) -> int:
    from appliance.bench.accuracy import run_accuracy_benchmark

    return run_accuracy_benchmark(args.out, quick=args.quick)


def _search(args: argparse.Namespace) -> int:
    from appliance.bench.search_table import run_search_benchmark

    return run_search_benchmark(args.out, full=args.full)


def _speed(args: argparse.Namespace) -> int:
    from appliance.bench.speed import run_speed_benchmark

    return run_speed_benchmark(args.out, args.json)


def _simulated(args: argparse.Namespace) -> int:
    from appliance.bench.simulated import run_simulated_benchmark

    return run_simulated_benchmark(args.out, quick=args.quick)


def _results(args: argparse.Namespace) -> int:
    from appliance.bench.results_accuracy import run_results_benchmark

    return run_results_benchmark(args.out, quick=args.quick)


def _transverse(args: argparse.Namespace) -> int:
    from appliance.bench.transverse import run_transverse_benchmark

    return run_transverse_benchmark(args.out, quick=args.quick)


def _realtime(args: argparse.Namespace) -> int:
    from appliance.bench.realtime import run_realtime_benchmark

    return run_realtime_benchmark(
        args.out, args.json, runs=args.runs, until_strain=args.until_strain, material=args.material
    )


def _modbus(args: argparse.Namespace) -> int:
    from appliance.bench.modbus import run_modbus_benchmark

    return run_modbus_benchmark(args.out, args.json)


def _camera(args: argparse.Namespace) -> int:
    from appliance.bench.camera import run_camera_benchmark

    return run_camera_benchmark(args.out, args.json, url=args.camera, frames=args.frames)


def _machine(args: argparse.Namespace) -> int:
    from appliance.bench.machine_client import run_machine_benchmark

    return run_machine_benchmark(args.out, args.json, url=args.machine, duration_s=args.duration)


def _trigger_jitter(args: argparse.Namespace) -> int:
    from appliance.bench.trigger_jitter import run_trigger_jitter_benchmark

    return run_trigger_jitter_benchmark(args.out, args.json)


def _clock_sync(args: argparse.Namespace) -> int:
    from appliance.bench.clock_sync import run_clock_sync_benchmark

    return run_clock_sync_benchmark(args.out, args.json)
