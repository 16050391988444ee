"""Modbus machine controller client: the `TestingMachine` protocol over Modbus TCP or RTU.

URLs (the registry maps both schemes here):

* `modbus-tcp://HOST[:PORT][?unit=N]`: port 502 and unit 1 by default (unit 0 ... 255; a TCP
  device reached directly usually answers any).
* `modbus-rtu:///dev/ttyX[?baud=B&parity=P&stop_bits=S&unit=N]`: an absolute device path;
  baud 19200, parity N (N, E or O), stop bits 1 (1 or 2), 8 data bits and unit 1 (1 ... 247)
  by default.

A bad URL piece raises `HardwareConfigError` at construction, one line naming the URL and the
piece. Where the quantities live is a `RegisterMap` (hal/machine/register_map.py; the generic
preset by default); the read plan is computed once, so `read_state` sends one request per
coalesced span (one request for the whole generic map) and decodes with pymodbus' converters.

Timeouts. Every call takes `timeout_s` and returns or raises within it (plus the scheduling
slack of the host): the lock that serialises calls, the reconnect, and every request share
one deadline. pymodbus' sync clients take one timeout at construction and may wait it out
once more for a reply that arrives in pieces; this module uses them with pymodbus' retries
disabled (`retries=0`) and subclasses that give each wait only what is left of the call's
deadline (`recv`), and whose `connect` keeps the cause of a failure for the message.

Errors, kept apart as hal/errors.py orders them:

* an exception response (the controller answered, refusing): `HardwareFault`, naming the
  URL, the entries and registers of the request and the code, e.g. "modbus-tcp://127.0.0.1:
  5020: reading force_n (input 4..5): exception 2 (illegal data address)". The link stays up.
* no valid reply within the timeout (nothing, or only garbage: an RTU message with a bad CRC is
  dropped by pymodbus' framer, so noise on the line ends as a timeout): `HardwareTimeout`.
* connection refused, closed by the peer, serial device gone, a reply for another request:
  `HardwareConnectError`.
* a command the machine is not configured to accept, a command or set point the map lacks, a
  set point the register cannot hold, a bad timeout: `HardwareConfigError`.

Connection loss and backoff. After any transport failure (timeouts included: a late reply
could otherwise be taken for the next request's) the client drops the connection and is
"disconnected". A call within the backoff window raises `HardwareConnectError` at once ("...
next attempt in 0.08 s"), so a measurement thread that reads the machine with every camera frame
never waits on a dead controller; the first call after the window tries once to reconnect
(with a fresh pymodbus client, bounded by the call's timeout) and then does its work. The
window starts at 0.1 s, doubles with every failed attempt up to 5 s, and is back to 0.1 s after
a reply. The caller flags the readings it did not get (the appliance records samples without
controller data). `open` failing leaves the client in the same state: later calls keep trying.

Readings. `MachineState.timestamp_ns` is the host's `time.monotonic_ns()` halfway between the
first request sent and the last reply received (the best guess of when the controller took
the values, which the protocol does not say). Without a `running` entry, `running` is
`speed_mm_min != 0`. `encoder_counts` is rounded to an integer, None without the entry.

Commands (`start`, `stop`, `return_to_start`) are written only when constructed with
`accepts_commands=True`; the speed set point is written before the start or return command
(both under one timeout), a command coil is written ON (function 5), a command register its
`value` (function 6, or 16 for 32 bits). A start or return with a map that has no set-point
entry is refused rather than started at a speed the controller decides.

`statistics()` counts what happened (see its docstring). Calls are serialised by a lock, so
a poller thread and a command from another thread may share one `ModbusMachine`.

What it does not do: poll in the background (appliance/devices/polled_machine.py does), read a
controller clock, verify the controller's identity, check that a command took effect (a
following `read_state` shows it), speak Modbus ASCII, UDP or TLS, or share a serial line
between several clients (the device is opened exclusively).
"""

from __future__ import annotations

import contextlib
import functools
import math
import socket
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any
from urllib.parse import parse_qsl

import serial
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.pdu import ModbusPDU

