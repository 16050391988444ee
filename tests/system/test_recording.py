"""Recordings as a user makes and reads them: `run --record`, `replay`, `info`, third-party readers.

One simulated rubber test is recorded once (module fixture); the tests replay it, read it
with the MCAP library's Foxglove protobuf decoders and with the rerun CLI's MCAP checker,
cut and corrupt copies of it, and kill a real-time run in mid-test.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from appliance.recording.format import JSON_SCHEMAS, decode_json
from appliance.recording.reader import RecordingReader
from tests.system import rerun_peers

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))


def cli(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run(
        [EXTENSOMETER, *args], capture_output=True, text=True, timeout=timeout, check=False
    )


def rerun_mcap_check(path: Path) -> None:
    """`rerun mcap check` passes and finds no issue on any of the main channels."""
    rerun_peers.disable_analytics()
    done = subprocess.run(
        [str(rerun_peers.rerun_binary()), "mcap", "check", str(path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    status = {
        parts[3]: (parts[0], parts[4])
        for parts in (line.split() for line in done.stdout.splitlines())
        if len(parts) == 5 and parts[3].startswith("/")
    }
    for topic in ("/camera/full", "/camera/window/0", "/strain", "/tracking/points", "/log"):
        assert status[topic] == ("ok", "—"), (topic, done.stdout)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> dict:
    base = tmp_path_factory.mktemp("recorded")
    path = base / "test.mcap"
    done = cli(
        "run", "--sim", "--until-strain", "0.5", "--record", str(path), "--out", str(base),
        "--json",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    return {"path": path, "dir": base, "summary": json.loads(done.stdout)}


def test_replay_reproduces_the_recorded_strain_bit_for_bit(recorded):
    done = cli("replay", str(recorded["path"]), "--json")
    assert done.returncode == 0, done.stderr
    replay = json.loads(done.stdout)
    run = recorded["summary"]
    assert replay["max_abs_diff_to_recorded"] == 0.0
    assert replay["samples_differing"] == 0 and replay["damage"] is None
    assert replay["frames_reading_unrecorded_pixels"] == 0
    for key in ("frames_processed", "final_strain", "truth_final_strain", "max_abs_strain_error"):
        assert replay[key] == run[key], key
    assert replay["recorded_exit_status"] == run["exit_status"] == "completed"


def test_the_recording_holds_every_sample_of_the_strain_file_exactly(recorded):
    rows = list(csv.DictReader((recorded["dir"] / "strain.csv").open()))
    reader = RecordingReader(recorded["path"])
    samples = list(reader.samples())
    reader.close()
    assert reader.complete and reader.damage is None
    assert len(samples) == len(rows) == recorded["summary"]["recording_samples"]
    for sample, row in zip(samples, rows, strict=True):
        assert repr(sample.strain["engineering_strain"]) == row["engineering_strain"]
        assert sample.strain["frame_id"] == int(row["frame_id"])
        assert sample.truth["true_engineering_strain"] == float(row["truth_strain"])
        assert set(sample.windows) == {0, 1}
    assert reader.meta("run_stop")["exit_status"] == "completed"


def test_foxglove_schemas_decode_every_channel(recorded):
    with recorded["path"].open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        schemas = {s.name: s for s in summary.schemas.values()}
        assert schemas["foxglove.RawImage"].encoding == "protobuf"
        images = {}
        for _schema, channel, _, decoded in reader.iter_decoded_messages(
            topics=["/camera/full", "/camera/window/0", "/log"]
        ):
            images.setdefault(channel.topic, []).append(decoded)
        full = images["/camera/full"][0]
        assert type(full).__name__ == "RawImage" and full.encoding == "mono8"
        assert (full.width, full.height) == (1024, 2048) and len(full.data) == 1024 * 2048
        assert all(type(e).__name__ == "Log" for e in images["/log"])
        for schema, channel, message in reader.iter_messages(topics=["/strain", "/machine/state"]):
            assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
            properties = json.loads(schema.data)["properties"]
            assert properties == JSON_SCHEMAS[schema.name]["properties"]
            assert set(decode_json(message.data)) <= set(properties)


def test_rerun_checks_the_recording(recorded):
    rerun_mcap_check(recorded["path"])


def test_info_summarises_the_recording(recorded):
    done = cli("info", str(recorded["path"]), "--json")
    assert done.returncode == 0, done.stderr
    info = json.loads(done.stdout)
    assert info["complete"] and info["damage"] is None
    assert info["format"] == "extensometer-mcap"
    assert info["samples"] == recorded["summary"]["frames_processed"]
    assert info["exit_status"] == "completed" and info["material"] == "rubber"
    assert info["attachments"]["reference.png"] > 0


@pytest.mark.parametrize("fraction", [0.45, 0.9])
def test_a_cut_recording_replays_up_to_the_damage(recorded, tmp_path, fraction):
    data = recorded["path"].read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * fraction)])
    done = cli("replay", str(cut), "--json")
    assert done.returncode == 1
    assert f"{cut}: damaged after byte" in done.stderr and "ends inside a record" in done.stderr
    replay = json.loads(done.stdout)
    assert 0 < replay["frames_processed"] < recorded["summary"]["frames_processed"]
    assert replay["samples_differing"] == 0 and replay["max_abs_diff_to_recorded"] == 0.0
    info = cli("info", str(cut), "--json")
    assert info.returncode == 1 and json.loads(info.stdout)["complete"] is False


def test_a_corrupted_chunk_is_found_and_named(recorded, tmp_path):
    data = bytearray(recorded["path"].read_bytes())
    data[int(len(data) * 0.6)] ^= 0x5A
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    done = cli("replay", str(bad), "--json")
    assert done.returncode == 1 and "damaged after byte" in done.stderr
    assert json.loads(done.stdout)["samples_differing"] == 0


def test_an_override_measures_again(recorded, tmp_path):
    override = tmp_path / "override.toml"
    override.write_text("[tracking]\nsubset_px = 31\n")
    done = cli("replay", str(recorded["path"]), "--config", str(override), "--json")
    assert done.returncode == 0, done.stderr
    replay = json.loads(done.stdout)
    assert replay["samples_differing"] > 0
    assert 0 < replay["max_abs_diff_to_recorded"] < 1e-3
    assert 0 <= replay["frames_reading_unrecorded_pixels"] <= replay["frames_processed"]
    assert replay["max_rel_strain_error"] < 0.01


@pytest.mark.parametrize(
    ("args", "culprit"),
    [
        (["replay", "absent.mcap"], "absent.mcap: no such recording"),
        (["info", "absent.mcap"], "absent.mcap: no such recording"),
        (["replay", "{csv}"], "strain.csv: not an MCAP file"),
        (["replay", "{mcap}", "--config", "{bad_toml}"], "[tracking] subset_px: must be odd"),
        (
            ["replay", "{mcap}", "--config", "{gauge_toml}"],
            "[gauge] length_mm: cannot be applied to a replay",
        ),
        (["run", "--sim", "--record", "{mcap}"], "exists (a recording is never overwritten)"),
    ],
)
def test_bad_inputs_give_one_line_naming_the_culprit(recorded, tmp_path, args, culprit):
    bad_toml = tmp_path / "bad.toml"
    bad_toml.write_text("[tracking]\nsubset_px = 40\n")
    gauge_toml = tmp_path / "gauge.toml"
    gauge_toml.write_text("[gauge]\nlength_mm = 20\n")
    names = {
        "csv": str(recorded["dir"] / "strain.csv"),
        "mcap": str(recorded["path"]),
        "bad_toml": str(bad_toml),
        "gauge_toml": str(gauge_toml),
    }
    done = cli(*[a.format(**names) for a in args], timeout=120)
    assert done.returncode == 2
    assert culprit in done.stderr and done.stderr.count("\n") == 1
    assert "Traceback" not in done.stderr


def test_a_killed_run_leaves_every_flushed_sample_replayable(tmp_path):
    """SIGKILL in mid-test: the samples flushed before the kill replay exactly; the loss is
    bounded by the flush interval (0.5 s here) plus the time a sample takes to reach the
    writer."""
    config = tmp_path / "run.toml"
    config.write_text("[record]\nflush_interval_s = 0.5\n[sim]\nrealtime = true\n")
    path = tmp_path / "killed.mcap"
    out = tmp_path / "out"
    process = subprocess.Popen(
        [EXTENSOMETER, "run", "--sim", "--config", str(config), "--record", str(path),
         "--out", str(out), "--json"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )  # fmt: skip
    csv_path = out / "strain.csv"
    deadline = time.monotonic() + 240
    try:
        while time.monotonic() < deadline:
            if csv_path.exists() and csv_path.read_text().count("\n") > 40:
                break
            assert process.poll() is None, process.stderr.read().decode()
            time.sleep(0.2)
        else:
            pytest.fail("the run did not reach 40 samples")
        os.kill(process.pid, signal.SIGKILL)
        process.wait(timeout=30)
    finally:
        if process.poll() is None:
            process.kill()
    rows = list(csv.DictReader(csv_path.open()))
    done = cli("replay", str(path), "--json")
    assert done.returncode == 1 and "damaged after byte" in done.stderr
    assert "the file ends inside a record" in done.stderr or "ends before its footer" in done.stderr
    replay = json.loads(done.stdout)
    print(f"killed after {len(rows)} samples in strain.csv; {replay['frames_processed']} replayed")
    assert replay["samples_differing"] == 0
    frame_rate = 20.0
    assert replay["frames_processed"] >= len(rows) - frame_rate * (0.5 + 1.0)
    reader = RecordingReader(path)
    samples = list(reader.samples())
    reader.close()
    for sample, row in zip(samples, rows, strict=False):
        assert repr(sample.strain["engineering_strain"]) == row["engineering_strain"]
