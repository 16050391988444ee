"""The JSON Schemas of a recording's JSON channels, each field described with its unit.

Every JSON channel of a recording (`appliance.recording.format`) registers one of these
schemas (MCAP schema encoding `jsonschema`), so Foxglove lists and plots the fields and shows
what each one is. Each property has a `description`; a property that has a unit also says it
in `unit` (a plain annotation keyword: `mm`, `N`, `mm/min`, `us`, `ns`, `ms`, `s`, `px`,
`bytes`, or `1` for a ratio such as a strain), and its name ends in that unit where the name
was free to.

Every record starts with `timestamp`, `{"sec": ..., "nsec": ...}` in UNIX time (what
Foxglove reads as a time value): the message's log time, which for per-frame records is the
frame's acquisition time (start of exposure). The older `timestamp_ns` fields keep their
meaning: the camera's device clock (the machine's own clock on `/machine/state`).
"""

from __future__ import annotations

from typing import Any


def _field(kind: str | list[str], description: str, unit: str | None = None) -> dict[str, Any]:
    schema: dict[str, Any] = {"type": kind, "description": description}
    if unit is not None:
        schema["unit"] = unit
    return schema


def _number(description: str, unit: str | None = None) -> dict[str, Any]:
    """A float field; null stands for NaN or an infinity."""
    return _field(["number", "null"], description + " (null: not a number)", unit)


def _integer(description: str, unit: str | None = None) -> dict[str, Any]:
    return _field("integer", description, unit)


def _numbers(description: str, unit: str | None = None) -> dict[str, Any]:
    """An array of floats, one per tracked point in the points' order."""
    schema: dict[str, Any] = {
        "type": "array",
        "description": description + ", one per point (null: not a number)",
        "items": {"type": ["number", "null"]},
    }
    if unit is not None:
        schema["unit"] = unit
    return schema


TIMESTAMP: dict[str, Any] = {
    "type": "object",
    "description": (
        "UNIX time of the message: the frame's acquisition time (start of exposure) for "
        "per-frame records, the same as the MCAP log time"
    ),
    "properties": {
        "sec": _integer("whole seconds since 1970-01-01 00:00 UTC", "s"),
        "nsec": _integer("nanoseconds past `sec` (0 to 999999999)", "ns"),
    },
    "required": ["sec", "nsec"],
}
"""The `timestamp` of every JSON record (Foxglove's time value, `{sec, nsec}`)."""

_DEVICE_TIME = _integer("start of exposure on the camera's device clock", "ns")
_INDEX = _integer("sample index, 0 = the first frame after the reference (the message sequence)")
_FRAME_ID = _integer("the camera's frame counter")
_EXPOSURE = _number("exposure time of the frame", "us")


def _record(title: str, properties: dict[str, Any]) -> dict[str, Any]:
    return {
        "type": "object",
        "title": title,
        "properties": {"timestamp": TIMESTAMP, **properties},
    }


