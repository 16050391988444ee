"""A simulated test with the tracker's automatic search: its choices are logged, and it replays
bit for bit."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [EXTENSOMETER, *args], capture_output=True, text=True, timeout=600, check=False
    )


def test_an_automatic_search_run_logs_its_choices_and_replays_bit_for_bit(tmp_path):
    config = tmp_path / "auto.toml"
    config.write_text('[tracking]\nsearch = "auto"\nreacquire_search = "auto"\n')
    recording = tmp_path / "test.mcap"
    done = cli(
        "run", "--sim", "--until-strain", "0.3", "--config", str(config),
        "--record", str(recording), "--out", str(tmp_path), "--json",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    choices = summary["search_choices"]
    assert [c["time_s"] for c in choices[:2]] == [None, None]
    later = choices[2:]
    assert later and all(c["inputs"]["exposure_s"] > 0 for c in later)
    assert all(c["inputs"]["one_step_stretch"] > 0 for c in later)
    assert all(c["choice"]["method"] == "zncc" for c in choices)
    with recording.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        logged = [
            message.message
            for _, _, _, message in reader.iter_decoded_messages(topics=["/log"])
            if message.message.startswith("search choice")
        ]
    assert len(logged) == len(choices)

    done = cli("replay", str(recording), "--json")
    assert done.returncode == 0, done.stderr
    replay = json.loads(done.stdout)
    assert replay["max_abs_diff_to_recorded"] == 0.0
    assert replay["samples_differing"] == 0 and replay["damage"] is None
    assert replay["frames_reading_unrecorded_pixels"] == 0
    assert replay["frames_processed"] == summary["frames_processed"]
