"""The Modbus strain server: the machine controller reads strain from it and writes commands.

`StrainRegisterServer` serves the register map of `appliance.live.modbus_map` over Modbus TCP, over
Modbus RTU on a serial device, or both at once (one register image), as `[modbus]` in the
configuration says. The servers run on an asyncio loop in a background thread; the
measurement never waits for the network:

* `publish(sample, facts)` is called on the measurement thread right after a frame's strain
  is computed. It encodes the sample (tens of microseconds) and swaps it into the register
  image under a lock that a reader only holds to copy registers out, so a request always
  sees one whole update: a float is never torn, and strain, status and frame counter read
  in one request belong to the same frame.
* Before the first sample every float of the measurement block reads NaN and `status` has no
  data-valid bit.
* `set_run_state(state)` updates the state bits and the run-state code; `tick()` moves the
  heartbeat while no frames come, so the controller sees the appliance alive;
  `set_camera_lost(lost)` clears data-valid and sets `camera lost` while the camera is away
  (no samples come then, so the latest one must not stay flagged valid).
* `set_exit_status(status, results)` says how the last test ended and writes its results
  (`appliance.live.result_registers`) in the same update, `results_valid` set and
  `results_counter` moved; `set_exit_status(None)` when the next test begins clears both, so
  the result registers never show another test's results than the one `exit_status` describes.
* A client's command write calls `on_command(name, value)` on the server's thread:
  ("start" | "stop" | "zero", None) or ("gauge_length", mm). It returns whether the command
  was accepted in the current run state (`command_result`, `command_counter`); it must return
  quickly, since no other request is served meanwhile.

Write access: with `[modbus] allow_write_from` empty anyone may write; otherwise only TCP
clients at the listed IP addresses, every other write (RTU included: a serial line carries
no client address) gets exception 1 (illegal function). Reads are open to every client.

Unit ids: over RTU the server answers only `unit_id` and stays silent for the other ids (and
for broadcasts), as a device on a shared line must; over TCP it answers `unit_id` and also 0
and 255, the ids clients use for a device they reach directly. Requests to other ids get no
answer.

Functions: those of `modbus_map.SERVED_FUNCTION_CODES` (3, 4, 6, 16, 22, 23); any other
function gets exception 1 before its request is looked at, over TCP and RTU alike. A request
of a served function whose size or quantity Modbus does not allow gets exception 3.

Modbus TCP runs on `modbus_connections.ModbusTcpListener` (asyncio streams): pipelined
requests are all answered in order, at most `[modbus] max_connections` connections are open
(one more drops the oldest idle one), a connection without a complete request for `[modbus]
idle_timeout_s` is closed, a client that does not read its answers is no longer read and then
closed, and every connection error goes to a `ThrottledLog` (one line per kind and 10 s, with
a count); so does any error of the asyncio loop (a failed accept when file descriptors run
out), never as a traceback. The listener hands each request's PDU to this server, which
decodes it with pymodbus' `DecodePDU` and runs it against a pymodbus `SimCore` of the map.
Modbus RTU is pymodbus' serial server.

The datastore is pymodbus 3.16's SimDevice/SimData API: the map's entries become SimData
blocks (read-only where the map says so, so pymodbus itself answers exception 2 to a write
of a read-only register or an address outside the map), and the device's `action` callback
copies this module's image into pymodbus' registers on every read and checks and executes
every write. pymodbus internals this relies on (pinned by tests/system/test_modbus_server.py):

* `SimCore(devices)` as the context of a request PDU's coroutine `datastore_update(context,
  device_id)`, which awaits the action inside the same task (so the TCP client's IP, a
  context variable, is seen by the write check);
* `ServerRequestHandler(owner, trace_packet, trace_pdu, trace_connect)` is what the serial
  server's `callback_new_connection` returns, and its coroutine `handle_request()` serves
  `self.last_pdu` (with its `dev_id`) to the end; a subclass wraps it to drop requests for
  other unit ids and to refuse functions the map does not serve;
* the SimDevice action's arguments `(function_code, start_address, address, count,
  current_registers, set_values)`, `set_values` None for reads, and pymodbus answering a read
  from `current_registers` right after the action returns (no await in between);
* `serve_forever(background=True)` of the serial server returning once the device is open
  and raising RuntimeError when it cannot (it logs the cause and swallows it, so the device
  is opened once first, to name the cause in the error).

What it does not do: it is not a Modbus client, it does not decide what a command does (the
`on_command` callback does), it keeps no history (only the latest sample), and it has no TLS
or authentication beyond the IP allow-list.
"""

