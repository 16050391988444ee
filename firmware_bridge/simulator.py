"""The real trigger firmware running on simavr, behind a pty: for tests and benchmarks.

    elf = build_firmware(build_dir); harness = build_harness(build_dir)
    with SimulatedMcu(elf, harness, tmp_path, hold=True) as mcu:
        link = mcu.open_serial(timeout=0.05)     # opens the pty, then lets the CPU run
        link.write(packets.encode("HELLO", 0))
        ...
        edges = mcu.edges()                      # [(sim_time_ns, "PB1", level), ...]
        walls = mcu.edge_wall_times()            # [(sim_time_ns, level, wall_ns), ...]

`SimulatedMcu` starts the harness (`firmware/sim/harness.c`) as a subprocess, waits for its
pty link to appear, and exposes `.port` (a path pyserial opens like a serial device; the
baud rate is ignored). The harness paces simulated time to the wall clock (`speed=1.0`;
`speed=0` runs unthrottled), so ticks are about wall time and host-side time-outs and clock
sync behave as against hardware; timestamps that must be exact are read in simulated time,
from the edge log or the ticks in the packets, never from the host's clock.

pyserial flushes input when it opens a port, so a BOOT sent before the host opened the pty
is lost. With `hold=True` the CPU stays in reset until `release()` (or `open_serial()`,
which opens the port first and then releases) so BOOT is seen; with `hold=False` (the
default) the firmware runs at once and a host syncs with HELLO.

Encoder: `encoder_schedule` is a sequence of `EncoderSegment`s (start in simulated ns, a
signed rate in x4 counts per second, an optional duration); `set_encoder_rate()` starts a
new constant rate from the current simulated time. `drive_pin("C0", 0)` drives any other
input (the test build's watchdog hang pin).

Stopping (leaving the `with`, or `stop()`) asks the harness to quit, which flushes its log
and removes the link; it is terminated, then killed, if it does not. What this does not
model is listed in harness.c (no other peripherals, UART bytes 10 % slower than real 8N1).
"""

from __future__ import annotations

import os
import subprocess
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any


class SimulationError(RuntimeError):
    """The harness did not start, or died; the message carries the end of its log."""


@dataclass(frozen=True)
class EncoderSegment:
    """Constant encoder rate from `start_ns` (simulated time) for `duration_ns`, or until the
    next segment starts when None. `counts_per_s` counts x4 steps; negative is reverse."""

    start_ns: int
    counts_per_s: float
    duration_ns: int | None = None

    def argument(self) -> str:
        """The harness's `--encoder` value."""
        text = f"{int(self.start_ns)}:{self.counts_per_s!r}"
        return text if self.duration_ns is None else f"{text}:{int(self.duration_ns)}"


