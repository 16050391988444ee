"""Exposure pacing: the simulated camera's exposure and the simulated trigger's period follow
the controller's speed readings; a plan that cannot be made or applied keeps the one in force."""

from __future__ import annotations

import pytest

from appliance.plan.exposure import plan_exposure
from appliance.plan.optics import Optics
from appliance.plan.pacing import ExposurePacer
from appliance.plan.trigger_plan import TriggerReplanner, plan_triggers
from appliance.sim.bar import BarModel
from appliance.sim.machine import MachineWithSpecimen
from appliance.sim.materials import ElasticPlastic
from appliance.sim.specimen import Specimen
from appliance.sim.trigger import SimTriggerController
from hal.camera.base import TriggerInfo, TriggerMode
from hal.machine.base import MachineState
from tests.unit.test_loop import StretchingScene, _camera

OPTICS = Optics(25.0, 250.0, 5.0)
TICK_HZ = 2_000_000.0


def _plan(speed_mm_min: float):
    exposure = plan_exposure(OPTICS, speed_mm_min, blur_budget_px=1.0, capture_range_px=10.0)
    return plan_triggers(exposure, tick_hz=TICK_HZ)


def _reading(speed_mm_min: float) -> MachineState:
    return MachineState(0.0, speed_mm_min, 0.0, True, 0)


@pytest.fixture
def devices():
    machine = MachineWithSpecimen(BarModel(Specimen.iso6892_flat(), ElasticPlastic.steel_s355()))
    trigger = SimTriggerController(machine, tick_hz=TICK_HZ)
    first = _plan(50.0)
    trigger.configure(first)
    trigger.arm(0.0)
    camera = _camera(StretchingScene())
    camera.prepare(TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=10.0))
    camera.set_exposure(first.exposure_us)
    return camera, trigger, first


def test_a_faster_speed_shortens_the_exposure_and_the_period_from_the_last_edge(devices):
    camera, trigger, first = devices
    pacer = ExposurePacer(
        _plan, TriggerReplanner(50.0), camera, trigger, exposure_us=first.exposure_us
    )
    edges = [trigger.next_edge_s(-1.0)]
    edges.append(trigger.next_edge_s(edges[-1]))
    pacer.follow(0.1, _reading(52.0))
    assert pacer.replans == []
    pacer.follow(0.2, _reading(200.0))
    [replan] = pacer.replans
    wanted = _plan(200.0 * 1.1)
    assert replan.error == "" and replan.period_ticks == wanted.period_ticks
    assert replan.exposure_us == pytest.approx(wanted.exposure_us)
    assert wanted.exposure_us < first.exposure_us
    camera.arm()
    assert camera.fetch(1.0).exposure_us == pytest.approx(wanted.exposure_us)
    for _ in range(3):
        edges.append(trigger.next_edge_s(edges[-1]))
    assert edges[1] - edges[0] == pytest.approx(first.frame_period_s)
    assert edges[2] - edges[1] == pytest.approx(wanted.frame_period_s)
    assert edges[4] - edges[3] == pytest.approx(wanted.frame_period_s)
    assert [event.trigger_seq for event in trigger.events] == [1, 2, 3, 4, 5]


def test_a_plan_that_cannot_be_made_or_applied_keeps_the_one_in_force(devices):
    camera, trigger, first = devices
    told = []

    def no_plan(speed_mm_min: float):
        raise ValueError(f"a pulse does not fit at {speed_mm_min:g} mm/min")

    pacer = ExposurePacer(
        no_plan,
        TriggerReplanner(50.0),
        camera,
        trigger,
        exposure_us=first.exposure_us,
        on_replan=told.append,
    )
    pacer.follow(1.0, _reading(500.0))
    assert pacer.failures == 1 and "does not fit" in told[0].error
    assert "plan in force kept" in told[0].describe()
    trigger.disarm()
    refused = ExposurePacer(
        _plan, TriggerReplanner(50.0), camera, trigger, exposure_us=first.exposure_us
    )
    refused.follow(1.0, _reading(500.0))
    assert refused.failures == 1 and "disarmed" in refused.replans[0].error
    camera.arm()
    assert camera.fetch(1.0).exposure_us == pytest.approx(first.exposure_us)


def test_no_reading_or_standing_still_changes_nothing(devices):
    camera, trigger, first = devices
    pacer = ExposurePacer(
        _plan, TriggerReplanner(50.0), camera, trigger, exposure_us=first.exposure_us
    )
    pacer.follow(4.0, None)
    pacer.follow(5.0, _reading(0.0))
    pacer.follow(6.0, _reading(float("nan")))
    assert pacer.replans == []
