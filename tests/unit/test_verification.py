"""ISO 9513 verification: the procedure's steps, the grading of bias, resolution and gauge
length, the lab's readings file and the report."""

from __future__ import annotations

import json
import math

import pytest

from appliance.errors import InputError
from appliance.run.iso9513 import class_named
from appliance.run.verification import (
    CalibrationPoint,
    VerificationData,
    calibration_steps,
    series_directions,
    series_elongations,
    verify,
)
from appliance.run.verification_readings import read_readings
from appliance.run.verification_report import write_verification

STEPS = calibration_steps(1000.0, 20.0)


def two_series(reading, *, gauge_length_mm=None):
    """Points of two series over STEPS, each reading `reading(l_t)`."""
    points = []
    for index, direction in enumerate(series_directions(2)):
        for value in series_elongations(STEPS, direction):
            points.append(CalibrationPoint(str(index + 1), value, reading(value), gauge_length_mm))
    return tuple(points)


def test_steps_spread_over_the_range_with_the_lower_range():
    assert calibration_steps(1000.0) == pytest.approx([100.0 * k for k in range(1, 11)])
    assert STEPS == pytest.approx([20.0, 50.0] + [100.0 * k for k in range(1, 11)])
    assert calibration_steps(500.0, 1.0)[:6] == pytest.approx([1.0, 2.0, 5.0, 10.0, 20.0, 50.0])
    assert series_directions(3) == ("increasing", "decreasing", "increasing")
    assert series_elongations([1.0, 3.0, 2.0], "decreasing") == (3.0, 2.0, 1.0)
    with pytest.raises(ValueError):
        calibration_steps(0.0)


@pytest.mark.parametrize(
    ("scale", "requested", "met", "achieved"),
    [
        (1.0, "0.2", True, "0.2"),
        (1 - 0.004, "0.5", True, "0.5"),
        (1 - 0.004, "0.2", False, "0.5"),
        (1 - 0.007, "0.5", False, "1"),
    ],
)
def test_a_scale_error_is_a_relative_bias_at_every_step(scale, requested, met, achieved):
    data = VerificationData(two_series(lambda v: scale * v), rest_readings_um=(0.0, 0.1))
    result = verify(data, class_named(requested))
    assert result.met is met
    assert result.achieved == achieved
    for point in data.points:
        assert point.relative_bias_percent == pytest.approx(100 * (scale - 1))
    if not met:
        assert result.findings and all("bias" in line for line in result.findings)
        assert any(f"beyond class {requested}" in line for line in result.findings)


def test_below_300_um_the_absolute_limit_decides():
    data = VerificationData(two_series(lambda v: v + 1.4), rest_readings_um=(0.0,))
    result = verify(data, class_named("0.5"))
    assert result.criteria["bias"].best_class == "0.5"
    assert result.worst_bias.calibrator_um <= 300.0
    assert result.worst_bias.bias_um == pytest.approx(1.4)


def test_resolution_is_half_the_range_at_rest_or_the_display_step():
    points = two_series(lambda v: v)
    rest = (0.0, 0.3, -0.3, 0.1)
    result = verify(VerificationData(points, rest), class_named("0.5"))
    assert result.resolution_um == pytest.approx(0.3)
    assert result.rest_std_um == pytest.approx(0.25)
    assert result.criteria["resolution"].best_class == "0.5"
    coarse = verify(VerificationData(points, rest, display_step_um=0.8), class_named("0.5"))
    assert coarse.resolution_um == 0.8
    assert coarse.criteria["resolution"].best_class == "1"
    assert not coarse.met and "resolution 0.8 um" in coarse.findings[0]
    lost = verify(VerificationData(points, (0.0, math.nan)), class_named("2"))
    assert lost.achieved is None and "reading at rest was not measured" in lost.findings[0]
    unknown = verify(VerificationData(points), class_named("0.2"))
    assert not unknown.criteria["resolution"].assessed and unknown.met


