"""The width profile along the axis: rows without a width stay out of the parallel length, and
an end whose width never rises is not reported as seen."""

from __future__ import annotations

import math

import numpy as np
import pytest

from appliance.measure.specimen_profile import parallel_ends, parallel_run


def test_a_long_stretch_without_widths_ends_the_parallel_run():
    widths = np.full(340, 50.0)
    widths[100:300] = np.nan
    assert parallel_run(widths, 15) == (0, 100)


def test_a_short_gap_in_the_widths_is_bridged():
    widths = np.full(300, 50.0)
    widths[140:160] = np.nan
    assert parallel_run(widths, 15) == (0, 300)


def test_rows_without_a_width_at_either_side_stay_out_of_the_run():
    widths = np.full(400, np.nan)
    widths[50:250] = 100.0
    assert parallel_run(widths, 15) == (50, 250)


def test_an_end_whose_width_does_not_rise_is_not_seen():
    widths = np.full(400, np.nan)
    widths[50:250] = 100.0
    s_grid = np.arange(400.0)
    low, centre, high = parallel_ends(s_grid, widths, 50, 250, np.ones(400, bool))
    assert low is None and high is None and math.isnan(centre)


def test_ends_where_the_width_rises_are_seen_and_centre_the_run():
    s_grid = np.arange(400.0)
    widths = 100.0 + np.clip(np.abs(s_grid - 180.0) - 100.0, 0.0, None)
    low, centre, high = parallel_ends(s_grid, widths, 81, 280, np.ones(400, bool))
    assert low is not None and high is not None
    assert centre == pytest.approx(0.5 * (low + high), abs=0.5)
    assert centre == pytest.approx(180.0, abs=0.1)