from hal.errors import (
    HardwareConfigError,
    HardwareConnectError,
    HardwareFault,
    HardwareTimeout,
)
from hal.machine.base import MachineState
from hal.machine.register_map import (
    BIT_TABLES,
    GENERIC_CONTROLLER,
    ReadSpan,
    Register,
    RegisterMap,
)
from hal.urls import split_url

INITIAL_BACKOFF_S = 0.1
"""Backoff window after the first transport failure."""
MAX_BACKOFF_S = 5.0
"""The window doubles per failed attempt up to this."""

EXCEPTION_NAMES = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value",
    4: "server device failure",
    5: "acknowledge",
    6: "server device busy",
    7: "negative acknowledge",
    8: "memory parity error",
    10: "gateway path unavailable",
    11: "gateway target device failed to respond",
}
"""Modbus exception codes by number (the names of the Modbus application protocol spec)."""

_TCP_KEYS = ("unit",)
_RTU_KEYS = ("baud", "parity", "stop_bits", "unit")


@dataclass(frozen=True)
class TcpLink:
    """Where a Modbus TCP controller is."""

    host: str
    port: int = 502
    unit: int = 1


@dataclass(frozen=True)
class RtuLink:
    """Where a Modbus RTU controller is, and the line's settings."""

    device: str
    baud: int = 19200
    parity: str = "N"
    stop_bits: int = 1
    unit: int = 1


def parse_url(url: str) -> TcpLink | RtuLink:
    """The link a `modbus-tcp://` or `modbus-rtu://` URL names.

    Raises:
        HardwareConfigError: one line naming the URL and the bad piece.
    """

    def bad(piece: str, reason: str) -> HardwareConfigError:
        return HardwareConfigError(f"machine URL {url!r}: {piece}: {reason}")

    split = split_url(url, "machine")
    if split.scheme not in ("modbus-tcp", "modbus-rtu"):
        raise bad("scheme", f"must be modbus-tcp:// or modbus-rtu://, got {split.scheme!r}")
    if split.fragment:
        raise bad("fragment", f"not used, got {split.fragment!r}")
    if split.username is not None or split.password is not None:
        raise bad("user", "Modbus has no login; remove 'user@'")
    query: dict[str, str] = {}
    for key, value in parse_qsl(split.query, keep_blank_values=True):
        if key in query:
            raise bad(key, "given twice")
        query[key] = value
    known = _TCP_KEYS if split.scheme == "modbus-tcp" else _RTU_KEYS
    for key in query:
        if key not in known:
            raise bad(key, f"unknown setting (known: {', '.join(known)})")

    def integer(key: str, default: int, low: int, high: int) -> int:
        text = query.get(key)
        if text is None:
            return default
        if not text.isdigit() or not low <= int(text) <= high:
            raise bad(key, f"must be an integer {low} ... {high}, got {text!r}")
        return int(text)

    if split.scheme == "modbus-tcp":
        if split.path not in ("", "/"):
            raise bad("path", f"not used, got {split.path!r} (modbus-tcp://HOST:PORT)")
        host = split.hostname
        if not host:
            raise bad("host", "missing (modbus-tcp://HOST:PORT)")
        try:
            port = split.port
        except ValueError:
            port_text = split.netloc.rpartition(":")[2]
            raise bad("port", f"must be an integer 1 ... 65535, got {port_text!r}") from None
        if port == 0:
            raise bad("port", "must be an integer 1 ... 65535, got '0'")
        return TcpLink(host=host, port=port or 502, unit=integer("unit", 1, 0, 255))
    if split.netloc:
        raise bad(
            "device",
            f"must be an absolute path (modbus-rtu:///dev/ttyX), got host {split.netloc!r}",
        )
    if not split.path.startswith("/") or split.path == "/":
        raise bad(
            "device", f"must be an absolute path (modbus-rtu:///dev/ttyX), got {split.path!r}"
        )
    parity = query.get("parity", "N")
    if parity not in ("N", "E", "O"):
        raise bad("parity", f"must be N, E or O, got {parity!r}")
    stop_bits = query.get("stop_bits", "1")
    if stop_bits not in ("1", "2"):
        raise bad("stop_bits", f"must be 1 or 2, got {stop_bits!r}")
    return RtuLink(
        device=split.path,
        baud=integer("baud", 19200, 50, 4_000_000),
        parity=parity,
        stop_bits=int(stop_bits),
        unit=integer("unit", 1, 1, 247),
    )


