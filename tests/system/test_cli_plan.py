"""The `extensometer plan` command as a user runs it: a real process."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))

# f 80 mm at 300 mm, 5.2 um pixels, 10 ms, 500 mm/min: 5.83 px, a cell of Table 1 of Zhang et
# al. (2016) under inputs reconstructed to be consistent with that table (see test_planner.py).
TABLE1_CELL = [
    "--focal-length-mm",
    "80",
    "--object-distance-mm",
    "300",
    "--pixel-size-um",
    "5.2",
    "--exposure-s",
    "0.01",
    "--speed-mm-min",
    "500",
]


def plan(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [EXTENSOMETER, "plan", *args], capture_output=True, text=True, timeout=120, check=False
    )


def test_json_output_has_the_documented_keys_and_table_1():
    done = plan(*TABLE1_CELL, "--json")
    assert done.returncode == 0, done.stderr
    document = json.loads(done.stdout)
    for key in (
        "image_distance_mm",
        "magnification",
        "blur_um",
        "blur_px",
        "planned_exposure_s",
        "planned_frame_period_s",
        "planned_frame_rate_hz",
        "planned_blur_px",
        "budget_met",
    ):
        assert key in document
    assert document["image_distance_mm"] == pytest.approx(80 * 300 / 220)
    assert document["magnification"] == pytest.approx(80 / 220)
    assert round(document["blur_px"], 2) == 5.83
    assert document["blur_um"] == pytest.approx(document["blur_px"] * 5.2)
    assert document["budget_met"] is True
    assert document["planned_blur_px"] <= 1.0
    assert document["planned_frame_rate_hz"] == pytest.approx(
        1 / document["planned_frame_period_s"]
    )
    # the default 20 px capture range sets the period at this speed
    assert document["planned_frame_period_s"] / document["planned_exposure_s"] == pytest.approx(
        20.0
    )


def test_json_reports_an_unmet_budget():
    done = plan(*TABLE1_CELL, "--min-exposure-us", "5000", "--json")
    assert done.returncode == 0, done.stderr
    document = json.loads(done.stdout)
    assert document["budget_met"] is False
    assert document["planned_exposure_s"] == pytest.approx(5e-3)
    assert round(document["planned_blur_px"], 2) == pytest.approx(5.83 / 2, abs=0.01)


def test_human_output_shows_the_figures():
    done = plan(*TABLE1_CELL)
    assert done.returncode == 0, done.stderr
    out = done.stdout
    assert "image distance    109.0909 mm" in out
    assert "magnification     0.363636" in out
    assert "30.303 um = 5.828 px" in out
    assert "planned exposure  1.7160 ms" in out
    assert "budget 1 px met" in out
    assert "planned period    34.3200 ms" in out


@pytest.mark.parametrize(
    ("option", "value"),
    [
        ("--focal-length-mm", "-80"),
        ("--pixel-size-um", "abc"),
        ("--speed-mm-min", "-1"),
        ("--exposure-s", "0"),
        ("--blur-budget-px", "nan"),
        ("--object-distance-mm", "50"),
        ("--speed-fraction", "1e308"),
        ("--focal-length-mm", "1e-300"),
    ],
)
def test_a_bad_value_is_one_line_naming_the_option(option, value):
    args = list(TABLE1_CELL)
    if option in args:
        args[args.index(option) + 1] = value
    else:
        args += [option, value]
    done = plan(*args)
    assert done.returncode == 2
    assert done.stdout == ""
    lines = done.stderr.splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith("extensometer: error: plan: ")
    assert option in lines[0]
    assert "Traceback" not in done.stderr


def test_plan_and_a_simulated_run_agree_on_exposure_and_frame_rate(tmp_path):
    """Both pace the plan by the same rule (`[camera] min_frame_rate_hz`, 20 Hz by default)."""
    from appliance.measure.tracking import TrackerSettings
    from appliance.sim.world import PRESETS

    optics = PRESETS["rubber"].optics
    run = subprocess.run(
        [EXTENSOMETER, "run", "--sim", "--until-strain", "0.002", "--json"],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert run.returncode == 0, run.stderr
    summary = json.loads(run.stdout)
    done = plan(
        "--focal-length-mm", str(optics.focal_length_mm),
        "--object-distance-mm", str(optics.object_distance_mm),
        "--pixel-size-um", str(optics.pixel_size_um),
        "--exposure-s", "0.01",
        "--speed-mm-min", str(summary["speed_mm_min"]),
        "--capture-range-px", str(TrackerSettings().search_radius_px),
        "--min-exposure-us", "100",
        "--json",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    document = json.loads(done.stdout)
    assert document["planned_frame_rate_hz"] == pytest.approx(summary["frame_rate_hz"])
    assert document["planned_exposure_s"] * 1e6 == pytest.approx(summary["exposure_us"])
    assert document["period_limit"] == "min_frame_rate"