from __future__ import annotations

import asyncio
import contextvars
import ipaddress
import logging
import math
import os
import socket
import threading
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import TimeoutError as FutureTimeoutError
from typing import TYPE_CHECKING, Any

from pymodbus.constants import ExcCodes
from pymodbus.pdu import DecodePDU, ExceptionResponse
from pymodbus.server import ModbusSerialServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.simulator import DataType, SimData, SimDevice
from pymodbus.simulator.simcore import SimCore

from appliance.config import ModbusConfig, parse_address
from appliance.errors import InputError
from appliance.live import modbus_map
from appliance.live.modbus_connections import ModbusTcpListener
from appliance.live.modbus_map import (
    BY_NAME,
    COMMANDS,
    EXIT_STATUS_CODES,
    GAUGE_LENGTH_COMMAND,
    MAP_SIZE,
    MEASUREMENT_BLOCK,
    REGISTER_MAP,
    RESULT_VALUES,
    RUN_STATE_CODES,
    SERVED_FUNCTION_CODES,
    WIDTH_BLOCK,
    CommandResult,
    Register,
    RegisterType,
    StatusBit,
)
from appliance.live.result_registers import CLEARED
from appliance.live.throttled_log import ThrottledLog
from appliance.measure.gauges import POISSON_MIN_AXIAL_STRAIN
from appliance.run.state import ExitStatus, RunState

if TYPE_CHECKING:
    from appliance.measure.frame_measurer import StrainSample
    from appliance.run.outputs import RunFacts

_log = logging.getLogger(__name__)

CommandHandler = Callable[[str, float | None], bool]
"""on_command(name, value) -> accepted: name "start", "stop", "zero" (value None) or
"gauge_length" (value in mm)."""

TCP_DIRECT_UNIT_IDS = (0, 255)
"""Unit ids a TCP client uses for a device it reaches directly; answered besides `unit_id`."""

_client_ip: contextvars.ContextVar[str | None] = contextvars.ContextVar(
    "modbus_client_ip", default=None
)
"""IP address of the TCP client whose request is being served (None over RTU)."""

_SAMPLE_BLOCK = tuple(
    r for r in MEASUREMENT_BLOCK if r.name not in ("status", "heartbeat", "run_state")
)
_VALID_STATES = (RunState.RUNNING, RunState.STOPPING)


def _width_values(sample: StrainSample) -> dict[str, float | int]:
    """The width registers' values of a sample (NaN and 0 without a width)."""
    width = sample.width
    values: dict[str, float | int] = {
        f"width_{k}_mm": math.nan for k in range(1, modbus_map.WIDTH_STATIONS_SERVED + 1)
    }
    if width is None:
        return {
            **values,
            "width_mm": math.nan,
            "width_transverse_strain": math.nan,
            "width_stations_seen": 0,
            "width_stations": 0,
            "width_poisson_ratio": math.nan,
        }
    axial = sample.reading.engineering_strain
    transverse = width.transverse_strain
    poisson = -transverse / axial if abs(axial) >= POISSON_MIN_AXIAL_STRAIN else math.nan
    for k, value in enumerate(width.widths_mm[: modbus_map.WIDTH_STATIONS_SERVED], start=1):
        values[f"width_{k}_mm"] = value
    return {
        **values,
        "width_mm": width.mean_width_mm,
        "width_transverse_strain": transverse,
        "width_stations_seen": width.stations_seen,
        "width_stations": len(width.widths_mm),
        "width_poisson_ratio": poisson,
    }


class ServerStartError(InputError):
    """The server cannot serve what `[modbus]` says; one line naming the key and the cause.

    An `InputError`, so the command line reports it as one line like any bad setting.
    """


