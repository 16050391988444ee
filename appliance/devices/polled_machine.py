"""A machine controller read on its own thread, so the camera's thread never waits for it.

A real controller answers over a network or a serial line: a read takes milliseconds and, when
the controller is away, up to its timeout. The measurement loop reads the controller's state
with every frame; `PolledMachine` makes that read free: a thread polls the controller at a fixed
rate (>= 100 Hz for the machine's own control to be followed) and `read_state` hands out the
latest reading, or raises `HardwareConnectError` when there is none younger than `max_age_s`
(with the poller's last error), which the loop records as a sample without controller data.

Commands (start, stop, return to start) go straight to the controller, serialised with the
poller's reads by one lock (a Modbus client is not to be shared between threads).

The simulated machine is not polled: its clock is the simulation's and moves with the frames.
"""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from hal.errors import HardwareConnectError, HardwareError
from hal.machine.base import MachineState, TestingMachine


@dataclass(frozen=True)
class PollStatistics:
    """Reads by the poller: count, failures and read latency (ms, over the last 100,000)."""

    reads: int
    failures: int
    p50_ms: float
    p99_ms: float
    max_ms: float


class PolledMachine:
    """A `TestingMachine` whose state is polled in the background.

    Args:
        machine: the controller (opened by `open`, closed by `close`).
        rate_hz: polling rate.
        max_age_s: the oldest reading `read_state` hands out; None = three poll periods or
            0.1 s, whichever is longer.
        read_timeout_s: timeout of each read.
    """

    def __init__(
        self,
        machine: TestingMachine,
        *,
        rate_hz: float = 100.0,
        max_age_s: float | None = None,
        read_timeout_s: float = 0.5,
    ) -> None:
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
        self.machine = machine
        self.url = machine.url
        self.period_s = 1.0 / rate_hz
        self.max_age_s = max_age_s if max_age_s is not None else max(3 * self.period_s, 0.1)
        self.read_timeout_s = read_timeout_s
        self._lock = threading.Lock()
        self._latest: tuple[float, MachineState] | None = None
        self._error: str = "no reading yet"
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._latencies_ms: collections.deque[float] = collections.deque(maxlen=100_000)
        self._reads = 0
        self._failures = 0

    def open(self, timeout_s: float = 5.0) -> None:
        """Open the controller, take a first reading (so a test starts with one) and poll."""
        self.machine.open(timeout_s)
        self._poll_once()
        self._stop.clear()
        self._thread = threading.Thread(target=self._poll, name="machine-poller", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop polling and close the controller; safe to call twice."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=self.read_timeout_s + 1.0)
            self._thread = None
        with self._lock:
            self.machine.close()

    def read_state(self, timeout_s: float = 1.0) -> MachineState:
        """The latest reading. Raises HardwareConnectError when it is older than `max_age_s`."""
        latest = self._latest
        if latest is not None and time.monotonic() - latest[0] <= self.max_age_s:
            return latest[1]
        age = "none" if latest is None else f"{time.monotonic() - latest[0]:.2f} s old"
        raise HardwareConnectError(
            f"{self.url}: no fresh controller reading ({age}): {self._error}"
        )

    def start(self, speed_mm_min: float, timeout_s: float = 1.0) -> None:
        with self._lock:
            self.machine.start(speed_mm_min, timeout_s)

    def stop(self, timeout_s: float = 1.0) -> None:
        with self._lock:
            self.machine.stop(timeout_s)

    def return_to_start(self, speed_mm_min: float, timeout_s: float = 1.0) -> None:
        with self._lock:
            self.machine.return_to_start(speed_mm_min, timeout_s)

    def statistics(self) -> dict[str, Any]:
        """The polled controller's own counters."""
        return self.machine.statistics()

    def poll_statistics(self) -> PollStatistics:
        """What the poller has read so far."""
        latencies = np.asarray(self._latencies_ms, dtype=np.float64)
        if latencies.size == 0:
            return PollStatistics(self._reads, self._failures, np.nan, np.nan, np.nan)
        p50, p99 = np.percentile(latencies, [50, 99])
        return PollStatistics(
            self._reads, self._failures, float(p50), float(p99), float(latencies.max())
        )

    def _poll_once(self) -> None:
        started = time.monotonic()
        try:
            with self._lock:
                state = self.machine.read_state(self.read_timeout_s)
        except HardwareError as exc:
            self._failures += 1
            self._error = str(exc)
            return
        done = time.monotonic()
        self._reads += 1
        self._latencies_ms.append((done - started) * 1e3)
        self._latest = (done, state)

    def _poll(self) -> None:
        next_at = time.monotonic()
        while not self._stop.is_set():
            self._poll_once()
            next_at += self.period_s
            wait = next_at - time.monotonic()
            if wait < 0:
                next_at = time.monotonic()
                wait = 0.0
            self._stop.wait(wait)
