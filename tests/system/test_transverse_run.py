"""A simulated metal test with the width measured at its edges (`[transverse] stations`):
the strain file's width columns follow the simulated sheet, the recording carries them, the
summary names the stations and Poisson's ratio, and a bad station count is refused in one
line."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from appliance.recording.reader import RecordingReader
from appliance.sim.metal import ElasticPlastic

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [EXTENSOMETER, *args], capture_output=True, text=True, timeout=600, check=False
    )


@pytest.fixture(scope="module")
def metal_run(tmp_path_factory) -> dict:
    base = tmp_path_factory.mktemp("transverse")
    config = base / "sheet.toml"
    config.write_text("[transverse]\nstations = 3\n[sim]\nsensor_width_px = 400\n")
    done = cli(
        "run", "--sim", "--material", "metal", "--config", str(config), "--until-strain",
        "0.008", "--speed-mm-min", "5", "--record", str(base / "sheet.mcap"),
        "--out", str(base), "--json",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    return {"dir": base, "summary": json.loads(done.stdout), "recording": base / "sheet.mcap"}


def test_the_width_follows_the_simulated_sheet(metal_run):
    rows = list(csv.DictReader((metal_run["dir"] / "strain.csv").open()))
    assert {"width_mm", "width_transverse_strain", "width_stations_seen"} <= set(rows[0])
    assert {"width_1_mm", "width_2_mm", "width_3_mm"} <= set(rows[0])
    assert all(row["width_stations_seen"] == "3" for row in rows)
    truth = np.array([float(row["truth_strain"]) for row in rows])
    measured = np.array([float(row["width_transverse_strain"]) for row in rows])
    expected = ElasticPlastic.steel_s355().lateral_stretch(1.0 + truth) - 1.0
    assert expected[-1] < -0.004
    far = np.abs(expected) > 0.003
    assert np.all(np.abs(measured[far] - expected[far]) < 0.05 * np.abs(expected[far]))
    width = float(rows[-1]["width_mm"])
    assert width == pytest.approx(12.5 * (1.0 + expected[-1]), abs=0.01)
    summary = metal_run["summary"]
    assert summary["width_stations"] == 3
    assert summary["reference_widths_mm"] == pytest.approx([12.5] * 3, abs=0.03)
    nu = summary["results"]["nu"]
    assert nu["value"] == pytest.approx(0.3, abs=0.05), nu
    assert nu["samples"][1] - nu["samples"][0] >= 10
    assert "width at its edges" in nu["basis"]
    assert summary["results"]["r"]["not_determined"]
    page = (metal_run["dir"] / "report.html").read_text(encoding="utf-8")
    figure = page[page.index('<figure id="transverse">') :]
    assert "width at its edges" in figure[: figure.index("</figure>")]


def test_the_recording_carries_each_station(metal_run):
    rows = list(csv.DictReader((metal_run["dir"] / "strain.csv").open()))
    reader = RecordingReader(metal_run["recording"])
    samples = list(reader.samples())
    reader.close()
    assert len(samples) == len(rows)
    for sample, row in zip(samples, rows, strict=True):
        assert repr(sample.strain["width_mm"]) == row["width_mm"]
        widths = sample.strain["widths_mm"]
        assert [repr(w) for w in widths] == [row[f"width_{k}_mm"] for k in (1, 2, 3)]
        assert sample.strain["width_stations_seen"] == 3


def test_a_bad_station_count_is_refused_in_one_line(tmp_path):
    config = tmp_path / "many.toml"
    config.write_text("[transverse]\nstations = 40\n")
    done = cli(
        "run", "--sim", "--material", "metal", "--config", str(config), "--out", str(tmp_path)
    )
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "[transverse] stations" in lines[0], done.stderr
