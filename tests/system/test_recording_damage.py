"""Damaged and foreign recordings as a user meets them: `info` and `replay` say what is wrong.

One short simulated test is recorded once (module fixture) with small chunks, so that its
samples lie in several chunks; the tests damage copies of it where a disk or a copy would (one
flipped bit in the reference attachment, in a chunk, in the summary), join two recordings with
`cat`, and write an MCAP file of another program. Where the damage lies is found with the MCAP
library's own index of the file, not with the product's reader.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Chunk, MessageIndex, SummaryOffset
from mcap.stream_reader import StreamReader
from mcap.writer import Writer

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))
SAMPLES = 9


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [EXTENSOMETER, *args], capture_output=True, text=True, timeout=300, check=False
    )


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    base = tmp_path_factory.mktemp("damage")
    config = base / "small.toml"
    config.write_text(
        '[sim]\nmaterial = "rubber"\nseed = 7\nsensor_width_px = 320\nsensor_height_px = 640\n'
        "[record]\nfull_frame_rate_hz = 0.0\nchunk_size_kb = 16\n"
        "[run]\nuntil_strain = 0.05\n"
    )
    path = base / "small.mcap"
    done = cli(
        "run", "--sim", "--config", str(config), "--record", str(path), "--out", str(base / "out"),
        "--json",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["frames_processed"] == SAMPLES
    return path


def _summary(path: Path):
    with path.open("rb") as f:
        return make_reader(f).get_summary()


def _flipped(source: Path, target: Path, *offsets: int) -> Path:
    data = bytearray(source.read_bytes())
    for offset in offsets:
        data[offset] ^= 0x10
    target.write_bytes(bytes(data))
    return target


def _reference_attachment_middle(path: Path) -> int:
    (index,) = [a for a in _summary(path).attachment_indexes if a.name == "reference.png"]
    return index.offset + index.length // 2


def _strain_messages_per_chunk(path: Path) -> list[tuple[int, int, int]]:
    """(start, length, /strain messages) of every chunk, from the chunk and message indexes."""
    summary = _summary(path)
    (strain,) = [c.id for c in summary.channels.values() if c.topic == "/strain"]
    counts: list[int] = []
    with path.open("rb") as f:
        for record in StreamReader(f, emit_chunks=True).records:
            if isinstance(record, Chunk):
                counts.append(0)
            elif isinstance(record, MessageIndex) and record.channel_id == strain:
                counts[-1] += len(record.records)
    indexes = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    return [(c.chunk_start_offset, c.chunk_length, n) for c, n in zip(indexes, counts, strict=True)]


def _one_line(stderr: str) -> str:
    assert stderr.count("\n") == 1 and "Traceback" not in stderr, stderr
    return stderr


def test_a_flipped_bit_in_the_reference_attachment_replays_from_the_recorded_full_frame(
    recorded, tmp_path
):
    bad = _flipped(recorded, tmp_path / "bad.mcap", _reference_attachment_middle(recorded))
    done = cli("replay", str(bad), "--json")
    assert done.returncode == 1
    line = _one_line(done.stderr)
    assert f"{bad}: damaged after byte" in line and "reference.png fails its CRC" in line
    assert f"{SAMPLES} of {SAMPLES} recorded samples measured" in line
    assert "the reference frame was read from /camera/full" in line
    replay = json.loads(done.stdout)
    assert replay["exit_status"] == "damaged" and replay["reference_frame"] == "/camera/full"
    assert replay["frames_processed"] == replay["recorded_samples"] == SAMPLES
    assert replay["samples_differing"] == 0 and replay["max_abs_diff_to_recorded"] == 0.0
    info = cli("info", str(bad), "--json")
    assert info.returncode == 1 and "reference.png fails its CRC" in _one_line(info.stderr)
    facts = json.loads(info.stdout)
    assert "reference.png" not in facts["attachments"] and facts["samples"] == SAMPLES


def test_a_reference_that_cannot_be_recovered_is_refused_in_one_line(recorded, tmp_path):
    first_chunk = _strain_messages_per_chunk(recorded)[0]
    bad = _flipped(
        recorded,
        tmp_path / "bad.mcap",
        _reference_attachment_middle(recorded),
        first_chunk[0] + first_chunk[1] // 2,
    )
    done = cli("replay", str(bad))
    assert done.returncode == 2
    line = _one_line(done.stderr)
    assert f"{bad}: the reference frame cannot be recovered" in line
    assert "the reference.png attachment is damaged" in line and "damaged after byte" in line


def test_damage_in_a_later_chunk_replays_every_sample_before_it(recorded, tmp_path):
    chunks = _strain_messages_per_chunk(recorded)
    whole = [sum(n for *_, n in chunks[:k]) for k in range(len(chunks))]
    damaged = next(k for k, samples in enumerate(whole) if samples >= SAMPLES // 2)
    start, length, _ = chunks[damaged]
    before = whole[damaged]
    assert 0 < before < SAMPLES
    bad = _flipped(recorded, tmp_path / "bad.mcap", start + length // 2)
    done = cli("replay", str(bad), "--json")
    assert done.returncode == 1
    line = _one_line(done.stderr)
    assert f"{bad}: damaged after byte {start} of {bad.stat().st_size}: chunk" in line
    assert f"{before} recorded samples measured before it" in line
    replay = json.loads(done.stdout)
    assert replay["exit_status"] == "damaged" and replay["frames_processed"] == before
    assert replay["samples_differing"] == 0 and replay["max_abs_diff_to_recorded"] == 0.0
    assert replay["reference_frame"] == "reference.png"


def test_damage_in_the_metadata_is_reported_by_the_data_section_crc(recorded, tmp_path):
    (devices,) = [m for m in _summary(recorded).metadata_indexes if m.name.endswith(".devices")]
    bad = _flipped(recorded, tmp_path / "bad.mcap", devices.offset + devices.length - 3)
    info = cli("info", str(bad), "--json")
    assert info.returncode == 1
    line = _one_line(info.stderr)
    assert f"{bad}: damaged before byte" in line and "the data section's CRC does not match" in line
    done = cli("replay", str(bad), "--json")
    assert done.returncode == 1 and f"{SAMPLES} of {SAMPLES}" in _one_line(done.stderr)
    replay = json.loads(done.stdout)
    assert replay["exit_status"] == "damaged" and replay["samples_differing"] == 0


def test_damage_in_the_summary_section_is_reported(recorded, tmp_path):
    with recorded.open("rb") as f:
        groups = {
            r.group_opcode: r.group_start
            for r in StreamReader(f, emit_chunks=True).records
            if isinstance(r, SummaryOffset)
        }
    message_count = groups[Opcode.STATISTICS] + 9
    bad = _flipped(recorded, tmp_path / "bad.mcap", message_count)
    info = cli("info", str(bad), "--json")
    assert info.returncode == 1
    assert "the summary section's CRC does not match" in _one_line(info.stderr)
    done = cli("replay", str(bad), "--json")
    assert done.returncode == 1 and f"{SAMPLES} of {SAMPLES}" in _one_line(done.stderr)
    assert json.loads(done.stdout)["samples_differing"] == 0


def test_two_joined_recordings_are_refused_by_info_and_replay(recorded, tmp_path):
    joined = tmp_path / "joined.mcap"
    joined.write_bytes(recorded.read_bytes() * 2)
    size = recorded.stat().st_size
    for command in ("info", "replay"):
        done = cli(command, str(joined))
        assert done.returncode == 2, command
        line = _one_line(done.stderr)
        assert f"{joined}: a second MCAP file starts at byte {size}" in line, command


def test_bytes_after_the_end_of_a_recording_are_refused(recorded, tmp_path):
    longer = tmp_path / "longer.mcap"
    longer.write_bytes(recorded.read_bytes() + b"\0" * 100)
    for command in ("info", "replay"):
        done = cli(command, str(longer))
        assert done.returncode == 2, command
        assert f"{longer}: 100 bytes follow the end of the recording" in _one_line(done.stderr)


def test_an_mcap_file_of_another_program_is_refused_by_info_and_replay(tmp_path):
    foreign = tmp_path / "foreign.mcap"
    with foreign.open("wb") as f:
        writer = Writer(f)
        writer.start(profile="ros2", library="another recorder 1.0")
        schema = writer.register_schema("Imu", "jsonschema", b'{"type": "object"}')
        channel = writer.register_channel("/imu", "json", schema)
        for k in range(20):
            writer.add_message(channel, k * 1000, json.dumps({"ax": k}).encode(), k * 1000)
        writer.add_metadata("calibration", {"imu": "factory"})
        writer.finish()
    for command in ("info", "replay"):
        done = cli(command, str(foreign))
        assert done.returncode == 2, command
        line = _one_line(done.stderr)
        assert f"{foreign}: not an extensometer recording" in line, command
        assert "'another recorder 1.0'" in line and "'ros2'" in line, command
