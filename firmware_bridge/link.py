"""The serial link to the trigger microcontroller: handshake, commands, events, clock sync.

`McuLink` opens a pyserial URL (a device path, a pty, ``loop://``, ``socket://HOST:PORT``),
reads it on a thread of its own that feeds a `packets.PacketDecoder`, and offers the
firmware's verbs as blocking calls with timeouts, in the manner of Klipper's
`klippy/serialhdl.py`:

* `connect` sends HELLO until HELLO_REPLY comes (pyserial flushes the input when it opens a
  port, so the firmware's BOOT and any first reply may be gone), then refuses firmware whose
  protocol version or message-table hash differs from this host's (`FirmwareMismatch`).
  It then takes a few quick round trips for the clock fit and, unless told not to, starts a
  background ping every `sync_interval_s`.
* `ping`, `configure`, `arm`, `retime`, `disarm`, `position`, `set_dead_man`: one request at
  a time (requests are serialised; the microcontroller's receive buffer is small), each
  waiting for its ACK or reply, or for the ERROR naming its sequence number
  (`FirmwareRejected`).
* Sequence numbers (see `messages`): every host packet takes the next number. When a reply
  does not come, the same packet (same number) is sent again: if the first copy was lost the
  firmware acts on the second; if only the answer was lost the firmware answers the copy with
  ``ERROR(OUT_OF_SEQUENCE, expected = number + 1)``: it took the first copy, so no command is
  taken twice. Its outcome went with the lost answer: CONFIGURE, RETIME, DISARM,
  SET_DEAD_MAN and GET_POSITION, which may be repeated, are then sent again under a new
  number for a definite answer; ARM, which may not, raises `AnswerLost`. Any other
  OUT_OF_SEQUENCE means the two sides disagree: the link resends HELLO (which resets the
  firmware's expectation and re-checks its identity) and sends the command again under a new
  number. PING is never resent: a late PONG would pair with the wrong send time.
* TRIGGER, STOPPED and BOOT packets become events (`TriggerEvent`, `StoppedEvent`,
  `BootEvent`) on a bounded queue (`next_event`, `events`); when it is full the oldest event
  is dropped and counted. A TRIGGER's tick is converted to host time with the clock fit at
  the moment it arrives. A BOOT means the microcontroller restarted: its clock fit is
  dropped and the next request begins with a new handshake.
* Garbage on the line costs no valid packet (the decoder resyncs), but for the rare one that
  garbage completes into a packet with a good CRC (a packet cut just before its last byte,
  when that byte is 0xA5, takes the next packet's start byte). When the line has been quiet
  for `quiet_s` with bytes held, a whole packet already behind the held start byte is taken
  (`PacketDecoder.recover_behind_partial`), so a start byte from noise holds back a valid
  packet by `quiet_s` at most; a partial packet with nothing whole behind it is kept, because
  its rest may be late (a loaded host, a USB adapter's latency timer, a simulator that fell
  behind), and is given up (`PacketDecoder.give_up_partial`) only after `partial_timeout_s`
  of silence, when its sender has stopped (a reset in mid-packet).
* `statistics()` counts packets, CRC and length errors, skipped bytes, firmware packets lost
  (gaps in its sequence numbers), round trips and their times, resends, resyncs, timeouts.

Every blocking call takes a timeout (seconds). Sends are thread-safe. Times are host
nanoseconds on the injected clock (`clock_ns`, default `time.monotonic_ns`); ticks are the
firmware's 64-bit tick.

What it does not do: it does not reconnect a port that failed (it raises `LinkClosed`; make a
new link), does not restore the trigger configuration after a firmware restart (the
`BootEvent` says so), and does not pace its sends to the microcontroller's buffer beyond
one request at a time.
"""

from __future__ import annotations

import itertools
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import serial

from firmware_bridge.clocksync import ClockEstimate, ClockNotSynced, ClockSync, RoundTrip
from firmware_bridge.messages import (
    BY_NAME,
    PROTOCOL_VERSION,
    TABLE_HASH,
    Direction,
    ErrorCode,
    ResetCause,
    StopReason,
    TriggerSource,
)
from firmware_bridge.packets import DecodedPacket, PacketDecoder, encode

_PACKET_OVERHEAD = 6
"""Start byte, LEN, SEQ, ID and the two CRC bytes."""


FIRMWARE_BAUD = 500000
"""The firmware's UART rate (firmware/config.h: UART_BAUD), 8N1."""


class FirmwareError(Exception):
    """Base of every error of the trigger microcontroller's link."""


class FirmwareUnavailable(FirmwareError):
    """The port cannot be opened (initialisation)."""


class FirmwareMismatch(FirmwareError):
    """The firmware speaks another protocol version or was built from another message table
    (initialisation); the link refuses to send it commands."""