class _DeadlineReceive:
    """Gives each wait for reply bytes only what is left until `deadline` (pymodbus' sync
    clients wait `comm_params.timeout_connect` per receive)."""

    deadline: float = math.inf
    connect_error: BaseException | None = None

    def recv(self, size: int | None) -> bytes:
        remaining = self.deadline - time.monotonic()
        if remaining <= 0:
            return b""
        self.comm_params.timeout_connect = remaining
        return super().recv(size)


class _DeadlineTcpClient(_DeadlineReceive, ModbusTcpClient):
    """pymodbus' TCP client whose waits end at `deadline` and whose connect keeps its error."""

    def connect(self) -> bool:
        if self.socket:
            return True
        remaining = self.deadline - time.monotonic()
        if remaining <= 0:
            self.connect_error = TimeoutError("no time left to connect")
            return False
        try:
            self.socket = socket.create_connection(
                (self.comm_params.host, self.comm_params.port), timeout=remaining
            )
            self.socket.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        except OSError as exc:
            self.connect_error = exc
            self.close()
        return self.socket is not None


class _DeadlineSerialClient(_DeadlineReceive, ModbusSerialClient):
    """pymodbus' serial client whose waits end at `deadline` and whose connect keeps its error."""

    def connect(self) -> bool:
        if self.socket:
            return True
        params = self.comm_params
        try:
            self.socket = serial.serial_for_url(
                params.host,
                timeout=max(self.deadline - time.monotonic(), 0.001),
                write_timeout=max(self.deadline - time.monotonic(), 0.001),
                bytesize=params.bytesize,
                stopbits=params.stopbits,
                baudrate=params.baudrate,
                parity=params.parity,
                exclusive=True,
            )
            self.socket.inter_byte_timeout = self.inter_byte_timeout
        except Exception as exc:  # pyserial raises undocumented kinds (termios.error)
            self.connect_error = exc
            self.close()
        return self.socket is not None


_Client = _DeadlineTcpClient | _DeadlineSerialClient


def _cause(exc: BaseException | None) -> str:
    """An OS or pyserial error as a short lower-case phrase."""
    if exc is None:
        return "unknown cause"
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror.lower()
    if isinstance(exc, TimeoutError | socket.timeout):
        return "timed out"
    return str(exc) or type(exc).__name__


