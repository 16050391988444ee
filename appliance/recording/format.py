"""The format of a test recording: MCAP channels, their schemas, and how records are encoded.

One MCAP file per test (written by `appliance.recording.writer`, read by
`appliance.recording.replay` and `extensometer info`). Log time of every per-frame message is
the frame's acquisition time (start of exposure) as UNIX time in ns; the message `sequence` is
the sample index, so the messages of one frame can be gathered from every channel. Per frame,
in this order:

* `/camera/window/<k>` (protobuf `foxglove.RawImage`, `frame_id` `camera/window/<k>`): the
  pixels mark k's tracking read, and `/annotations/window/<k>` (`foxglove.ImageAnnotations`):
  mark k's points drawn on them;
* `/camera/full` (`foxglove.RawImage`, `frame_id` `camera`): the whole frame at the configured
  rate, and the reference frame, and `/annotations/full` (`foxglove.ImageAnnotations`): every
  point and window outline drawn on it;
* `/camera/transforms` (`foxglove.FrameTransforms`): where each window sits in the frame
  (`appliance.recording.overlays`);
* `/camera/trigger` (JSON): what started the exposure (frame id, time, exposure, mode; with
  the trigger microcontroller also the trigger's sequence number and tick, and the camera's
  own timestamp when the frame was stamped with its trigger's time);
* `/machine/state` (JSON): the controller's state read with the frame (crosshead, speed, force);
* `/tracking/points` (JSON): every point's position, displacement, shape parameters, ZNCC and
  status, and where the windows lie;
* `/sim/truth` (JSON): the simulation's true strain and elongation (simulated tests only);
* `/strain` (JSON, the last of each frame): strains, elongation, gauge length, Poisson's
  ratio, data-valid flag.

Other channels: `/recorder/status` (JSON: changes of the full-frame rate when the disk falls
behind) and `/log` (protobuf `foxglove.Log`: run states, commands, degradation, the end).

The images, annotations, transforms and log entries carry their log time as their
`timestamp`. JSON channels carry a JSON Schema (`jsonschema` encoding, so Foxglove plots their
fields) with every field described and its unit (`appliance.recording.json_schemas`); every
JSON record starts with `timestamp` (`{"sec", "nsec"}`, UNIX time, its log time), while the
`timestamp_ns` fields stay on the device clock that replay measures with. Numbers are written
with Python's shortest exact representation, so every float reads back bit for bit; NaN and
infinities are written as null and read back as NaN.

Metadata records (`extensometer.*`): `recording` (format and version), `run_start` (test id,
start time, the device-to-UNIX clock offset, the reference frame's facts), `config` (the
configuration in force, as JSON), `calibration`, `marks` (the points and how they form marks
and gauges), `devices` (camera, the machine's controller, software), and at the end
`run_stop` (exit status, reason, counts). The reference frame is the attachment
`reference.png` (lossless).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import Any

import cv2
import numpy as np
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from google.protobuf.message import DecodeError
from mcap_protobuf.schema import build_file_descriptor_set

from appliance.measure.frame_measurer import StrainSample
from appliance.measure.frame_windows import ImageWindow
from appliance.measure.tracking import TrackStatus
from appliance.recording.json_schemas import JSON_SCHEMAS
from appliance.recording.overlays import (
    FULL_FRAME_ID,
    TOPIC_FULL_ANNOTATIONS,
    TOPIC_TRANSFORMS,
    TOPIC_WINDOW_ANNOTATIONS,
)
from hal.machine.base import MachineState

FORMAT_NAME = "extensometer-mcap"
FORMAT_VERSION = "2"
"""Version 2 calls the testing machine the machine (`/machine/state`, `[machine]`,
`machine_url`); version 1 called it the frame. `appliance.recording.migration` reads both."""
PROFILE = ""
REFERENCE_ATTACHMENT = "reference.png"
META_PREFIX = "extensometer."

TOPIC_FULL = "/camera/full"
TOPIC_WINDOW = "/camera/window/{mark}"
TOPIC_TRIGGER = "/camera/trigger"
TOPIC_MACHINE = "/machine/state"
TOPIC_POINTS = "/tracking/points"
TOPIC_STRAIN = "/strain"
TOPIC_TRUTH = "/sim/truth"
TOPIC_RECORDER = "/recorder/status"
TOPIC_LOG = "/log"

PROTOBUF_TYPES = {
    "foxglove.RawImage": RawImage,
    "foxglove.Log": Log,
    "foxglove.ImageAnnotations": ImageAnnotations,
    "foxglove.FrameTransforms": FrameTransforms,
}
"""Protobuf schema name -> message class."""

TOPIC_SCHEMAS: dict[str, str] = {
    TOPIC_FULL: "foxglove.RawImage",
    TOPIC_TRIGGER: "extensometer.Trigger",
    TOPIC_MACHINE: "extensometer.MachineState",
    TOPIC_POINTS: "extensometer.TrackedPoints",
    TOPIC_STRAIN: "extensometer.Strain",
    TOPIC_TRUTH: "extensometer.Truth",
    TOPIC_RECORDER: "extensometer.RecorderStatus",
    TOPIC_LOG: "foxglove.Log",
    TOPIC_FULL_ANNOTATIONS: "foxglove.ImageAnnotations",
    TOPIC_TRANSFORMS: "foxglove.FrameTransforms",
}
"""Topic -> schema name; window topics use foxglove.RawImage, their annotations
foxglove.ImageAnnotations."""

_WINDOW_PREFIX = TOPIC_WINDOW.split("{")[0]
_WINDOW_ANNOTATIONS_PREFIX = TOPIC_WINDOW_ANNOTATIONS.split("{")[0]

STRAIN_FIELDS = (
    "engineering_strain",
    "true_strain",
    "transverse_strain",
    "poisson_ratio",
    "elongation_mm",
    "gauge_length_mm",
    "axial_px",
)
"""The measured quantities of a strain record (the reading's fields)."""


class FormatError(ValueError):
    """A record that does not follow this format (names the record)."""


def schema_of(topic: str) -> str:
    """The schema name of a topic."""
    if topic.startswith(_WINDOW_PREFIX):
        return "foxglove.RawImage"
    if topic.startswith(_WINDOW_ANNOTATIONS_PREFIX):
        return "foxglove.ImageAnnotations"
    return TOPIC_SCHEMAS[topic]


def schema_data(name: str) -> tuple[str, bytes]:
    """(schema encoding, schema bytes) of a schema name, as MCAP stores them."""
    if name in PROTOBUF_TYPES:
        return "protobuf", build_file_descriptor_set(PROTOBUF_TYPES[name]).SerializeToString()
    return "jsonschema", json.dumps(JSON_SCHEMAS[name]).encode()


def message_encoding(name: str) -> str:
    """The message encoding of a schema name."""
    return "protobuf" if name in PROTOBUF_TYPES else "json"


def _plain(value: Any) -> Any:
    if isinstance(value, float | np.floating):
        value = float(value)
        return value if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.ndarray):
        return [_plain(v) for v in value.tolist()]
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value