class NotConnected(FirmwareError):
    """A command before a successful `connect` (or after a refused one)."""


class LinkClosed(FirmwareError):
    """The link was closed, or its port failed."""


class FirmwareTimeout(FirmwareError, TimeoutError):
    """No answer within the timeout (operation)."""


class AnswerLost(FirmwareError):
    """The firmware took a command that may not be repeated (ARM), but its answer, ACK or
    ERROR, was lost (operation): whether it armed shows in the events that follow."""


class FirmwareRejected(FirmwareError):
    """The firmware answered a command with ERROR (operation).

    Attributes:
        request: the message name of the rejected command.
        code: the `ErrorCode` (an int when the firmware sent a code this host does not know).
        detail: ERROR's detail byte: the expected sequence number for OUT_OF_SEQUENCE, the
            message id otherwise.
    """

    def __init__(self, request: str, code: ErrorCode | int, detail: int) -> None:
        name = code.name if isinstance(code, ErrorCode) else f"code {code}"
        super().__init__(f"firmware rejected {request}: {name} (detail {detail})")
        self.request = request
        self.code = code
        self.detail = detail


@dataclass(frozen=True)
class FirmwareInfo:
    """What HELLO_REPLY said.

    Attributes:
        version: (major, minor) of the firmware's protocol.
        table_hash: CRC-32 of the firmware's message table (`messages.TABLE_HASH`).
        tick_hz: the firmware's nominal tick rate (ticks per second).
        tick: the firmware's tick when it replied.
    """

    version: tuple[int, int]
    table_hash: int
    tick_hz: int
    tick: int


@dataclass(frozen=True)
class TriggerEvent:
    """A trigger pulse began.

    Attributes:
        trigger_seq: its number since ARM (1 for the first, as the firmware counts).
        tick: the firmware tick at which it began.
        position: the encoder position then (counts).
        host_time_ns: `tick` on the host clock by the clock fit when the event arrived (ns);
            None when no fit existed yet.
        uncertainty_ns: 1 sigma statistical error of `host_time_ns` (ns; None without a fit);
            see `clocksync` for what it leaves out.
        received_ns: host time at which the packet was decoded (ns).
    """

    trigger_seq: int
    tick: int
    position: int
    host_time_ns: int | None
    uncertainty_ns: float | None
    received_ns: int


@dataclass(frozen=True)
class StoppedEvent:
    """Triggering ended.

    Attributes:
        reason: why (`StopReason`; an int for a reason this host does not know).
        triggers: pulses since ARM.
        received_ns: host time at which the packet was decoded (ns).
    """

    reason: StopReason | int
    triggers: int
    received_ns: int


@dataclass(frozen=True)
class BootEvent:
    """The microcontroller restarted: configuration and clock are gone.

    Attributes:
        cause: what reset it (`ResetCause`; an int for a cause this host does not know).
        received_ns: host time at which the packet was decoded (ns).
    """

    cause: ResetCause | int
    received_ns: int


Event = TriggerEvent | StoppedEvent | BootEvent


@dataclass(frozen=True)
class Position:
    """An encoder reading.

    Attributes:
        position: encoder counts.
        tick: firmware tick of the reading.
        host_time_ns: `tick` on the host clock (ns), None without a clock fit.
    """

    position: int
    tick: int
    host_time_ns: int | None


@dataclass(frozen=True)
class LinkStatistics:
    """Counters of one link since it was opened (a snapshot).

    Attributes:
        packets_sent: packets written, resends included.
        packets_received: packets with a good CRC.
        crc_errors, length_errors, skipped_bytes: the decoder's counts of line damage.
        partials_given_up: times a partial packet was dropped after `partial_timeout_s` of
            silence.
        unusable_packets: packets with a good CRC but an unknown id or a payload that does not
            fit, or sent in the wrong direction.
        lost_packets: firmware packets missing from its sequence numbers.
        round_trips: completed request/answer pairs.
        rtt_min_ns, rtt_last_ns, rtt_max_ns: their round-trip times (ns; 0 before any).
        resends: packets sent again under the same number after no answer.
        resyncs: HELLOs sent to resynchronise after OUT_OF_SEQUENCE or a firmware restart.
        timeouts: requests that got no answer in time.
        errors: ERROR packets received, by code name.
        unmatched_replies: packets that answer no waiting request (late or duplicate answers,
            and the ERRORs the firmware sends about damaged bytes).
        events_dropped: events pushed out of the full queue.
        sync_failures: background pings that failed.
        clock_samples_rejected: round trips the clock fit rejected as outliers.
        boots: BOOT packets received.
    """

    packets_sent: int = 0
    packets_received: int = 0
    crc_errors: int = 0
    length_errors: int = 0
    skipped_bytes: int = 0
    partials_given_up: int = 0
    unusable_packets: int = 0
    lost_packets: int = 0
    round_trips: int = 0
    rtt_min_ns: int = 0
    rtt_last_ns: int = 0
    rtt_max_ns: int = 0
    resends: int = 0
    resyncs: int = 0
    timeouts: int = 0
    errors: dict[str, int] = field(default_factory=dict)
    unmatched_replies: int = 0
    events_dropped: int = 0
    sync_failures: int = 0
    clock_samples_rejected: int = 0
    boots: int = 0


