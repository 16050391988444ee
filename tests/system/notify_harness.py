"""A stand-in for systemd's notification side: run a service command under a fake NOTIFY_SOCKET.

`NotifySocket` is the receiving end systemd would hold: an AF_UNIX SOCK_DGRAM socket with
SO_PASSCRED, so every datagram arrives with the sender's pid. `NotifyHarness` starts a command
the way a `Type=notify` unit would (`NOTIFY_SOCKET`, `WATCHDOG_USEC`, `WATCHDOG_PID` = the
child's own pid), collects every notification on a thread with its receive time, offers waits
on them, and stops the child as systemd does (SIGTERM to its process group, SIGKILL after a
timeout). It always cleans up: use it as a context manager.

    with NotifyHarness([extensometer, "serve", "--config", path], watchdog_usec=2_000_000) as run:
        run.wait_for("READY=1", timeout=120)
        run.wait_for(lambda n: n.value("STATUS", "").startswith("measuring"), timeout=30)
        assert len(run.watchdog_times()) >= 2
        assert run.terminate() == 0
        run.wait_for("STOPPING=1", timeout=1)
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import struct
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

__all__ = ["HarnessError", "Notification", "NotifyHarness", "NotifySocket"]

NOTIFY_VARIABLES = ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID")

_UCRED = struct.Struct("iII")
_MAX_DATAGRAM = 65536
_POLL_S = 0.05


class HarnessError(AssertionError):
    """A wait that failed: timed out, or the child exited first. The message says what was seen."""


@dataclass(frozen=True)
class Notification:
    """One datagram received on the notify socket.

    Attributes:
        text: the datagram as text (newline-separated `KEY=VALUE` assignments).
        pid: the sender's pid from its socket credentials (None if the kernel sent none).
        received_s: `time.monotonic()` when the datagram was read.
    """

    text: str
    pid: int | None
    received_s: float

    @property
    def assignments(self) -> tuple[str, ...]:
        """The non-empty lines of the datagram."""
        return tuple(line for line in self.text.split("\n") if line)

    def value(self, key: str, default: str | None = None) -> str | None:
        """The value assigned to `key` (the last one if repeated), else `default`."""
        found = default
        for line in self.assignments:
            name, sep, value = line.partition("=")
            if sep and name == key:
                found = value
        return found

    def matches(self, assignment: str) -> bool:
        """Whether a line equals `assignment` ("READY=1"); "KEY=" matches any value of KEY."""
        if assignment.endswith("="):
            return any(line.startswith(assignment) for line in self.assignments)
        return assignment in self.assignments


Match = str | Callable[[Notification], bool]
"""An assignment as `Notification.matches` takes it, or a predicate on a notification."""


def _predicate(match: Match) -> Callable[[Notification], bool]:
    if isinstance(match, str):
        return lambda notification: notification.matches(match)
    return match


class NotifySocket:
    """The receiving end of sd_notify: a bound AF_UNIX datagram socket with SO_PASSCRED.

    Args:
        path: file system path to bind (AF_UNIX paths are limited to 107 bytes), removed by
            `close()`; ignored when `abstract` is true. Default: `notify` in a new temporary
            directory, removed by `close()`.
        abstract: bind a unique name in the abstract namespace instead of a path.

    Attributes:
        name: the value for `NOTIFY_SOCKET` (the path, or "@" and the abstract name).
    """

    def __init__(self, path: str | Path | None = None, *, abstract: bool = False) -> None:
        self._directory: str | None = None
        self._bound_path: Path | None = None
        self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        try:
            self._socket.setsockopt(socket.SOL_SOCKET, socket.SO_PASSCRED, 1)
            if abstract:
                self.name = f"@extensometer-notify-test-{os.getpid()}-{id(self):x}"
                self._socket.bind(b"\0" + self.name[1:].encode())
            else:
                if path is None:
                    self._directory = tempfile.mkdtemp(prefix="notify-")
                    path = Path(self._directory) / "notify"
                self.name = str(path)
                self._socket.bind(self.name)
                self._bound_path = Path(path)
        except BaseException:
            self.close()
            raise

    def receive(self, timeout: float) -> Notification | None:
        """The next datagram, or None if none arrives within `timeout` seconds."""
        self._socket.settimeout(timeout)
        try:
            data, ancillary, _flags, _address = self._socket.recvmsg(
                _MAX_DATAGRAM, socket.CMSG_SPACE(_UCRED.size)
            )
        except TimeoutError:
            return None
        received_s = time.monotonic()
        pid = None
        for level, kind, payload in ancillary:
            if level == socket.SOL_SOCKET and kind == socket.SCM_CREDENTIALS:
                pid = _UCRED.unpack(payload[: _UCRED.size])[0]
        return Notification(data.decode("utf-8", "replace"), pid, received_s)

    def close(self) -> None:
        """Close the socket and remove its file (and the temporary directory it made, if any)."""
        self._socket.close()
        if self._bound_path is not None:
            self._bound_path.unlink(missing_ok=True)
            self._bound_path = None
        if self._directory is not None:
            shutil.rmtree(self._directory, ignore_errors=True)
            self._directory = None

    def __enter__(self) -> NotifySocket:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


class NotifyHarness:
    """Runs `command` as systemd runs a `Type=notify` service, and records what it notifies.

    Args:
        command: the program and its arguments.
        watchdog_usec: `WATCHDOG_USEC` for the child (None: no watchdog variables at all).
        watchdog_pid: `WATCHDOG_PID`: "child" (the child's own pid, as systemd sets it), None
            (left unset) or a pid (a foreign one makes the watchdog not the child's).
        env: extra environment for the child, over this process's environment (from which any
            notification variables are removed first).
        cwd: working directory of the child.
        abstract_socket: use an abstract notify socket ("@name") instead of a path.

    The child runs in its own session and process group. As under systemd's default
    KillMode=control-group, the whole group is signalled: `terminate()` sends SIGTERM, then
    SIGKILL after a timeout, and once the child has exited whatever it left running is killed,
    so no grandchild outlives a test. Its stdout and stderr go to files, readable at any time
    through `stdout` and `stderr`.
    """

    def __init__(
        self,
        command: Sequence[str],
        *,
        watchdog_usec: int | None = None,
        watchdog_pid: Literal["child"] | int | None = "child",
        env: Mapping[str, str] | None = None,
        cwd: str | Path | None = None,
        abstract_socket: bool = False,
    ) -> None:
        self.command = list(command)
        self._watchdog_usec = watchdog_usec
        self._watchdog_pid = watchdog_pid
        self._extra_env = dict(env or {})
        self._cwd = cwd
        self._abstract_socket = abstract_socket
        self._directory: Path | None = None
        self._socket: NotifySocket | None = None
        self._process: subprocess.Popen | None = None
        self._collector: threading.Thread | None = None
        self._stop = threading.Event()
        self._changed = threading.Condition()
        self._messages: list[Notification] = []
        self._empty_polls = 0
        self._started_s = time.monotonic()

    def start(self) -> NotifyHarness:
        """Bind the socket, start the collector thread and the child; returns self."""
        if self._directory is not None:
            raise RuntimeError("the harness has already been started")
        self._directory = Path(tempfile.mkdtemp(prefix="notify-harness-"))
        try:
            self._socket = NotifySocket(self._directory / "notify", abstract=self._abstract_socket)
            self._collector = threading.Thread(
                target=self._collect, name="notify-collector", daemon=True
            )
            self._collector.start()
            self._process = self._spawn()
        except BaseException:
            self.close()
            raise
        return self

    @property
    def socket_name(self) -> str:
        """The `NOTIFY_SOCKET` value given to the child."""
        if self._socket is None:
            raise RuntimeError("the harness has not been started")
        return self._socket.name

    @property
    def pid(self) -> int:
        """The child's pid (also the pid its notifications must come from)."""
        return self._require_process().pid

    @property
    def returncode(self) -> int | None:
        """The child's exit status (negative: killed by that signal); None while it runs."""
        return self._reap_if_exited()

    @property
    def stdout(self) -> str:
        """What the child has written to stdout so far."""
        return self._read_output("stdout")

    @property
    def stderr(self) -> str:
        """What the child has written to stderr so far."""
        return self._read_output("stderr")

    @property
    def messages(self) -> list[Notification]:
        """Every notification received so far, in order of arrival (a copy)."""
        with self._changed:
            return list(self._messages)

    def watchdog_times(self) -> list[float]:
        """Receive times (`time.monotonic()`) of every `WATCHDOG=1` so far."""
        return [n.received_s for n in self.messages if n.matches("WATCHDOG=1")]

    def wait_for(self, match: Match, timeout: float, *, since: int = 0) -> Notification:
        """The first notification from index `since` on that matches, waiting up to `timeout` s.

        `match` is an assignment ("READY=1"; "STATUS=" for any status) or a predicate on a
        `Notification`. Raises HarnessError on timeout, or as soon as the child has exited
        without sending it (what it sent before exiting is still read).
        """
        accept = _predicate(match)
        deadline = time.monotonic() + timeout
        exited_at_poll: int | None = None
        with self._changed:
            while True:
                for notification in self._messages[since:]:
                    if accept(notification):
                        return notification
                # An empty poll that ended after the exit was seen proves the queue was read;
                # one poll may have ended before it and still be uncounted, hence the + 1.
                if exited_at_poll is not None and self._empty_polls > exited_at_poll + 1:
                    reason = f"the child exited with status {self.returncode}"
                    break
                if exited_at_poll is None and self.returncode is not None:
                    exited_at_poll = self._empty_polls
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    reason = f"timed out after {timeout} s"
                    break
                self._changed.wait(min(remaining, _POLL_S))
        raise HarnessError(f"no notification matching {match!r}: {reason}\n{self.describe()}")

    def wait_for_silence(
        self, match: Match = "WATCHDOG=1", *, quiet_s: float, timeout: float
    ) -> float | None:
        """Wait until no matching notification has arrived for `quiet_s` seconds.

        Returns the receive time of the last matching notification (None if none came).
        Raises HarnessError if they keep coming for `timeout` seconds.
        """
        accept = _predicate(match)
        deadline = time.monotonic() + timeout
        while True:
            times = [n.received_s for n in self.messages if accept(n)]
            last = times[-1] if times else None
            now = time.monotonic()
            if now - (self._started_s if last is None else last) >= quiet_s:
                return last
            if now >= deadline:
                raise HarnessError(
                    f"notifications matching {match!r} did not stop for {quiet_s} s within "
                    f"{timeout} s\n{self.describe()}"
                )
            time.sleep(min(_POLL_S, deadline - now))

    def wait(self, timeout: float) -> int:
        """Wait up to `timeout` s for the child to exit on its own; its exit status.

        Raises HarnessError if it is still running (it is left running).
        """
        deadline = time.monotonic() + timeout
        while (status := self._reap_if_exited()) is None:
            if time.monotonic() >= deadline:
                raise HarnessError(f"the child did not exit within {timeout} s\n{self.describe()}")
            time.sleep(0.01)
        return status

    def terminate(self, timeout: float = 10.0) -> int:
        """SIGTERM to the child's process group, SIGKILL after `timeout` s; its exit status."""
        process = self._require_process()
        if self._reap_if_exited() is None:
            self._signal_group(signal.SIGTERM)
            try:
                return self.wait(timeout)
            except HarnessError:
                self._signal_group(signal.SIGKILL)
                process.wait()
        return self._reap_if_exited()

    def close(self) -> None:
        """Kill the child's process group if anything of it still runs, and release everything."""
        if self._process is not None and self._process.returncode is None:
            self._kill_group()
            self._process.wait()
        self._stop.set()
        if self._collector is not None:
            self._collector.join()
        if self._socket is not None:
            self._socket.close()
        if self._directory is not None:
            shutil.rmtree(self._directory, ignore_errors=True)

    def describe(self) -> str:
        """What was seen: notifications, exit status and the tail of stderr (for failures)."""
        status = self._process.returncode if self._process is not None else None
        lines = [f"command: {self.command}", f"returncode: {status}", "notifications:"]
        for notification in self.messages:
            at = notification.received_s - self._started_s
            lines.append(f"  +{at:7.3f} s from pid {notification.pid}: {notification.text!r}")
        lines += ["stderr (last 4000 characters):", self.stderr[-4000:]]
        return "\n".join(lines)

    def __enter__(self) -> NotifyHarness:
        return self.start()

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def _spawn(self) -> subprocess.Popen:
        assert self._socket is not None and self._directory is not None
        env = {k: v for k, v in os.environ.items() if k not in NOTIFY_VARIABLES}
        env.update(self._extra_env)
        env["NOTIFY_SOCKET"] = self._socket.name
        command = self.command
        if self._watchdog_usec is not None:
            env["WATCHDOG_USEC"] = str(self._watchdog_usec)
            if self._watchdog_pid == "child":
                # The pid is known only after fork: the shell exports its own pid and `exec`
                # keeps it for the command, as systemd sets WATCHDOG_PID between fork and exec.
                command = [
                    "/bin/sh",
                    "-c",
                    'WATCHDOG_PID=$$; export WATCHDOG_PID; exec "$@"',
                    "notify-harness",
                    *command,
                ]
            elif self._watchdog_pid is not None:
                env["WATCHDOG_PID"] = str(self._watchdog_pid)
        self._started_s = time.monotonic()
        with (
            open(self._directory / "stdout", "wb") as stdout,
            open(self._directory / "stderr", "wb") as stderr,
        ):
            return subprocess.Popen(
                command,
                env=env,
                cwd=self._cwd,
                stdin=subprocess.DEVNULL,
                stdout=stdout,
                stderr=stderr,
                start_new_session=True,
            )

    def _collect(self) -> None:
        assert self._socket is not None
        while not self._stop.is_set():
            try:
                notification = self._socket.receive(_POLL_S)
            except OSError:
                return
            with self._changed:
                if notification is None:
                    self._empty_polls += 1
                else:
                    self._messages.append(notification)
                self._changed.notify_all()

    def _reap_if_exited(self) -> int | None:
        """The exit status once the child has exited, after killing what it left in its group.

        The child is looked at without reaping it first (WNOWAIT): while it is an unreaped
        zombie its pid, and so the process group id, cannot be reused, so the SIGKILL cannot
        reach anyone else's process.
        """
        process = self._require_process()
        if process.returncode is not None:
            return process.returncode
        try:
            exited = os.waitid(os.P_PID, process.pid, os.WEXITED | os.WNOHANG | os.WNOWAIT)
        except ChildProcessError:
            exited = True
        if exited is None:
            return None
        self._kill_group()
        return process.wait()

    def _kill_group(self, timeout: float = 10.0) -> None:
        """SIGKILL the child's process group and wait until none of it runs any more.

        A killed process may take a moment to die; zombies (which a container's init may
        never reap) do not count as running.
        """
        assert self._process is not None
        self._signal_group(signal.SIGKILL)
        deadline = time.monotonic() + timeout
        while _group_members_running(self._process.pid) and time.monotonic() < deadline:
            self._signal_group(signal.SIGKILL)
            time.sleep(0.005)

    def _signal_group(self, signum: int) -> None:
        assert self._process is not None
        try:
            os.killpg(self._process.pid, signum)
        except (ProcessLookupError, PermissionError):
            pass

    def _read_output(self, name: str) -> str:
        if self._directory is None:
            return ""
        try:
            return (self._directory / name).read_text(errors="replace")
        except FileNotFoundError:
            return ""

    def _require_process(self) -> subprocess.Popen:
        if self._process is None:
            raise RuntimeError("the harness has not been started")
        return self._process


def _group_members_running(group: int) -> bool:
    """Whether a process of process group `group` other than a zombie still exists."""
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rpartition(")")[2].split()
        except OSError:
            continue
        if len(fields) > 2 and int(fields[2]) == group and fields[0] not in ("Z", "X"):
            return True
    return False
