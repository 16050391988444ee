"""The specimen's width at its edges on rendered views: each station's width against the
view's truth, the transverse strain between two views of known width ratio, a station that
cannot see its edges flagged (not guessed), and a frame without a specimen refused."""

from __future__ import annotations

import math

import numpy as np
import pytest

from appliance.measure.edge_width import EdgesNotFound, EdgeWidthGauge, edge_width_gauge
from appliance.measure.gauges import Calibration
from appliance.sim.specimen import Specimen
from appliance.sim.specimen_view import render_specimen_view
from appliance.sim.world import PRESETS

SENSOR = (1024, 2048)
SCALE_MM_PER_PX = PRESETS["metal"].optics.scale_mm_per_px
HALF_GAUGE_MM = 25.0


def _view(scale_mm_per_px: float, lighting: str, seed: int = 3):
    """A metal specimen view and its two marks' positions (the gauge's ends on its axis)."""
    image, truth = render_specimen_view(
        Specimen.iso6892_flat(),
        scale_mm_per_px=scale_mm_per_px,
        sensor_size=SENSOR,
        lighting=lighting,
        seed=seed,
    )
    centre = np.array(truth.centre_px)
    half = HALF_GAUGE_MM / scale_mm_per_px * np.array([0.0, 1.0])
    return image, truth, centre - half, centre + half


@pytest.mark.parametrize(
    ("lighting", "width_tolerance_px", "strain_tolerance"),
    [("back-lit", 0.02, 0.005), ("front-dark", 0.5, 0.02), ("front-bright", 0.5, 0.02)],
)
def test_each_station_measures_the_width_and_a_one_percent_change(
    lighting, width_tolerance_px, strain_tolerance
):
    image, truth, first, second = _view(SCALE_MM_PER_PX, lighting)
    gauge = EdgeWidthGauge(
        image, first, second, Calibration(SCALE_MM_PER_PX), 5, 0.5 * truth.width_px + 3.0
    )
    widths_px = np.array(gauge.reference_widths_mm) / SCALE_MM_PER_PX
    assert widths_px == pytest.approx(np.full(5, truth.width_px), abs=width_tolerance_px)
    stretched, _, first, second = _view(SCALE_MM_PER_PX / 1.01, lighting)
    reading = gauge.read(stretched, first, second)
    assert reading.seen == (True,) * 5 and reading.stations_seen == 5
    assert reading.transverse_strain == pytest.approx(0.01, rel=strain_tolerance)
    assert reading.mean_width_mm == pytest.approx(np.mean(reading.widths_mm))
    assert reading.mean_width_mm == pytest.approx(12.5 * 1.01, abs=0.5 * SCALE_MM_PER_PX)


def test_the_stations_lie_between_the_marks_and_move_with_them():
    image, truth, first, second = _view(SCALE_MM_PER_PX, "back-lit")
    gauge = EdgeWidthGauge(
        image, first, second, Calibration(SCALE_MM_PER_PX), 3, 0.5 * truth.width_px
    )
    points = gauge.station_points_px(first, second)
    ys = [0.5 * (left[1] + right[1]) for left, right in points]
    assert ys == pytest.approx([first[1] + f * (second[1] - first[1]) for f in (0.25, 0.5, 0.75)])
    widths = [np.hypot(*(right - left)) for left, right in points]
    assert widths == pytest.approx([truth.width_px] * 3, abs=0.02)


def test_a_station_that_cannot_see_its_edges_is_flagged_not_guessed():
    image, truth, first, second = _view(SCALE_MM_PER_PX, "front-dark")
    gauge = EdgeWidthGauge(
        image, first, second, Calibration(SCALE_MM_PER_PX), 3, 0.5 * truth.width_px
    )
    covered = image.copy()
    middle = int(round(0.5 * (first[1] + second[1])))
    covered[middle - 40 : middle + 40, :] = image.min()
    reading = gauge.read(covered, first, second)
    assert reading.seen == (True, False, True)
    assert math.isnan(reading.widths_mm[1])
    assert reading.mean_width_mm == pytest.approx(np.nanmean(reading.widths_mm))
    assert reading.transverse_strain == pytest.approx(0.0, abs=2e-4)
    shifted = gauge.read(image, first + [600.0, 0.0], second + [600.0, 0.0])
    assert shifted.seen == (False, False, False)
    assert math.isnan(shifted.transverse_strain) and math.isnan(shifted.mean_width_mm)
    again = gauge.read(image, first, second)
    assert again.seen == (True, True, True)


def test_a_reference_frame_without_a_specimen_is_refused():
    blank = np.full((512, 256), 40, np.uint8)
    with pytest.raises(EdgesNotFound, match="no specimen"):
        edge_width_gauge(blank, (128.0, 100.0), (128.0, 400.0), Calibration(0.05), 3)
    with pytest.raises(ValueError, match="stations must be"):
        EdgeWidthGauge(blank, (128.0, 100.0), (128.0, 400.0), Calibration(0.05), 0, 50.0)


def test_a_zero_restarts_each_station_from_its_width_in_the_zeroed_frame():
    image, truth, first, second = _view(SCALE_MM_PER_PX, "back-lit")
    gauge = EdgeWidthGauge(
        image, first, second, Calibration(SCALE_MM_PER_PX), 3, 0.5 * truth.width_px + 3.0
    )
    wider, _, first_1, second_1 = _view(SCALE_MM_PER_PX / 1.01, "back-lit")
    zeroed = gauge.rezero(gauge.read(wider, first_1, second_1))
    assert zeroed.transverse_strain == 0.0
    assert gauge.reference_widths_mm == pytest.approx(zeroed.widths_mm)
    widest, _, first_2, second_2 = _view(SCALE_MM_PER_PX / 1.02, "back-lit")
    reading = gauge.read(widest, first_2, second_2)
    assert reading.transverse_strain == pytest.approx(1.02 / 1.01 - 1.0, rel=0.01)
    assert gauge.read(image, first, second).transverse_strain == pytest.approx(
        1.0 / 1.01 - 1.0, rel=0.01
    )
