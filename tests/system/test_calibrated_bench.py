"""The typical simulated bench (entocentric lens with barrel distortion, tilted camera) measured
by nominal scale and in the object plane of a calibration made by `extensometer calibrate` from
simulated ChArUco views of the same lens. The specimen stays in its plane here (no thinning, no
slack), so what remains is what a calibration can correct."""

import csv
import json

import numpy as np
import pytest

from appliance.bench.optics_calibration import target_views
from appliance.config import load_config
from appliance.optics.calibration_target import CalibrationTarget
from appliance.plan.optics import configured_optics
from appliance.sim.world import PRESETS, SimWorld
from tests.system.test_calibrated_run import extensometer

BENCH = """[run]
until_strain = 0.5
[sim]
bench = "typical"
thinning_out_of_plane = false
slack_out_of_plane_mm = 0.0
sensor_width_px = 512
sensor_height_px = 1024
"""
TARGET = CalibrationTarget("charuco", 7, 10, 8.0, 5.6)


def _views(config_path, folder) -> list:
    """Images of the target through the world's lens, as a lab would take them: the first in
    the specimen's plane, the others tilted over the field."""
    config = load_config(config_path)
    optics = configured_optics(config, PRESETS[config.sim.material].optics)
    world = SimWorld.from_config(config, optics)
    return target_views(world.lens_camera, world.specimen_plane, TARGET, folder, seed=5, count=12)


def _errors(folder):
    with (folder / "strain.csv").open() as rows:
        table = list(csv.DictReader(rows))
    strain = np.array([float(r["engineering_strain"]) for r in table])
    truth = np.array([float(r["truth_strain"]) for r in table])
    elongation = np.array([float(r["elongation_mm"]) for r in table])
    true_elongation = np.array([float(r["truth_elongation_mm"]) for r in table])
    gauge_error = elongation[-1] / strain[-1] - true_elongation[-1] / truth[-1]
    return (strain[-1] - truth[-1]) / truth[-1], gauge_error


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench")
    (root / "bench.toml").write_text(BENCH)
    views = _views(root / "bench.toml", root)
    made = extensometer(
        "calibrate",
        *views,
        "--target",
        "charuco",
        "--squares",
        "7x10",
        "--square-mm",
        "8",
        "--marker-mm",
        "5.6",
        "--out",
        root / "lens.cal.json",
    )
    assert made.returncode == 0, made.stderr
    (root / "calibrated.toml").write_text(BENCH + '[optics]\ncalibration = "lens.cal.json"\n')
    summaries = {}
    for name in ("bench", "calibrated"):
        done = extensometer(
            "run", "--sim", "--config", root / f"{name}.toml", "--out", root / name, "--json"
        )
        assert done.returncode == 0, done.stderr
        summaries[name] = json.loads(done.stdout)
    return root, summaries


def test_the_calibrated_bench_measures_the_gauge_length_and_strain_in_the_object_plane(bench):
    root, summaries = bench
    nominal, calibrated = summaries["bench"], summaries["calibrated"]
    assert nominal["measured_in"] == "nominal scale"
    assert calibrated["measured_in"] == "object plane"
    assert calibrated["out_of_plane_stand_off_from"] == "calibration"
    assert calibrated["out_of_plane_stand_off_mm"] == pytest.approx(400.0, rel=0.01)
    nominal_strain, nominal_gauge = _errors(root / "bench")
    strain_error, gauge_error = _errors(root / "calibrated")
    assert abs(gauge_error) < 0.005 < abs(nominal_gauge)
    assert abs(strain_error) < 0.001 < abs(nominal_strain)
    assert calibrated["max_abs_strain_error"] < nominal["max_abs_strain_error"]