class ModbusMachine:
    """A testing machine controller reached over Modbus TCP or RTU.

    Args:
        url: `modbus-tcp://HOST:PORT?unit=1` or `modbus-rtu:///dev/ttyX?baud=115200&parity=N&
            stop_bits=1&unit=1` (see the module docstring).
        register_map: where the quantities live; None = `GENERIC_CONTROLLER`.
        accepts_commands: whether start / stop / return_to_start may be written (off: they
            raise HardwareConfigError naming the command).
        **_: other resources the registry hands to every machine backend (ignored).

    Raises:
        HardwareConfigError: a bad URL piece.
    """

    def __init__(
        self,
        url: str,
        *,
        register_map: RegisterMap | None = None,
        accepts_commands: bool = False,
        **_: Any,
    ) -> None:
        self.url = url
        self.link = parse_url(url)
        self.register_map = register_map if register_map is not None else GENERIC_CONTROLLER
        self.accepts_commands = accepts_commands
        self.read_plan: tuple[ReadSpan, ...] = self.register_map.read_plan()
        self._lock = threading.Lock()
        self._client: _Client | None = None
        self._wanted = False
        self._ever_connected = False
        self._backoff_s = INITIAL_BACKOFF_S
        self._next_attempt_at = 0.0
        self._lost_at: float | None = None
        self._last_error: str | None = None
        self._counts = dict.fromkeys(
            (
                "reads",
                "requests",
                "exceptions",
                "transport_failures",
                "timeouts",
                "connect_attempts",
                "reconnects",
                "refused_while_disconnected",
                "commands",
            ),
            0,
        )
        self._last_latency_s: float | None = None
        self._max_latency_s: float | None = None

    def open(self, timeout_s: float = 5.0) -> None:
        """Connect and read the state once (to prove the controller answers the map).

        Raises:
            HardwareConnectError: not reachable, or no answer within the timeout; later calls
                keep trying to reconnect (with backoff) until `close`.
            HardwareFault: the controller answered with an exception (the map does not fit).
        """
        deadline = self._deadline(timeout_s)
        with self._locked(deadline, "open"):
            self._wanted = True
            self._next_attempt_at = 0.0
            client = self._connected(deadline, "open")
            try:
                self._read_values(client, deadline)
            except HardwareTimeout as exc:
                raise HardwareConnectError(f"{exc} (at open)") from None

    def close(self) -> None:
        """Disconnect; safe to call twice. Later calls raise HardwareConnectError until `open`."""
        with self._lock:
            self._wanted = False
            self._drop()

    def read_state(self, timeout_s: float = 1.0) -> MachineState:
        """The controller's state: one request per span of the read plan.

        Raises:
            HardwareConnectError: disconnected (within the backoff window, at once), the
                reconnect failed, or the connection broke.
            HardwareTimeout: no valid reply within `timeout_s`.
            HardwareFault: the controller answered a read with an exception.
        """
        deadline = self._deadline(timeout_s)
        with self._locked(deadline, "read_state"):
            client = self._connected(deadline, "reading")
            started = time.monotonic_ns()
            values = self._read_values(client, deadline)
            ended = time.monotonic_ns()
            latency_s = (ended - started) * 1e-9
            self._counts["reads"] += 1
            self._last_latency_s = latency_s
            self._max_latency_s = max(self._max_latency_s or 0.0, latency_s)
        speed = float(values["speed_mm_min"])
        running = values.get("running")
        counts = values.get("encoder_counts")
        return MachineState(
            crosshead_mm=float(values["crosshead_mm"]),
            speed_mm_min=speed,
            force_n=float(values["force_n"]),
            running=bool(running) if running is not None else speed != 0.0,
            timestamp_ns=(started + ended) // 2,
            encoder_counts=round(counts) if counts is not None and math.isfinite(counts) else None,
        )

    def start(self, speed_mm_min: float, timeout_s: float = 1.0) -> None:
        """Write the speed set point, then the start command.

        Raises:
            HardwareConfigError: commands not accepted, the map lacks start or the set point,
                or the register cannot hold the speed.
            HardwareConnectError, HardwareTimeout, HardwareFault: as `read_state`.
        """
        self._command("start", speed_mm_min, timeout_s)

    def stop(self, timeout_s: float = 1.0) -> None:
        """Write the stop command. Raises as `start`."""
        self._command("stop", None, timeout_s)

    def return_to_start(self, speed_mm_min: float, timeout_s: float = 1.0) -> None:
        """Write the speed set point (as given), then the return command. Raises as `start`."""
        self._command("return_to_start", speed_mm_min, timeout_s)

    def statistics(self) -> dict[str, Any]:
        """What the client has done since construction.

        Keys: `reads` (successful read_state calls), `requests` (Modbus requests answered,
        exceptions included), `exceptions` (exception responses), `transport_failures`
        (connects refused, connections lost, timeouts), `timeouts` (of those, no valid reply
        in time), `connect_attempts`, `reconnects` (connections made after a loss),
        `refused_while_disconnected` (calls refused within the backoff window), `commands`
        (commands written), `connected` (bool), `backoff_s` (the present window),
        `next_attempt_in_s` (0 when connected or due), `last_error` (text or None),
        `last_latency_ms` and `max_latency_ms` (of read_state's requests, None before one).
        """
        now = time.monotonic()
        connected = self._client is not None
        next_in = 0.0 if connected else max(0.0, self._next_attempt_at - now)
        return {
            **self._counts,
            "connected": connected,
            "backoff_s": self._backoff_s,
            "next_attempt_in_s": next_in,
            "last_error": self._last_error,
            "last_latency_ms": _ms(self._last_latency_s),
            "max_latency_ms": _ms(self._max_latency_s),
        }

    def __enter__(self) -> ModbusMachine:
        self.open()
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def _deadline(self, timeout_s: float) -> float:
        if not (isinstance(timeout_s, int | float) and timeout_s > 0 and math.isfinite(timeout_s)):
            raise HardwareConfigError(f"{self.url}: timeout_s must be > 0, got {timeout_s!r}")
        return time.monotonic() + timeout_s

    @contextlib.contextmanager
    def _locked(self, deadline: float, what: str) -> Iterator[None]:
        if not self._lock.acquire(timeout=max(deadline - time.monotonic(), 0.0)):
            raise HardwareTimeout(f"{self.url}: {what}: another call held the client too long")
        try:
            yield
        finally:
            self._lock.release()

    def _new_client(self, deadline: float) -> _Client:
        link = self.link
        client: _Client
        if isinstance(link, TcpLink):
            client = _DeadlineTcpClient(link.host, port=link.port, retries=0, timeout=1.0)
        else:
            client = _DeadlineSerialClient(
                link.device,
                baudrate=link.baud,
                parity=link.parity,
                stopbits=link.stop_bits,
                bytesize=8,
                retries=0,
                timeout=1.0,
            )
        client.deadline = deadline
        return client

    def _connected(self, deadline: float, what: str) -> _Client:
        """The connected client; reconnects once when the backoff window has passed."""
        if self._client is not None:
            return self._client
        if not self._wanted:
            raise HardwareConnectError(f"{self.url}: {what}: not open")
        now = time.monotonic()
        if now < self._next_attempt_at:
            self._counts["refused_while_disconnected"] += 1
            away = f" for {now - self._lost_at:.2f} s" if self._lost_at is not None else ""
            raise HardwareConnectError(
                f"{self.url}: {what}: disconnected{away}, last error: {self._last_error}; "
                f"next attempt in {self._next_attempt_at - now:.2f} s"
            )
        self._counts["connect_attempts"] += 1
        client = self._new_client(deadline)
        if not client.connect():
            where = (
                f"{self.link.host}:{self.link.port}"
                if isinstance(self.link, TcpLink)
                else self.link.device
            )
            window = self._failed(f"cannot connect to {where}: {_cause(client.connect_error)}")
            raise HardwareConnectError(
                f"{self.url}: {what}: {self._last_error}; next attempt in {window:.2f} s"
            )
        if self._ever_connected:
            self._counts["reconnects"] += 1
        self._ever_connected = True
        self._client = client
        return client

    def _failed(self, cause: str) -> float:
        """Record a transport failure and start the backoff window; the window, s."""
        self._drop()
        now = time.monotonic()
        self._counts["transport_failures"] += 1
        self._last_error = cause
        if self._lost_at is None:
            self._lost_at = now
        window = self._backoff_s
        self._next_attempt_at = now + window
        self._backoff_s = min(2 * window, MAX_BACKOFF_S)
        return window

    def _drop(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            client.close()

    def _answered(self) -> None:
        self._backoff_s = INITIAL_BACKOFF_S
        self._lost_at = None

    def _request(
        self, client: _Client, deadline: float, what: str, call: Callable[[], ModbusPDU]
    ) -> ModbusPDU:
        """One request within the deadline; transport failures and exceptions raised apart."""
        if deadline - time.monotonic() <= 0:
            raise HardwareTimeout(f"{self.url}: {what}: no time left for the request")
        client.deadline = deadline
        client.comm_params.timeout_connect = deadline - time.monotonic()
        sent_at = time.monotonic()
        try:
            response = call()
        except ModbusIOException as exc:
            if "No response received" in str(exc):
                self._counts["timeouts"] += 1
                waited = time.monotonic() - sent_at
                window = self._failed(f"no reply within {waited:.2f} s")
                raise HardwareTimeout(
                    f"{self.url}: {what}: no valid reply within {waited:.2f} s; "
                    f"reconnecting in {window:.2f} s"
                ) from None
            window = self._failed(f"bad reply ({exc})")
            raise HardwareConnectError(
                f"{self.url}: {what}: {self._last_error}; reconnecting in {window:.2f} s"
            ) from None
        except ConnectionException as exc:
            closed = "closed" in str(exc).lower()
            window = self._failed(
                "connection lost (closed by the controller)" if closed else "connection lost"
            )
            raise HardwareConnectError(
                f"{self.url}: {what}: {self._last_error}; reconnecting in {window:.2f} s"
            ) from None
        except (ModbusException, OSError) as exc:
            window = self._failed(f"connection lost ({_cause(exc)})")
            raise HardwareConnectError(
                f"{self.url}: {what}: {self._last_error}; reconnecting in {window:.2f} s"
            ) from None
        self._counts["requests"] += 1
        self._answered()
        if response.isError():
            code = getattr(response, "exception_code", None)
            self._counts["exceptions"] += 1
            name = EXCEPTION_NAMES.get(code, "unknown code") if code is not None else "no code"
            raise HardwareFault(f"{self.url}: {what}: exception {code} ({name})")
        return response

    def _read_values(self, client: _Client, deadline: float) -> dict[str, float | bool]:
        unit = self.link.unit
        readers = {
            "holding": client.read_holding_registers,
            "input": client.read_input_registers,
            "coil": client.read_coils,
            "discrete": client.read_discrete_inputs,
        }
        values: dict[str, float | bool] = {}
        for span in self.read_plan:
            what = f"reading {span.describe()}"
            read = functools.partial(
                readers[span.table], span.address, count=span.count, device_id=unit
            )
            response = self._request(client, deadline, what, read)
            raw = response.bits if span.table in BIT_TABLES else response.registers
            if len(raw) < span.count:
                raise HardwareFault(
                    f"{self.url}: {what}: the reply holds {len(raw)} values for {span.count}"
                )
            values.update(span.decode(raw))
        return values

    def _command(self, name: str, speed_mm_min: float | None, timeout_s: float) -> None:
        if not self.accepts_commands:
            raise HardwareConfigError(
                f"{self.url}: command {name} refused: this machine is not configured to accept "
                "commands (accepts_commands is off)"
            )
        register: Register | None = getattr(self.register_map, name)
        if register is None:
            raise HardwareConfigError(
                f"{self.url}: command {name} refused: the register map has no {name} entry"
            )
        writes: list[tuple[str, Register, list[int] | None]] = []
        if speed_mm_min is not None:
            setpoint = self.register_map.speed_setpoint_mm_min
            if setpoint is None:
                raise HardwareConfigError(
                    f"{self.url}: command {name} refused: the register map has no "
                    f"speed_setpoint_mm_min entry to set {speed_mm_min} mm/min"
                )
            try:
                words = setpoint.encode(speed_mm_min)
            except (ValueError, TypeError) as exc:
                raise HardwareConfigError(
                    f"{self.url}: command {name}: speed_setpoint_mm_min "
                    f"({setpoint.describe()}) cannot hold {speed_mm_min!r} mm/min: {exc}"
                ) from None
            writes.append(("speed_setpoint_mm_min", setpoint, words))
        command_words = register.command_words() if register.table == "holding" else None
        writes.append((name, register, command_words))
        deadline = self._deadline(timeout_s)
        unit = self.link.unit
        with self._locked(deadline, f"command {name}"):
            client = self._connected(deadline, f"command {name}")
            for entry, target, words in writes:
                what = f"writing {entry} ({target.describe()})"
                if words is None:
                    call = functools.partial(
                        client.write_coil, target.address, True, device_id=unit
                    )
                elif len(words) == 1:
                    call = functools.partial(
                        client.write_register, target.address, words[0], device_id=unit
                    )
                else:
                    call = functools.partial(
                        client.write_registers, target.address, words, device_id=unit
                    )
                self._request(client, deadline, what, call)
            self._counts["commands"] += 1


def _ms(seconds: float | None) -> float | None:
    return None if seconds is None else seconds * 1e3
