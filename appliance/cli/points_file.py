"""Points-of-interest files: CSV with header `x,y` and optional initial guess `u0,v0`."""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from appliance.errors import InputError, read_user_text


@dataclass(frozen=True)
class PointsOfInterest:
    """Subset centres in reference pixel coordinates and an optional displacement guess.

    Attributes:
        xy: (n, 2) float64, columns x (column) and y (row), 0-based pixel coordinates.
        guess: (n, 2) float64 initial (u, v) in px, or None when the file has no u0, v0.
        lines: (n,) line number of each point in its file, for error messages.
    """

    xy: np.ndarray
    guess: np.ndarray | None
    lines: np.ndarray


def read_points(path: str | Path) -> PointsOfInterest:
    """Read a points CSV.

    The first line is a header naming the columns: `x,y` or `x,y,u0,v0` (any order, no other
    columns). Every following non-blank line holds finite numbers; lines starting with `#`
    are comments.

    Raises:
        InputError: naming the file and line of the first problem.
    """
    path = Path(path)
    text = read_user_text(path, "points file")
    rows = [
        (number, row)
        for number, row in enumerate(csv.reader(text.splitlines()), start=1)
        if row and any(cell.strip() for cell in row) and not row[0].lstrip().startswith("#")
    ]
    if not rows:
        raise InputError(f"{path}: empty points file (header x,y expected)")
    header_line, header = rows[0]
    names = [cell.strip().lower() for cell in header]
    if sorted(names) not in (["x", "y"], ["u0", "v0", "x", "y"]):
        raise InputError(
            f"{path}:{header_line}: header must be x,y or x,y,u0,v0, got {','.join(header)}"
        )
    if len(rows) == 1:
        raise InputError(f"{path}: no points after the header")
    columns = {name: index for index, name in enumerate(names)}
    values = np.empty((len(rows) - 1, len(names)))
    for k, (number, row) in enumerate(rows[1:]):
        if len(row) != len(names):
            raise InputError(f"{path}:{number}: expected {len(names)} values, got {len(row)}")
        for j, cell in enumerate(row):
            try:
                value = float(cell)
            except ValueError:
                raise InputError(
                    f"{path}:{number}: {names[j]}={cell.strip()!r} is not a number"
                ) from None
            if not math.isfinite(value):
                raise InputError(f"{path}:{number}: {names[j]}={cell.strip()} is not finite")
            values[k, j] = value
    xy = values[:, [columns["x"], columns["y"]]]
    guess = values[:, [columns["u0"], columns["v0"]]] if "u0" in columns else None
    lines = np.array([number for number, _ in rows[1:]], dtype=np.int64)
    return PointsOfInterest(xy=np.ascontiguousarray(xy), guess=guess, lines=lines)
