"""Recordings made by earlier releases still open, replay bit for bit and report.

`data/recording_v1/` holds a short simulated rubber test recorded by the last release that
wrote format version 1 (its README says how it was made). The reader migrates its names to
the current ones (`appliance.recording.migration`); the file itself is never changed.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from mcap.writer import Writer

from appliance.recording.format import FORMAT_NAME, FORMAT_VERSION
from appliance.recording.reader import RecordingReader, config_table, recorded_devices, run_facts

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))
VERSION_1 = Path(__file__).parent / "data" / "recording_v1" / "rubber_to_8_percent.mcap"


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [EXTENSOMETER, *args], capture_output=True, text=True, timeout=300, check=False
    )


def test_a_version_1_recording_replays_bit_for_bit():
    done = cli("replay", str(VERSION_1), "--json")
    assert done.returncode == 0, done.stderr
    replay = json.loads(done.stdout)
    assert replay["max_abs_diff_to_recorded"] == 0.0 and replay["samples_differing"] == 0
    assert replay["damage"] is None and replay["frames_processed"] == 13
    assert replay["recorded_exit_status"] == "completed"
    assert replay["machine_url"] == "sim://machine" and "frame_url" not in replay


def test_a_version_1_recording_reads_in_the_current_names():
    reader = RecordingReader(VERSION_1)
    try:
        samples = list(reader.samples())
        reader.check_format()
        assert reader.version == 1 and reader.damage is None
        assert len(samples) == 13 and all(s.machine is not None for s in samples)
        assert all(s.machine["speed_mm_min"] > 0 for s in samples)
        table = config_table(reader)
        assert "frame" not in table and table["machine"]["url"] == "sim://machine"
        assert run_facts(reader)["machine_url"] == "sim://machine"
        assert recorded_devices(reader) == {
            "camera": "sim://camera",
            "machine": "sim://machine",
            "software": "extensometer 0.1.0",
        }
    finally:
        reader.close()


def test_info_reports_a_version_1_recording_as_it_was_written():
    done = cli("info", str(VERSION_1), "--json")
    assert done.returncode == 0, done.stderr
    info = json.loads(done.stdout)
    assert info["format_version"] == "1" and info["complete"] and info["damage"] is None
    assert info["channels"]["/frame/state"] == 13 and info["samples"] == 13
    assert info["exit_status"] == "completed" and info["material"] == "rubber"


def test_a_recording_of_a_newer_format_is_refused_in_one_line(tmp_path):
    newer = tmp_path / "newer.mcap"
    with newer.open("wb") as f:
        writer = Writer(f)
        writer.start(profile="", library="test")
        writer.add_metadata(
            "extensometer.recording",
            {"format": FORMAT_NAME, "version": str(int(FORMAT_VERSION) + 1)},
        )
        writer.finish()
    done = cli("replay", str(newer))
    assert done.returncode == 2 and done.stderr.count("\n") == 1
    assert f"{newer}: recording format version '{int(FORMAT_VERSION) + 1}'" in done.stderr


def test_info_into_a_pipe_closed_early_ends_without_a_traceback():
    process = subprocess.Popen(
        [EXTENSOMETER, "info", str(VERSION_1)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    process.stdout.close()
    stderr = process.stderr.read()
    assert process.wait(timeout=120) == 141
    assert stderr == ""
