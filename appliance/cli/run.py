"""`extensometer run` and `extensometer serve`: a tensile test, once or as a service.

`run` measures one test (`appliance.runner.run_test`) with the Modbus server and the viewer
the configuration or the options ask for, and prints its summary; `serve` runs the appliance
under systemd, one test per start command (`appliance.service.Service`). The options that
set configuration keys are applied as `appliance.config.Override`s, checked as the file is.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import sys
from pathlib import Path

from appliance.cli import arguments
from appliance.cli.printing import print_summary
from appliance.config import Config, Override
from appliance.errors import InputError
from appliance.run.object_plane import resolved_calibration_path
from hal.errors import HardwareError

RUN_OPTIONS = (
    ("speed_mm_min", "run", "speed_mm_min"),
    ("until_strain", "run", "until_strain"),
    ("exposure_us", "camera", "exposure_us"),
    ("frame_rate_hz", "camera", "frame_rate_hz"),
    ("material", "sim", "material"),
    ("seed", "sim", "seed"),
)
"""(argument, table, key) of `run`'s options that set configuration keys."""


def add_parsers(commands: argparse._SubParsersAction) -> None:
    """The `run` and `serve` commands."""
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
    run.add_argument(
        "--speed-mm-min", type=arguments.positive_float, help="crosshead speed, mm/min"
    )
    run.add_argument(
        "--exposure-us", type=arguments.positive_float, help="exposure (default: planned)"
    )
    run.add_argument(
        "--frame-rate-hz", type=arguments.positive_float, help="frame rate (default: planned)"
    )
    run.add_argument("--seed", type=arguments.non_negative_int, help="seed of the simulated world")
    until = run.add_mutually_exclusive_group()
    until.add_argument(
        "--until-strain", type=arguments.positive_float, help="stop at this engineering strain"
    )
    until.add_argument("--until-break", action="store_true", help="run to the break (default)")
    pace = run.add_mutually_exclusive_group()
    pace.add_argument("--realtime", action="store_true", help="simulate in real time")
    pace.add_argument("--fast", action="store_true", help="simulate as fast as possible")
    run.add_argument(
        "--out",
        type=arguments.output_directory,
        help="output directory for strain.csv, summary.json",
    )
    run.add_argument(
        "--record", type=Path, metavar="FILE.mcap", help="record the test to a new MCAP file"
    )
    arguments.add_modbus_options(run)
    arguments.add_rerun_options(run)
    run.add_argument("--json", action="store_true", help="print the summary as JSON, quietly")
    run.set_defaults(handler=run_one_test)

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
    arguments.add_modbus_options(serve)
    arguments.add_rerun_options(serve)
    serve.set_defaults(handler=serve_tests)


def run_configuration(args: argparse.Namespace) -> Config:
    """`run`'s configuration: the file's (or the defaults), with every option applied."""
    overrides = arguments.option_overrides(args, RUN_OPTIONS)
    if args.until_break:
        overrides += [
            Override("--until-break", "run", "until_strain", 0.0),
            Override("--until-break", "run", "until_break", True),
        ]
    if args.realtime or args.fast:
        option = "--realtime" if args.realtime else "--fast"
        overrides.append(Override(option, "sim", "realtime", bool(args.realtime)))
    config = arguments.configuration(args.config, args, overrides)
    return resolved_calibration_path(config, args.config)


def viewer_of(config: Config):
    """The Rerun viewer the configuration asks for, or None."""
    from appliance.live.viewer import RerunViewer, has_sinks

    return RerunViewer(config.rerun) if has_sinks(config.rerun) else None


def run_one_test(args: argparse.Namespace) -> int:
    """Run `run`; exit status 0 when the test ended by its criterion, a break or a stop, else
    1. The test is named `test-<UTC start time>` in its recording and the viewer."""
    from appliance.live.link import LiveLink
    from appliance.runner import OutputFiles, run_test

    config = run_configuration(args)
    test_id = f"test-{datetime.datetime.now(datetime.UTC):%Y%m%dT%H%M%SZ}"
    progress = None if args.json or not sys.stderr.isatty() else sys.stderr
    link = LiveLink(config, viewer=viewer_of(config))
    leave_progress_line = "\n" if progress is not None else ""

    def warn(text: str) -> None:
        print(f"{leave_progress_line}extensometer: warning: {text}", file=sys.stderr, flush=True)

    try:
        link.start()
        outcome = run_test(
            config,
            simulate=args.sim,
            files=OutputFiles.in_directory(args.out, args.record),
            progress=progress,
            hooks=dataclasses.replace(link.hooks(), on_warning=warn),
            test_id=test_id,
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


def serve_tests(args: argparse.Namespace) -> int:
    """Run `serve` until SIGTERM; exit status 0 after a clean stop."""
    from appliance.live.sd_notify import ServiceNotifier
    from appliance.service import Service

    config = resolved_calibration_path(arguments.configuration(args.config, args), args.config)
    with ServiceNotifier() as notifier:
        return Service(
            config, record_path=args.record, notifier=notifier, viewer=viewer_of(config)
        ).run()
