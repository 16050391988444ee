"""A calibration lab's readings file for `extensometer verify --readings FILE.csv`.

A CSV file with a header line naming its columns (any order):

    series           the series' name (1, 2, ...); "rest": a reading with the calibrator
                     at rest (for the resolution)
    calibrator_um    um: the calibrator's elongation l_t
    reading_um       um: the extensometer's reading l_i
    gauge_length_mm  mm, optional: the gauge length the extensometer measured at this point
                     (empty: none)

Blank lines and lines starting with `#` are skipped. Every value is checked; the first bad one
is refused in one line naming the file, the line and the column.
"""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path

from appliance.errors import InputError, read_user_text
from appliance.run.verification import CalibrationPoint

REQUIRED_COLUMNS = ("series", "calibrator_um", "reading_um")
OPTIONAL_COLUMNS = ("gauge_length_mm",)
REST_SERIES = "rest"
"""The `series` of a reading taken with the calibrator at rest (for the resolution)."""


def read_readings(path: Path) -> tuple[tuple[CalibrationPoint, ...], tuple[float, ...]]:
    """The calibration points and the readings at rest of a readings file.

    Raises:
        InputError: "<path>: line N, column C (name): why" (or "<path>: why" for the file).
    """
    text = read_user_text(path, "readings file")
    lines = [
        (number, line)
        for number, line in enumerate(text.splitlines(), start=1)
        if line.strip() and not line.lstrip().startswith("#")
    ]
    if not lines:
        raise InputError(f"{path}: no header line (columns: {', '.join(REQUIRED_COLUMNS)})")
    header_number, header_line = lines[0]
    header = [name.strip() for name in _split(header_line, path, header_number)]
    for index, name in enumerate(header, start=1):
        if name not in REQUIRED_COLUMNS + OPTIONAL_COLUMNS:
            raise InputError(
                f"{path}: line {header_number}, column {index}: unknown column {name!r} "
                f"(columns: {', '.join(REQUIRED_COLUMNS + OPTIONAL_COLUMNS)})"
            )
        if header.index(name) != index - 1:
            raise InputError(f"{path}: line {header_number}, column {index}: {name!r} twice")
    missing = [name for name in REQUIRED_COLUMNS if name not in header]
    if missing:
        raise InputError(f"{path}: line {header_number}: no column {missing[0]!r}")
    points: list[CalibrationPoint] = []
    rest: list[float] = []
    for number, line in lines[1:]:
        fields = [value.strip() for value in _split(line, path, number)]
        if len(fields) != len(header):
            raise InputError(
                f"{path}: line {number}: {len(fields)} values, the header names {len(header)}"
            )
        row = dict(zip(header, fields, strict=True))
        column = {name: header.index(name) + 1 for name in header}

        def where(name: str, number: int = number, column: dict = column) -> str:
            return f"{path}: line {number}, column {column[name]} ({name})"

        series = row["series"]
        if not series:
            raise InputError(f"{where('series')}: empty")
        calibrator = _number(row["calibrator_um"], where("calibrator_um"))
        reading = _number(row["reading_um"], where("reading_um"))
        gauge = None
        if row.get("gauge_length_mm"):
            gauge = _number(row["gauge_length_mm"], where("gauge_length_mm"))
            if not gauge > 0:
                raise InputError(f"{where('gauge_length_mm')}: {gauge:g} must be > 0")
        if series == REST_SERIES:
            rest.append(reading)
        else:
            points.append(CalibrationPoint(series, calibrator, reading, gauge))
    if not points:
        raise InputError(f"{path}: no calibration points (only a header and readings at rest)")
    return tuple(points), tuple(rest)


def _split(line: str, path: Path, number: int) -> list[str]:
    try:
        return next(csv.reader(io.StringIO(line)))
    except (csv.Error, StopIteration) as exc:
        raise InputError(f"{path}: line {number}: not CSV ({exc})") from None


def _number(text: str, where: str) -> float:
    if not text:
        raise InputError(f"{where}: empty")
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"{where}: {text!r} is not a number") from None
    if not math.isfinite(value):
        raise InputError(f"{where}: {text!r} is not finite")
    return value
