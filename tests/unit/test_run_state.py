import itertools

import pytest

from appliance.run.state import (
    TRANSITIONS,
    IllegalTransition,
    RunEvent,
    RunState,
    RunStateMachine,
)


def test_a_completed_run_goes_round_the_cycle_and_is_recorded():
    ticks = itertools.count()
    seen = []
    machine = RunStateMachine(clock=lambda: float(next(ticks)), on_transition=seen.append)
    for event in (RunEvent.ARM, RunEvent.START, RunEvent.STOP, RunEvent.FINISH):
        machine.handle(event, reason=f"because {event.value}")
    assert machine.state is RunState.IDLE
    assert [t.target for t in machine.history] == [
        RunState.ARMED,
        RunState.RUNNING,
        RunState.STOPPING,
        RunState.IDLE,
    ]
    assert [t.time_s for t in machine.history] == [0.0, 1.0, 2.0, 3.0]
    assert seen == list(machine.history) and seen[2].reason == "because stop"


@pytest.mark.parametrize(
    ("state", "event"), [(s, e) for s in RunState for e in RunEvent if (s, e) not in TRANSITIONS]
)
def test_every_pair_outside_the_table_is_refused_and_changes_nothing(state, event):
    machine = RunStateMachine()
    path = {
        RunState.IDLE: [],
        RunState.ARMED: [RunEvent.ARM],
        RunState.RUNNING: [RunEvent.ARM, RunEvent.START],
        RunState.STOPPING: [RunEvent.ARM, RunEvent.START, RunEvent.STOP],
        RunState.ABORTED: [RunEvent.ARM, RunEvent.ABORT],
        RunState.FAULT: [RunEvent.ARM, RunEvent.FAULT],
    }[state]
    for step in path:
        machine.handle(step)
    assert machine.state is state
    before = machine.history
    with pytest.raises(IllegalTransition, match=f"run state {state.value}: event {event.value}"):
        machine.handle(event)
    assert machine.state is state and machine.history == before


def test_abort_and_fault_need_a_reset():
    machine = RunStateMachine()
    machine.handle(RunEvent.ARM)
    machine.handle(RunEvent.START)
    machine.handle(RunEvent.ABORT, "operator")
    with pytest.raises(IllegalTransition):
        machine.handle(RunEvent.ARM)
    machine.handle(RunEvent.FAULT, "camera lost")
    assert machine.handle(RunEvent.RESET) is RunState.IDLE