def test_gauge_length_error_against_the_nominal():
    points = two_series(lambda v: v, gauge_length_mm=50.3)
    result = verify(
        VerificationData(points, (0.0,), nominal_gauge_length_mm=50.0), class_named("0.5")
    )
    assert result.gauge_length_error_percent == pytest.approx(0.6)
    assert result.criteria["gauge_length"].best_class == "1"
    assert not result.met and "gauge length error +0.600 %" in result.findings[0]
    no_nominal = verify(VerificationData(points, (0.0,)), class_named("0.5"))
    assert not no_nominal.criteria["gauge_length"].assessed


def test_a_run_short_of_the_procedure_reaches_no_class():
    one = tuple(p for p in two_series(lambda v: v) if p.series == "1")
    result = verify(VerificationData(one, (0.0,)), class_named("2"))
    assert result.achieved is None and not result.met
    assert "1 series of measurements" in result.findings[0]
    few = tuple(p for p in two_series(lambda v: v) if p.calibrator_um <= 500.0)
    assert (
        "series 1: 7 calibration points"
        in verify(VerificationData(few, (0.0,)), class_named("2")).findings[0]
    )


def test_a_missing_reading_fails_every_class():
    points = list(two_series(lambda v: v))
    points[3] = CalibrationPoint("1", points[3].calibrator_um, math.nan)
    result = verify(VerificationData(tuple(points), (0.0,)), class_named("2"))
    assert result.achieved is None
    assert "no reading" in result.findings[0]


READINGS = """\
# a lab's readings
series,calibrator_um,reading_um,gauge_length_mm
rest,0,0.1,
rest,0,-0.1,
""" + "".join(
    f"{s},{v:g},{v * 0.996:.4f},{50.02 if s == '1' else ''}\n"
    for s, direction in (("1", "increasing"), ("2", "decreasing"))
    for v in series_elongations(STEPS, direction)
)


def test_readings_file_and_report(tmp_path):
    path = tmp_path / "readings.csv"
    path.write_text(READINGS)
    points, rest = read_readings(path)
    assert len(points) == 24 and rest == (0.1, -0.1)
    assert points[0].gauge_length_mm == 50.02 and points[-1].gauge_length_mm is None
    data = VerificationData(points, rest, nominal_gauge_length_mm=50.0, source="lab")
    assert data.direction_of("2") == "decreasing"
    result = verify(data, class_named("0.5"))
    assert result.met and result.achieved == "0.5"
    json_path, html_path = write_verification(
        result, tmp_path / "out", {"software_version": "9.9", "calibration_checksum": None}
    )
    document = json.loads(json_path.read_text())
    assert document["software_version"] == "9.9"
    assert document["achieved_class"] == "0.5" and document["met"] is True
    assert document["resolution_um"] == pytest.approx(0.1)
    assert document["gauge_length_error_percent"] == pytest.approx(0.04)
    assert [p["relative_bias_percent"] for p in document["points"]] == pytest.approx(
        [-0.4] * 24, abs=1e-3
    )
    page = html_path.read_text()
    assert page.count("<svg") == 2
    assert 'id="bias-absolute"' in page and 'id="bias-relative"' in page
    assert "series 2 (decreasing)" in page and "class 0.5" in page


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "no header line"),
        ("series,calibrator_um\n1,2\n", "line 1: no column 'reading_um'"),
        ("series,calibrator_um,reading_um,force\n", "line 1, column 4: unknown column 'force'"),
        ("series,calibrator_um,reading_um\n1,10,abc\n", "line 2, column 3 (reading_um): 'abc'"),
        ("series,calibrator_um,reading_um\n1,nan,1\n", "line 2, column 2 (calibrator_um)"),
        ("series,calibrator_um,reading_um\n1,10\n", "line 2: 2 values, the header names 3"),
        ("series,reading_um,calibrator_um\n,10,1\n", "line 2, column 1 (series): empty"),
        (
            "series,calibrator_um,reading_um,gauge_length_mm\n1,1,1,-5\n",
            "line 2, column 4 (gauge_length_mm): -5 must be > 0",
        ),
        ("series,calibrator_um,reading_um\nrest,0,0.1\n", "no calibration points"),
    ],
)
def test_bad_readings_are_refused_in_one_line(tmp_path, text, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(InputError) as caught:
        read_readings(path)
    assert message in str(caught.value)
    assert str(path) in str(caught.value) and "\n" not in str(caught.value)