def encode_json(record: Mapping[str, Any]) -> bytes:
    """A record as strict JSON (NaN and infinities as null, floats exact)."""
    return json.dumps(_plain(record), allow_nan=False, separators=(",", ":")).encode()


def decode_json(data: bytes) -> dict[str, Any]:
    """A JSON record (nulls stay None; use `number` to read a float field)."""
    return json.loads(data)


def number(value: Any) -> float:
    """A JSON number field as a float (null -> NaN)."""
    return math.nan if value is None else float(value)


def _encoding(image: np.ndarray) -> str:
    if image.dtype == np.uint8:
        return "mono8"
    if image.dtype == np.uint16:
        return "mono16"
    raise FormatError(f"images must be uint8 or uint16, got {image.dtype}")


def raw_image(image: np.ndarray, time_ns: int, frame_id: str = FULL_FRAME_ID) -> bytes:
    """A grey image as a serialised `foxglove.RawImage` (mono8, or mono16 little-endian)."""
    encoding = _encoding(image)
    height, width = image.shape
    pixels = np.ascontiguousarray(image, dtype="<u2" if encoding == "mono16" else np.uint8)
    message = RawImage(
        frame_id=frame_id,
        width=width,
        height=height,
        encoding=encoding,
        step=width * pixels.itemsize,
        data=pixels.tobytes(),
    )
    message.timestamp.FromNanoseconds(int(time_ns))
    return message.SerializeToString()


def image_of(data: bytes) -> np.ndarray:
    """The grey image of a serialised `foxglove.RawImage` written by `raw_image`."""
    try:
        message = RawImage.FromString(data)
    except DecodeError as exc:
        raise FormatError(f"not a foxglove.RawImage ({exc})") from None
    dtypes = {"mono8": np.uint8, "mono16": np.dtype("<u2")}
    if message.encoding not in dtypes:
        raise FormatError(f"RawImage encoding {message.encoding!r} is not mono8 or mono16")
    dtype = np.dtype(dtypes[message.encoding])
    row = message.width * dtype.itemsize
    if message.step != row or len(message.data) != row * message.height:
        raise FormatError(
            f"RawImage {message.width}x{message.height} step {message.step}: "
            f"{len(message.data)} bytes do not match"
        )
    image = np.frombuffer(message.data, dtype=dtype).reshape(message.height, message.width)
    return image.astype(np.uint16) if dtype.itemsize == 2 else image.copy()


