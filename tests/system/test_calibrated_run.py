"""`[optics] calibration` in whole simulated tests: run, record, replay, info, refusals."""

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest

from appliance.optics.calibration_file import CameraCalibration, save_calibration
from appliance.optics.camera_model import CameraModel, LensDistortion, PlanePose
from appliance.sim.world import PRESETS

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))
WIDTH, HEIGHT = 512, 1024
SCALE = PRESETS["rubber"].optics.scale_mm_per_px
STAND_OFF = PRESETS["rubber"].optics.object_distance_mm
BASE = f"""[run]
until_strain = 0.3
[sim]
sensor_width_px = {WIDTH}
sensor_height_px = {HEIGHT}
"""


def extensometer(*args, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run(
        [EXTENSOMETER, *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


def ideal_calibration(path: Path, size=(WIDTH, HEIGHT)) -> CameraCalibration:
    """The simulated camera as a distortion-free pinhole facing the specimen at the preset's
    stand-off, with the preset's scale at the plane."""
    camera = CameraModel.ideal(*size, STAND_OFF / SCALE)
    calibration = CameraCalibration(camera, PlanePose.facing(STAND_OFF), SCALE)
    save_calibration(calibration, path)
    return calibration


def configuration(folder: Path, calibration: str | None) -> Path:
    optics = f'[optics]\ncalibration = "{calibration}"\n' if calibration is not None else ""
    path = folder / "run.toml"
    path.write_text(BASE + optics)
    return path


def strains(folder: Path) -> list[float]:
    with (folder / "strain.csv").open() as rows:
        return [float(row["engineering_strain"]) for row in csv.DictReader(rows)]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The same simulated test by nominal scale and through an ideal calibration, recorded."""
    root = tmp_path_factory.mktemp("calibrated")
    calibration = ideal_calibration(root / "ideal.cal.json")
    done = {}
    for name, file in (("nominal", None), ("calibrated", "ideal.cal.json")):
        folder = root / name
        folder.mkdir()
        config = configuration(root, file)
        run = extensometer(
            "run", "--sim", "--config", config, "--out", folder, "--record", folder / "t.mcap"
        )
        assert run.returncode == 0, run.stderr
        done[name] = (folder, run.stdout)
    return root, calibration, done


def test_an_ideal_calibration_measures_as_the_nominal_scale(runs):
    _, calibration, done = runs
    nominal, calibrated = (json.loads((done[k][0] / "summary.json").read_text()) for k in done)
    assert nominal["frames_processed"] == calibrated["frames_processed"]
    assert strains(done["calibrated"][0]) == pytest.approx(strains(done["nominal"][0]), abs=1e-12)
    assert calibrated["final_strain"] == pytest.approx(nominal["final_strain"], abs=1e-12)
    assert calibrated["gauge_length_mm"] == nominal["gauge_length_mm"]
    assert calibrated["measured_in"] == "object plane"
    assert calibrated["calibration_checksum"] == calibration.checksum
    assert calibrated["calibration_file"].endswith("ideal.cal.json")
    assert nominal["measured_in"] == "nominal scale"
    assert nominal["calibration_file"] is None and nominal["calibration_checksum"] is None
    for summary in (nominal, calibrated):
        assert summary["out_of_plane_false_strain"] == pytest.approx(0.1 / STAND_OFF)
        assert summary["out_of_plane_motion_mm"] == 0.1
    assert nominal["out_of_plane_stand_off_from"] == "[optics] object_distance_mm"
    assert calibrated["out_of_plane_stand_off_from"] == "calibration"
    printed = done["calibrated"][1]
    assert "object plane" in printed and calibration.checksum in printed
    assert "ideal.cal.json" in printed and "out_of_plane_false_strain" in printed


def test_the_recording_carries_the_calibration_and_replay_measures_with_it(runs):
    root, calibration, done = runs
    recording = done["calibrated"][0] / "t.mcap"
    (root / "ideal.cal.json").rename(root / "moved.cal.json")
    try:
        replay = extensometer("replay", recording, "--json")
    finally:
        (root / "moved.cal.json").rename(root / "ideal.cal.json")
    assert replay.returncode == 0, replay.stderr
    summary = json.loads(replay.stdout)
    assert summary["max_abs_diff_to_recorded"] == 0.0 and summary["samples_differing"] == 0
    assert summary["measured_in"] == "object plane"
    assert summary["calibration_checksum"] == calibration.checksum
    info = extensometer("info", recording, "--json")
    assert info.returncode == 0, info.stderr
    facts = json.loads(info.stdout)
    assert facts["calibration_checksum"] == calibration.checksum
    assert facts["measured_in"] == "object plane"
    assert facts["scale_mm_per_px"] == pytest.approx(SCALE)
    shown = extensometer("info", recording).stdout
    assert calibration.checksum in shown and "scale_mm_per_px" in shown


def test_replay_applies_another_calibration_as_post_processing(runs, tmp_path):
    _, _, done = runs
    lens = CameraCalibration(
        CameraModel.ideal(WIDTH, HEIGHT, STAND_OFF / SCALE, distortion=LensDistortion(k1=0.4)),
        PlanePose.facing(STAND_OFF),
        SCALE,
    )
    save_calibration(lens, tmp_path / "lens.cal.json")
    override = tmp_path / "override.toml"
    override.write_text('[optics]\ncalibration = "lens.cal.json"\n')
    replay = extensometer("replay", done["nominal"][0] / "t.mcap", "--config", override, "--json")
    assert replay.returncode == 0, replay.stderr
    summary = json.loads(replay.stdout)
    assert summary["measured_in"] == "object plane"
    assert summary["calibration_checksum"] == lens.checksum
    assert summary["samples_differing"] > 0
    assert summary["max_abs_diff_to_recorded"] > 1e-6
    back = tmp_path / "nominal.toml"
    back.write_text('[optics]\ncalibration = ""\n')
    nominal = extensometer("replay", done["calibrated"][0] / "t.mcap", "--config", back, "--json")
    assert nominal.returncode == 0, nominal.stderr
    measured = json.loads(nominal.stdout)
    assert measured["measured_in"] == "nominal scale" and measured["calibration_checksum"] is None
    assert measured["final_strain"] == pytest.approx(
        json.loads((done["nominal"][0] / "summary.json").read_text())["final_strain"], abs=1e-12
    )


def _altered(path: Path) -> None:
    ideal_calibration(path)
    document = json.loads(path.read_text())
    document["scale_mm_per_px"] *= 1.01
    path.write_text(json.dumps(document))


def _refused(done: subprocess.CompletedProcess, *phrases: str) -> None:
    assert done.returncode == 2, done.stdout + done.stderr
    line = done.stderr.strip()
    assert len(line.splitlines()) == 1 and line.startswith("extensometer: error: ")
    assert "Traceback" not in done.stderr
    for phrase in phrases:
        assert phrase in line


def test_replay_refuses_a_calibration_for_another_size_and_other_optics_keys(runs, tmp_path):
    _, _, done = runs
    recording = done["nominal"][0] / "t.mcap"
    ideal_calibration(tmp_path / "big.cal.json", size=(1024, 2048))
    override = tmp_path / "big.toml"
    override.write_text('[optics]\ncalibration = "big.cal.json"\n')
    _refused(
        extensometer("replay", recording, "--config", override),
        "big.cal.json",
        "1024x2048 px sensor",
        "512x1024 px",
    )
    lens = tmp_path / "lens.toml"
    lens.write_text('[optics]\ncalibration = "big.cal.json"\nfocal_length_mm = 25\n')
    _refused(
        extensometer("replay", recording, "--config", lens),
        "[optics] focal_length_mm",
        "cannot be applied to a replay",
    )


@pytest.mark.parametrize(
    ("make", "phrases"),
    [
        (lambda d: ideal_calibration(d / "c.json", (1024, 2048)), ["1024x2048 px sensor"]),
        (lambda d: None, ["no such calibration file"]),
        (lambda d: (d / "c.json").write_text("{"), ["not a calibration file"]),
        (lambda d: _altered(d / "c.json"), ["checksum mismatch"]),
    ],
    ids=["other-size", "missing", "not-json", "altered"],
)
def test_run_refuses_a_bad_calibration_before_the_test(tmp_path, make, phrases):
    make(tmp_path)
    config = configuration(tmp_path, "c.json")
    out = tmp_path / "out"
    done = extensometer(
        "run", "--sim", "--config", config, "--out", out, "--record", tmp_path / "r.mcap"
    )
    _refused(done, "[optics] calibration", str(tmp_path / "c.json"), *phrases)
    assert not (tmp_path / "r.mcap").exists() and not (out / "summary.json").exists()


def test_camera_check_refuses_a_calibration_for_another_region(tmp_path):
    ideal_calibration(tmp_path / "c.json")
    config = tmp_path / "check.toml"
    config.write_text(
        BASE
        + '[optics]\ncalibration = "c.json"\n'
        + "[camera]\nregion_x_px = 0\nregion_y_px = 0\nregion_width_px = 256\n"
        + "region_height_px = 512\n"
    )
    _refused(extensometer("camera-check", "--config", config, "--frames", "3"), "512x1024")
    fits = configuration(tmp_path, "c.json")
    checked = extensometer("camera-check", "--config", fits, "--frames", "3", "--json")
    report = json.loads(checked.stdout)
    assert report["calibration"]["max_distortion_px"] == pytest.approx(0.0, abs=1e-9)
    assert report["calibration"]["checksum"].startswith("sha256:")
