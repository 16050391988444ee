"""Real machine-controller peers for the Modbus machine client's tests: pymodbus servers on
loopback.

* `ControllerServer` and `MachineRegisters` come from `appliance.sim.controller_server`: a
  pymodbus server on an asyncio thread, TCP on 127.0.0.1 or RTU on one end of a socat pty
  pair, answering from a register source, which may stop serving and serve again.
* `SimulatedController`: `MachineRegisters` for a live machine: `TinyMachine` (crosshead moving at a
  set speed, force from a stiffness, encoder counts) behind a `RegisterMap` (the generic
  preset by default). It honours the map's command coils or command registers and the speed
  set point, logging every command in the order it arrived.
* `RecordedController`: the source that replays a recorded register table
  (tests/system/data/controller_registers.csv: time and raw register values per row), held
  at one row or played at the recorded pace. It refuses writes (exception 1).
* `SilentTcpPeer`: accepts TCP connections and never answers (a controller that hangs).
* `GarbageRtuPeer`: answers every request on a pty with bytes that are no valid RTU message.

`TinyMachine` is a few lines on purpose: the tests compare what the client reads with it
(bracketed by its state just before and just after a read, so no timing decides a result).
What the peers do not model: controller scan cycles, filtering, interlocks, a shared RS-485
line, inter-message timing on the wire (a pty ignores baud rate).
"""

from __future__ import annotations

import bisect
import csv
import math
import socket
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path

import serial
from pymodbus.constants import ExcCodes

from appliance.sim.controller_server import MachineRegisters
from hal.machine.register_map import BIT_TABLES, GENERIC_CONTROLLER, RegisterMap

DATA = Path(__file__).parent / "data"
RECORDED_TABLE = DATA / "controller_registers.csv"
RECORDED_MAP = DATA / "recorded_controller.toml"