JSON_SCHEMAS: dict[str, dict[str, Any]] = {
    "extensometer.Trigger": _record(
        "What started one exposure",
        {
            "frame_id": _FRAME_ID,
            "timestamp_ns": _DEVICE_TIME,
            "exposure_us": _EXPOSURE,
            "mode": _field("string", "how the camera was triggered (internal, software, ...)"),
            "sequence": _field(
                ["integer", "null"], "the trigger microcontroller's edge number (null: none)"
            ),
            "tick": _field(
                ["integer", "null"],
                "the trigger microcontroller's clock at the edge, in its ticks (null: none)",
            ),
            "device_timestamp_ns": _field(
                ["integer", "null"],
                "the camera's own timestamp of a frame stamped with its trigger's time "
                "(null: not stamped)",
                "ns",
            ),
        },
    ),
    "extensometer.MachineState": _record(
        "The testing machine's state read with a frame",
        {
            "crosshead_mm": _number(
                "crosshead position from its start (+ = opening the grips)", "mm"
            ),
            "speed_mm_min": _number("crosshead speed", "mm/min"),
            "force_n": _number("force on the load cell", "N"),
            "running": _field("boolean", "the crosshead is commanded to move"),
            "timestamp_ns": _integer(
                "time of the reading on the controller's (or simulation's) clock", "ns"
            ),
            "encoder_counts": _field(
                ["integer", "null"], "crosshead encoder position in counts (null: not exposed)"
            ),
        },
    ),
    "extensometer.TrackedPoints": _record(
        "Every tracked point of one frame",
        {
            "index": _INDEX,
            "frame_id": _FRAME_ID,
            "timestamp_ns": _DEVICE_TIME,
            "exposure_us": _EXPOSURE,
            "zeroed": _field("boolean", "the strain was zeroed just before this frame"),
            "windows": {
                "type": "array",
                "description": "where each mark's window (/camera/window/<mark>) lies in the frame",
                "items": {
                    "type": "object",
                    "properties": {
                        "mark": _integer("the mark the window belongs to"),
                        "x": _integer("column of the window's first pixel in the frame", "px"),
                        "y": _integer("row of the window's first pixel in the frame", "px"),
                        "width": _integer("width of the window", "px"),
                        "height": _integer("height of the window", "px"),
                    },
                },
            },
            "points": {
                "type": "object",
                "description": "one array entry per point, in the order of the marks metadata",
                "properties": {
                    "x": _numbers(
                        "column of the point in the frame (pixel centres at integers)", "px"
                    ),
                    "y": _numbers(
                        "row of the point in the frame (pixel centres at integers)", "px"
                    ),
                    "u": _numbers("displacement along x since the reference frame", "px"),
                    "v": _numbers("displacement along y since the reference frame", "px"),
                    "ux": _numbers("displacement gradient du/dx against the mark's reference", "1"),
                    "uy": _numbers("displacement gradient du/dy against the mark's reference", "1"),
                    "vx": _numbers("displacement gradient dv/dx against the mark's reference", "1"),
                    "vy": _numbers("displacement gradient dv/dy against the mark's reference", "1"),
                    "zncc": _numbers("zero-normalised cross-correlation of the match, -1 to 1"),
                    "status": {
                        "type": "array",
                        "description": "tracked, reacquired (by the wider search) or lost "
                        "(position estimated), one per point",
                        "items": {"type": "string", "enum": ["tracked", "reacquired", "lost"]},
                    },
                },
            },
        },
    ),
    "extensometer.Strain": _record(
        "Strain of one frame",
        {
            "index": _INDEX,
            "frame_id": _FRAME_ID,
            "timestamp_ns": _DEVICE_TIME,
            "time_s": _number("time since the reference frame on the camera's clock", "s"),
            "engineering_strain": _number("axial engineering strain", "1"),
            "true_strain": _number("axial true (logarithmic) strain", "1"),
            "transverse_strain": _number("transverse engineering strain", "1"),
            "poisson_ratio": _number(
                "-transverse / axial strain (null until the axial strain reaches 1e-4)", "1"
            ),
            "elongation_mm": _number("change of the axial gauge length", "mm"),
            "gauge_length_mm": _number("axial gauge length L0 the strain refers to", "mm"),
            "axial_px": _number("current axial gauge length in the image", "px"),
            "data_valid": _field(
                "boolean", "every axial mark measured and the specimen not broken"
            ),
            "points_lost": _integer("points not measured in this frame"),
            "reference_updates": _integer("mark references replaced after this frame"),
            "frames_dropped": _integer("camera frames dropped since the test started"),
            "latency_ms": _number("wall time from the frame's delivery to this sample", "ms"),
            "width_mm": _number(
                "specimen width at its edges, mean of the stations seen ([transverse] stations)",
                "mm",
            ),
            "width_transverse_strain": _number(
                "transverse engineering strain from the width (mean of w / w0 - 1)", "1"
            ),
            "width_stations_seen": _integer("stations whose two edges were located"),
            "widths_mm": {
                "type": "array",
                "description": "width at each station from the first mark (null: flagged)",
                "items": {"type": ["number", "null"]},
                "unit": "mm",
            },
        },
    ),
    "extensometer.Truth": _record(
        "True strain of a simulated frame",
        {
            "index": _INDEX,
            "true_engineering_strain": _number("the simulation's axial engineering strain", "1"),
            "true_elongation_mm": _number("the simulation's elongation of the gauge", "mm"),
        },
    ),
    "extensometer.RecorderStatus": _record(
        "Full-frame recording rate",
        {
            "full_frame_interval_s": _number("time between recorded full frames", "s"),
            "degradation_level": _integer("halvings of the full-frame rate in force, 0 = none"),
            "backlog_bytes": _integer("records not yet written to disk", "bytes"),
            "full_frames_skipped": _integer("full frames not recorded so far"),
            "reason": _field("string", "why the rate changed"),
        },
    ),
}
"""JSON channel schema name -> JSON Schema."""


def foxglove_time(time_ns: int) -> dict[str, int]:
    """A UNIX time in ns as the `timestamp` value of a record (`{"sec", "nsec"}`)."""
    sec, nsec = divmod(int(time_ns), 1_000_000_000)
    return {"sec": sec, "nsec": nsec}