@dataclass
class _Pending:
    seq: int
    request: str
    reply: str
    token: int | None = None
    sent_ns: int = 0
    answer: DecodedPacket | None = None
    answered_ns: int = 0
    done: threading.Event = field(default_factory=threading.Event)


_REPLY_TO = {
    "HELLO": "HELLO_REPLY",
    "PING": "PONG",
    "CONFIGURE": "ACK",
    "ARM": "ACK",
    "RETIME": "ACK",
    "DISARM": "ACK",
    "SET_DEAD_MAN": "ACK",
    "GET_POSITION": "POSITION",
}
_EVENTS = frozenset({"TRIGGER", "STOPPED", "BOOT"})
_REPEATABLE = frozenset({"CONFIGURE", "RETIME", "DISARM", "SET_DEAD_MAN", "GET_POSITION"})
"""Commands that do the same when taken twice in a row."""
_LINE_ERRORS = frozenset({ErrorCode.BAD_CRC, ErrorCode.BAD_LENGTH})
"""ERRORs about damaged bytes: the firmware cannot know whose packet they were (their sequence
number is the damaged packet's byte, or 0), so they answer no request; the request's own
resend covers a command of ours that was damaged."""


def _packet_bytes(name: str) -> int:
    return _PACKET_OVERHEAD + BY_NAME[name].payload_size


def wire_asymmetry_ns(byte_ns: float) -> float:
    """How far a PING's stamp lies after its round trip's midpoint because of the two packets'
    lengths on the wire (ns; negative: before it), for `ClockSync(asymmetry_ns=...)`.

    The firmware stamps a PING at its last byte; the PONG's last byte is what the host
    waits for. With one wire time per byte (`byte_ns`: 10 bit times for 8N1) and all else
    even, the way out is the PING's length and the way back the PONG's, so the stamp lies
    half their difference before the midpoint. Latencies that differ by direction (USB
    polling, a pty bridge's polling) are not in it.
    """
    return 0.5 * (_packet_bytes("PING") - _packet_bytes("PONG")) * byte_ns


def _enum_or_int(kind: type, value: int) -> Any:
    try:
        return kind(value)
    except ValueError:
        return value


