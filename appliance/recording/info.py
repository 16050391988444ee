"""`extensometer info FILE.mcap`: what a recording holds, and whether it is whole.

The file is read front to back with every CRC checked (`appliance.recording.reader`), so the
summary doubles as an integrity check: a file cut short or corrupted is reported with the
place of the damage, and everything before it is still counted.
"""

from __future__ import annotations

import datetime
from pathlib import Path
from typing import Any, TextIO

from appliance.recording.format import TOPIC_STRAIN
from appliance.recording.reader import RecordingReader, config_table, run_facts


def _utc(unix_ns: int) -> str:
    moment = datetime.datetime.fromtimestamp(unix_ns / 1e9, tz=datetime.UTC)
    return moment.isoformat(timespec="milliseconds").replace("+00:00", "Z")


def recording_info(path: str | Path) -> dict[str, Any]:
    """A summary of a recording (JSON-ready).

    Keys: `path`, `size_bytes`, `complete` (summary and footer present), `damage` (None, or
    where and why the file stops being readable), `format`, `format_version`, `test_id`,
    `started_utc`, `duration_s` (span of the messages' log times), `samples`, `channels`
    (topic -> messages), `attachments` (name -> bytes), `material`, `gauge_length_mm`,
    `scale_mm_per_px`, `exit_status` and `reason` (None when the run's end was not recorded),
    `frames_processed`, `frames_dropped`, `full_frames_skipped`.

    Raises:
        InputError: the file is missing or not an MCAP file.
    """
    reader = RecordingReader(path)
    try:
        reader.read_all()
    finally:
        reader.close()
    recording = reader.meta("recording") or {}
    start = reader.meta("run_start") or {}
    stop = reader.meta("run_stop") or {}
    calibration = reader.meta("calibration") or {}
    facts = run_facts(reader)
    material = facts.get("material")
    if material is None and reader.meta("config"):
        material = config_table(reader).get("sim", {}).get("material")
    low_high = reader.log_time_range_ns
    return {
        "path": str(reader.path),
        "size_bytes": reader.size,
        "complete": reader.complete,
        "damage": reader.damage.describe() if reader.damage else None,
        "format": recording.get("format"),
        "format_version": recording.get("version"),
        "test_id": start.get("test_id"),
        "started_utc": _utc(int(start["started_unix_ns"])) if "started_unix_ns" in start else None,
        "duration_s": (low_high[1] - low_high[0]) * 1e-9 if low_high else 0.0,
        "samples": reader.message_counts.get(TOPIC_STRAIN, 0),
        "channels": dict(sorted(reader.message_counts.items())),
        "attachments": {name: len(data) for name, data in reader.attachments.items()},
        "material": material,
        "gauge_length_mm": _float(calibration.get("gauge_length_mm")),
        "scale_mm_per_px": _float(calibration.get("scale_mm_per_px")),
        "exit_status": stop.get("exit_status"),
        "reason": stop.get("reason"),
        "frames_processed": _int(stop.get("frames_processed")),
        "frames_dropped": _int(stop.get("frames_dropped")),
        "full_frames_skipped": _int(stop.get("recording_full_frames_skipped")),
    }


def _float(text: str | None) -> float | None:
    return float(text) if text is not None else None


def _int(text: str | None) -> int | None:
    return int(text) if text is not None else None


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
