"""A log that a flood of events cannot flood: at most one line per kind of event and interval.

The Modbus server meets events that come by the thousand when a network misbehaves (dropped
connections, idle timeouts, garbage, failed accepts). `ThrottledLog.note` logs the first
event of a kind at once and then at most one line per `interval_s` for that kind, saying how
many more came meanwhile; `flush`, called periodically and at close, logs the counts still
held back. Lines are single
lines: an exception is written as its type and message, never as a traceback.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

LOG_INTERVAL_S = 10.0
"""The shortest time between two lines of the same kind."""


@dataclass
class _Kind:
    logged_at_s: float
    held_back: int = 0
    last_message: str = ""


class ThrottledLog:
    """Logs events of each kind at most once per `interval_s`, with the count held back.

    Args:
        logger: where the lines go.
        interval_s: the shortest time between two lines of one kind.
        clock: seconds of a monotonic clock.

    Thread-safe; `note` never raises and never blocks on anything but the logger.
    """

    def __init__(
        self,
        logger: logging.Logger,
        interval_s: float = LOG_INTERVAL_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.logger = logger
        self.interval_s = interval_s
        self._clock = clock
        self._kinds: dict[str, _Kind] = {}
        self._lock = threading.Lock()

    def note(self, kind: str, message: str, level: int = logging.WARNING) -> None:
        """One event of `kind`: logs `message` now, or counts it until the interval is over."""
        now = self._clock()
        with self._lock:
            seen = self._kinds.get(kind)
            if seen is not None and now - seen.logged_at_s < self.interval_s:
                seen.held_back += 1
                seen.last_message = message
                return
            held_back = seen.held_back if seen is not None else 0
            self._kinds[kind] = _Kind(logged_at_s=now)
        suffix = f" (and {held_back} more like it since the last such line)"
        self.logger.log(level, "%s%s", message, suffix if held_back else "")

    def flush(self, *, force: bool = False) -> None:
        """Log the count held back of each kind whose interval is over (every kind: `force`).

        Called periodically, so a burst's count is reported one interval after it, not only
        with the next event of its kind; and with `force` at close.
        """
        now = self._clock()
        lines = []
        with self._lock:
            for seen in self._kinds.values():
                if seen.held_back and (force or now - seen.logged_at_s >= self.interval_s):
                    lines.append((seen.last_message, seen.held_back))
                    seen.held_back = 0
                    seen.logged_at_s = now
        for message, held_back in lines:
            self.logger.warning("%s (%d like it since the last such line)", message, held_back)
