"""Run states of a test and the only transitions allowed between them.

    IDLE --arm--> ARMED --start--> RUNNING --stop--> STOPPING --finish--> IDLE
    ARMED --disarm--> IDLE
    ARMED, RUNNING, STOPPING --abort--> ABORTED --reset--> IDLE
    any state but IDLE --fault--> FAULT --reset--> IDLE

A run ends in IDLE through STOPPING (completed: the stop criterion, a break, or an operator
stop), through ABORTED (the operator or the controller abandoned it; results so far are kept
and marked aborted), or through FAULT (hardware or software failure; results so far are kept).
Every transition is recorded with its time and reason; an event that the table does not allow
in the current state raises `IllegalTransition` and changes nothing.
"""

from __future__ import annotations

import enum
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass


class RunState(enum.Enum):
    """State of the appliance's run."""

    IDLE = "idle"
    ARMED = "armed"
    RUNNING = "running"
    STOPPING = "stopping"
    ABORTED = "aborted"
    FAULT = "fault"


class ExitStatus(enum.StrEnum):
    """How a test ended: the summary's, the recording's and the viewer's `exit_status`.

    COMPLETED: its stop criterion (strain, time or frame limit).
    BREAK: the specimen broke (a force drop; without force readings, inferred from a gauge
        mark lost for several frames).
    STOPPED: stopped before its criterion by a stop command (the controller's, the service's
        on SIGTERM); what was measured is kept and valid.
    ABORTED: interrupted by the operator; what was measured so far is kept.
    FAULT: a device or the measurement failed, or no valid sample was measured; what was
        measured so far is kept.
    DAMAGED: a replay stopped at damage in its recording.
    """

    COMPLETED = "completed"
    BREAK = "break"
    STOPPED = "stopped"
    ABORTED = "aborted"
    FAULT = "fault"
    DAMAGED = "damaged"

    @property
    def ended_normally(self) -> bool:
        """Whether the test ended as asked (COMPLETED, BREAK or STOPPED): exit status 0 of
        `run`."""
        return self in (ExitStatus.COMPLETED, ExitStatus.BREAK, ExitStatus.STOPPED)


class RunEvent(enum.Enum):
    """What moves the run from one state to another."""

    ARM = "arm"
    DISARM = "disarm"
    START = "start"
    STOP = "stop"
    FINISH = "finish"
    ABORT = "abort"
    FAULT = "fault"
    RESET = "reset"


TRANSITIONS: dict[tuple[RunState, RunEvent], RunState] = {
    (RunState.IDLE, RunEvent.ARM): RunState.ARMED,
    (RunState.ARMED, RunEvent.DISARM): RunState.IDLE,
    (RunState.ARMED, RunEvent.START): RunState.RUNNING,
    (RunState.RUNNING, RunEvent.STOP): RunState.STOPPING,
    (RunState.STOPPING, RunEvent.FINISH): RunState.IDLE,
    (RunState.ARMED, RunEvent.ABORT): RunState.ABORTED,
    (RunState.RUNNING, RunEvent.ABORT): RunState.ABORTED,
    (RunState.STOPPING, RunEvent.ABORT): RunState.ABORTED,
    (RunState.ARMED, RunEvent.FAULT): RunState.FAULT,
    (RunState.RUNNING, RunEvent.FAULT): RunState.FAULT,
    (RunState.STOPPING, RunEvent.FAULT): RunState.FAULT,
    (RunState.ABORTED, RunEvent.FAULT): RunState.FAULT,
    (RunState.ABORTED, RunEvent.RESET): RunState.IDLE,
    (RunState.FAULT, RunEvent.RESET): RunState.IDLE,
}
"""(state, event) -> next state; every pair not listed is illegal."""


class IllegalTransition(RuntimeError):
    """An event the transition table does not allow in the current state."""


@dataclass(frozen=True)
class Transition:
    """One recorded change of state."""

    time_s: float
    source: RunState
    event: RunEvent
    target: RunState
    reason: str


class RunStateMachine:
    """The run's state, changed only through `handle`; thread-safe.

    Args:
        clock: time source in seconds for the transition record (injected for tests).
        on_transition: called after every transition, outside the lock.
    """

    def __init__(
        self,
        *,
        clock: Callable[[], float] = time.monotonic,
        on_transition: Callable[[Transition], None] | None = None,
    ) -> None:
        self._clock = clock
        self._on_transition = on_transition
        self._lock = threading.Lock()
        self._state = RunState.IDLE
        self._history: list[Transition] = []

    @property
    def state(self) -> RunState:
        """Current state."""
        with self._lock:
            return self._state

    @property
    def history(self) -> tuple[Transition, ...]:
        """Every transition so far, oldest first."""
        with self._lock:
            return tuple(self._history)

    def handle(self, event: RunEvent, reason: str = "") -> RunState:
        """Apply an event; returns the new state.

        Raises:
            IllegalTransition: the event is not allowed in the current state.
        """
        with self._lock:
            target = TRANSITIONS.get((self._state, event))
            if target is None:
                raise IllegalTransition(
                    f"run state {self._state.value}: event {event.value} is not allowed"
                )
            record = Transition(self._clock(), self._state, event, target, reason)
            self._history.append(record)
            self._state = target
        if self._on_transition is not None:
            self._on_transition(record)
        return target
