import math

import numpy as np
import pytest

from appliance.measure.gauges import Calibration, Gauge, StrainGauges, place_marks


def stretch(points, centre, axial, lateral):
    """Uniaxial stretch along y (rows) about centre."""
    out = points.astype(float).copy()
    out[:, 1] = centre[1] + axial * (points[:, 1] - centre[1])
    out[:, 0] = centre[0] + lateral * (points[:, 0] - centre[0])
    return out


def test_auto_placed_marks_measure_a_uniaxial_stretch():
    calibration = Calibration.from_optics(pixel_size_um=5.5, magnification=0.11)
    assert calibration.scale_mm_per_px == pytest.approx(0.05)
    points, layout = place_marks((400.0, 300.0), 20.0, calibration, transverse_width_mm=4.0)
    assert points.shape == (8, 2)
    gauges = StrainGauges(layout.axial, points, calibration, layout.transverse)
    assert gauges.gauge_length_mm == pytest.approx(20.0)
    lam = 1.5
    reading = gauges.read(stretch(points, (400.0, 300.0), lam, lam**-0.5))
    assert reading.engineering_strain == pytest.approx(0.5)
    assert reading.true_strain == pytest.approx(math.log(1.5))
    assert reading.elongation_mm == pytest.approx(10.0)
    assert reading.gauge_length_mm == pytest.approx(30.0)
    assert reading.transverse_strain == pytest.approx(lam**-0.5 - 1)
    assert reading.poisson_ratio == pytest.approx(-(lam**-0.5 - 1) / 0.5)


def test_marks_average_their_points_and_skip_invalid_ones():
    reference = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 100.0], [10.0, 100.0]])
    gauge = Gauge((0, 1), (2, 3))
    gauges = StrainGauges(gauge, reference, Calibration(0.1))
    moved = reference + np.array([[0, 0.5], [0, -0.5], [0, 1.0], [0, 1.0]])
    assert gauges.read(moved).engineering_strain == pytest.approx(0.01)
    valid = np.array([True, False, True, True])
    expected = math.hypot(5.0, 100.5) / 100.0 - 1.0
    assert gauges.read(moved, valid).engineering_strain == pytest.approx(expected)
    assert math.isnan(gauges.read(moved, np.array([True, True, False, False])).engineering_strain)
    assert math.isnan(gauges.read(moved).poisson_ratio)


def test_bad_gauges_and_calibrations_are_refused():
    with pytest.raises(ValueError, match="share points"):
        Gauge((0, 1), (1, 2))
    with pytest.raises(ValueError, match="at least one point"):
        Gauge((), (1,))
    with pytest.raises(ValueError, match="scale_mm_per_px"):
        Calibration(0.0)
    assert Calibration.from_known_distance(25.0, 500.0).scale_mm_per_px == pytest.approx(0.05)
    with pytest.raises(ValueError, match="zero length"):
        StrainGauges(Gauge((0,), (1,)), np.zeros((2, 2)), Calibration(1.0))


def test_marks_along_the_axis_for_narrow_specimens():
    points, layout = place_marks(
        (50.0, 200.0),
        10.0,
        Calibration(0.1),
        points_per_mark=3,
        mark_width_px=16.0,
        along_axis=True,
    )
    assert points[:, 0].tolist() == [50.0] * 6
    assert points[:, 1].tolist() == pytest.approx([142, 150, 158, 242, 250, 258])
    assert layout.axial.length_px(points) == pytest.approx(100.0)
