"""The optics benchmark, run reduced (one calibration per lens, short tests, a half-size
sensor, the ideal bench verified): it calibrates the simulated lens from target views, measures
the rubber and metal tests by the nominal scale and in the object plane, verifies, and writes
its report and figures."""

import json
import subprocess
import sys

import pytest

from appliance.bench.optics import Plan, run_optics_benchmark
from appliance.errors import InputError

REDUCED = Plan(
    calibration_seeds=(1,),
    rubber_until_strain=0.3,
    metal_until_strain=0.003,
    verify_benches=("ideal",),
    sim={"sensor_width_px": 512, "sensor_height_px": 1024},
)


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    out = tmp_path_factory.mktemp("results")
    assert run_optics_benchmark(out, plan=REDUCED) == 0
    document = json.loads((out / "optics.json").read_text())
    return out, document["figures"]


def test_the_report_and_its_figures_are_written_and_indexed(results):
    out, figures = results
    report = (out / "optics.md").read_text()
    for section in ("## 1. Calibration", "## 2. Rubber", "## 3. Metal", "## 4. ISO 9513"):
        assert section in report
    assert "failed" not in report
    assert "optics.md" in (out / "README.md").read_text()
    assert (out / "optics" / "figures.json").exists()
    assert figures["mode"] == "quick"


def test_the_calibration_from_target_views_recovers_the_lens(results):
    _, figures = results
    trial = figures["calibration"]["trials"][0]
    assert trial["rms_reprojection_px"] < 0.1
    assert abs(trial["scale_error_percent"]) < 0.05
    assert trial["true_corner_distortion_px"] > 1.0
    assert trial["corner_distortion_error_px"] < 0.1 * trial["true_corner_distortion_px"]
    rows = figures["calibration"]["figures"]
    assert rows["rms_reprojection_px"]["verdict"] in ("met", "missed")


def test_the_calibration_brings_the_rubber_test_in_its_plane_to_the_object_plane(results):
    _, figures = results
    ideal, nominal, fitted, in_plane = figures["rubber"]["cases"]
    assert nominal["measured_in"] == "nominal scale"
    assert fitted["measured_in"] == in_plane["measured_in"] == "object plane"
    assert in_plane["max_rel_strain_error"] < nominal["max_rel_strain_error"]
    assert ideal["iso9513_class"] is not None
    assert len(figures["rubber"]["verdicts"]) == 5


def test_the_metal_cases_and_the_out_of_plane_share_are_measured(results):
    _, figures = results
    metal = figures["metal"]
    assert [c["case"] for c in metal["cases"]] == [
        "telecentric lens",
        "entocentric lens, nominal scale",
        "entocentric lens, calibrated",
        "entocentric lens, calibrated, specimen in its plane",
        "telecentric lens, calibrated",
    ]
    assert all("error" not in c for c in metal["cases"])
    assert metal["cases"][4]["measured_in"] == "object plane"
    telecentric = metal["telecentric_calibration"]
    assert telecentric["rms_reprojection_px"] < 0.1
    assert abs(telecentric["scale_error_percent"]) < 0.05
    assert metal["out_of_plane_share"] is not None
    assert metal["out_of_plane_share"] <= 1.0


def test_verify_grades_the_bench(results):
    _, figures = results
    (row,) = figures["verify"]
    assert row["bench"] == "ideal"
    assert row["achieved_class"] in ("0.2", "0.5", "1", "2", None)
    assert "error" not in row


def test_one_section_is_measured_again_into_the_report_keeping_the_others(results):
    out, figures = results
    assert run_optics_benchmark(out, plan=REDUCED, only="verify") == 0
    again = json.loads((out / "optics.json").read_text())["figures"]
    assert again["rubber"] == figures["rubber"] and again["metal"] == figures["metal"]
    (remeasured,) = again["remeasured"]
    assert remeasured["section"] == "verify"
    assert "measured again" in (out / "optics.md").read_text()


def test_the_calibration_section_is_measured_again_keeping_the_tests(results):
    out, _ = results
    before = json.loads((out / "optics.json").read_text())["figures"]
    assert run_optics_benchmark(out, plan=REDUCED, only="calibration") == 0
    again = json.loads((out / "optics.json").read_text())["figures"]
    assert again["metal"] == before["metal"] and again["verify"] == before["verify"]
    assert again["remeasured"][-1]["section"] == "calibration"
    assert again["calibration"]["figures"]["rms_reprojection_px"]["worst"] < 0.05


def test_a_section_alone_needs_an_earlier_report(tmp_path):
    with pytest.raises(InputError, match="optics.json: no earlier optics report"):
        run_optics_benchmark(tmp_path, plan=REDUCED, only="metal")


def test_the_command_needs_an_output_directory():
    done = subprocess.run(
        [sys.executable, "-m", "appliance.cli", "bench", "optics"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 2
    assert "--out" in done.stderr
