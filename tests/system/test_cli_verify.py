"""`extensometer verify` as a lab runs it: a simulated calibrator with a known error, a readings
file, and bad input refused in one line."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))

QUIET_CAMERA = """\
[sim]
material = "metal"
sensor_width_px = 256
sensor_height_px = 768
read_noise_grey = 0.0
electrons_per_grey = 0.0

[gauge]
length_mm = 20.0
"""


def verify(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run(
        [EXTENSOMETER, "verify", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


@pytest.fixture(scope="module")
def config_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("config") / "quiet.toml"
    path.write_text(QUIET_CAMERA)
    return path


def test_a_calibrator_reading_0_4_percent_long_meets_class_0_5(tmp_path, config_file):
    done = verify(
        "--sim", "--config", str(config_file), "--calibrator-error-percent", "0.4",
        "--out", str(tmp_path),
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "achieved_class              0.5" in done.stdout
    document = json.loads((tmp_path / "verification.json").read_text())
    assert document["met"] is True and document["achieved_class"] == "0.5"
    assert document["criteria"]["bias"]["best_class"] == "0.5"
    assert document["software_version"]
    assert document["calibration_checksum"] is None
    assert document["calibrator_error_percent"] == 0.4
    assert [s["direction"] for s in document["series"]] == ["increasing", "decreasing"]
    assert all(s["points"] >= 10 for s in document["series"])
    for point in document["points"]:
        true_um = point["calibrator_um"] / 1.004
        assert point["bias_um"] == pytest.approx(true_um - point["calibrator_um"], abs=0.3)
        if point["calibrator_um"] >= 500:
            assert point["relative_bias_percent"] == pytest.approx(-0.4, abs=0.05)
    page = (tmp_path / "report.html").read_text()
    assert page.count("<svg") == 2 and "class 0.5" in page


def test_a_calibrator_reading_0_7_percent_long_fails_class_0_5(tmp_path, config_file):
    done = verify(
        "--sim", "--config", str(config_file), "--calibrator-error-percent", "0.7",
        "--out", str(tmp_path),
    )  # fmt: skip
    assert done.returncode == 1, done.stderr
    assert "finding: series" in done.stdout and "beyond class 0.5" in done.stdout
    document = json.loads((tmp_path / "verification.json").read_text())
    assert document["met"] is False and document["achieved_class"] == "1"
    assert document["findings"]


def test_readings_file_against_two_classes(tmp_path):
    lines = ["series,calibrator_um,reading_um", "rest,0,0.05", "rest,0,-0.05"]
    steps = [20, 50, *range(100, 1001, 100)]
    for series, order in (("1", steps), ("2", steps[::-1])):
        lines += [f"{series},{v},{v * 0.996:.4f}" for v in order]
    readings = tmp_path / "readings.csv"
    readings.write_text("\n".join(lines) + "\n")
    passed = verify("--readings", str(readings), "--out", str(tmp_path / "a"))
    assert passed.returncode == 0, passed.stderr
    document = json.loads((tmp_path / "a" / "verification.json").read_text())
    assert document["readings_file"] == str(readings)
    assert not document["criteria"]["gauge_length"]["assessed"]
    strict = verify("--readings", str(readings), "--class", "0.2", "--out", str(tmp_path / "b"))
    assert strict.returncode == 1
    assert "beyond class 0.2" in strict.stdout


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("--out", "X"), "one of the arguments --sim --readings is required"),
        (("--sim", "--readings", "r.csv", "--out", "X"), "not allowed with argument"),
        (("--readings", "missing.csv", "--out", "X"), "missing.csv: no such readings file"),
        (("--sim", "--class", "0.3", "--out", "X"), "--class: invalid choice: '0.3'"),
        (("--sim", "--range-um", "-5", "--out", "X"), "--range-um"),
        (("--sim", "--lower-um", "0", "--out", "X"), "--lower-um"),
        (("--sim", "--series", "0", "--out", "X"), "--series"),
        (("--readings", "r.csv", "--bench", "harsh", "--out", "X"), "--bench applies to --sim"),
        (("--sim", "--display-step-um", "1", "--out", "X"), "applies to --readings only"),
    ],
)
def test_bad_input_is_refused_in_one_line(tmp_path, args, message):
    done = subprocess.run(
        [EXTENSOMETER, "verify", *args],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        cwd=tmp_path,
    )
    assert done.returncode == 2
    assert done.stderr.startswith("extensometer: error: ") and message in done.stderr
    assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr


def test_a_bad_readings_line_is_named(tmp_path):
    readings = tmp_path / "r.csv"
    readings.write_text("series,calibrator_um,reading_um\n1,100,1O0.2\n")
    done = verify("--readings", str(readings), "--out", str(tmp_path / "out"))
    assert done.returncode == 2
    assert f"{readings}: line 2, column 3 (reading_um): '1O0.2' is not a number" in done.stderr