class McuLink:
    """The host's end of the trigger microcontroller's serial link.

    The port is opened and its reader thread started by the constructor; `connect` does the
    handshake. Use it as a context manager or call `close`.

    Args:
        url: a pyserial URL or device path (``/dev/ttyUSB0``, a pty path, ``loop://``,
            ``socket://127.0.0.1:5000``).
        baudrate: the serial rate (ignored by ptys, ``loop://`` and ``socket://``); the
            firmware's 500000 by default.
        expected_version: the protocol (major, minor) this host speaks.
        expected_table_hash: the message table's hash this host was built from.
        clock_ns: the host clock (ns) for send/receive stamps and event times.
        quiet_s: how long the line must be silent, with bytes held, before the decoder looks
            behind the held start byte for a whole packet (s); the read timeout.
        partial_timeout_s: how long the line must be silent before a partial packet with
            nothing whole behind it is given up (s). Longer than any gap inside one packet
            on this kind of line.
        write_timeout_s: limit of one write (s).
        event_queue_size: events kept until read; the oldest is dropped when full.
        sync_interval_s: period of the background clock-sync ping after `connect` (s); None
            for none (then call `ping` yourself, and feed the dead-man).
        initial_pings: round trips `connect` takes before it returns, `initial_ping_gap_s`
            apart (a first rate needs a few tens of ms of span).
        initial_ping_gap_s: the pause between those round trips (s).
        wire_byte_ns: how long one byte takes on the firmware's UART line (ns; 10 bit times
            for 8N1, 20000 at 500 kBd), for the clock fit's asymmetry correction
            (`wire_asymmetry_ns`). None: no correction (the path is taken as symmetric).
        clock_sync: the clock fit to feed, with its own settings (`asymmetry_ns` included);
            by default a `ClockSync` made at `connect` with the firmware's tick rate.

    Raises:
        FirmwareUnavailable: the port cannot be opened.
        ValueError: both `wire_byte_ns` and `clock_sync` given.
    """

    def __init__(
        self,
        url: str,
        *,
        baudrate: int = FIRMWARE_BAUD,
        expected_version: tuple[int, int] = PROTOCOL_VERSION,
        expected_table_hash: int = TABLE_HASH,
        clock_ns: Callable[[], int] = time.monotonic_ns,
        quiet_s: float = 0.01,
        partial_timeout_s: float = 0.5,
        write_timeout_s: float = 1.0,
        event_queue_size: int = 4096,
        sync_interval_s: float | None = 0.1,
        initial_pings: int = 8,
        initial_ping_gap_s: float = 0.01,
        wire_byte_ns: float | None = None,
        clock_sync: ClockSync | None = None,
    ) -> None:
        if clock_sync is not None and wire_byte_ns is not None:
            raise ValueError(
                "give the asymmetry to the ClockSync, not wire_byte_ns, with clock_sync"
            )
        self.url = url
        self.expected_version = tuple(expected_version)
        self.expected_table_hash = int(expected_table_hash)
        self._clock_ns = clock_ns
        self._quiet_s = float(quiet_s)
        self._partial_timeout_ns = int(float(partial_timeout_s) * 1e9)
        self._sync_interval_s = sync_interval_s
        self._initial_pings = int(initial_pings)
        self._initial_ping_gap_s = float(initial_ping_gap_s)
        self._wire_byte_ns = wire_byte_ns
        self._clock = clock_sync
        self._decoder = PacketDecoder()
        self._stats = LinkStatistics()
        self._errors: Counter[str] = Counter()
        self._state_lock = threading.Lock()
        self._write_lock = threading.Lock()
        self._request_lock = threading.Lock()
        self._events: deque[Event] = deque(maxlen=max(1, int(event_queue_size)))
        self._events_ready = threading.Condition(self._state_lock)
        self._pending: _Pending | None = None
        self._tx_seq = 0
        self._rx_seq: int | None = None
        self._tokens = itertools.count(1)
        self._connected = False
        self._refused: FirmwareMismatch | None = None
        self._needs_hello = False
        self._failure: BaseException | None = None
        self._closing = threading.Event()
        self.firmware: FirmwareInfo | None = None
        """What the last handshake said; None before `connect`."""
        try:
            self._port = serial.serial_for_url(
                url, baudrate=baudrate, timeout=self._quiet_s, write_timeout=write_timeout_s
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise FirmwareUnavailable(f"cannot open {url}: {exc}") from exc
        self._reader = threading.Thread(target=self._read_loop, name="mcu-link-reader")
        self._reader.daemon = True
        self._reader.start()
        self._syncer: threading.Thread | None = None

    def __enter__(self) -> McuLink:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    @property
    def clock(self) -> ClockSync | None:
        """The clock fit (None before `connect`, unless one was given)."""
        return self._clock

    @property
    def connected(self) -> bool:
        """Whether a handshake succeeded and the link is open."""
        return self._connected and not self._closing.is_set()

    def connect(self, timeout_s: float = 2.0, *, hello_interval_s: float = 0.05) -> FirmwareInfo:
        """Handshake: HELLO until HELLO_REPLY (resent every `hello_interval_s`), identity
        check, `initial_pings` round trips for the clock fit, then the background sync.

        Returns:
            What the firmware said about itself.

        Raises:
            FirmwareMismatch: another protocol version or message table (both values named).
            FirmwareTimeout: no HELLO_REPLY within `timeout_s`.
            LinkClosed: the link is closed or its port failed.
        """
        deadline = time.monotonic() + timeout_s
        self._check_open()
        self._refused = None
        with self._acquire(self._request_lock, deadline, "HELLO"):
            info = self._hello(deadline, hello_interval_s)
            if self._clock is None:
                self._clock = ClockSync(info.tick_hz, asymmetry_ns=self._asymmetry_ns())
            else:
                self._clock.reset()
            self._connected = True
        for index in range(self._initial_pings):
            if index:
                self._closing.wait(self._initial_ping_gap_s)
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            try:
                self.ping(timeout_s=min(remaining, 0.2))
            except FirmwareTimeout:
                continue
        if self._sync_interval_s and self._syncer is None:
            self._syncer = threading.Thread(target=self._sync_loop, name="mcu-link-sync")
            self._syncer.daemon = True
            self._syncer.start()
        return info

    def ping(self, *, timeout_s: float = 0.5) -> RoundTrip:
        """One PING/PONG round trip, fed to the clock fit.

        Returns:
            The round trip (host send time, firmware tick at reception, host receive time).

        Raises:
            FirmwareTimeout, FirmwareRejected, NotConnected, LinkClosed.
        """
        token = next(self._tokens) & 0xFFFFFFFF
        pending = self._request("PING", {"token": token}, timeout_s, token=token, resend=False)
        assert pending.answer is not None
        sample = RoundTrip(pending.sent_ns, pending.answer.values["tick"], pending.answered_ns)
        if self._clock is not None:
            self._clock.add(sample)
        return sample

    def configure(
        self,
        source: TriggerSource | int,
        pulse_width_ticks: int,
        period_ticks: int,
        encoder_divisor: int = 1,
        count: int = 0,
        start_tick: int = 0,
        *,
        timeout_s: float = 0.5,
    ) -> None:
        """Set up triggering (only while disarmed; `retime` changes the spacing while armed).

        Args:
            source: `TriggerSource.PERIOD` (a pulse every `period_ticks`) or
                `TriggerSource.ENCODER` (a pulse every `encoder_divisor` encoder counts).
            pulse_width_ticks: length of each pulse (ticks).
            period_ticks: pulse period for PERIOD (ticks).
            encoder_divisor: encoder counts per pulse for ENCODER.
            count: pulses before stopping by itself; 0 = until disarmed.
            start_tick: firmware tick of the first pulse; 0 = at ARM. Use `tick_at` to
                place it at a host time.

        Raises:
            FirmwareRejected: e.g. BAD_STATE while armed, BAD_VALUE for values it refuses.
            FirmwareTimeout, NotConnected, LinkClosed; PacketError (a ValueError) for a value
            its field cannot hold.
        """
        self._request(
            "CONFIGURE",
            {
                "source": int(source),
                "pulse_width_ticks": pulse_width_ticks,
                "period_ticks": period_ticks,
                "encoder_divisor": encoder_divisor,
                "count": count,
                "start_tick": start_tick,
            },
            timeout_s,
        )

    def arm(self, *, timeout_s: float = 0.5) -> None:
        """Start triggering as configured; TRIGGER events follow.

        Raises:
            FirmwareRejected (e.g. BAD_STATE), FirmwareTimeout, NotConnected, LinkClosed.
        """
        self._request("ARM", {}, timeout_s)

    def retime(
        self, *, period_ticks: int = 0, encoder_divisor: int = 0, timeout_s: float = 0.5
    ) -> None:
        """Change the spacing of the armed trigger without stopping it (RETIME).

        The pulse width, the pulse count of `configure` and the TRIGGER numbering carry on
        (no STOPPED, no gap in `trigger_seq`); the new spacing also replaces the configured
        one, so a later `arm` without a new `configure` uses it. Only the field of the
        configured source is looked at; the other one is ignored (any value).

        PERIOD source: `period_ticks` must be what `configure` accepts with the configured
        pulse width (width + 100 <= period <= 2^31 ticks). The firmware programs each rising
        edge when the pulse before it falls, so the new period first separates pulse k from
        pulse k + 1, where k is the first pulse whose falling edge comes after the firmware
        took the RETIME: sent during a pulse, the next rise is that pulse's rise +
        `period_ticks`; sent between pulses, the rise already programmed keeps its old tick
        and the one after it is at the new spacing; sent before the first pulse, the first
        pulse still rises at the configured start. So the change takes effect within one old
        period plus one new one.

        ENCODER source: `encoder_divisor` (1 ... 2^31 - 1) applies from the last trigger
        position: the next pulse comes when the encoder is `encoder_divisor` counts from it,
        and the grid goes on in steps of the new divisor. When the encoder is already that
        far or further from the last trigger position, the next count triggers once and the
        grid goes on from that count (no burst catching up the old grid). A pulse already
        due when RETIME arrives (the old divisor reached while a pulse ran) still follows.

        Args:
            period_ticks: the new pulse period (ticks) for the PERIOD source.
            encoder_divisor: the new encoder counts per pulse for the ENCODER source.
            timeout_s: how long to wait for the answer (s).

        Raises:
            FirmwareRejected: BAD_STATE when not armed (also after the run ended by its
                count or the dead-man), BAD_VALUE for a period or divisor the firmware
                refuses; the running trigger is then unchanged.
            FirmwareTimeout, NotConnected, LinkClosed; PacketError (a ValueError) for a value
            its field cannot hold.
        """
        self._request(
            "RETIME",
            {"period_ticks": period_ticks, "encoder_divisor": encoder_divisor},
            timeout_s,
        )

    def disarm(self, *, timeout_s: float = 0.5) -> None:
        """Stop triggering; a STOPPED event follows.

        Raises:
            FirmwareRejected, FirmwareTimeout, NotConnected, LinkClosed.
        """
        self._request("DISARM", {}, timeout_s)

    def position(self, *, timeout_s: float = 0.5) -> Position:
        """The encoder position now, with its tick and host time.

        Raises:
            FirmwareRejected, FirmwareTimeout, NotConnected, LinkClosed.
        """
        pending = self._request("GET_POSITION", {}, timeout_s)
        assert pending.answer is not None
        values = pending.answer.values
        return Position(values["position"], values["tick"], self._host_time(values["tick"])[0])

    def set_dead_man(self, timeout_ms: int, *, timeout_s: float = 0.5) -> None:
        """Make the firmware stop triggering when no valid packet arrives for `timeout_ms`
        (0 = off). The background sync's pings count as packets; without it, send something
        (e.g. `ping`) more often than that.

        Raises:
            FirmwareRejected, FirmwareTimeout, NotConnected, LinkClosed; PacketError for a
            timeout above 65535 ms.
        """
        self._request("SET_DEAD_MAN", {"timeout_ms": timeout_ms}, timeout_s)

    def host_time_ns(self, tick: int) -> int:
        """A firmware tick on the host clock (ns).

        Raises:
            ClockNotSynced: no round trip yet (before `connect`, or after a restart).
        """
        return self._require_clock().host_time_ns(tick)

    def tick_at(self, host_ns: int) -> int:
        """The firmware tick at a host time (ns).

        Raises:
            ClockNotSynced: no round trip yet.
        """
        return self._require_clock().tick_at(host_ns)

    def clock_estimate(self) -> ClockEstimate | None:
        """The current clock fit (immutable), None without one."""
        return None if self._clock is None else self._clock.estimate

    def next_event(self, timeout_s: float) -> Event | None:
        """The oldest event not yet read, waiting up to `timeout_s`; None when none came.

        Raises:
            LinkClosed: the port failed (events already queued are still returned first).
        """
        deadline = time.monotonic() + timeout_s
        with self._events_ready:
            while not self._events:
                if self._failure is not None:
                    raise LinkClosed(f"{self.url}: {self._failure}") from self._failure
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self._closing.is_set():
                    return None
                self._events_ready.wait(remaining)
            return self._events.popleft()

    def events(self, timeout_s: float) -> Iterator[Event]:
        """Events as they come, until none arrives for `timeout_s`."""
        while (event := self.next_event(timeout_s)) is not None:
            yield event

    def drain_events(self) -> list[Event]:
        """Every event queued now, without waiting."""
        with self._state_lock:
            events = list(self._events)
            self._events.clear()
            return events

    def statistics(self) -> LinkStatistics:
        """A snapshot of the link's counters."""
        with self._state_lock:
            decoder = self._decoder.statistics
            clock = self._clock
            return replace(
                self._stats,
                packets_received=decoder.packets,
                crc_errors=decoder.crc_errors,
                length_errors=decoder.length_errors,
                skipped_bytes=decoder.skipped_bytes,
                errors=dict(self._errors),
                clock_samples_rejected=clock.rejected if clock else 0,
            )

    def close(self, timeout_s: float = 1.0) -> None:
        """Stop the threads and close the port; idempotent. Blocked calls end with
        LinkClosed or their timeout."""
        self._closing.set()
        with self._events_ready:
            self._events_ready.notify_all()
            pending = self._pending
        if pending is not None:
            pending.done.set()
        for thread in (self._syncer, self._reader):
            if thread is not None and thread is not threading.current_thread():
                thread.join(timeout_s)
        try:
            self._port.close()
        except (serial.SerialException, OSError):
            pass

    def _asymmetry_ns(self) -> float:
        return wire_asymmetry_ns(self._wire_byte_ns) if self._wire_byte_ns else 0.0

    def _require_clock(self) -> ClockSync:
        if self._clock is None:
            raise ClockNotSynced("the link has not connected yet")
        return self._clock

    def _host_time(self, tick: int) -> tuple[int | None, float | None]:
        estimate = None if self._clock is None else self._clock.estimate
        if estimate is None:
            return None, None
        return estimate.host_time_ns(tick), estimate.uncertainty_ns(tick)

    def _acquire(self, lock: threading.Lock, deadline: float, what: str) -> _Held:
        if not lock.acquire(timeout=max(0.0, deadline - time.monotonic())):
            self._count("timeouts")
            raise FirmwareTimeout(f"{what}: the link stayed busy with another request")
        return _Held(lock)

    def _count(self, name: str, amount: int = 1) -> None:
        with self._state_lock:
            self._stats = replace(self._stats, **{name: getattr(self._stats, name) + amount})

    def _check_open(self) -> None:
        if self._failure is not None:
            raise LinkClosed(f"{self.url}: {self._failure}") from self._failure
        if self._closing.is_set():
            raise LinkClosed(f"{self.url}: the link is closed")

    def _next_seq(self) -> int:
        seq = self._tx_seq
        self._tx_seq = (seq + 1) & 0xFF
        return seq

    def _send(self, packet: bytes) -> int:
        self._check_open()
        with self._write_lock:
            sent_ns = self._clock_ns()
            try:
                self._port.write(packet)
                self._port.flush()
            except (serial.SerialException, OSError) as exc:
                self._failure = exc
                raise LinkClosed(f"{self.url}: write failed: {exc}") from exc
        self._count("packets_sent")
        return sent_ns

    def _await(self, pending: _Pending, until: float) -> bool:
        pending.done.wait(max(0.0, until - time.monotonic()))
        with self._state_lock:
            if self._pending is pending:
                self._pending = None
        self._check_open()
        return pending.answer is not None

    def _hello(self, deadline: float, interval_s: float) -> FirmwareInfo:
        seq = self._next_seq()
        packet = encode("HELLO", seq)
        pending = _Pending(seq, "HELLO", "HELLO_REPLY")
        with self._state_lock:
            self._pending = pending
        pending.sent_ns = self._send(packet)
        while True:
            until = min(deadline, time.monotonic() + interval_s)
            pending.done.wait(max(0.0, until - time.monotonic()))
            self._check_open()
            if pending.answer is not None or time.monotonic() >= deadline:
                break
            self._send(packet)
            self._count("resends")
        with self._state_lock:
            if self._pending is pending:
                self._pending = None
        if pending.answer is None:
            self._count("timeouts")
            raise FirmwareTimeout(f"{self.url}: no HELLO_REPLY from the firmware")
        values = pending.answer.values
        info = FirmwareInfo(
            (values["version_major"], values["version_minor"]),
            values["table_hash"],
            values["tick_hz"],
            values["tick"],
        )
        self.firmware = info
        if info.version != self.expected_version or info.table_hash != self.expected_table_hash:
            self._connected = False
            self._refused = FirmwareMismatch(
                f"{self.url}: firmware speaks protocol {info.version[0]}.{info.version[1]} "
                f"with message table {info.table_hash:#010x}; this host speaks "
                f"{self.expected_version[0]}.{self.expected_version[1]} with table "
                f"{self.expected_table_hash:#010x}: rebuild and flash the firmware from "
                "this host's firmware_bridge"
            )
            raise self._refused
        if info.tick_hz <= 0:
            raise FirmwareMismatch(f"{self.url}: firmware reports a tick rate of {info.tick_hz}")
        self._needs_hello = False
        return info

    def _request(
        self,
        name: str,
        values: dict[str, int],
        timeout_s: float,
        *,
        token: int | None = None,
        resend: bool = True,
        retries: int = 2,
    ) -> _Pending:
        deadline = time.monotonic() + timeout_s
        self._check_open()
        if self._refused is not None:
            raise self._refused
        if not self._connected:
            raise NotConnected(f"{name}: connect() first")
        reply = _REPLY_TO[name]
        with self._acquire(self._request_lock, deadline, name):
            if self._needs_hello:
                self._count("resyncs")
                self._hello(deadline, 0.05)
            attempts = retries + 1 if resend else 1
            attempt_s = timeout_s / attempts
            resynced = False
            boots = self._stats.boots
            seq = self._next_seq()
            packet = encode(name, seq, **values)
            copies = 0
            while True:
                pending = _Pending(seq, name, reply, token)
                with self._state_lock:
                    self._pending = pending
                pending.sent_ns = self._send(packet)
                answered = self._await(pending, min(deadline, time.monotonic() + attempt_s))
                if not answered:
                    if copies + 1 < attempts and time.monotonic() < deadline:
                        copies += 1
                        self._count("resends")
                        continue
                    self._count("timeouts")
                    raise FirmwareTimeout(f"{name}: no answer within {timeout_s:g} s")
                answer = pending.answer
                assert answer is not None
                if answer.name != "ERROR":
                    self._note_round_trip(pending.answered_ns - pending.sent_ns)
                    return pending
                code = _enum_or_int(ErrorCode, answer.values["code"])
                detail = answer.values["detail"]
                if code == ErrorCode.OUT_OF_SEQUENCE:
                    restarted = self._stats.boots != boots
                    if copies and detail == (seq + 1) & 0xFF and not restarted:
                        if name not in _REPEATABLE:
                            raise AnswerLost(f"{name} was taken but its answer was lost")
                        seq = self._next_seq()
                        packet = encode(name, seq, **values)
                        continue
                    if resynced:
                        raise FirmwareRejected(name, code, detail)
                    resynced = True
                    self._count("resyncs")
                    self._hello(deadline, 0.05)
                    seq = self._next_seq()
                    packet = encode(name, seq, **values)
                    copies = 0
                    continue
                raise FirmwareRejected(name, code, detail)

    def _note_round_trip(self, rtt_ns: int) -> None:
        with self._state_lock:
            s = self._stats
            self._stats = replace(
                s,
                round_trips=s.round_trips + 1,
                rtt_last_ns=rtt_ns,
                rtt_min_ns=rtt_ns if s.round_trips == 0 else min(s.rtt_min_ns, rtt_ns),
                rtt_max_ns=max(s.rtt_max_ns, rtt_ns),
            )

    def _sync_loop(self) -> None:
        interval = float(self._sync_interval_s or 0.0)
        while not self._closing.wait(interval):
            if self._failure is not None:
                return
            try:
                self.ping(timeout_s=max(0.05, min(0.5, interval)))
            except (FirmwareTimeout, FirmwareRejected, NotConnected):
                self._count("sync_failures")
            except (LinkClosed, FirmwareMismatch):
                return

    def _read_loop(self) -> None:
        port = self._port
        last_byte_ns = time.monotonic_ns()
        while not self._closing.is_set():
            try:
                data = port.read(1)
                if data:
                    waiting = port.in_waiting
                    if waiting:
                        data += port.read(waiting)
            except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
                if not self._closing.is_set():
                    self._fail(exc)
                return
            now = self._clock_ns()
            moment_ns = time.monotonic_ns()
            if data:
                last_byte_ns = moment_ns
            with self._state_lock:
                if data:
                    packets = self._decoder.feed(data)
                elif not self._decoder.pending():
                    continue
                elif moment_ns - last_byte_ns < self._partial_timeout_ns:
                    packets = self._decoder.recover_behind_partial()
                else:
                    packets = self._decoder.give_up_partial()
                    self._stats = replace(
                        self._stats, partials_given_up=self._stats.partials_given_up + 1
                    )
                for packet in packets:
                    self._dispatch(packet, now)

    def _fail(self, exc: BaseException) -> None:
        with self._events_ready:
            self._failure = exc
            self._events_ready.notify_all()
            pending = self._pending
        if pending is not None:
            pending.done.set()

    def _dispatch(self, packet: DecodedPacket, now: int) -> None:
        """Handle one decoded packet; runs on the reader thread with the state lock held."""
        stats = self._stats
        if packet.problem or packet.message is None or packet.message.direction is Direction.TO_MCU:
            self._stats = replace(stats, unusable_packets=stats.unusable_packets + 1)
            return
        if packet.name == "BOOT":
            self._rx_seq = packet.seq
        elif self._rx_seq is not None:
            gap = (packet.seq - self._rx_seq - 1) & 0xFF
            if gap:
                self._stats = replace(stats, lost_packets=stats.lost_packets + gap)
            self._rx_seq = packet.seq
        else:
            self._rx_seq = packet.seq
        if packet.name in _EVENTS:
            self._push_event(packet, now)
            return
        if packet.name == "ERROR":
            code = _enum_or_int(ErrorCode, packet.values["code"])
            self._errors[code.name if isinstance(code, ErrorCode) else str(code)] += 1
        pending = self._pending
        if pending is None or pending.answer is not None or not self._answers(pending, packet):
            self._stats = replace(self._stats, unmatched_replies=self._stats.unmatched_replies + 1)
            return
        pending.answer = packet
        pending.answered_ns = now
        pending.done.set()

    @staticmethod
    def _answers(pending: _Pending, packet: DecodedPacket) -> bool:
        values = packet.values
        if packet.name == "ERROR":
            return values["code"] not in _LINE_ERRORS and values["rejected_seq"] == pending.seq
        if packet.name != pending.reply:
            return False
        if packet.name == "ACK":
            return values["acked_seq"] == pending.seq
        if packet.name == "PONG":
            return values["token"] == pending.token
        return True

    def _push_event(self, packet: DecodedPacket, now: int) -> None:
        values = packet.values
        event: Event
        if packet.name == "TRIGGER":
            host_ns, sigma = self._host_time(values["tick"])
            event = TriggerEvent(
                values["trigger_seq"], values["tick"], values["position"], host_ns, sigma, now
            )
        elif packet.name == "STOPPED":
            event = StoppedEvent(
                _enum_or_int(StopReason, values["reason"]), values["triggers"], now
            )
        else:
            event = BootEvent(_enum_or_int(ResetCause, values["cause"]), now)
            self._stats = replace(self._stats, boots=self._stats.boots + 1)
            if self._clock is not None:
                self._clock.reset()
            if self._connected:
                self._needs_hello = True
        if len(self._events) == self._events.maxlen:
            self._stats = replace(self._stats, events_dropped=self._stats.events_dropped + 1)
        self._events.append(event)
        self._events_ready.notify_all()


class _Held:
    """A lock already acquired, released on leaving the with-block."""

    def __init__(self, lock: threading.Lock) -> None:
        self._lock = lock

    def __enter__(self) -> None:
        return None

    def __exit__(self, *exc_info: object) -> None:
        self._lock.release()
