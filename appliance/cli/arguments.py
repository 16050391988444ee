"""What every command's parser shares: one-line errors, checked numbers, common options.

`Parser` turns argparse's usage errors into `InputError`, so a bad option ends like every
other bad input: one line `extensometer: error: ...` naming it, exit status 2. The number
types check a value when it is parsed (`subset_size`, `positive_float`, ...). Options that
set configuration keys (`--modbus-tcp`, `--rerun-save`, `--speed-mm-min`, ...) are turned
into `appliance.config.Override`s and applied with `appliance.config.with_overrides`, the one
way a command line changes a configuration, checked as a file is.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

from appliance.config import Config, Override, load_config, with_overrides
from appliance.errors import InputError


class Parser(argparse.ArgumentParser):
    """Argument parser whose errors are one line, like every other error of the tool."""

    def error(self, message: str) -> None:  # type: ignore[override]
        command = self.prog.removeprefix("extensometer").strip()
        raise InputError(f"{command}: {message}" if command else message)


def _number(parse: Callable[[str], Any], accept: Callable[[Any], bool], requirement: str):
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


subset_size = _number(int, lambda v: v >= 5 and v % 2 == 1, "must be an odd size >= 5")
window_size = _number(int, lambda v: v >= 3 and v % 2 == 1, "must be an odd size >= 3")
non_negative_int = _number(int, lambda v: v >= 0, "must be >= 0")
non_negative_float = _number(float, lambda v: v >= 0, "must be a finite number >= 0")
finite_float = _number(float, lambda v: True, "is not finite")
positive_float = _number(float, lambda v: v > 0, "must be a finite number > 0")
frame_count = _number(int, lambda v: v >= 2, "must be >= 2")
read_count = _number(int, lambda v: v >= 1, "must be >= 1")

LIVE_OPTIONS = (
    ("modbus_tcp", "modbus", "tcp"),
    ("modbus_rtu", "modbus", "rtu_device"),
    ("rerun_serve", "rerun", "serve"),
    ("rerun_connect", "rerun", "connect"),
    ("rerun_save", "rerun", "save"),
)
"""(argument, table, key) of the options that set the live outputs' keys."""


def add_modbus_options(parser: argparse.ArgumentParser) -> None:
    """--modbus-tcp and --modbus-rtu: the strain server's [modbus] keys."""
    parser.add_argument(
        "--modbus-tcp", metavar="HOST:PORT", help="serve strain on Modbus TCP ([modbus] tcp)"
    )
    parser.add_argument(
        "--modbus-rtu", metavar="DEVICE", help="serve strain on Modbus RTU ([modbus] rtu_device)"
    )


def add_rerun_options(parser: argparse.ArgumentParser) -> None:
    """--rerun-serve, --rerun-connect and --rerun-save: the viewer's [rerun] keys."""
    parser.add_argument(
        "--rerun-serve", metavar="HOST:PORT", help="gRPC server for Rerun viewers ([rerun] serve)"
    )
    parser.add_argument(
        "--rerun-connect", metavar="URL", help="push to a Rerun viewer at URL ([rerun] connect)"
    )
    parser.add_argument("--rerun-save", metavar="FILE.rrd", help="save an .rrd ([rerun] save)")


def option_overrides(
    args: argparse.Namespace, options: tuple[tuple[str, str, str], ...]
) -> list[Override]:
    """The overrides of the `(argument, table, key)` options given on the command line."""
    overrides = []
    for argument, table, key in options:
        value = getattr(args, argument, None)
        if value is not None:
            overrides.append(Override("--" + argument.replace("_", "-"), table, key, value))
    return overrides


def configuration(
    path: Path | None, args: argparse.Namespace, extra: list[Override] | None = None
) -> Config:
    """The configuration of `--config` (the defaults without it), with the command line's
    live-output options and `extra` overrides applied.

    Raises:
        InputError: naming the file and key, or the option, at fault.
    """
    config = load_config(path) if path is not None else Config()
    overrides = option_overrides(args, LIVE_OPTIONS) + list(extra or [])
    return with_overrides(config, overrides) if overrides else config
