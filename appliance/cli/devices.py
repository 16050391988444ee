"""`extensometer camera-check`, `machine-check` and `trigger-check`: the installer's checks.

Each opens one device as a test would, exercises it without starting a test, prints a report
(or JSON) and exits 0 when the device is fit, 1 when it cannot be reached or misbehaves, 2
for a bad URL or setting (one line naming it). The checks themselves are
`appliance.cli.device_checks`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from appliance.cli import arguments, device_checks
from appliance.config import CameraConfig
from appliance.errors import InputError
from appliance.run.object_plane import calibration_file, resolved_calibration_path
from hal.errors import HardwareConfigError, HardwareError

CAMERA_OPTIONS = (("camera", "camera", "url"),)
MACHINE_OPTIONS = (("machine", "machine", "url"),)


def add_parsers(commands: argparse._SubParsersAction) -> None:
    """The `camera-check`, `machine-check` and `trigger-check` commands."""
    camera_check = commands.add_parser(
        "camera-check",
        help="grab frames from a camera and report what arrived",
        description=(
            "Open the camera, free-run it, grab N frames and report image size, pixel "
            "format, the frame rate achieved, lost frames, device timestamps and grey "
            "levels, and a verdict: whether the camera is fit to measure (rate, lost frames, "
            "exposure, saturation, texture and focus). The first command to run on a new "
            "installation. Exit status 1 when the camera cannot be opened or sends nothing, "
            "or is not fit to measure (each problem named); 2 for a bad URL or setting."
        ),
    )
    camera_check.add_argument("--camera", metavar="URL", help="camera URL ([camera] url)")
    camera_check.add_argument("--config", type=Path, help="TOML configuration ([camera] table)")
    camera_check.add_argument(
        "--frames", type=arguments.frame_count, default=100, help="frames (100)"
    )
    camera_check.add_argument(
        "--rate",
        type=arguments.within(float, 0.1, 10000.0),
        default=30.0,
        help="frame rate asked for, Hz (30)",
    )
    camera_check.add_argument(
        "--exposure-us", type=arguments.like_key(CameraConfig, "exposure_us"), help="exposure, us"
    )
    camera_check.add_argument(
        "--save",
        type=Path,
        metavar="FILE.png",
        help="write the last frame with the detected specimen and the gauge drawn over it",
    )
    camera_check.add_argument("--json", action="store_true", help="print JSON on stdout")
    camera_check.set_defaults(handler=check_camera)

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
    machine_check.add_argument("--reads", type=arguments.read_count, default=50, help="reads (50)")
    machine_check.add_argument("--json", action="store_true", help="print JSON on stdout")
    machine_check.set_defaults(handler=check_machine)

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
    trigger_check.add_argument(
        "--pings", type=arguments.read_count, default=50, help="round trips (50)"
    )
    trigger_check.add_argument("--json", action="store_true", help="print JSON on stdout")
    trigger_check.set_defaults(handler=check_trigger)


def check_camera(args: argparse.Namespace) -> int:
    """Run `camera-check`: exit status 1 when the camera is away or not fit to measure (the
    report's `problems`)."""
    config = arguments.configuration(
        args.config, args, arguments.option_overrides(args, CAMERA_OPTIONS)
    )
    config = resolved_calibration_path(config, args.config)
    region = config.camera.region()
    calibration = calibration_file(config, (region.width, region.height) if region else None)
    try:
        camera = device_checks.camera_for_check(config, config.camera.url)
        report = device_checks.check_camera(
            camera,
            config,
            frames=args.frames,
            rate_hz=args.rate,
            exposure_us=args.exposure_us,
            calibration=calibration,
            save_path=args.save,
        )
    except HardwareConfigError as error:
        raise InputError(f"camera-check: {error}") from None
    except HardwareError as error:
        print(f"extensometer: camera-check: {error}", file=sys.stderr)
        return 1
    _show(args, report, device_checks.camera_report_lines(report))
    return 0 if report["fit"] else 1


def check_machine(args: argparse.Namespace) -> int:
    """Run `machine-check`: exit status 1 when the controller is away or answers an error."""
    config = arguments.configuration(
        args.config, args, arguments.option_overrides(args, MACHINE_OPTIONS)
    )
    try:
        machine = device_checks.machine_for_check(config, config.machine.url)
        report = device_checks.check_machine(machine, reads=args.reads)
    except HardwareConfigError as error:
        raise InputError(f"machine-check: {error}") from None
    except HardwareError as error:
        print(f"extensometer: machine-check: {error}", file=sys.stderr)
        return 1
    _show(args, report, device_checks.machine_report_lines(report))
    return 0


def check_trigger(args: argparse.Namespace) -> int:
    """Run `trigger-check`: exit status 1 when the microcontroller does not answer or runs
    other firmware."""
    from firmware_bridge.link import FirmwareError

    try:
        report = device_checks.check_trigger(args.port, pings=args.pings)
    except FirmwareError as error:
        print(f"extensometer: trigger-check: {args.port}: {error}", file=sys.stderr)
        return 1
    _show(args, report, device_checks.trigger_report_lines(report))
    return 0


def _show(args: argparse.Namespace, report: dict, lines: list[str]) -> None:
    print(json.dumps(report, indent=2) if args.json else "\n".join(lines))
