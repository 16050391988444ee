"""The strain series of a run as a CSV file, one row per measured frame.

Columns (units in the names): sample index, camera frame id, device time, exposure, the
strains, elongation and current gauge length, the data-valid flag, points lost in the frame,
reference updates, the frames dropped so far in the test (a rise is a gap in the series), the
controller's crosshead position and force, and the processing latency; with the width
measured at N stations (`[transverse] stations`), the mean width `width_mm`, the transverse
strain from it `width_transverse_strain`, the stations seen `width_stations_seen` and each
station's width `width_1_mm` ... `width_N_mm` (empty where a station is flagged);
then any extra columns the caller adds (a simulation's ground truth, for instance). Every row
is written to the file as it is measured, whole: a run that ends abruptly keeps every sample
measured before, and a write that fails (a full disk) leaves no partial row behind.
"""

from __future__ import annotations

import csv
import errno
import io
import math
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from appliance.measure.frame_measurer import StrainSample

COLUMNS: tuple[str, ...] = (
    "index",
    "frame_id",
    "time_s",
    "timestamp_ns",
    "exposure_us",
    "engineering_strain",
    "true_strain",
    "transverse_strain",
    "poisson_ratio",
    "elongation_mm",
    "gauge_length_mm",
    "data_valid",
    "points_lost",
    "reference_updates",
    "frames_dropped",
    "crosshead_mm",
    "force_n",
    "latency_ms",
)


def sample_row(sample: StrainSample) -> dict[str, Any]:
    """The standard columns of one sample."""
    reading = sample.reading
    machine = sample.machine
    return {
        "index": sample.index,
        "frame_id": sample.frame_id,
        "time_s": sample.time_s,
        "timestamp_ns": sample.timestamp_ns,
        "exposure_us": sample.exposure_us,
        "engineering_strain": reading.engineering_strain,
        "true_strain": reading.true_strain,
        "transverse_strain": reading.transverse_strain,
        "poisson_ratio": reading.poisson_ratio,
        "elongation_mm": reading.elongation_mm,
        "gauge_length_mm": reading.gauge_length_mm,
        "data_valid": int(sample.data_valid),
        "points_lost": sample.points_lost,
        "frames_dropped": sample.frames_dropped,
        "reference_updates": sample.reference_updates,
        "crosshead_mm": machine.crosshead_mm if machine is not None else math.nan,
        "force_n": machine.force_n if machine is not None else math.nan,
        "latency_ms": sample.latency_s * 1e3,
    }


def width_columns(stations: int) -> tuple[str, ...]:
    """The columns of the width measured at `stations` stations (none when 0)."""
    if stations == 0:
        return ()
    each = tuple(f"width_{k}_mm" for k in range(1, stations + 1))
    return ("width_mm", "width_transverse_strain", "width_stations_seen", *each)


def width_row(sample: StrainSample, stations: int) -> dict[str, Any]:
    """The width columns of one sample (NaN where nothing was measured)."""
    width = sample.width
    if width is None:
        return dict.fromkeys(width_columns(stations), math.nan)
    row: dict[str, Any] = {
        "width_mm": width.mean_width_mm,
        "width_transverse_strain": width.transverse_strain,
        "width_stations_seen": width.stations_seen,
    }
    for k, value in enumerate(width.widths_mm, start=1):
        row[f"width_{k}_mm"] = value
    return row


class StrainFileError(RuntimeError):
    """A row could not be written; names the file and the cause, and how many rows it keeps."""


class StrainCsvWriter:
    """A sink writing every sample as a CSV row.

    Each row goes to the file in one piece as soon as it is measured. A write that fails is
    undone (the file is cut back to its last whole row) and raised as `StrainFileError`; on a
    full disk, `on_no_space` is called first and, when it says it freed room (a reserve file
    released, `appliance.run.disk_space.DiskReserve`), the row is written once more.

    Args:
        path: file to create (its directory must exist).
        extra_columns: names of additional columns, after the standard ones.
        extras: returns the values of the extra columns for a sample.
        on_no_space: called when the disk is full; returns True when it freed room.
        width_stations: the stations the width is measured at (`width_columns`); 0 = none.

    Attributes:
        rows: the rows written so far (the header not counted).

    Raises:
        OSError: the file cannot be created.
    """

    def __init__(
        self,
        path: str | Path,
        extra_columns: Sequence[str] = (),
        extras: Callable[[StrainSample], Mapping[str, Any]] | None = None,
        *,
        on_no_space: Callable[[], bool] | None = None,
        width_stations: int = 0,
    ) -> None:
        self.path = Path(path)
        self._width_stations = width_stations
        self.rows = 0
        self._extras = extras
        self._on_no_space = on_no_space
        self._text = io.StringIO()
        self._csv = csv.DictWriter(
            self._text, fieldnames=[*COLUMNS, *width_columns(width_stations), *extra_columns]
        )
        self._file = self.path.open("wb", buffering=0)
        self._size = 0
        self._csv.writeheader()
        try:
            self._append(self._pending())
        except StrainFileError:
            self._file.close()
            raise

    def __call__(self, sample: StrainSample) -> None:
        row = sample_row(sample)
        if self._width_stations:
            row.update(width_row(sample, self._width_stations))
        if self._extras is not None:
            row.update(self._extras(sample))
        self._csv.writerow({k: _format(v) for k, v in row.items()})
        self._append(self._pending())
        self.rows += 1

    def close(self) -> None:
        """Close the file; safe to call twice."""
        if not self._file.closed:
            self._file.close()

    def _pending(self) -> bytes:
        data = self._text.getvalue().encode("utf-8")
        self._text.seek(0)
        self._text.truncate()
        return data

    def _append(self, data: bytes) -> None:
        for attempt in (1, 2):
            try:
                view = memoryview(data)
                while view:
                    view = view[self._file.write(view) :]
            except OSError as exc:
                os.ftruncate(self._file.fileno(), self._size)
                self._file.seek(self._size)
                room = (
                    attempt == 1
                    and exc.errno == errno.ENOSPC
                    and self._on_no_space is not None
                    and self._on_no_space()
                )
                if room:
                    continue
                raise StrainFileError(
                    f"{self.path}: cannot write ({exc.strerror}); "
                    f"it keeps the {self.rows} rows written before"
                ) from None
            self._size += len(data)
            return


def _format(value: Any) -> Any:
    if isinstance(value, float):
        return "" if math.isnan(value) else repr(value)
    return value
