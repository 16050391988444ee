"""The simulated calibrator measured by the extensometer's own tracking: a calibrator with a
known scale error gives the bias it must, and the verification grades it."""

from __future__ import annotations

import numpy as np
import pytest

from appliance.config import GaugeConfig, SimConfig
from appliance.measure.gauges import Calibration
from appliance.measure.tracking import TrackerSettings
from appliance.optics.calibration_file import CameraCalibration
from appliance.run.calibrator_measurement import Setup, line_offset_px, measure_series
from appliance.run.iso9513 import class_named
from appliance.run.verification import (
    VerificationData,
    calibration_steps,
    series_directions,
    verify,
)
from appliance.sim.bench import bench_errors
from appliance.sim.calibrator import SimCalibrator, calibrator_bench
from appliance.sim.world import ideal_bench

SCALE_MM_PER_PX = 0.0566
SENSOR = (256, 768)
GAUGE_LENGTH_MM = 20.0
STEPS = calibration_steps(1000.0, 20.0)


STAND_OFF_MM = 400.0


def calibrator(scale_error: float, bench=None, **noise) -> SimCalibrator:
    bench = bench or calibrator_bench(
        ideal_bench(),
        scale_mm_per_px=SCALE_MM_PER_PX,
        object_distance_mm=STAND_OFF_MM,
        sensor_size=SENSOR,
    )
    return SimCalibrator(
        gauge_length_mm=GAUGE_LENGTH_MM,
        bench=bench,
        speckle_radius_mm=0.12,
        travel_mm=1.2,
        scale_error=scale_error,
        **({"read_noise": 0.0, "electrons_per_grey": 0.0} | noise),
    )


def measured(
    scale_error: float, calibration: Calibration | None = None, bench=None, **noise
) -> VerificationData:
    sim = calibrator(scale_error, bench, **noise)
    setup = Setup(
        GAUGE_LENGTH_MM,
        (0.5 * (SENSOR[0] - 1), 0.5 * (SENSOR[1] - 1)),
        calibration or Calibration(SCALE_MM_PER_PX),
        GaugeConfig(),
        TrackerSettings(),
    )
    points, rest = [], ()
    for index, direction in enumerate(series_directions(2)):
        series = measure_series(
            sim, setup, str(index + 1), direction, STEPS, rest_frames=10 if index == 0 else 0
        )
        points += series.points
        rest = rest or series.rest_um
    return VerificationData(tuple(points), rest, nominal_gauge_length_mm=GAUGE_LENGTH_MM)


@pytest.fixture(scope="module")
def scale_error_0_4():
    return measured(0.004)


def test_a_calibrator_reading_long_makes_the_extensometer_read_short(scale_error_0_4):
    data = scale_error_0_4
    assert len(data.points) == 2 * len(STEPS)
    for point in data.points:
        expected_um = point.calibrator_um / 1.004 - point.calibrator_um
        assert point.bias_um == pytest.approx(expected_um, abs=0.3)
        if point.calibrator_um >= 500.0:
            assert point.relative_bias_percent == pytest.approx(-0.4, abs=0.05)
    assert data.points[0].gauge_length_mm == pytest.approx(GAUGE_LENGTH_MM, rel=5e-4)


def test_the_injected_error_passes_class_0_5_and_fails_0_2(scale_error_0_4):
    assert verify(scale_error_0_4, class_named("0.5")).met
    strict = verify(scale_error_0_4, class_named("0.2"))
    assert not strict.met and strict.achieved == "0.5"
    assert strict.criteria["bias"].best_class == "0.5"
    assert strict.criteria["gauge_length"].best_class == "0.2"


def test_a_larger_error_fails_class_0_5():
    result = verify(measured(0.007), class_named("0.5"))
    assert not result.met
    assert result.criteria["bias"].best_class == "1"
    assert any("beyond class 0.5" in line for line in result.findings)


def test_a_camera_with_noise_has_a_resolution_and_still_reads_true():
    data = measured(0.0, read_noise=0.5, electrons_per_grey=40.0)
    result = verify(data, class_named("1"))
    assert 0.0 < result.resolution_um < 1.0
    assert max(abs(p.bias_um) for p in data.points) < 1.5
    assert result.met


def test_the_calibrator_moves_the_block_by_its_true_displacement():
    sim = calibrator(0.01)
    assert sim.displacement_um(101.0) == pytest.approx(100.0)
    sim.move_to(0.0)
    still = sim.grab().astype(float)
    sim.move_to(101.0 * 5 * SCALE_MM_PER_PX * 1e3 / 100.0)
    moved = sim.grab().astype(float)
    centre = np.array(
        [0.5 * (SENSOR[0] - 1), 0.5 * (SENSOR[1] - 1) + 0.5 * GAUGE_LENGTH_MM / SCALE_MM_PER_PX]
    )
    axis = np.array([0.0, 1.0])
    before = line_offset_px(still, centre, axis, 15.0)
    after = line_offset_px(moved, centre, axis, 15.0)
    assert after - before == pytest.approx(5.0, abs=0.05)
    with pytest.raises(ValueError, match="travel"):
        sim.move_to(5000.0)


def test_a_distorting_lens_needs_the_object_plane():
    """The typical bench's entocentric lens, its distortion and tilt (its drift, vibration and
    flicker left out): by the nominal scale the extensometer reads short; through a
    calibration of that camera (the true one here, as `extensometer calibrate` would find it)
    it reads true."""
    errors = bench_errors(
        SimConfig(
            bench="typical", vibration_px_rms=0.0, warm_up_drift_percent=0.0, flicker_percent=0.0
        ),
        SENSOR,
        STAND_OFF_MM / SCALE_MM_PER_PX,
    )
    bench = calibrator_bench(
        errors, scale_mm_per_px=SCALE_MM_PER_PX, object_distance_mm=STAND_OFF_MM, sensor_size=SENSOR
    )
    nominal = verify(measured(0.0, bench=bench), class_named("0.5"))
    assert not nominal.met and nominal.criteria["bias"].best_class == "1"
    assert nominal.worst_bias.relative_bias_percent < -0.5
    camera = CameraCalibration(bench.camera, bench.pose, SCALE_MM_PER_PX)
    plane = verify(measured(0.0, Calibration.object_plane(camera), bench=bench), class_named("0.2"))
    assert plane.met, plane.findings
    assert abs(plane.gauge_length_error_percent) < 0.05
