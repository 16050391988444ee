"""Motion blur (Zhang et al. 2016, Eq. 9) and the exposure planner."""

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from appliance.plan.exposure import ExposurePlan, motion_blur_length, plan_exposure
from appliance.plan.optics import Optics

# Table 1 of Zhang et al. (2016): motion blur in px; rows = crosshead speed, columns = focal
# length. The stored copies of the paper do not give the table's inputs. The inputs below are a
# reconstruction consistent with the table (they reproduce all nine values to 2 decimals), not
# quoted from it: pixel 5.2 um, exposure 10 ms, object distance 300 mm.
TABLE1_PIXEL_UM = 5.2
TABLE1_EXPOSURE_S = 10e-3
TABLE1_OBJECT_DISTANCE_MM = 300.0
TABLE1_FOCAL_LENGTHS_MM = (20.0, 50.0, 80.0)
TABLE1_SPEEDS_MM_MIN = (100.0, 200.0, 500.0)
TABLE1_BLUR_PX = (
    (0.23, 0.64, 1.17),
    (0.46, 1.28, 2.33),
    (1.14, 3.21, 5.83),
)

OPTICS = Optics(50.0, 300.0, 5.2)  # m = 0.2, 26 um of object per px


@pytest.mark.parametrize(
    ("row", "column"), [(r, c) for r in range(3) for c in range(3)], ids=lambda k: str(k)
)
def test_blur_reproduces_table_1(row, column):
    """Inputs reconstructed to be consistent with Table 1 (see the note above), not quoted."""
    optics = Optics(TABLE1_FOCAL_LENGTHS_MM[column], TABLE1_OBJECT_DISTANCE_MM, TABLE1_PIXEL_UM)
    blur = motion_blur_length(optics, TABLE1_SPEEDS_MM_MIN[row], TABLE1_EXPOSURE_S)
    assert round(blur.px, 2) == TABLE1_BLUR_PX[row][column]
    assert blur.um == pytest.approx(blur.px * TABLE1_PIXEL_UM)


def test_blur_follows_equation_9():
    # 500 mm/min = 8.333 mm/s; x 10 ms = 83.33 um of travel; x m 0.2 = 16.67 um = 3.205 px
    blur = motion_blur_length(OPTICS, 500.0, 0.01)
    assert blur.um == pytest.approx(500 / 60 * 0.01 * 0.2 * 1000)
    assert blur.px == pytest.approx(blur.um / 5.2)
    assert isinstance(blur.um, float) and isinstance(blur.px, float)


def test_blur_broadcasts_arrays():
    speeds = np.array(TABLE1_SPEEDS_MM_MIN)[:, None]
    exposures = np.array([1e-3, 1e-2])
    blur = motion_blur_length(OPTICS, speeds, exposures)
    assert blur.px.shape == (3, 2)
    np.testing.assert_allclose(blur.px, speeds / 60 * exposures * 0.2e3 / 5.2)


def test_blur_is_zero_without_motion_or_time():
    assert motion_blur_length(OPTICS, 0.0, 0.01).px == 0.0
    assert motion_blur_length(OPTICS, 500.0, 0.0).px == 0.0


@pytest.mark.parametrize(
    ("speed", "exposure", "name"),
    [(-1.0, 0.01, "speed_mm_min"), (math.nan, 0.01, "speed_mm_min"), (1.0, -0.01, "exposure_s")],
)
def test_blur_refuses_bad_values_by_name(speed, exposure, name):
    with pytest.raises(ValueError, match=name):
        motion_blur_length(OPTICS, speed, exposure)


def blur_px(speed_mm_min, exposure_s):
    return motion_blur_length(OPTICS, speed_mm_min, exposure_s).px


def test_plan_within_budget_takes_the_longest_exposure():
    # image speed at 500 mm/min: 8.333 mm/s * 0.2 / 5.2 um = 320.5 px/s -> 1 px in 3.12 ms
    plan = plan_exposure(OPTICS, 500.0, blur_budget_px=1.0, capture_range_px=20.0)
    assert isinstance(plan, ExposurePlan)
    assert plan.budget_met and plan.exposure_limit == "blur_budget"
    assert plan.exposure_s == pytest.approx(3.12e-3)
    assert plan.blur_px == pytest.approx(1.0)
    assert plan.blur_px <= 1.0
    assert blur_px(500.0, plan.exposure_s * (1 + 1e-9)) > 1.0
    assert plan.frame_period_s == pytest.approx(62.4e-3)
    assert plan.frame_rate_hz == pytest.approx(1 / 62.4e-3)
    assert plan.motion_per_frame_px <= 20.0
    assert plan.period_limit == "capture_range" and plan.period_covers_exposure


def test_plan_is_clipped_at_the_longest_exposure():
    plan = plan_exposure(OPTICS, 10.0, max_exposure_s=5e-3)
    assert plan.exposure_s == 5e-3
    assert plan.exposure_limit == "max_exposure"
    assert plan.budget_met and plan.blur_px < 1.0


