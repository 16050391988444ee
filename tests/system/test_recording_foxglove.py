"""A simulated test's recording as a Foxglove user opens it, and the version it carries.

One simulated rubber test is recorded through the command line; its file is read with the
MCAP library and the Foxglove schemas' protobuf decoders, checked by the rerun CLI's MCAP
checker, and its recorded software version compared with `extensometer --version`.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from mcap.reader import make_reader

from appliance.recording.reader import RecordingReader
from tests.foxglove_checks import decoded_messages, schema_violations
from tests.system import rerun_peers

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))
PYPROJECT = Path(__file__).resolve().parents[2] / "pyproject.toml"


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [EXTENSOMETER, *args], capture_output=True, text=True, timeout=600, check=False
    )


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    base = tmp_path_factory.mktemp("foxglove")
    path = base / "test.mcap"
    done = cli("run", "--sim", "--until-strain", "0.3", "--record", str(path), "--out", str(base))
    assert done.returncode == 0, done.stderr
    return path


def test_every_channel_decodes_with_the_foxglove_schemas_and_stamps_its_log_time(recorded):
    messages = decoded_messages(recorded)
    topics = {m.topic for m in messages}
    assert {"/annotations/full", "/annotations/window/0", "/annotations/window/1"} <= topics
    assert "/camera/transforms" in topics
    json_checked = 0
    for m in messages:
        if m.schema is not None:
            assert schema_violations(m.message, m.schema) == [], m.topic
            stamp = m.message["timestamp"]
            assert stamp["sec"] * 1_000_000_000 + stamp["nsec"] == m.log_time_ns, m.topic
            json_checked += 1
        elif m.schema_name == "foxglove.FrameTransforms":
            assert len(m.message.transforms) == 2
            for t in m.message.transforms:
                assert t.timestamp.ToNanoseconds() == m.log_time_ns
        else:
            assert m.message.timestamp.ToNanoseconds() == m.log_time_ns, m.topic
    assert json_checked > 0
    first_full = next(m for m in messages if m.topic == "/annotations/full")
    assert len(first_full.message.circles) == len(first_full.message.texts) > 0


def test_window_annotations_and_transforms_put_every_point_back_where_it_was_tracked(recorded):
    by_seq: dict[tuple[str, int], object] = {}
    for m in decoded_messages(recorded):
        by_seq.setdefault((m.topic, m.sequence), m.message)
    reader = RecordingReader(recorded)
    marks = None
    for sample in reader.samples():
        marks = marks or json.loads(reader.meta("marks")["marks"])
        xs, ys = sample.points["points"]["x"], sample.points["points"]["y"]
        transforms = by_seq[("/camera/transforms", sample.index)].transforms
        for mark, numbers in enumerate(marks):
            offset = transforms[mark].translation
            circles = by_seq[(f"/annotations/window/{mark}", sample.index)].circles
            placed = [
                v for c in circles for v in (c.position.x + offset.x, c.position.y + offset.y)
            ]
            tracked = [v for n in numbers for v in (xs[n] + 0.5, ys[n] + 0.5)]
            assert placed == pytest.approx(tracked, abs=1e-9)
    reader.close()
    assert marks is not None


def test_rerun_checks_every_channel(recorded):
    rerun_peers.disable_analytics()
    done = subprocess.run(
        [str(rerun_peers.rerun_binary()), "mcap", "check", str(recorded)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    rows = [line.split() for line in done.stdout.splitlines()]
    status = {r[3]: (r[0], r[4]) for r in rows if len(r) == 5 and r[3].startswith("/")}
    assert {"/annotations/full", "/annotations/window/0", "/camera/transforms"} <= set(status)
    assert all(v == ("ok", "—") for v in status.values()), done.stdout


def test_version_prints_the_version_every_recording_carries(recorded):
    done = cli("--version")
    assert done.returncode == 0 and done.stderr == ""
    printed = done.stdout.strip()
    version = tomllib.loads(PYPROJECT.read_text())["project"]["version"]
    assert printed == f"extensometer {version}"
    with recorded.open("rb") as f:
        assert make_reader(f).get_header().library == printed
    reader = RecordingReader(recorded)
    reader.read_all()
    reader.close()
    assert reader.meta("run_start")["software_version"] == version
