"""The sd_notify(3) protocol without libsystemd: readiness, status, watchdog and stopping.

A service of `Type=notify` tells its manager how it is doing by sending short datagrams of
newline-separated `KEY=VALUE` assignments to the AF_UNIX socket named in `$NOTIFY_SOCKET`:
`READY=1` once it serves, `STATUS=...` for `systemctl status`, `WATCHDOG=1` to prove it is alive
(when the unit sets `WatchdogSec=`, the manager passes the interval in `$WATCHDOG_USEC` and kills
the service when the pings stop), `STOPPING=1` when it begins to shut down and
`EXTEND_TIMEOUT_USEC=...` to ask for more time to start or stop. The manager reads the sender's
pid from the socket credentials; with `NotifyAccess=main` only the main process is heard.

Environment, as libsystemd reads it (sd_notify(3), sd_watchdog_enabled(3)):

- `NOTIFY_SOCKET`: a file system path (`/run/systemd/notify`) or an abstract socket name
  written with a leading `@`. Unset or empty: every method is a no-op, so the same code runs
  from a terminal. Other forms (systemd 254's `vsock:`) are logged once and ignored.
- `WATCHDOG_USEC`: the watchdog interval in microseconds; unset, empty or invalid: no watchdog.
- `WATCHDOG_PID`: when set, the watchdog is this process's only if the pid is its own, so a
  child that inherited the environment does not ping on the service's behalf.

The variables are read once, when the notifier is made, and left in the environment (libsystemd's
`unset_environment=0`): unsetting them from a process whose other threads (numba, Rerun, the
Modbus server) may read the environment at the same time is not thread-safe in C, and a child
that inherits them cannot do harm: `WATCHDOG_PID` keeps it off the watchdog and
`NotifyAccess=main` makes the manager ignore it. Pass `child_environment()` to a subprocess that
should not see them at all.
"""

from __future__ import annotations

import logging
import math
import os
import socket
import threading
import time
from collections.abc import Callable, Mapping

__all__ = ["NOTIFY_VARIABLES", "ServiceNotifier", "child_environment"]

NOTIFY_VARIABLES = ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID")
"""The environment variables through which a service manager configures notification."""

_logger = logging.getLogger(__name__)

_READY = "READY=1"
_STOPPING = "STOPPING=1"
_WATCHDOG_DATAGRAM = b"WATCHDOG=1"


def child_environment(environ: Mapping[str, str] | None = None) -> dict[str, str]:
    """A copy of `environ` (default: `os.environ`) without the notification variables.

    For a subprocess that must not talk to the service manager in the service's name.
    """
    source = os.environ if environ is None else environ
    return {key: value for key, value in source.items() if key not in NOTIFY_VARIABLES}


def _socket_address(text: str) -> bytes | None:
    """The socket address `$NOTIFY_SOCKET` names, as `sendto` takes it; None if unusable."""
    if not text:
        return None
    if text.startswith("/"):
        return os.fsencode(text)
    if text.startswith("@") and len(text) > 1:
        return b"\0" + os.fsencode(text[1:])
    _logger.warning("NOTIFY_SOCKET=%r is not a socket path or @name; not notifying", text)
    return None


def _watchdog_interval_s(environ: Mapping[str, str], pid: int) -> float | None:
    """The watchdog interval `$WATCHDOG_USEC` gives this process, in seconds; None if none."""
    usec_text = environ.get("WATCHDOG_USEC", "")
    if not usec_text:
        return None
    pid_text = environ.get("WATCHDOG_PID", "")
    if pid_text:
        if not pid_text.isdigit():
            _logger.warning("WATCHDOG_PID=%r is not a pid; watchdog disabled", pid_text)
            return None
        if int(pid_text) != pid:
            return None
    if not usec_text.isdigit() or int(usec_text) == 0:
        _logger.warning("WATCHDOG_USEC=%r is not a positive integer; watchdog disabled", usec_text)
        return None
    return int(usec_text) / 1e6


