"""A recording as Foxglove shows it: points drawn where they were tracked, windows placed
where they were cut from, every timestamp in UNIX time, every JSON field described.

The recorder writes a short test of known samples (four points in two marks, one of them
reacquired, one lost); the file is read back with the MCAP library and decoded with the
Foxglove schemas' protobuf classes, as a viewer would.
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from appliance.config import Config, RecordConfig
from appliance.measure.frame_measurer import StrainSample
from appliance.measure.frame_windows import cut_windows
from appliance.measure.gauges import Calibration, Gauge, StrainGaugesLayout, StrainReading
from appliance.measure.tracking import ReadRegion, TrackStatus
from appliance.recording.format import JSON_SCHEMAS, image_of
from appliance.recording.overlays import STATUS_COLOURS
from appliance.recording.reader import RecordingReader
from appliance.recording.writer import McapRecorder
from appliance.run.loop import LoopResult
from appliance.run.outputs import RunFacts
from hal.camera.base import Frame
from tests.foxglove_checks import decoded_messages, schema_violations

SIZE = 200
EPOCH_OFFSET_NS = 1_700_000_000_123_456_789
PERIOD_NS = 20_000_000
SAMPLES = 12
POINTS = np.array([[60.0, 40.0], [80.0, 45.0], [62.0, 150.0], [81.0, 155.0]])
MARKS = ((0, 1), (2, 3))
STATUS = np.array([TrackStatus.TRACKED, TrackStatus.REACQUIRED, TrackStatus.LOST, 0], np.int8)


def _image(k: int) -> np.ndarray:
    return np.random.default_rng(k).integers(0, 256, (SIZE, SIZE), dtype=np.uint8)


def _sample(k: int) -> StrainSample:
    image = _image(k + 1)
    positions = POINTS + [0.25 * k, 1.5 * k + 0.125]
    regions = [ReadRegion(40 + k, 20 + k, 61, 41), ReadRegion(42, 130 + 2 * k, 57, 43)]
    strain = 1e-3 * k
    return StrainSample(
        index=k,
        frame_id=k + 1,
        timestamp_ns=(k + 1) * PERIOD_NS,
        time_s=(k + 1) * PERIOD_NS * 1e-9,
        exposure_us=100.0,
        reading=StrainReading(110.0, strain, math.log1p(strain), 11 * strain, 11.0, math.nan, 0.3),
        positions=positions,
        status=STATUS.copy(),
        zncc=np.array([0.99, 0.97, math.nan, 0.98]),
        gradients=np.zeros((4, 4)),
        data_valid=True,
        reference_updates=0,
        machine=None,
        latency_s=0.001,
        windows=cut_windows(image, regions),
        image=image,
    )


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("overlays") / "test.mcap"
    recorder = McapRecorder(path, RecordConfig(full_frame_rate_hz=10.0))
    recorder.begin(
        RunFacts(
            config=Config(),
            reference=Frame(_image(0), 0, 0, 100.0),
            points=POINTS,
            marks=MARKS,
            layout=StrainGaugesLayout(Gauge((0, 1), (2, 3)), None),
            calibration=Calibration(0.1),
            gauge_length_mm=11.0,
            epoch_offset_ns=EPOCH_OFFSET_NS,
        )
    )
    for k in range(SAMPLES):
        recorder(_sample(k))
    recorder.end(LoopResult(frames_processed=SAMPLES))
    messages = decoded_messages(path)
    by_topic: dict[str, dict[int, object]] = {}
    for m in messages:
        by_topic.setdefault(m.topic, {}).setdefault(m.sequence, m)
    return {"path": path, "messages": messages, "by_topic": by_topic}


def _centres(annotations) -> list[tuple[float, float]]:
    return [(c.position.x, c.position.y) for c in annotations.circles]


def _ns(stamp) -> int:
    return stamp.seconds * 1_000_000_000 + stamp.nanos


def test_full_frame_annotations_draw_every_point_where_it_was_tracked(recording):
    full = recording["by_topic"]["/annotations/full"]
    points = recording["by_topic"]["/tracking/points"]
    samples_with_full_frames = sorted(s for s in full if s in points and s > 0)
    assert len(samples_with_full_frames) >= 2
    for seq in samples_with_full_frames:
        annotations = full[seq].message
        tracked = points[seq].message
        expected = [
            (x + 0.5, y + 0.5)
            for x, y in zip(tracked["points"]["x"], tracked["points"]["y"], strict=True)
        ]
        assert _centres(annotations) == expected
        assert [t.text for t in annotations.texts] == ["0", "1", "2", "3"]
        colours = [
            (c.outline_color.r, c.outline_color.g, c.outline_color.b) for c in annotations.circles
        ]
        assert colours == [STATUS_COLOURS[TrackStatus(int(s))] for s in STATUS]
        outlines = [[(p.x, p.y) for p in loop.points] for loop in annotations.points]
        assert outlines == [
            [(w["x"], w["y"]), (w["x"] + w["width"], w["y"]),
             (w["x"] + w["width"], w["y"] + w["height"]), (w["x"], w["y"] + w["height"])]
            for w in tracked["windows"]
        ]  # fmt: skip
    reference = full[0]
    assert reference.log_time_ns == EPOCH_OFFSET_NS
    assert _centres(reference.message) == [(x + 0.5, y + 0.5) for x, y in POINTS]
    assert {(kv.key, kv.value) for kv in reference.message.metadata} == {("sample", "reference")}


def test_window_annotations_hold_their_marks_points_in_the_windows_pixels(recording):
    by_topic = recording["by_topic"]
    for seq in range(SAMPLES):
        tracked = by_topic["/tracking/points"][seq].message
        for mark, numbers in enumerate(MARKS):
            annotations = by_topic[f"/annotations/window/{mark}"][seq].message
            place = tracked["windows"][mark]
            assert _centres(annotations) == [
                (tracked["points"]["x"][n] - place["x"] + 0.5,
                 tracked["points"]["y"][n] - place["y"] + 0.5)
                for n in numbers
            ]  # fmt: skip
            assert [t.text for t in annotations.texts] == [str(n) for n in numbers]


def test_each_window_sits_where_it_was_cut_from_in_the_full_frame(recording):
    by_topic = recording["by_topic"]
    checked = 0
    for seq, transforms in by_topic["/camera/transforms"].items():
        assert [t.parent_frame_id for t in transforms.message.transforms] == ["camera", "camera"]
        for mark, transform in enumerate(transforms.message.transforms):
            window = by_topic[f"/camera/window/{mark}"][seq]
            assert transform.child_frame_id == window.message.frame_id == f"camera/window/{mark}"
            rotation = transform.rotation
            assert (rotation.x, rotation.y, rotation.z, rotation.w) == (0, 0, 0, 1)
            assert transform.translation.z == 0
            full = by_topic["/camera/full"].get(seq)
            if full is None or seq == 0:
                continue
            assert full.message.frame_id == "camera"
            x, y = int(transform.translation.x), int(transform.translation.y)
            assert (x, y) == (transform.translation.x, transform.translation.y)
            pixels = image_of(window.message.SerializeToString())
            frame = image_of(full.message.SerializeToString())
            assert np.array_equal(frame[y : y + pixels.shape[0], x : x + pixels.shape[1]], pixels)
            checked += 1
    assert checked >= 4


def test_every_timestamp_in_a_message_is_its_log_time_in_unix_time(recording):
    kinds = set()
    for m in recording["messages"]:
        if m.schema_encoding == "jsonschema":
            stamp = m.message["timestamp"]
            assert 0 <= stamp["nsec"] < 1_000_000_000
            assert stamp["sec"] * 1_000_000_000 + stamp["nsec"] == m.log_time_ns, m.topic
            if "timestamp_ns" in m.message and m.topic != "/machine/state":
                assert m.log_time_ns == EPOCH_OFFSET_NS + m.message["timestamp_ns"]
        elif m.schema_name == "foxglove.FrameTransforms":
            assert {_ns(t.timestamp) for t in m.message.transforms} == {m.log_time_ns}
        else:
            assert _ns(m.message.timestamp) == m.log_time_ns, m.topic
        kinds.add(m.schema_name)
    assert kinds >= {
        "foxglove.RawImage", "foxglove.ImageAnnotations", "foxglove.FrameTransforms",
        "foxglove.Log", "extensometer.Strain", "extensometer.TrackedPoints",
        "extensometer.Trigger",
    }  # fmt: skip
    assert min(m.log_time_ns for m in recording["messages"]) >= EPOCH_OFFSET_NS


def test_every_json_message_follows_the_schema_registered_for_its_channel(recording):
    checked = 0
    for m in recording["messages"]:
        if m.schema is not None:
            assert m.schema == JSON_SCHEMAS[m.schema_name]
            assert schema_violations(m.message, m.schema) == [], m.topic
            checked += 1
    assert checked == 3 * SAMPLES


def _properties(schema: dict, where: str = ""):
    for name, item in schema.get("properties", {}).items():
        yield f"{where}{name}", item
        yield from _properties(item, f"{where}{name}.")
        yield from _properties(item.get("items", {}), f"{where}{name}[].")


UNIT_SUFFIXES = {
    "_mm_min": "mm/min", "_mm": "mm", "_n": "N", "_us": "us", "_ns": "ns", "_ms": "ms",
    "_s": "s", "_px": "px", "_bytes": "bytes",
}  # fmt: skip


@pytest.mark.parametrize("name", sorted(JSON_SCHEMAS))
def test_every_json_field_is_described_with_its_unit(name):
    for where, item in _properties(JSON_SCHEMAS[name]):
        assert len(item.get("description", "")) > 8, (name, where)
        suffix = next((s for s in UNIT_SUFFIXES if re.search(f"{s}$", where)), None)
        if suffix is not None:
            assert item.get("unit") == UNIT_SUFFIXES[suffix], (name, where)


def test_the_reader_and_its_samples_ignore_the_viewers_channels(recording):
    reader = RecordingReader(recording["path"])
    samples = list(reader.samples())
    reader.close()
    assert reader.complete and reader.damage is None
    assert [s.index for s in samples] == list(range(SAMPLES))
    assert all(set(s.windows) == {0, 1} for s in samples)
    assert reader.message_counts["/annotations/full"] == reader.message_counts["/camera/full"]
    assert reader.message_counts["/camera/transforms"] == SAMPLES