def log_message(time_ns: int, level: str, text: str, name: str = "extensometer") -> bytes:
    """A serialised `foxglove.Log` entry; `level` is INFO, WARNING, ERROR, ..."""
    message = Log(level=Log.Level.Value(level), message=text, name=name)
    message.timestamp.FromNanoseconds(int(time_ns))
    return message.SerializeToString()


def png(image: np.ndarray) -> bytes:
    """A grey image as lossless PNG (8 or 16 bit)."""
    _encoding(image)
    ok, data = cv2.imencode(".png", np.ascontiguousarray(image))
    if not ok:
        raise FormatError("the image could not be encoded as PNG")
    return data.tobytes()


def image_of_png(data: bytes) -> np.ndarray:
    """The grey image of `png`'s bytes."""
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None or image.ndim != 2:
        raise FormatError("the reference attachment is not a grey PNG image")
    return image


def trigger_record(sample: StrainSample, mode: str) -> dict[str, Any]:
    """What started the exposure of a sample's frame."""
    trigger = sample.metadata.get("trigger", {}) if sample.metadata else {}
    return {
        "frame_id": sample.frame_id,
        "timestamp_ns": sample.timestamp_ns,
        "exposure_us": sample.exposure_us,
        "mode": mode,
        "sequence": trigger.get("sequence"),
        "tick": trigger.get("tick"),
        "device_timestamp_ns": sample.metadata.get("device_timestamp_ns")
        if sample.metadata
        else None,
    }


def machine_record(state: MachineState) -> dict[str, Any]:
    """A controller state as a record."""
    return {
        "crosshead_mm": state.crosshead_mm,
        "speed_mm_min": state.speed_mm_min,
        "force_n": state.force_n,
        "running": state.running,
        "timestamp_ns": state.timestamp_ns,
        "encoder_counts": state.encoder_counts,
    }


def machine_of(record: Mapping[str, Any]) -> MachineState:
    """The controller state of a `machine_record`."""
    return MachineState(
        crosshead_mm=number(record["crosshead_mm"]),
        speed_mm_min=number(record["speed_mm_min"]),
        force_n=number(record["force_n"]),
        running=bool(record["running"]),
        timestamp_ns=int(record["timestamp_ns"]),
        encoder_counts=record.get("encoder_counts"),
    )


def points_record(
    sample: StrainSample, reference_points: np.ndarray, zeroed: bool
) -> dict[str, Any]:
    """Every point of a sample, and where its windows lie."""
    positions = sample.positions
    gradients = sample.gradients
    return {
        "index": sample.index,
        "frame_id": sample.frame_id,
        "timestamp_ns": sample.timestamp_ns,
        "exposure_us": sample.exposure_us,
        "zeroed": zeroed,
        "windows": [
            {"mark": k, "x": w.x, "y": w.y, "width": w.pixels.shape[1], "height": w.pixels.shape[0]}
            for k, w in enumerate(sample.windows)
        ],
        "points": {
            "x": positions[:, 0],
            "y": positions[:, 1],
            "u": positions[:, 0] - reference_points[:, 0],
            "v": positions[:, 1] - reference_points[:, 1],
            "ux": gradients[:, 0],
            "uy": gradients[:, 1],
            "vx": gradients[:, 2],
            "vy": gradients[:, 3],
            "zncc": sample.zncc,
            "status": [TrackStatus(int(s)).name.lower() for s in sample.status],
        },
    }


def strain_record(sample: StrainSample) -> dict[str, Any]:
    """The strain of a sample."""
    reading = sample.reading
    return {
        "index": sample.index,
        "frame_id": sample.frame_id,
        "timestamp_ns": sample.timestamp_ns,
        "time_s": sample.time_s,
        **{name: getattr(reading, name) for name in STRAIN_FIELDS},
        "data_valid": sample.data_valid,
        "points_lost": sample.points_lost,
        "reference_updates": sample.reference_updates,
        "frames_dropped": sample.frames_dropped,
        "latency_ms": sample.latency_s * 1e3,
        **width_record(sample),
    }


def width_record(sample: StrainSample) -> dict[str, Any]:
    """The width at the specimen's edges of a sample (`[transverse] stations`); empty when
    the test measures none."""
    width = sample.width
    if width is None:
        return {}
    return {
        "width_mm": width.mean_width_mm,
        "width_transverse_strain": width.transverse_strain,
        "width_stations_seen": width.stations_seen,
        "widths_mm": list(width.widths_mm),
    }


def window_of(data: bytes, place: Mapping[str, Any]) -> ImageWindow:
    """A window from its `/camera/window/<k>` image and its place in `/tracking/points`."""
    pixels = image_of(data)
    if pixels.shape != (place["height"], place["width"]):
        raise FormatError(
            f"window of mark {place['mark']}: image {pixels.shape[1]}x{pixels.shape[0]} "
            f"does not match its place {place['width']}x{place['height']}"
        )
    return ImageWindow(int(place["x"]), int(place["y"]), pixels)
