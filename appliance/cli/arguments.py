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
import dataclasses
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


def output_directory(text: str) -> Path:
    """An argparse type for a directory a command writes into: one that exists, or can be made
    (nothing on its path is a file); checked before the command's work starts, so a long
    benchmark does not end in an error it could have given first."""
    path = Path(text)
    for part in (path, *path.parents):
        if part.exists():
            if not part.is_dir():
                raise argparse.ArgumentTypeError(f"{part} is not a directory")
            break
    return path


def within(parse: Callable[[str], Any], low: float, high: float, *, above: bool = False):
    """An argparse type for a value of physical range `low` .. `high` (inclusive; with `above`
    the value must exceed `low`)."""
    if above:
        return _number(parse, lambda v: low < v <= high, f"must be > {low:g} and <= {high:g}")
    return _number(parse, lambda v: low <= v <= high, f"must be in {low:g} .. {high:g}")


def like_key(table: type, key: str, *, above: bool = False):
    """An argparse type with the range of a configuration key (`OpticsConfig`,
    `"focal_length_mm"`): an option and a key for the same quantity share one range."""
    f = next(f for f in dataclasses.fields(table) if f.name == key)
    parse = int if f.type in (int, "int", "int | None") else float
    return within(parse, f.metadata["minimum"], f.metadata["maximum"], above=above)


subset_size = _number(
    int, lambda v: 5 <= v <= 301 and v % 2 == 1, "must be an odd size in 5 .. 301"
)
window_size = _number(
    int, lambda v: 3 <= v <= 301 and v % 2 == 1, "must be an odd size in 3 .. 301"
)
non_negative_int = _number(int, lambda v: v >= 0, "must be >= 0")
non_negative_float = _number(float, lambda v: v >= 0, "must be a finite number >= 0")
finite_float = _number(float, lambda v: True, "is not finite")
positive_float = _number(float, lambda v: v > 0, "must be a finite number > 0")
frame_count = within(int, 2, 100_000)
read_count = within(int, 1, 100_000)

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