class _RtuRequestHandler(ServerRequestHandler):
    """pymodbus' handler of the serial line, told the unit ids and the functions to answer."""

    async def handle_request(self) -> None:
        pdu = self.last_pdu
        if pdu is None or pdu.dev_id not in self.server.unit_ids:
            return
        if pdu.function_code not in SERVED_FUNCTION_CODES:
            refused = ExceptionResponse(
                pdu.function_code,
                ExcCodes.ILLEGAL_FUNCTION,
                device_id=pdu.dev_id,
                transaction=pdu.transaction_id,
            )
            self.server_send(refused, self.last_addr)
            return
        await super().handle_request()


class _SerialServer(ModbusSerialServer):
    def __init__(self, device: SimDevice, unit_ids: Sequence[int], **serial: Any):
        super().__init__(device, **serial)
        self.unit_ids = frozenset(unit_ids)

    def callback_new_connection(self) -> _RtuRequestHandler:
        return _RtuRequestHandler(self, self.trace_packet, self.trace_pdu, self.trace_connect)


def _normalised_ip(text: str) -> str:
    """An IP address in one spelling (an IPv4-mapped IPv6 address as IPv4)."""
    address = ipaddress.ip_address(text)
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        address = address.ipv4_mapped
    return str(address)


class StrainRegisterServer:
    """Serves the strain registers over Modbus TCP and/or RTU, as `[modbus]` configures.

    Args:
        config: the `[modbus]` table. `tcp` = "HOST:PORT" to listen on (empty = no TCP),
            `rtu_device` = serial device for RTU (empty = no RTU); with neither, `start`
            serves nothing and the image is still kept (publishing costs the same).
            `max_connections` and `idle_timeout_s` bound the TCP connections.
        on_command: called on the server's thread for each command a client writes:
            ("start" | "stop" | "zero", None) or ("gauge_length", mm); returns whether it
            was accepted in the current run state. An exception it raises is answered with
            exception 4 and logged.
        gauge_length_setpoint_mm: the set point the gauge length register reads before a
            client writes one (NaN = the specimen's default).

    Raises:
        InputError: an address of `allow_write_from` is not an IP address, or `tcp` is not
            HOST:PORT.
    """

    def __init__(
        self,
        config: ModbusConfig,
        on_command: CommandHandler,
        *,
        gauge_length_setpoint_mm: float = math.nan,
    ) -> None:
        self.config = config
        self.on_command = on_command
        self._word_order = "little" if config.word_order == "little" else "big"
        try:
            self._allowed = frozenset(_normalised_ip(ip) for ip in config.allow_write_from)
        except ValueError as exc:
            raise InputError(f"[modbus] allow_write_from: {exc}") from None
        self._tcp = parse_address(config.tcp, "[modbus] tcp") if config.tcp else None
        self._lock = threading.Lock()
        self._image = [0] * MAP_SIZE
        self._state = RunState.IDLE
        self._sample_bits = StatusBit(0)
        self._sample_valid = False
        self._camera_lost = False
        self._frames_dropped = 0
        self._heartbeat = 0
        self._command_counter = 0
        self._results_counter = 0
        self._entries = [modbus_map.register_at(address) for address in range(MAP_SIZE)]
        self._status_at = BY_NAME["status"].address
        self._heartbeat_at = BY_NAME["heartbeat"].address
        self._run_state_at = BY_NAME["run_state"].address
        self._exit_status_at = BY_NAME["exit_status"].address
        self._results_at = RESULT_VALUES[0].address
        self._sample_parts = self._contiguous_parts(_SAMPLE_BLOCK)
        self._width_parts = self._contiguous_parts(WIDTH_BLOCK)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._servers: list[_SerialServer] = []
        self._listener: ModbusTcpListener | None = None
        self._tcp_unit_ids = frozenset((config.unit_id, *TCP_DIRECT_UNIT_IDS))
        self._tcp_context: SimCore | None = None
        self._decoder = DecodePDU(True)
        self._log = ThrottledLog(_log)
        self._closed = False
        for register in (*MEASUREMENT_BLOCK, *WIDTH_BLOCK, *RESULT_VALUES):
            if register.data_type is RegisterType.FLOAT32:
                self._put(register, math.nan)
        self._put(BY_NAME["gauge_length_setpoint_mm"], gauge_length_setpoint_mm)
        self._write_state_registers()

    @property
    def enabled(self) -> bool:
        """Whether the configuration asks for a TCP or an RTU server."""
        return bool(self._tcp or self.config.rtu_device)

    def start(self, timeout_s: float = 5.0) -> None:
        """Bind the TCP address and open the serial device, then serve in the background.

        With neither `tcp` nor `rtu_device` configured it returns at once and serves nothing.

        Raises:
            ServerStartError: one line naming the key and the cause, e.g.
                "[modbus] tcp 127.0.0.1:5020: address already in use"; nothing is left
                running.
            RuntimeError: started twice or after `close`.
        """
        if self._thread is not None or self._closed:
            raise RuntimeError("StrainRegisterServer: start() once, before close()")
        if not self.enabled:
            return
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(
            target=self._run_loop, name="modbus-server", args=(self._loop,), daemon=True
        )
        self._thread.start()
        opened = asyncio.run_coroutine_threadsafe(self._open_servers(), self._loop)
        try:
            opened.result(timeout_s)
        except FutureTimeoutError:
            opened.cancel()
            self.close(timeout_s)
            raise ServerStartError(
                f"[modbus]: the server did not start within {timeout_s:g} s"
            ) from None
        except BaseException:
            self.close(timeout_s)
            raise

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop serving and release the port and the device; safe to call twice."""
        self._closed = True
        loop, thread = self._loop, self._thread
        if loop is None or thread is None or not thread.is_alive():
            return
        if loop.is_running():
            closing = asyncio.run_coroutine_threadsafe(self._close_servers(), loop)
            try:
                closing.result(timeout_s)
            except (FutureTimeoutError, RuntimeError):
                _log.warning("modbus server did not close within %g s", timeout_s)
            loop.call_soon_threadsafe(loop.stop)
        thread.join(timeout_s)
        self._log.flush(force=True)

    def __enter__(self) -> StrainRegisterServer:
        self.start()
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def publish(self, sample: StrainSample, facts: RunFacts | None) -> None:
        """Write one sample into the registers (measurement thread; never blocks on I/O).

        Args:
            sample: the frame's measurement.
            facts: the run's facts, for the UNIX time of the sample; None = timestamp 0
                (unknown).
        """
        reading = sample.reading
        machine = sample.machine
        stamp = facts.unix_time_ns(sample.timestamp_ns) if facts is not None else 0
        lost = sample.points_lost
        values = {
            "axial_strain": reading.engineering_strain,
            "transverse_strain": reading.transverse_strain,
            "true_strain": reading.true_strain,
            "elongation_mm": reading.elongation_mm,
            "gauge_length_mm": reading.gauge_length_mm,
            "frame_counter": sample.frame_id,
            "timestamp_unix_ns": max(stamp, 0),
            "poisson_ratio": reading.poisson_ratio,
            "crosshead_mm": machine.crosshead_mm if machine is not None else math.nan,
            "force_n": machine.force_n if machine is not None else math.nan,
            "time_since_reference_s": sample.time_s,
            "points_lost": lost,
            "latency_ms": sample.latency_s * 1e3,
        }
        values.update(_width_values(sample))
        parts = [
            (start, modbus_map.encode_block(block, values, self._word_order))
            for start, block in (*self._sample_parts, *self._width_parts)
        ]
        bits = StatusBit(0)
        if machine is None:
            bits |= StatusBit.NO_CONTROLLER_DATA
        if sample.frames_dropped > self._frames_dropped:
            bits |= StatusBit.FRAMES_DROPPED
        if lost:
            bits |= StatusBit.POINT_LOST
        if sample.reference_updates:
            bits |= StatusBit.REFERENCE_UPDATED
        image = self._image
        with self._lock:
            for start, words in parts:
                image[start : start + len(words)] = words
            self._frames_dropped = sample.frames_dropped
            self._put(BY_NAME["frames_dropped"], sample.frames_dropped)
            self._sample_valid = bool(sample.data_valid)
            self._sample_bits = bits
            self._write_state_registers()

    def set_run_state(self, state: RunState) -> None:
        """The run's state changed: state bits of `status` and the `run_state` code."""
        with self._lock:
            self._state = state
            if state is RunState.ARMED:
                self._camera_lost = False
                self._frames_dropped = 0
                self._put(BY_NAME["frames_dropped"], 0)
            self._write_state_registers()

    def set_exit_status(
        self, status: ExitStatus | None, results: Mapping[str, float | int] | None = None
    ) -> None:
        """How the last test ended (None: none yet, or a test is under way) and its results,
        in one update.

        Args:
            status: how the test ended; None when the next test begins.
            results: the values of `modbus_map.RESULT_VALUES`
                (`result_registers.result_register_values`); None = no results: the
                result registers are cleared (NaN) and `results_valid` reads 0. Given, they
                are written, `results_valid` reads 1 and `results_counter` moves on.
        """
        values = CLEARED if results is None else {**CLEARED, **results}
        words = modbus_map.encode_block(RESULT_VALUES, values, self._word_order)
        with self._lock:
            code = EXIT_STATUS_CODES[status] if status is not None else 0
            self._image[self._exit_status_at] = code
            self._image[self._results_at : self._results_at + len(words)] = words
            if results is not None:
                self._results_counter = (self._results_counter + 1) & 0xFFFF
                self._image[BY_NAME["results_counter"].address] = self._results_counter
            self._image[BY_NAME["results_valid"].address] = int(results is not None)
            self._beat()

    def set_camera_lost(self, lost: bool) -> None:
        """The camera went away (data valid cleared, `camera lost` set) or came back."""
        with self._lock:
            self._camera_lost = lost
            self._write_state_registers()

    def tick(self) -> None:
        """Move the heartbeat (the service calls this periodically while no frames come)."""
        with self._lock:
            self._write_state_registers()

    def set_gauge_length_setpoint(self, length_mm: float) -> None:
        """The set point in force changed outside Modbus (NaN = the specimen's default)."""
        with self._lock:
            self._put(BY_NAME["gauge_length_setpoint_mm"], length_mm)
            self._beat()

    def read_registers(self, address: int, count: int) -> list[int]:
        """The registers a client would read now, zero-based (no network involved).

        Raises:
            ValueError: the range is outside the map.
        """
        if not (0 <= address and count >= 0 and address + count <= MAP_SIZE):
            raise ValueError(f"registers {address} ... {address + count - 1} outside the map")
        with self._lock:
            return self._image[address : address + count]

    @staticmethod
    def _contiguous_parts(block: Sequence[Register]) -> list[tuple[int, tuple[Register, ...]]]:
        parts: list[tuple[int, tuple[Register, ...]]] = []
        current: list[Register] = []
        for register in block:
            if current and register.address != current[-1].end:
                parts.append((current[0].address, tuple(current)))
                current = []
            current.append(register)
        if current:
            parts.append((current[0].address, tuple(current)))
        return parts

    def _put(self, register: Register, value: float | int) -> None:
        words = modbus_map.encode(register, value, self._word_order)
        self._image[register.address : register.end] = words

    def _beat(self) -> None:
        self._heartbeat = (self._heartbeat + 1) & 0xFFFF
        self._image[self._heartbeat_at] = self._heartbeat

    def _write_state_registers(self) -> None:
        """Status, run state and heartbeat from the current state (caller holds the lock)."""
        state = self._state
        bits = self._sample_bits if state in _VALID_STATES else StatusBit(0)
        if self._camera_lost:
            bits |= StatusBit.CAMERA_LOST
        elif self._sample_valid and state in _VALID_STATES:
            bits |= StatusBit.DATA_VALID
        if state is RunState.RUNNING:
            bits |= StatusBit.TRACKING
        elif state is RunState.ARMED:
            bits |= StatusBit.CALIBRATING
        elif state is RunState.FAULT:
            bits |= StatusBit.FAULT
        self._image[self._status_at] = int(bits)
        self._image[self._run_state_at] = RUN_STATE_CODES[state]
        self._beat()

    async def _on_access(
        self,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        current_registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        """pymodbus' SimDevice action: every read and write of a register passes here."""
        if function_code not in SERVED_FUNCTION_CODES:
            return ExcCodes.ILLEGAL_FUNCTION
        if set_values is None:
            offset = address - start_address
            with self._lock:
                current_registers[offset : offset + count] = self._image[address : address + count]
            return None
        return self._write(address, [int(v) for v in set_values])

    def _write(self, address: int, words: list[int]) -> ExcCodes | None:
        if self._allowed and _client_ip.get() not in self._allowed:
            return ExcCodes.ILLEGAL_FUNCTION
        end = address + len(words)
        touched: list[Register] = []
        for index in range(address, end):
            register = self._entries[index] if 0 <= index < MAP_SIZE else None
            if register is None or not register.writable:
                return ExcCodes.ILLEGAL_ADDRESS
            if register.address < address or register.end > end:
                return ExcCodes.ILLEGAL_ADDRESS
            if not touched or touched[-1] is not register:
                touched.append(register)
        decoded = []
        for register in touched:
            chunk = words[register.address - address : register.end - address]
            value = modbus_map.decode(register, chunk, self._word_order)
            if not register.accepts(value):
                return ExcCodes.ILLEGAL_VALUE
            decoded.append((register, value))
        for register, value in decoded:
            failed = self._command(register, value)
            if failed is not None:
                return failed
        return None

    def _command(self, register: Register, value: float | int) -> ExcCodes | None:
        """Hand one validated write to `on_command` (outside the lock: it may change state)."""
        if register.name == "command":
            name, argument = COMMANDS[int(value)], None
        else:
            name, argument = GAUGE_LENGTH_COMMAND, float(value)
        try:
            accepted = bool(self.on_command(name, argument))
        except Exception:
            _log.exception("modbus command %s(%s) failed", name, argument)
            return ExcCodes.DEVICE_FAILURE
        with self._lock:
            if register.name == "command":
                self._image[register.address] = int(value)
            elif accepted:
                self._put(register, value)
            self._command_counter = (self._command_counter + 1) & 0xFFFF
            self._image[BY_NAME["command_counter"].address] = self._command_counter
            result = CommandResult.ACCEPTED if accepted else CommandResult.REFUSED
            self._image[BY_NAME["command_result"].address] = int(result)
            self._beat()
        return None

    def _device(self) -> SimDevice:
        blocks = [
            SimData(
                address=register.address,
                count=register.count,
                datatype=DataType.REGISTERS,
                readonly=not register.writable,
            )
            for register in REGISTER_MAP
        ]
        return SimDevice(id=0, simdata=blocks, action=self._on_access)

    def _run_loop(self, loop: asyncio.AbstractEventLoop) -> None:
        asyncio.set_event_loop(loop)
        loop.set_exception_handler(self._on_loop_error)
        loop.call_soon(self._flush_log_periodically, loop)
        try:
            loop.run_forever()
        finally:
            pending = asyncio.all_tasks(loop)
            for task in pending:
                task.cancel()
            loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
            loop.run_until_complete(loop.shutdown_asyncgens())
            loop.close()

    def _flush_log_periodically(self, loop: asyncio.AbstractEventLoop) -> None:
        self._log.flush()
        loop.call_later(self._log.interval_s, self._flush_log_periodically, loop)

    def _on_loop_error(self, loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        """asyncio's errors (a failed accept when file descriptors run out, ...): one line."""
        exc = context.get("exception")
        cause = f": {type(exc).__name__}: {exc}" if exc is not None else ""
        self._log.note("loop", f"modbus server: {context.get('message', 'error')}{cause}")

    async def _answer_tcp(self, unit_id: int, request: bytes, client: str | None) -> bytes | None:
        """One Modbus TCP request PDU -> its response PDU (None: not for this server)."""
        if unit_id not in self._tcp_unit_ids:
            return None
        token = _client_ip.set(_normalised_ip(client) if client else None)
        try:
            return await self._respond(unit_id, request)
        finally:
            _client_ip.reset(token)

    async def _respond(self, unit_id: int, request: bytes) -> bytes:
        """A request PDU -> the response PDU: a served function's answer or an exception.

        Functions the map does not serve get exception 1 before anything else is looked at; a
        request of a served function that does not decode (short, or a quantity outside what
        the function allows) gets exception 3.
        """
        function_code = request[0]
        if function_code not in SERVED_FUNCTION_CODES:
            return bytes((function_code | 0x80, ExcCodes.ILLEGAL_FUNCTION))
        pdu = self._decoder.decode(request) if _well_formed(request) else None
        if pdu is None:
            return bytes((function_code | 0x80, ExcCodes.ILLEGAL_VALUE))
        pdu.dev_id = unit_id
        try:
            response = await pdu.datastore_update(self._tcp_context, unit_id)
        except Exception as exc:
            self._log.note(
                "request", f"modbus request {function_code} failed: {type(exc).__name__}: {exc}"
            )
            return bytes((function_code | 0x80, ExcCodes.DEVICE_FAILURE))
        return bytes((response.function_code,)) + response.encode()

    async def _open_servers(self) -> None:
        config = self.config
        if self._tcp is not None:
            where = f"[modbus] tcp {config.tcp}"
            cause = _tcp_failure(*self._tcp)
            if cause is not None:
                raise ServerStartError(f"{where}: {cause}")
            self._tcp_context = SimCore(self._device())
            listener = ModbusTcpListener(
                *self._tcp,
                self._answer_tcp,
                max_connections=config.max_connections,
                idle_timeout_s=config.idle_timeout_s,
                log=self._log,
            )
            self._listener = listener
            try:
                await listener.start()
            except OSError as exc:
                raise ServerStartError(f"{where}: {_tcp_failure(*self._tcp) or exc}") from None
        if config.rtu_device:
            where = f"[modbus] rtu_device {config.rtu_device}"
            cause = _serial_failure(config)
            if cause is not None:
                raise ServerStartError(f"{where}: {cause}")
            server = _SerialServer(
                self._device(),
                (config.unit_id,),
                port=config.rtu_device,
                baudrate=config.rtu_baud,
                parity=config.rtu_parity,
                stopbits=config.rtu_stop_bits,
                bytesize=8,
            )
            self._servers.append(server)
            try:
                await server.serve_forever(background=True)
            except (RuntimeError, OSError, ValueError) as exc:
                raise ServerStartError(f"{where}: {_serial_failure(config) or exc}") from None

    async def _close_servers(self) -> None:
        listener, self._listener = self._listener, None
        if listener is not None:
            await listener.close()
        servers, self._servers = self._servers, []
        for server in servers:
            await server.shutdown()


def _well_formed(request: bytes) -> bool:
    """Whether a request PDU of a served function has the size and quantities Modbus allows.

    Reads ask for 1 ... 125 registers, a write multiple for 1 ... 123 with a byte count of
    twice that, read/write multiple for 1 ... 125 and 1 ... 121; the PDU holds exactly what
    its fields say. Checked before pymodbus decodes it, which would log every failure.
    """
    size = len(request)
    function_code = request[0]
    if function_code in (3, 4):
        return size == 5 and 1 <= int.from_bytes(request[3:5], "big") <= 125
    if function_code == 6:
        return size == 5
    if function_code == 22:
        return size == 7
    if function_code == 16:
        if size < 6:
            return False
        count, byte_count = int.from_bytes(request[3:5], "big"), request[5]
        return 1 <= count <= 123 and byte_count == 2 * count and size == 6 + byte_count
    if function_code == 23:
        if size < 10:
            return False
        reads = int.from_bytes(request[3:5], "big")
        writes, byte_count = int.from_bytes(request[7:9], "big"), request[9]
        return (
            1 <= reads <= 125
            and 1 <= writes <= 121
            and byte_count == 2 * writes
            and size == 10 + byte_count
        )
    return False


def _tcp_failure(host: str, port: int) -> str | None:
    """Why (host, port) cannot be listened on (None: it can), found by binding a probe."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as exc:
        return f"cannot resolve {host!r} ({exc.strerror})"
    family, kind, proto, _, address = infos[0]
    with socket.socket(family, kind, proto) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind(address)
        except OSError as exc:
            return (exc.strerror or str(exc)).lower()
    return None


def _serial_failure(config: ModbusConfig) -> str | None:
    """Why the serial device cannot be opened (None: it can), found by opening it once."""
    import serial

    try:
        port = serial.serial_for_url(
            config.rtu_device,
            exclusive=True,
            baudrate=config.rtu_baud,
            parity=config.rtu_parity,
            stopbits=config.rtu_stop_bits,
        )
    except ValueError as exc:
        return str(exc)
    except serial.SerialException as exc:
        if "lock" in str(exc):
            return "in use by another program (cannot lock it)"
        if exc.errno:
            return os.strerror(exc.errno).lower()
        return str(exc)
    port.close()
    return None
