"""Results and report.html of whole simulated tests, run and replayed in a real process."""

import html
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from appliance.sim.metal import ElasticPlastic

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))

METAL_TO_RM = """
[sim]
material = "metal"
sensor_width_px = 320
speed_change_after_s = 12.0
speed_change_mm_min = 100.0

[run]
speed_mm_min = 2.0
until_strain = 0.17

[camera]
exposure_us = 500.0
frame_rate_hz = 20.0

[trigger]
replan_hysteresis = 0.0
"""
"""A quick simulated steel test past Rm (`appliance.bench.results_accuracy.METAL_TO_RM`):
2 mm/min through the elastic range and the proof strength (about 40 samples in the modulus's
fit range), then 100 mm/min to 17 %, past the maximum force at Agt = 15.1 %; a narrow sensor,
as only the marks' columns are read."""


def extensometer(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run(
        [EXTENSOMETER, *args], capture_output=True, text=True, timeout=timeout, check=False
    )


def results_table(page: str) -> str:
    start = page.index('<table id="results">')
    return page[start : page.index("</table>", start)]


def assert_self_contained(page: str) -> None:
    assert not re.search(r"https?:", page, re.IGNORECASE)
    assert not re.search(r"""(src|href)=["'](?!data:|#)""", page)


@pytest.fixture(scope="module")
def metal_test(tmp_path_factory):
    out = tmp_path_factory.mktemp("metal")
    config = out / "metal.toml"
    config.write_text(METAL_TO_RM)
    done = extensometer(
        "run", "--sim", "--config", str(config), "--out", str(out), "--record", str(out / "t.mcap")
    )
    assert done.returncode == 0, done.stderr
    return out, done.stdout


def test_the_simulated_steel_results_meet_their_targets(metal_test):
    out, _ = metal_test
    steel = ElasticPlastic.steel_s355()
    results = json.loads((out / "summary.json").read_text())["results"]
    assert results["standard"] == "ISO 6892-1" and results["cross_section_mm2"] == 25.0
    assert results["Rp0.2"]["value"] == pytest.approx(steel.proof_stress_mpa, rel=0.005)
    assert results["Rm"]["value"] == pytest.approx(steel.tensile_strength_mpa, rel=0.002)
    assert results["E"]["value"] * 1e3 == pytest.approx(steel.youngs_modulus_mpa, rel=0.01)
    assert results["A"]["not_determined"] == "the test ended before the fracture"
    assert results["ReH"]["value"] is None
    for symbol in ("E", "Rp0.2", "Rm", "Ag"):
        first, last = results[symbol]["samples"]
        assert 0 <= first <= last and results[symbol]["basis"]


def test_run_writes_the_report_beside_the_summary(metal_test):
    out, printed = metal_test
    page = (out / "report.html").read_text()
    assert_self_contained(page)
    table = results_table(page)
    results = json.loads((out / "summary.json").read_text())["results"]
    assert f"{results['Rp0.2']['value']:.5g} MPa" in table
    for anchor in ("stress-strain", "time-series", "gauge", "validity", "truth-error"):
        assert f'id="{anchor}"' in page
    assert re.search(r"^results +ISO 6892-1: E 2\d\d\.\d+ GPa, Rp0.2 3\d\d", printed, re.M)
    summary = json.loads((out / "summary.json").read_text())
    achieved = f"{summary['gauge_length_achieved_mm']:.6g}"
    label = html.escape("gauge length L0 as placed, the strain's reference (mm)")
    assert f"<th>{label}</th><td>{achieved}</td>" in page
    assert f"<th>gauge placement</th><td>{summary['gauge_placement']}</td>" in page
    assert "<th>gauge length requested (mm)</th>" in page
    assert re.search(rf"^report +{re.escape(str(out / 'report.html'))}$", printed, re.M)


def test_replay_writes_its_report_and_summary_into_its_output_directory(metal_test, tmp_path):
    out, _ = metal_test
    replayed_out = tmp_path / "replayed"
    done = extensometer("replay", str(out / "t.mcap"), "--json", "--out", str(replayed_out))
    assert done.returncode == 0, done.stderr
    replayed = json.loads(done.stdout)
    assert json.loads((replayed_out / "summary.json").read_text()) == replayed
    ran = json.loads((out / "summary.json").read_text())
    assert replayed["results"] == ran["results"]
    assert replayed["report"] == str(replayed_out / "report.html")
    page = (replayed_out / "report.html").read_text()
    assert_self_contained(page)
    assert results_table(page) == results_table((out / "report.html").read_text())
    assert sorted(p.name for p in out.iterdir()) == [
        "metal.toml",
        "report.html",
        "strain.csv",
        "summary.json",
        "t.mcap",
    ]


def test_a_replay_of_a_test_that_broke_determines_what_needs_the_fracture(tmp_path):
    config = tmp_path / "metal.toml"
    config.write_text(METAL_TO_RM.replace("until_strain = 0.17", "until_break = true"))
    done = extensometer(
        "run",
        "--sim",
        "--config",
        str(config),
        "--out",
        str(tmp_path / "ran"),
        "--record",
        str(tmp_path / "t.mcap"),
    )
    assert done.returncode == 0, done.stderr
    ran = json.loads((tmp_path / "ran" / "summary.json").read_text())
    assert ran["exit_status"] == "break"
    assert ran["results"]["A"]["value"] is not None
    done = extensometer("replay", str(tmp_path / "t.mcap"), "--json")
    assert done.returncode == 0, done.stderr
    replayed = json.loads(done.stdout)
    assert replayed["exit_status"] == "completed"
    assert replayed["recorded_exit_status"] == "break"
    assert replayed["results"] == ran["results"]


def test_a_report_that_cannot_be_written_is_said_in_one_line(metal_test, tmp_path):
    out, _ = metal_test
    (tmp_path / "report.html").mkdir()
    done = extensometer("replay", str(out / "t.mcap"), "--json", "--out", str(tmp_path))
    assert done.returncode == 1
    assert (
        done.stderr == f"extensometer: {tmp_path / 'report.html'}: cannot write (Is a directory)\n"
    )
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["report"].endswith("cannot write (Is a directory)")


def test_a_replay_output_directory_that_cannot_be_made_refuses_the_replay(metal_test, tmp_path):
    out, _ = metal_test
    (tmp_path / "file").write_text("")
    done = extensometer("replay", str(out / "t.mcap"), "--out", str(tmp_path / "file" / "out"))
    assert done.returncode == 2
    assert (
        done.stderr
        == f"extensometer: error: {tmp_path / 'file' / 'out'}: cannot create (Not a directory)\n"
    )


def test_the_configured_cross_section_is_used_and_early_ends_are_not_determined(tmp_path):
    config = tmp_path / "rubber.toml"
    config.write_text(
        "[sim]\nsensor_width_px = 320\nsensor_height_px = 640\n"
        "[specimen]\nwidth_mm = 3.0\nthickness_mm = 2.0\n"
    )
    done = extensometer(
        "run", "--sim", "--config", str(config), "--until-strain", "0.02", "--out", str(tmp_path)
    )
    assert done.returncode == 0, done.stderr
    summary = json.loads((tmp_path / "summary.json").read_text())
    results = summary["results"]
    assert summary["cross_section_source"] == "[specimen]"
    assert results["standard"] == "ISO 37" and results["cross_section_mm2"] == 6.0
    assert results["S100"]["value"] is None
    assert results["S100"]["not_determined"].startswith("the test ended at 2")
    assert results["TS"]["not_determined"] == "the test ended before the break"
    page = (tmp_path / "report.html").read_text()
    assert_self_contained(page)
    assert "ISO 37; original cross-section S0 6 mm²" in page


def test_a_half_given_cross_section_is_refused_in_one_line(tmp_path):
    config = tmp_path / "bad.toml"
    config.write_text("[specimen]\nwidth_mm = 3.0\n")
    done = extensometer("run", "--sim", "--config", str(config), timeout=120)
    assert done.returncode == 2
    assert done.stderr == (
        f"extensometer: error: {config}: [specimen]: thickness_mm: missing "
        "(width_mm and thickness_mm go together)\n"
    )
