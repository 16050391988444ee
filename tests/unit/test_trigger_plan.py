"""Trigger plans from exposure plans: period in ticks or encoder divisor, and re-planning."""

import math

import pytest

from appliance.plan.exposure import plan_exposure
from appliance.plan.optics import Optics
from appliance.plan.trigger_plan import TriggerReplanner, plan_triggers

OPTICS = Optics(25.0, 250.0, 5.0)
TICK_HZ = 2_000_000.0


def _plan(speed_mm_min: float):
    return plan_exposure(OPTICS, speed_mm_min, blur_budget_px=1.0, capture_range_px=10.0)


def test_period_triggers_round_the_planned_period_down_to_whole_ticks():
    exposure = _plan(50.0)
    plan = plan_triggers(exposure, tick_hz=TICK_HZ)
    assert plan.source == "period" and plan.encoder_divisor == 0
    assert plan.period_ticks == math.floor(exposure.frame_period_s * TICK_HZ)
    assert plan.frame_period_s <= exposure.frame_period_s
    assert plan.pulse_width_ticks == 120 and plan.exposure_us == exposure.exposure_s * 1e6
    assert plan.motion_per_frame_mm == pytest.approx(50.0 / 60.0 * plan.frame_period_s)


def test_encoder_triggers_space_frames_by_the_planned_crosshead_travel():
    slow = plan_triggers(_plan(200.0), tick_hz=TICK_HZ, counts_per_mm=1000.0)
    fast = plan_triggers(_plan(2000.0), tick_hz=TICK_HZ, counts_per_mm=1000.0)
    for plan, speed in ((slow, 200.0), (fast, 2000.0)):
        exposure = _plan(speed)
        assert plan.source == "encoder" and plan.period_ticks == 0
        planned_travel = speed / 60.0 * exposure.frame_period_s
        assert plan.encoder_divisor == math.floor(planned_travel * 1000.0)
        assert plan.motion_per_frame_mm <= planned_travel
        assert plan.frame_period_s == pytest.approx(plan.motion_per_frame_mm / (speed / 60.0))
    assert fast.exposure_us < slow.exposure_us


def test_standing_still_falls_back_to_the_period_and_bad_values_are_named():
    assert plan_triggers(_plan(0.0), tick_hz=TICK_HZ, counts_per_mm=1000.0).source == "period"
    with pytest.raises(ValueError, match="tick_hz"):
        plan_triggers(_plan(5.0), tick_hz=0.0)
    with pytest.raises(ValueError, match="counts_per_mm"):
        plan_triggers(_plan(5.0), tick_hz=TICK_HZ, counts_per_mm=-1.0)
    with pytest.raises(ValueError, match="does not fit the period"):
        plan_triggers(_plan(5.0), tick_hz=TICK_HZ, pulse_width_us=2e6)


def test_a_faster_speed_beyond_the_hysteresis_is_planned_for_at_once():
    replanner = TriggerReplanner(50.0, hysteresis=0.1)
    assert replanner.due(54.0, 0.0) is None and replanner.due(-54.0, 0.1) is None
    assert replanner.due(56.0, 0.2) == 56.0 and replanner.planned_for == 56.0
    assert replanner.due(-70.0, 0.3) == 70.0


def test_a_slower_speed_is_planned_for_after_the_dwell_at_the_fastest_reading_meanwhile():
    replanner = TriggerReplanner(100.0, hysteresis=0.1, slow_down_after_s=2.0)
    assert replanner.due(50.0, 10.0) is None
    assert replanner.due(60.0, 11.0) is None
    assert replanner.due(40.0, 11.9) is None
    assert replanner.due(45.0, 12.0) == 60.0 and replanner.planned_for == 60.0


def test_a_reading_back_within_the_hysteresis_restarts_the_dwell():
    replanner = TriggerReplanner(100.0, hysteresis=0.1, slow_down_after_s=2.0)
    assert replanner.due(50.0, 0.0) is None
    assert replanner.due(95.0, 1.0) is None
    assert replanner.due(50.0, 2.5) is None
    assert replanner.due(50.0, 4.5) == 50.0


def test_standing_still_never_replans_and_a_restart_from_rest_is_planned_for():
    replanner = TriggerReplanner(100.0, slow_down_after_s=0.0)
    assert replanner.due(0.0, 0.0) is None and replanner.due(0.001, 5.0) is None
    assert replanner.planned_for == 100.0
    resting = TriggerReplanner(0.0)
    assert resting.due(0.0, 0.0) is None and resting.due(5.0, 1.0) == 5.0
    with pytest.raises(ValueError, match="hysteresis"):
        TriggerReplanner(1.0, hysteresis=0.0)
