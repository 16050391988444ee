"""Command line `extensometer`.

Subcommands, each parsed and handled in its own module of this package:
    track          correlate points of interest between a reference image and target images.
    plan           motion blur of an exposure, and the exposure and frame period for a blur
                   budget.
    detect         find the specimen in an image (centre, axis, width, parallel length) and
                   the gauge marks a test would place on it.
    run            a tensile test: measure strain until a strain limit or the break (`--sim`:
                   the simulated test, with its ground truth and errors in the summary).
    serve          run as a service: a test per start command, Modbus, Rerun, systemd watchdog.
    replay         measure a recorded test again from its recorded pixels.
    info           summarise a recording and check its integrity.
    camera-check   grab frames from a camera and report size, format, rate and losses.
    preview        stream the live camera image to a Rerun viewer with focus, exposure,
                   speckle quality and the gauge a test would place, until stopped.
    machine-check  read the machine's state and report it, with read rate and latency.
    trigger-check  handshake with the trigger microcontroller, time its link, fit its clock.
    calibrate      camera calibration from images of a target (ChArUco, chessboard, circle
                   grid) into a calibration file; `--check FILE`: does it still fit.
    verify         ISO 9513 verification against a calibrator (`--sim`: a simulated one; or a
                   lab's readings): bias, resolution, gauge length, class; a JSON and an HTML
                   report.
    bench          the benchmarks (accuracy, speed, simulated tests, Modbus latency, camera,
                   machine, trigger jitter, clock sync): figures and reports.

`extensometer --version` prints `extensometer <version>`, the software version every recording
carries (its MCAP header's library and its `run_start` metadata).

Bad input ends with one line `extensometer: error: ...` naming the culprit and exit status 2.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Sequence

from appliance import __version__
from appliance.cli import (
    bench,
    calibrate,
    detect,
    devices,
    plan,
    preview,
    recording,
    run,
    track,
    verify,
)
from appliance.cli.arguments import Parser
from appliance.errors import InputError

EXIT_USAGE = 2


def build_parser() -> argparse.ArgumentParser:
    """The `extensometer` argument parser: every command's parser, each with its handler."""
    parser = Parser(prog="extensometer", description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--version",
        action="version",
        version=f"extensometer {__version__}",
        help="print the software version (the one recordings carry) and exit",
    )
    commands = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    track.add_parser(commands)
    calibrate.add_parser(commands)
    bench.add_parser(commands)
    plan.add_parser(commands)
    detect.add_parser(commands)
    run.add_parsers(commands)
    recording.add_parsers(commands)
    devices.add_parsers(commands)
    preview.add_parser(commands)
    verify.add_parser(commands)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the `extensometer` command line; returns the process exit status."""
    # Device failures are reported by the appliance, once each; pymodbus would log every
    # failed request of a machine controller's outage on stderr.
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    try:
        args = build_parser().parse_args(argv)
        return args.handler(args)
    except InputError as error:
        print(f"extensometer: error: {error}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("extensometer: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