def test_plan_reports_a_budget_it_cannot_meet():
    plan = plan_exposure(OPTICS, 50_000.0, blur_budget_px=1.0, min_exposure_s=1e-3)
    assert plan.exposure_s == 1e-3
    assert plan.exposure_limit == "min_exposure"
    assert not plan.budget_met
    assert plan.blur_px == pytest.approx(blur_px(50_000.0, 1e-3))
    assert plan.blur_px > 1.0


def test_the_period_never_undercuts_the_exposure():
    # a capture range below the blur budget would need a period shorter than the exposure
    plan = plan_exposure(OPTICS, 500.0, blur_budget_px=2.0, capture_range_px=1.0)
    assert plan.frame_period_s == plan.exposure_s
    assert not plan.period_covers_exposure
    assert plan.period_limit == "exposure"
    assert plan.motion_per_frame_px == pytest.approx(2.0)


def test_speed_fraction_scales_the_point_speed():
    full = plan_exposure(OPTICS, 500.0)
    half = plan_exposure(OPTICS, 500.0, speed_fraction=0.5)
    assert half.point_speed_mm_min == 250.0 and half.speed_mm_min == 500.0
    assert half.exposure_s == pytest.approx(2 * full.exposure_s)
    assert half.frame_period_s == pytest.approx(2 * full.frame_period_s)


def test_zero_speed_takes_the_longest_exposure_and_period():
    plan = plan_exposure(OPTICS, 0.0, max_exposure_s=8e-3, max_period_s=0.5)
    assert plan.exposure_s == 8e-3 and plan.exposure_limit == "max_exposure"
    assert plan.frame_period_s == 0.5 and plan.period_limit == "max_period"
    assert plan.frame_rate_hz == 2.0
    assert plan.blur_px == 0.0 and plan.motion_per_frame_px == 0.0
    assert plan.budget_met and plan.period_covers_exposure


def test_slow_speed_is_capped_at_the_longest_period():
    plan = plan_exposure(OPTICS, 0.1, max_period_s=2.0)
    assert plan.frame_period_s == 2.0 and plan.period_limit == "max_period"
    assert plan.motion_per_frame_px < 20.0


@pytest.mark.parametrize(
    ("speed", "options", "name"),
    [
        (-1.0, {}, "speed_mm_min"),
        (math.inf, {}, "speed_mm_min"),
        ("fast", {}, "speed_mm_min"),
        (100.0, {"blur_budget_px": 0.0}, "blur_budget_px"),
        (100.0, {"capture_range_px": -1.0}, "capture_range_px"),
        (100.0, {"min_exposure_s": 0.0}, "min_exposure_s"),
        (100.0, {"max_exposure_s": math.nan}, "max_exposure_s"),
        (100.0, {"max_period_s": 0.0}, "max_period_s"),
        (100.0, {"speed_fraction": 0.0}, "speed_fraction"),
        (100.0, {"min_exposure_s": 2e-3, "max_exposure_s": 1e-3}, "min_exposure_s"),
        (100.0, {"max_exposure_s": 0.1, "max_period_s": 0.05}, "max_period_s"),
    ],
)
def test_plan_refuses_bad_arguments_by_name(speed, options, name):
    with pytest.raises(ValueError, match=name):
        plan_exposure(OPTICS, speed, **options)


def test_tuning_parameters_are_keyword_only():
    with pytest.raises(TypeError):
        plan_exposure(OPTICS, 100.0, 1.0)  # type: ignore[misc]


@given(
    speed=st.floats(0.0, 1e5),
    budget=st.floats(0.05, 20.0),
    capture=st.floats(0.05, 100.0),
    min_exposure=st.floats(1e-6, 1e-3),
    span=st.floats(1.0, 1e3),
    fraction=st.floats(0.01, 1.0),
)
def test_plan_properties(speed, budget, capture, min_exposure, span, fraction):
    max_exposure = min_exposure * span
    plan = plan_exposure(
        OPTICS,
        speed,
        blur_budget_px=budget,
        capture_range_px=capture,
        min_exposure_s=min_exposure,
        max_exposure_s=max_exposure,
        max_period_s=10.0,
        speed_fraction=fraction,
    )
    point_speed = speed * fraction
    assert min_exposure <= plan.exposure_s <= max_exposure
    assert plan.exposure_s <= plan.frame_period_s <= 10.0
    assert plan.blur_px == blur_px(point_speed, plan.exposure_s)
    assert plan.motion_per_frame_px == blur_px(point_speed, plan.frame_period_s)
    assert plan.frame_rate_hz == pytest.approx(1 / plan.frame_period_s)
    # within budget when met, and no longer exposure in range would be
    assert plan.budget_met == (plan.blur_px <= budget)
    if plan.budget_met:
        longer = plan.exposure_s * (1 + 1e-9)
        assert plan.exposure_s == max_exposure or blur_px(point_speed, longer) > budget
    else:
        assert plan.exposure_s == min_exposure
    # frame-to-frame motion within the capture range with the longest period that allows it
    assert plan.period_covers_exposure == (plan.motion_per_frame_px <= capture)
    if plan.period_covers_exposure:
        longer = plan.frame_period_s * (1 + 1e-9)
        assert plan.frame_period_s == 10.0 or blur_px(point_speed, longer) > capture
    else:
        assert plan.frame_period_s == plan.exposure_s
