"""`extensometer run --sim` as a user runs it: whole simulated tests in a real process."""

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))

SUMMARY_KEYS = (
    "frames_processed",
    "frames_dropped",
    "latency_ms_p50",
    "latency_ms_p99",
    "final_strain",
    "truth_final_strain",
    "max_abs_strain_error",
    "max_rel_strain_error",
    "max_elongation_error_um",
    "lost_points",
    "reference_updates",
    "iso9513_class",
)


def run(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run(
        [EXTENSOMETER, "run", *args], capture_output=True, text=True, timeout=timeout, check=False
    )


def test_short_rubber_test_meets_the_strain_bounds(tmp_path):
    """One realisation of the camera noise, held to ISO 9513 class 1 sample by sample (1 % of
    the reading or 3 um); class 0.5 over seeds is the accuracy benchmark's
    (`extensometer bench sim`), where a single draw at the first samples, within 2 um of the
    start, does not decide it."""
    done = run(
        "--sim", "--material", "rubber", "--until-strain", "0.5", "--json", "--out", str(tmp_path)
    )
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    for key in SUMMARY_KEYS:
        assert key in summary
    assert summary["exit_status"] == "completed"
    assert summary["final_strain"] >= 0.5
    assert summary["frames_dropped"] == 0 and summary["lost_points"] == 0
    assert summary["reference_updates"] > 0
    # ISO 9513 class 1: |error| <= max(1 % of the reading, 3 um / L0)
    assert summary["max_rel_strain_error"] <= 0.01
    assert summary["iso9513_class"] in ("0.2", "0.5", "1")
    assert summary["run_states"] == ["armed", "running", "stopping", "idle"]
    assert json.loads((tmp_path / "summary.json").read_text()) == summary
    rows = list(csv.DictReader((tmp_path / "strain.csv").open()))
    assert len(rows) == summary["frames_processed"]
    assert sum(int(r["points_lost"]) for r in rows) == summary["lost_points"]
    assert sum(r["data_valid"] == "0" for r in rows) == summary["invalid_samples"]
    assert sum(int(r["reference_updates"]) for r in rows) == summary["reference_updates"]
    errors = [abs(float(r["strain_error"])) for r in rows]
    bounds = [max(0.01 * abs(float(r["engineering_strain"])), 3e-3 / 25.0) for r in rows]
    assert all(e <= b for e, b in zip(errors, bounds, strict=True))


def test_short_metal_test_meets_the_elongation_bound(tmp_path):
    done = run("--sim", "--material", "metal", "--until-strain", "0.004", "--json")
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["max_elongation_error_um_below_300um"] <= 1.5
    assert summary["lost_points"] == 0
    assert summary["speed_mm_min"] == 10.0


def test_the_simulated_world_is_deterministic_for_a_seed(tmp_path):
    outputs = []
    for name in ("a", "b"):
        done = run(
            "--sim",
            "--until-strain",
            "0.05",
            "--seed",
            "7",
            "--out",
            str(tmp_path / name),
            "--json",
        )
        assert done.returncode == 0, done.stderr
        rows = list(csv.DictReader((tmp_path / name / "strain.csv").open()))
        outputs.append([(r["engineering_strain"], r["truth_strain"]) for r in rows])
    assert outputs[0] == outputs[1]


@pytest.mark.parametrize(
    ("args", "culprit"),
    [
        (["--sim", "--speed-mm-min", "-5"], "--speed-mm-min"),
        (["--sim", "--speed-mm-min", "20000"], "--speed-mm-min: must be <= 10000"),
        (["--sim", "--modbus-tcp", "127.0.0.1"], "--modbus-tcp: must be HOST:PORT"),
        (["--sim", "--material", "wood"], "--material"),
        (["--sim", "--until-strain", "1", "--until-break"], "--until-break"),
        (["--sim", "--exposure-us", "fast"], "--exposure-us"),
        (["--sim", "--config", "absent.toml"], "absent.toml"),
        (["--until-strain", "0.1"], "--sim"),
        (["--sim", "--out", "/dev/null/run"], "--out: /dev/null is not a directory"),
    ],
)
def test_bad_values_give_one_line_naming_the_culprit(args, culprit):
    done = run(*args, timeout=120)
    assert done.returncode == 2
    assert culprit in done.stderr and done.stderr.count("\n") == 1
    assert "Traceback" not in done.stderr


def test_bad_configuration_key_is_named(tmp_path):
    config = tmp_path / "run.toml"
    config.write_text("[tracking]\nsubset_px = 40\n")
    done = run("--sim", "--config", str(config), timeout=120)
    assert done.returncode == 2
    assert f"{config}: [tracking] subset_px: must be odd" in done.stderr


@pytest.mark.parametrize("source", ["period", "encoder"])
def test_triggers_from_the_simulated_microcontroller_space_the_frames_as_planned(tmp_path, source):
    config = tmp_path / "trigger.toml"
    config.write_text(f'[trigger]\nsource = "{source}"\nencoder_counts_per_mm = 2000\n')
    done = run(
        "--sim",
        "--material",
        "metal",
        "--until-strain",
        "0.004",
        "--json",
        "--config",
        str(config),
        "--out",
        str(tmp_path),
    )
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["trigger_source"] == source and summary["frames_dropped"] == 0
    assert summary["max_elongation_error_um_below_300um"] <= 1.5
    rows = list(csv.DictReader((tmp_path / "strain.csv").open()))
    times = [float(r["time_s"]) for r in rows]
    crosshead = [float(r["crosshead_mm"]) for r in rows]
    running = [i for i in range(1, len(rows)) if crosshead[i] > crosshead[i - 1]]
    steady = running[len(running) // 4 :]
    if source == "period":
        period_s = summary["trigger_period_ticks"] / 2e6
        assert summary["trigger_encoder_divisor"] == 0
        assert all(abs(times[i] - times[i - 1] - period_s) < 1e-9 for i in range(1, len(rows)))
    else:
        step_mm = summary["trigger_encoder_divisor"] / 2000
        assert summary["trigger_period_ticks"] == 0 and step_mm > 0
        assert all(abs(crosshead[i] - crosshead[i - 1] - step_mm) < 1e-6 for i in steady)
        interval = times[steady[-1]] - times[steady[-1] - 1]
        assert interval == pytest.approx(summary["frame_period_s"], rel=1e-6)


def test_the_recording_may_go_into_the_output_directory_the_run_makes(tmp_path):
    config = tmp_path / "small.toml"
    config.write_text("[sim]\nsensor_width_px = 320\nsensor_height_px = 640\n")
    out = tmp_path / "new" / "run"
    done = run(
        "--sim", "--config", str(config), "--until-strain", "0.02", "--out", str(out),
        "--record", str(out / "test.mcap"), "--json", timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["recording_samples"] > 0
    assert (out / "test.mcap").stat().st_size > 0 and (out / "strain.csv").is_file()
    info = subprocess.run(
        [EXTENSOMETER, "info", str(out / "test.mcap"), "--json"],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    assert json.loads(info.stdout)["test_id"].startswith("test-20")