class SimulatedMcu:
    """Context manager around one harness process; see the module docstring."""

    def __init__(
        self,
        elf: Path,
        harness: Path,
        workdir: Path,
        encoder_schedule: Sequence[EncoderSegment] | None = None,
        *,
        speed: float = 1.0,
        hold: bool = False,
        start_timeout_s: float = 10.0,
    ) -> None:
        self.elf = Path(elf)
        self.harness = Path(harness)
        self.workdir = Path(workdir)
        self.encoder_schedule = tuple(encoder_schedule or ())
        self.speed = speed
        self.hold = hold
        self.start_timeout_s = start_timeout_s
        self.port = str(self.workdir / "mcu.pty")
        self.edge_log = self.workdir / "edges.log"
        self.harness_log = self.workdir / "harness.log"
        self._process: subprocess.Popen[bytes] | None = None
        self._held = hold

    def __enter__(self) -> SimulatedMcu:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.stop()

    def start(self) -> None:
        """Start the harness and wait (up to `start_timeout_s`) for its pty link."""
        self.workdir.mkdir(parents=True, exist_ok=True)
        for stale in (Path(self.port), self.edge_log):
            if stale.is_symlink() or stale.exists():
                stale.unlink()
        command = [
            str(self.harness),
            str(self.elf),
            "--pty",
            self.port,
            "--edges",
            str(self.edge_log),
            "--speed",
            repr(float(self.speed)),
        ]
        for segment in self.encoder_schedule:
            command += ["--encoder", segment.argument()]
        if self.hold:
            command.append("--hold")
        with open(self.harness_log, "wb") as log:
            self._process = subprocess.Popen(
                command, stdin=subprocess.PIPE, stdout=log, stderr=subprocess.STDOUT
            )
        deadline = time.monotonic() + self.start_timeout_s
        while not os.path.exists(self.port):
            if self._process.poll() is not None:
                raise SimulationError(
                    f"harness exited ({self._process.returncode}): {self._tail()}"
                )
            if time.monotonic() > deadline:
                self.stop()
                raise SimulationError(f"no pty link after {self.start_timeout_s} s: {self._tail()}")
            time.sleep(0.01)

    def release(self) -> None:
        """Let a held CPU run (no effect when not held or already running)."""
        if self._held:
            self._command("go")
            self._held = False

    def open_serial(self, **serial_kwargs: Any) -> Any:
        """Open `.port` with pyserial (`serial.Serial(port, **serial_kwargs)`), then release
        the CPU, so nothing the firmware sends is flushed by the open."""
        import serial

        link = serial.Serial(self.port, **serial_kwargs)
        self.release()
        return link

    def set_encoder_rate(self, counts_per_s: float) -> None:
        """From the current simulated time on, count at this constant rate (replaces the
        rest of the schedule)."""
        self._command(f"encoder {counts_per_s!r}")

    def drive_pin(self, pin: str, level: int) -> None:
        """Drive input `pin` (e.g. "C0") to `level` (0 or 1)."""
        self._command(f"pin {pin} {1 if level else 0}")

    def edges(self, pin: str = "PB1") -> list[tuple[int, str, int]]:
        """The edge log so far: (simulated ns, pin, level) of every change of `pin`."""
        return [entry for entry in self._log_entries() if entry[1] == pin]

    def edge_wall_times(self, pin: str = "PB1") -> list[tuple[int, int, int]]:
        """(simulated ns, level, wall ns) of every change of `pin`: wall ns is the host's
        CLOCK_MONOTONIC (`time.monotonic_ns`) when the harness simulated the edge, which is
        when a watcher of the wire would see it, to the harness's 20 us pacing step."""
        return [
            (ns, level, wall)
            for ns, name, level, wall in self._log_records()
            if name == pin and wall is not None
        ]

    def resets(self) -> list[int]:
        """Simulated ns of every MCU reset after the first start (the watchdog's)."""
        return [entry[0] for entry in self._log_entries() if entry[1] == "RESET"]

    def alive(self) -> bool:
        """The harness is still running."""
        return self._process is not None and self._process.poll() is None

    def log_text(self) -> str:
        """What the harness (and simavr) printed."""
        try:
            return self.harness_log.read_text(errors="replace")
        except FileNotFoundError:
            return ""

    def stop(self, timeout_s: float = 5.0) -> int | None:
        """Stop the harness; returns its exit status (None if it was never started)."""
        process = self._process
        if process is None:
            return None
        if process.poll() is None:
            try:
                self._command("quit")
                process.stdin.close()  # type: ignore[union-attr]
            except (BrokenPipeError, OSError, ValueError):
                pass
            try:
                process.wait(timeout_s)
            except subprocess.TimeoutExpired:
                process.terminate()
                try:
                    process.wait(timeout_s)
                except subprocess.TimeoutExpired:
                    process.kill()
                    process.wait()
        if os.path.islink(self.port):
            os.unlink(self.port)
        return process.returncode

    def _command(self, line: str) -> None:
        process = self._process
        if process is None or process.stdin is None or process.poll() is not None:
            raise SimulationError(f"harness not running: {self._tail()}")
        process.stdin.write(line.encode("ascii") + b"\n")
        process.stdin.flush()

    def _log_entries(self) -> list[tuple[int, str, int]]:
        return [(ns, name, level) for ns, name, level, _ in self._log_records()]

    def _log_records(self) -> list[tuple[int, str, int, int | None]]:
        """(simulated ns, name, level, wall ns or None) of every whole line of the log (a
        line still being written is left for the next call)."""
        try:
            text = self.edge_log.read_text()
        except FileNotFoundError:
            return []
        records = []
        for line in text.split("\n")[:-1]:
            parts = line.split()
            if len(parts) in (3, 4):
                wall = int(parts[3]) if len(parts) == 4 else None
                records.append((int(parts[0]), parts[1], int(parts[2]), wall))
        return records

    def _tail(self, lines: int = 8) -> str:
        return " | ".join(self.log_text().strip().splitlines()[-lines:])
