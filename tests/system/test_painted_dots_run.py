"""A simulated rubber test measured between painted dots (`[gauge] marks = "dots"` on a world
that paints them, `[sim] painted_marks = "dots"`): every sample valid to 200 %, the strain
within its tolerance of the truth, the recording replayed bit for bit; painted lines likewise
to 100 %; and a reference frame without the dots refused in one line before the crosshead
moves."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))


def cli(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run(
        [EXTENSOMETER, *args], capture_output=True, text=True, timeout=timeout, check=False
    )


def _config(path: Path, *, gauge_marks: str, painted: str) -> Path:
    path.write_text(f'[gauge]\nmarks = "{gauge_marks}"\n[sim]\npainted_marks = "{painted}"\n')
    return path


@pytest.fixture(scope="module")
def dots_run(tmp_path_factory) -> dict:
    base = tmp_path_factory.mktemp("dots")
    config = _config(base / "dots.toml", gauge_marks="dots", painted="dots")
    recording = base / "test.mcap"
    done = cli(
        "run", "--sim", "--config", str(config), "--until-strain", "2.0",
        "--record", str(recording), "--out", str(base / "out"), "--json",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    return {"summary": json.loads(done.stdout), "recording": recording, "out": base / "out"}


def test_painted_dots_keep_every_sample_valid_to_200_percent(dots_run):
    summary = dots_run["summary"]
    assert summary["exit_status"] == "completed"
    assert summary["gauge_placement"] == "painted dots"
    assert summary["points"] == 2
    assert summary["final_strain"] >= 2.0
    assert summary["lost_points"] == 0 and summary["invalid_samples"] == 0
    assert summary["frames_dropped"] == 0


def test_the_strain_between_painted_dots_follows_the_truth(dots_run):
    with (dots_run["out"] / "strain.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == dots_run["summary"]["frames_processed"]
    for row in rows:
        truth = float(row["truth_strain"])
        error = abs(float(row["engineering_strain"]) - truth)
        assert error <= max(0.005 * truth, 0.001), row["index"]


def test_a_test_measured_between_painted_dots_replays_bit_for_bit(dots_run):
    done = cli("replay", str(dots_run["recording"]), "--json")
    assert done.returncode == 0, done.stderr
    replay = json.loads(done.stdout)
    assert replay["max_abs_diff_to_recorded"] == 0.0
    assert replay["samples_differing"] == 0
    assert replay["frames_reading_unrecorded_pixels"] == 0
    assert replay["final_strain"] == dots_run["summary"]["final_strain"]


def test_a_reference_frame_without_painted_dots_is_refused_before_the_start(tmp_path):
    config = _config(tmp_path / "dots.toml", gauge_marks="dots", painted="none")
    done = cli("run", "--sim", "--config", str(config), "--out", str(tmp_path / "out"))
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert "error: reference frame: no painted dot found above grey" in lines[0], lines[0]
    assert lines[0].endswith('two are needed ([gauge] marks = "dots")'), lines[0]
    assert "Traceback" not in done.stderr
    strain_file = tmp_path / "out" / "strain.csv"
    assert not strain_file.exists() or len(strain_file.read_text().splitlines()) <= 1


def test_painted_lines_keep_every_sample_valid_and_follow_the_truth(tmp_path):
    config = _config(tmp_path / "lines.toml", gauge_marks="lines", painted="lines")
    out = tmp_path / "out"
    done = cli(
        "run", "--sim", "--config", str(config), "--until-strain", "1.0", "--out", str(out),
        "--json",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["gauge_placement"] == "painted lines"
    assert summary["lost_points"] == 0 and summary["invalid_samples"] == 0
    with (out / "strain.csv").open() as f:
        for row in csv.DictReader(f):
            truth = float(row["truth_strain"])
            error = abs(float(row["engineering_strain"]) - truth)
            assert error <= max(0.005 * truth, 0.0015), row["index"]