class ServiceNotifier:
    """Notifications to the service manager (systemd) over `$NOTIFY_SOCKET`.

    Made once by the service, shared by its threads: every method is thread-safe, never blocks
    (the socket is non-blocking; `watchdog()` skips its turn rather than wait for a lock) and
    never raises. A notification that cannot be sent (no listener, full queue, closed notifier)
    is counted in `lost_notifications`; the first loss of an outage is logged as a warning, the
    recovery once at info level. Without `$NOTIFY_SOCKET` every method does nothing and returns
    False.

    Args:
        environ: where to read `NOTIFY_SOCKET`, `WATCHDOG_USEC` and `WATCHDOG_PID`
            (default: `os.environ`); read once, here.
        clock: monotonic time in seconds, for the watchdog's rate limit (injectable for tests).

    Attributes:
        watchdog_interval_s: the manager's watchdog interval in seconds (`WatchdogSec=`), or
            None when this process has no watchdog (`$WATCHDOG_USEC` unset or invalid,
            `$WATCHDOG_PID` naming another process, or no socket to ping). Pings must come at
            least this often; `watchdog()` sends at most one per half interval, so a loop that
            calls it must run at least every half interval: check the frame period against it.
        lost_notifications: notifications that could not be sent so far.
    """

    def __init__(
        self,
        environ: Mapping[str, str] | None = None,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        environ = os.environ if environ is None else environ
        self._clock = clock
        self._lock = threading.Lock()
        self._socket_name = environ.get("NOTIFY_SOCKET", "")
        self._address = _socket_address(self._socket_name)
        self._socket: socket.socket | None = None
        self._losing = False
        self._watchdog_period_s = math.inf
        self._next_watchdog_s = math.inf
        self.lost_notifications = 0
        self.watchdog_interval_s: float | None = None
        if self._address is None:
            return
        try:
            self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
            self._socket.setblocking(False)
        except OSError as exc:
            _logger.warning("cannot open a socket to notify the service manager: %s", exc)
            return
        self.watchdog_interval_s = _watchdog_interval_s(environ, os.getpid())
        if self.watchdog_interval_s is not None:
            self._watchdog_period_s = self.watchdog_interval_s / 2
            self._next_watchdog_s = -math.inf

    @property
    def enabled(self) -> bool:
        """Whether notifications are being sent (a usable `$NOTIFY_SOCKET`, not closed)."""
        return self._socket is not None

    def notify(self, *assignments: str) -> bool:
        """Send `KEY=VALUE` assignments in one datagram; True when it was sent.

        Newlines inside an assignment would start a new one, so they are replaced by spaces.
        """
        message = "\n".join(a.replace("\n", " ") for a in assignments)
        return self._send(message.encode("utf-8", "backslashreplace"))

    def ready(self, status: str | None = None) -> bool:
        """`READY=1`: start-up is complete (with an optional `STATUS=` in the same datagram).

        The manager considers the service started and arms its watchdog from here on.
        """
        return self.notify(_READY, *self._status_assignment(status))

    def status(self, text: str) -> bool:
        """`STATUS=text`: one line shown by `systemctl status`."""
        return self.notify(f"STATUS={text}")

    def stopping(self, status: str | None = None) -> bool:
        """`STOPPING=1`: the service has begun to shut down (with an optional `STATUS=`)."""
        return self.notify(_STOPPING, *self._status_assignment(status))

    def extend_timeout(self, seconds: float) -> bool:
        """`EXTEND_TIMEOUT_USEC`: ask for `seconds` more to finish starting or stopping.

        Only meaningful before `READY=1` (against `TimeoutStartSec=`) or after `STOPPING=1`
        (against `TimeoutStopSec=`); the manager ignores it otherwise.
        """
        return self.notify(f"EXTEND_TIMEOUT_USEC={max(0, round(seconds * 1e6))}")

    def watchdog(self) -> bool:
        """`WATCHDOG=1`, at most once per half `watchdog_interval_s`; True when a ping went out.

        Made to be called for every measured frame from the measurement thread: between pings it
        costs a clock read and a comparison, and it never waits (if another thread is sending,
        this turn is skipped and the next call pings). Call it only from the loop whose progress
        proves the service healthy, so that a stalled loop stops the pings and the manager
        restarts the service. No-op when there is no watchdog.
        """
        now = self._clock()
        if now < self._next_watchdog_s:
            return False
        if not self._lock.acquire(blocking=False):
            return False
        try:
            if now < self._next_watchdog_s or self._socket is None:
                return False
            self._next_watchdog_s = now + self._watchdog_period_s
            return self._send_locked(_WATCHDOG_DATAGRAM)
        finally:
            self._lock.release()

    def close(self) -> None:
        """Close the socket; later notifications are dropped silently."""
        with self._lock:
            if self._socket is not None:
                self._socket.close()
                self._socket = None
            self._next_watchdog_s = math.inf

    def __enter__(self) -> ServiceNotifier:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    @staticmethod
    def _status_assignment(status: str | None) -> tuple[str, ...]:
        return () if status is None else (f"STATUS={status}",)

    def _send(self, datagram: bytes) -> bool:
        if self._socket is None:
            return False
        with self._lock:
            return self._send_locked(datagram)

    def _send_locked(self, datagram: bytes) -> bool:
        if self._socket is None:
            return False
        try:
            self._socket.sendto(datagram, self._address)
        except OSError as exc:
            self.lost_notifications += 1
            if not self._losing:
                self._losing = True
                _logger.warning(
                    "cannot notify the service manager at %s (%s); dropping notifications",
                    self._socket_name,
                    exc,
                )
            return False
        if self._losing:
            self._losing = False
            _logger.info(
                "notifying the service manager again (%d notifications lost so far)",
                self.lost_notifications,
            )
        return True