class TinyMachine:
    """A crosshead at a constant speed between commands, and a specimen as a linear spring.

    Position in mm from the start, speed in mm/min (+ = opening), force = stiffness *
    position, encoder = round(position * counts_per_mm). `return_to_start` drives towards 0 at
    |speed| and stops there. Times are `clock()` seconds (time.monotonic by default).
    """

    def __init__(
        self,
        *,
        position_mm: float = 10.0,
        stiffness_n_per_mm: float = 1500.0,
        counts_per_mm: float = 1000.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.stiffness_n_per_mm = stiffness_n_per_mm
        self.counts_per_mm = counts_per_mm
        self.clock = clock
        self._lock = threading.Lock()
        self._segment = (clock(), position_mm, 0.0, None)
        """(since_s, position_mm, speed_mm_min, stop_at_mm or None)."""

    def position_at(self, t_s: float) -> float:
        return self._position(self._segment, t_s)

    def state_at(self, t_s: float) -> dict[str, float | bool]:
        """The quantities of a register map's reads at time t_s."""
        segment = self._segment
        position = self._position(segment, t_s)
        since, _, speed, stop_at = segment
        moving = speed != 0.0 and not (stop_at is not None and position == stop_at)
        return {
            "crosshead_mm": position,
            "speed_mm_min": speed if moving else 0.0,
            "force_n": self.stiffness_n_per_mm * position,
            "running": moving,
            "encoder_counts": round(position * self.counts_per_mm),
        }

    def state(self) -> dict[str, float | bool]:
        """The quantities of a register map's reads now."""
        return self.state_at(self.clock())

    def start(self, speed_mm_min: float) -> None:
        self._change(speed_mm_min, None)

    def stop(self) -> None:
        self._change(0.0, None)

    def return_to_start(self, speed_mm_min: float) -> None:
        now = self.clock()
        toward = -abs(speed_mm_min) if self.position_at(now) > 0 else abs(speed_mm_min)
        self._change(toward, 0.0)

    def _change(self, speed_mm_min: float, stop_at: float | None) -> None:
        with self._lock:
            now = self.clock()
            self._segment = (now, self._position(self._segment, now), speed_mm_min, stop_at)

    @staticmethod
    def _position(segment: tuple[float, float, float, float | None], t_s: float) -> float:
        since, position, speed, stop_at = segment
        moved = position + speed / 60.0 * max(t_s - since, 0.0)
        if stop_at is not None and (moved - stop_at) * (position - stop_at) <= 0:
            return stop_at
        return moved


class SimulatedController(MachineRegisters):
    """A live machine controller: `TinyMachine` served through `register_map`.

    Args:
        register_map: the layout it serves (the generic preset by default).
        machine: the machine (a fresh `TinyMachine` by default).
    """

    def __init__(
        self, register_map: RegisterMap = GENERIC_CONTROLLER, machine: TinyMachine | None = None
    ) -> None:
        super().__init__(register_map, machine if machine is not None else TinyMachine())


class RecordedController:
    """Replays a recorded register table: rows of time and raw register values.

    The file is CSV with '#' comment lines first, then a header `t_s,TABLE:ADDRESS,...`
    (e.g. `holding:100`, `discrete:5`) and one row per sample: the time in s from the start
    of the recording and each cell's raw value (a register as an unsigned 16-bit integer, a
    bit as 0 or 1).

    Args:
        path: the CSV file.
    """

    def __init__(self, path: Path = RECORDED_TABLE) -> None:
        lines = [line for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]
        rows = list(csv.reader(line for line in lines if not line.startswith("#")))
        header, body = rows[0], rows[1:]
        if header[0] != "t_s":
            raise ValueError(f"{path}: the first column must be t_s, got {header[0]!r}")
        self.cells: list[tuple[str, int]] = []
        for name in header[1:]:
            table, _, address = name.partition(":")
            self.cells.append((table, int(address)))
        self.times_s = [float(row[0]) for row in body]
        self.rows: list[dict[tuple[str, int], int]] = [
            {cell: int(text) for cell, text in zip(self.cells, row[1:], strict=True)}
            for row in body
        ]
        self._held: int | None = 0
        self._playing_since = time.monotonic()
        self.writes = 0

    def hold(self, index: int) -> None:
        """Serve row `index` until told otherwise."""
        if not 0 <= index < len(self.rows):
            raise IndexError(f"row {index} of {len(self.rows)}")
        self._held = index

    def play(self) -> None:
        """Serve the rows at the recorded pace from now, from the first, looping."""
        self._playing_since = time.monotonic()
        self._held = None

    def row_now(self) -> int:
        """The row served now."""
        if self._held is not None:
            return self._held
        length = self.times_s[-1] - self.times_s[0]
        elapsed = (time.monotonic() - self._playing_since) % max(length, 1e-9)
        return max(bisect.bisect_right(self.times_s, self.times_s[0] + elapsed) - 1, 0)

    def image(self, table: str) -> Mapping[int, int | bool]:
        row = self.rows[self.row_now()]
        if table in BIT_TABLES:
            return {address: bool(v) for (t, address), v in row.items() if t == table}
        return {address: v for (t, address), v in row.items() if t == table}

    def write(self, table: str, address: int, values: list[int] | list[bool]) -> int | None:
        self.writes += 1
        return int(ExcCodes.ILLEGAL_FUNCTION)


class SilentTcpPeer:
    """Listens on 127.0.0.1:port, accepts every connection and never answers."""

    def __init__(self, port: int) -> None:
        self.port = port
        self._listener = socket.create_server(("127.0.0.1", port))
        self._listener.settimeout(0.1)
        self._connections: list[socket.socket] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._accept, name="silent-peer", daemon=True)
        self._thread.start()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                connection, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            self._connections.append(connection)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self._listener.close()
        for connection in self._connections:
            connection.close()

    def __enter__(self) -> SilentTcpPeer:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


class GarbageRtuPeer:
    """On one end of a pty pair: answers each request with bytes that fail the RTU CRC.

    The answer starts like a reply of unit 1 to a read (address, function, byte count), so
    the framer has to take it apart before it rejects it.
    """

    def __init__(self, device: str) -> None:
        self._port = serial.Serial(device, baudrate=115200, timeout=0.05)
        self.answers = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="garbage-peer", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                request = self._port.read(64)
            except (OSError, serial.SerialException):
                return
            if not request:
                continue
            function = request[1] if len(request) > 1 else 4
            garbage = bytes([1, function, 18]) + bytes(range(18)) + b"\x00\x00"
            self._port.write(garbage)
            self.answers += 1

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self._port.close()

    def __enter__(self) -> GarbageRtuPeer:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


def bracketed(
    read: Callable[[], object], machine: TinyMachine
) -> tuple[object, dict[str, float | bool], dict[str, float | bool]]:
    """`read()` with the machine's state just before and just after it."""
    before = machine.state_at(machine.clock())
    result = read()
    after = machine.state_at(machine.clock())
    return result, before, after


def within(value: float, low: float, high: float, *, rel: float = 1e-6) -> bool:
    """low <= value <= high, allowing float32 rounding (`rel` of the larger magnitude)."""
    low, high = min(low, high), max(low, high)
    slack = rel * max(abs(low), abs(high), 1.0)
    return low - slack <= value <= high + slack and math.isfinite(value)
