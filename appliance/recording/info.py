"""`extensometer info FILE.mcap`: what a recording holds, and whether it is whole.

The file is read front to back with every CRC checked (`appliance.recording.reader`), so the
summary doubles as an integrity check: a file cut short or corrupted is reported with the
place of the damage, and everything before it is still counted. A file that is not one
extensometer recording (another program's MCAP file, two recordings joined into one file, a
newer format) is refused in one line.
"""

from __future__ import annotations

import datetime
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

from appliance.errors import InputError
from appliance.recording.format import TOPIC_STRAIN
from appliance.recording.reader import RecordingReader, config_table, run_facts


def _utc(unix_ns: int) -> str:
    moment = datetime.datetime.fromtimestamp(unix_ns / 1e9, tz=datetime.UTC)
    return moment.isoformat(timespec="milliseconds").replace("+00:00", "Z")


def recording_info(path: str | Path) -> dict[str, Any]:
    """A summary of a recording (JSON-ready).

    Keys: `path`, `size_bytes`, `complete` (summary and footer present), `damage` (None, or
    where and why the file is damaged, one line), `format`, `format_version`, `test_id`,
    `started_utc`, `duration_s` (span of the messages' log times), `samples`, `channels`
    (topic -> messages), `attachments` (name -> bytes; a damaged one is left out),
    `material`, `gauge_length_mm`, `scale_mm_per_px`, `measured_in` ("object plane" or
    "nominal scale"), `calibration_checksum` (None by nominal scale), `exit_status` and
    `reason` (None when the run's end was not recorded), `frames_processed`, `frames_dropped`,
    `full_frames_skipped`. In a damaged file, a recorded fact that cannot be read is None.

    Raises:
        InputError: the file is missing, not an MCAP file, not one recording (bytes or a
            second MCAP file after its end), not an extensometer recording or of a newer
            format version, or, in a file without damage, holds a fact that cannot be read.
    """
    reader = RecordingReader(path)
    try:
        reader.read_all()
    finally:
        reader.close()
    if reader.meta("recording") is not None or not reader.damages:
        reader.check_format()
    recording = reader.meta("recording") or {}
    start = reader.meta("run_start") or {}
    stop = reader.meta("run_stop") or {}
    calibration = reader.meta("calibration") or {}

    def fact(what: str, read: Callable[[], Any]) -> Any:
        try:
            return read()
        except (InputError, KeyError, ValueError, TypeError, OverflowError, OSError):
            if reader.damages:
                return None
            raise InputError(f"{reader.path}: the recorded {what} is not readable") from None

    facts = fact("run facts", lambda: run_facts(reader))
    material = (facts or {}).get("material")
    if material is None and reader.meta("config"):
        material = fact("configuration", lambda: _material(config_table(reader)))
    low_high = reader.log_time_range_ns
    started_ns = start.get("started_unix_ns")
    return {
        "path": str(reader.path),
        "size_bytes": reader.size,
        "complete": reader.complete,
        "damage": reader.describe_damage(),
        "format": recording.get("format"),
        "format_version": recording.get("version"),
        "test_id": start.get("test_id"),
        "started_utc": fact("start time", lambda: _utc(int(started_ns))) if started_ns else None,
        "duration_s": (low_high[1] - low_high[0]) * 1e-9 if low_high else 0.0,
        "samples": reader.message_counts.get(TOPIC_STRAIN, 0),
        "channels": dict(sorted(reader.message_counts.items())),
        "attachments": {name: len(data) for name, data in reader.attachments.items()},
        "material": material,
        "gauge_length_mm": fact("gauge length", lambda: _float(calibration, "gauge_length_mm")),
        "scale_mm_per_px": fact("scale", lambda: _float(calibration, "scale_mm_per_px")),
        "measured_in": calibration.get("measured_in", "nominal scale") if calibration else None,
        "calibration_checksum": calibration.get("checksum") or None,
        "exit_status": stop.get("exit_status"),
        "reason": stop.get("reason"),
        "frames_processed": fact("frame count", lambda: _int(stop, "frames_processed")),
        "frames_dropped": fact("drop count", lambda: _int(stop, "frames_dropped")),
        "full_frames_skipped": fact(
            "full-frame count", lambda: _int(stop, "recording_full_frames_skipped")
        ),
    }


def _material(config: dict[str, Any]) -> Any:
    sim = config.get("sim")
    return sim.get("material") if isinstance(sim, dict) else None


def _float(record: dict[str, str], key: str) -> float | None:
    return float(record[key]) if key in record else None


def _int(record: dict[str, str], key: str) -> int | None:
    return int(record[key]) if key in record else None


def print_info(info: dict[str, Any], stream: TextIO) -> None:
    """The summary as aligned lines; channels one per line."""
    for key, value in info.items():
        if key == "channels":
            stream.write("channels\n")
            for topic, count in value.items():
                stream.write(f"  {topic:36s} {count}\n")
        elif key == "attachments":
            for name, size in value.items():
                stream.write(f"{'attachment':38s} {name} ({size} bytes)\n")
        else:
            shown = f"{value:.6g}" if isinstance(value, float) else value
            stream.write(f"{key:38s} {shown}\n")
