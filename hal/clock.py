"""Clocks shared by the simulated devices: one virtual time line, real time or as fast as possible.

A simulated camera and a simulated machine read and advance the same `SimClock`, so images,
forces and crosshead positions agree. In FAST mode `wait_until` jumps the clock forward at
once; in REAL_TIME mode it sleeps until the wall clock reaches that moment of the simulation.
The wall-clock source and the sleep function are injected, so tests run deterministically.
"""

from __future__ import annotations

import enum
import threading
import time
from collections.abc import Callable


class Pace(enum.Enum):
    """How simulated time relates to wall time."""

    REAL_TIME = "realtime"
    FAST = "fast"


class SimClock:
    """Simulation time in seconds from the start of the simulation.

    Args:
        pace: REAL_TIME or FAST.
        wall: monotonic wall-clock source in seconds (REAL_TIME only).
        sleep: sleep function in seconds (REAL_TIME only).
    """

    def __init__(
        self,
        pace: Pace = Pace.FAST,
        *,
        wall: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        self.pace = pace
        self._wall = wall
        self._sleep = sleep
        self._lock = threading.Lock()
        self._now = 0.0
        self._wall_start = wall()

    def now_s(self) -> float:
        """Current simulation time, s."""
        if self.pace is Pace.REAL_TIME:
            return self._wall() - self._wall_start
        with self._lock:
            return self._now

    def at_wall_s(self, wall_s: float) -> float:
        """The simulation time of a reading of the wall clock (REAL_TIME only), s: how an
        event stamped on the host's monotonic clock is placed in the simulation."""
        if self.pace is not Pace.REAL_TIME:
            raise ValueError("only a real-time simulation clock follows the wall clock")
        return wall_s - self._wall_start

    def now_ns(self) -> int:
        """Current simulation time, ns."""
        return int(round(self.now_s() * 1e9))

    def wait_until(self, t_s: float) -> None:
        """Return once simulation time has reached `t_s` (never moves time backwards)."""
        if self.pace is Pace.REAL_TIME:
            remaining = t_s - self.now_s()
            if remaining > 0:
                self._sleep(remaining)
            return
        with self._lock:
            self._now = max(self._now, t_s)
