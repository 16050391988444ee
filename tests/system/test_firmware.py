"""The trigger firmware itself, built from source with avr-gcc and run on simavr over a pty.

Every test talks to the real firmware through `firmware_bridge.simulator.SimulatedMcu` with
pyserial, building and parsing packets with `firmware_bridge.packets`, and checks timing in
simulated time (the harness's edge log of the trigger pin, and the ticks in the packets),
never by the host's clock. Skipped, with the reason, when avr-gcc or libsimavr is missing.

Bounds used below: an edge made by Timer1's compare unit is logged at its exact CPU cycle,
so periods and widths match the command to one CPU cycle (62.5 ns); a TRIGGER's tick maps to
its rising edge as tick * 500 ns + a constant offset (the time from reset to Timer1's start,
under 1 ms), the same to one cycle for every pulse.
"""

from __future__ import annotations

import itertools
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from firmware_bridge.messages import (
    BY_NAME,
    PROTOCOL_VERSION,
    START_BYTE,
    TABLE_HASH,
    ErrorCode,
    ResetCause,
    StopReason,
    TriggerSource,
    crc16,
)
from firmware_bridge.packets import DecodedPacket, PacketDecoder, encode
from firmware_bridge.simulator import EncoderSegment, SimulatedMcu
from tests.system.firmware_peers import firmware_binaries

ROOT = Path(__file__).resolve().parents[2]
TICK_NS = 500
CYCLE_NS = 62.5
NS_PER_S = 1_000_000_000


@pytest.fixture(scope="session")
def binaries() -> dict[str, Path]:
    return firmware_binaries()


class Link:
    """The host end: numbered packets out, decoded packets in, everything received kept."""

    def __init__(self, port) -> None:
        self.port = port
        self.decoder = PacketDecoder()
        self.seq = 0
        self.received: list[DecodedPacket] = []
        self._unread = 0

    def send(self, name: str, **values) -> int:
        seq = self.seq
        self.port.write(encode(name, seq, **values))
        self.seq = (seq + 1) % 256
        return seq

    def send_raw(self, data: bytes) -> None:
        self.port.write(data)

    def poll(self) -> None:
        data = self.port.read(max(1, self.port.in_waiting))
        if data:
            self.received.extend(self.decoder.feed(data))

    def wait_for(
        self, match: Callable[[DecodedPacket], bool], timeout_s: float = 2.0
    ) -> DecodedPacket:
        """The first matching packet after the one the previous wait_for returned; packets
        skipped on the way stay in `received` (for `packets()`) but are not matched again."""
        deadline = time.monotonic() + timeout_s
        while True:
            for index in range(self._unread, len(self.received)):
                if match(self.received[index]):
                    self._unread = index + 1
                    return self.received[index]
            if time.monotonic() > deadline:
                names = [f.name for f in self.received[self._unread :]]
                raise AssertionError(f"no matching packet in {timeout_s} s; unread: {names}")
            self.poll()

    def expect(self, name: str, timeout_s: float = 2.0, **values) -> DecodedPacket:
        def match(packet: DecodedPacket) -> bool:
            return packet.name == name and all(packet.values.get(k) == v for k, v in values.items())

        return self.wait_for(match, timeout_s)

    def hello(self, seq: int = 0) -> DecodedPacket:
        self.seq = seq
        self.send("HELLO")
        return self.expect("HELLO_REPLY")

    def command(self, name: str, **values) -> DecodedPacket:
        """Send a command; its ACK or ERROR."""
        seq = self.send(name, **values)
        return self.wait_for(
            lambda f: (
                (f.name == "ACK" and f.values["acked_seq"] == seq)
                or (f.name == "ERROR" and f.values["rejected_seq"] == seq)
            )
        )

    def packets(self, name: str) -> list[DecodedPacket]:
        return [f for f in self.received if f.name == name]


def configure(
    link: Link,
    *,
    source: TriggerSource = TriggerSource.PERIOD,
    width: int = 200,
    period: int = 2000,
    divisor: int = 0,
    count: int = 0,
    start_tick: int = 0,
) -> DecodedPacket:
    return link.command(
        "CONFIGURE",
        source=int(source),
        pulse_width_ticks=width,
        period_ticks=period,
        encoder_divisor=divisor,
        count=count,
        start_tick=start_tick,
    )


def retime(link: Link, *, period: int = 0, divisor: int = 0) -> DecodedPacket:
    return link.command("RETIME", period_ticks=period, encoder_divisor=divisor)


def bracketed_retime(link: Link, *, period: int = 0, divisor: int = 0) -> tuple[str, int, int]:
    """RETIME sent between a PING and a GET_POSITION: its answer's name, and a tick before
    and one after the firmware took it (the PING's reception, the POSITION's reading)."""
    token = 0x5E700 + link.seq
    link.send("PING", token=token)
    seq = link.send("RETIME", period_ticks=period, encoder_divisor=divisor)
    link.send("GET_POSITION")
    before = link.expect("PONG", token=token).values["tick"]
    answer = link.wait_for(
        lambda f: (
            (f.name == "ACK" and f.values["acked_seq"] == seq)
            or (f.name == "ERROR" and f.values["rejected_seq"] == seq)
        )
    )
    after = link.expect("POSITION").values["tick"]
    return answer.name, before, after


def raw_packet(seq: int, message_id: int, payload: bytes = b"") -> bytes:
    body = bytes([len(payload) + 2, seq, message_id]) + payload
    crc = crc16(body)
    return bytes([START_BYTE]) + body + bytes([crc & 0xFF, crc >> 8])


def pulses(mcu: SimulatedMcu) -> list[tuple[int, int]]:
    """(rise ns, fall ns) of every complete pulse in the edge log."""
    edges = [(ns, level) for ns, _, level in mcu.edges()]
    result = []
    for (t0, l0), (t1, l1) in itertools.pairwise(edges):
        if l0 == 1 and l1 == 0:
            result.append((t0, t1))
    return result


def wait_until(condition: Callable[[], bool], timeout_s: float = 2.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met in time")
        time.sleep(0.005)


@pytest.fixture
def start_mcu(binaries, tmp_path) -> Iterator[Callable[..., tuple[SimulatedMcu, Link]]]:
    started: list[tuple[SimulatedMcu, object]] = []

    def start(*, test_build: bool = False, encoder=None) -> tuple[SimulatedMcu, Link]:
        mcu = SimulatedMcu(
            binaries["test_elf" if test_build else "elf"],
            binaries["harness"],
            tmp_path / f"mcu{len(started)}",
            encoder_schedule=encoder,
            hold=True,
        )
        mcu.start()
        port = mcu.open_serial(timeout=0.01)
        started.append((mcu, port))
        return mcu, Link(port)

    yield start
    for mcu, port in started:
        port.close()
        mcu.stop()


def test_generated_header_is_current():
    done = subprocess.run(
        [sys.executable, "-m", "firmware_bridge.gen_header", "--check"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stdout + done.stderr


def test_boot_then_handshake(start_mcu):
    mcu, link = start_mcu()
    boot = link.expect("BOOT")
    assert boot.seq == 0 and boot.values["cause"] == ResetCause.POWER_ON
    reply = link.hello(seq=17).values
    assert (reply["version_major"], reply["version_minor"]) == PROTOCOL_VERSION
    assert reply["table_hash"] == TABLE_HASH
    assert reply["tick_hz"] == 2_000_000
    later = link.hello(seq=200).values
    assert later["tick"] > reply["tick"] > 0


@pytest.mark.parametrize(
    ("width", "period", "count"),
    [(200, 2000, 20), (60_000, 150_000, 3)],
    ids=["1ms-period", "75ms-period-long-pulse"],
)
def test_period_mode_edges_match_the_command(start_mcu, width, period, count):
    mcu, link = start_mcu()
    now = link.hello().values["tick"]
    start_tick = now + 100_000
    assert (
        configure(link, width=width, period=period, count=count, start_tick=start_tick).name
        == "ACK"
    )
    assert link.command("ARM").name == "ACK"
    stopped = link.expect("STOPPED", timeout_s=2.0 + count * period * TICK_NS / NS_PER_S)
    assert stopped.values == {"reason": StopReason.COUNT_DONE, "triggers": count}

    triggers = link.packets("TRIGGER")
    assert [t.values["trigger_seq"] for t in triggers] == list(range(1, count + 1))
    assert [t.values["tick"] for t in triggers] == [start_tick + k * period for k in range(count)]
    measured = pulses(mcu)
    assert len(measured) == count
    assert mcu.edges()[-1][2] == 0
    for rise, fall in measured:
        assert abs((fall - rise) - width * TICK_NS) <= CYCLE_NS
    for (rise0, _), (rise1, _) in itertools.pairwise(measured):
        assert abs((rise1 - rise0) - period * TICK_NS) <= CYCLE_NS
    offsets = [
        rise - t.values["tick"] * TICK_NS for (rise, _), t in zip(measured, triggers, strict=True)
    ]
    assert 0 <= min(offsets) and max(offsets) < 1_000_000
    assert max(offsets) - min(offsets) <= CYCLE_NS


def test_start_tick_in_the_past_is_refused(start_mcu):
    _, link = start_mcu()
    now = link.hello().values["tick"]
    assert configure(link, start_tick=max(1, now - 1000)).name == "ACK"
    seq = link.seq
    refused = link.command("ARM")
    assert refused.name == "ERROR"
    assert refused.values == {
        "code": ErrorCode.BAD_VALUE,
        "detail": BY_NAME["ARM"].id,
        "rejected_seq": seq,
    }


@pytest.mark.parametrize("counts_per_s", [17_000.0, -17_000.0], ids=["forward", "reverse"])
def test_encoder_mode_triggers_every_divisor_counts(start_mcu, counts_per_s):
    divisor, count = 100, 8
    mcu, link = start_mcu(encoder=[EncoderSegment(0, counts_per_s)])
    link.hello()
    assert (
        configure(link, source=TriggerSource.ENCODER, width=200, divisor=divisor, count=count).name
        == "ACK"
    )
    assert link.command("ARM").name == "ACK"
    link.expect("STOPPED", timeout_s=3.0)

    triggers = [t.values for t in link.packets("TRIGGER")]
    assert len(triggers) == count
    step = divisor if counts_per_s > 0 else -divisor
    positions = [t["position"] for t in triggers]
    assert positions == [positions[0] + k * step for k in range(count)]
    expected_ticks = divisor / abs(counts_per_s) * 2_000_000
    gaps = [b["tick"] - a["tick"] for a, b in itertools.pairwise(triggers[1:])]
    assert all(abs(gap - expected_ticks) <= 20 for gap in gaps), gaps
    measured = pulses(mcu)
    assert len(measured) == count
    assert all(abs((fall - rise) - 200 * TICK_NS) <= CYCLE_NS for rise, fall in measured)
    offsets = [rise - t["tick"] * TICK_NS for (rise, _), t in zip(measured, triggers, strict=True)]
    assert max(offsets) - min(offsets) <= CYCLE_NS

    link.send("GET_POSITION")
    a = link.expect("POSITION").values
    time.sleep(0.05)
    link.send("GET_POSITION")
    b = link.expect("POSITION").values
    rate = (b["position"] - a["position"]) / ((b["tick"] - a["tick"]) / 2_000_000)
    assert rate == pytest.approx(counts_per_s, rel=0.02)


@pytest.mark.parametrize(
    ("delay_s", "taken_during_a_pulse"),
    [(0.0, True), (0.1, False)],
    ids=["during-a-pulse", "between-pulses"],
)
def test_retime_changes_the_period_from_the_first_rise_not_yet_programmed(
    start_mcu, delay_s, taken_during_a_pulse
):
    """40 ms pulses every 240 ms; RETIME to 150 ms right after TRIGGER 3 (while pulse 3 is
    high) or 100 ms later (pulse 3 has fallen, rise 4 is programmed). The new period starts
    at the rise of the first pulse whose falling edge comes after the RETIME; the count, the
    width and trigger_seq carry on, and the next ARM runs at the new period. The windows are
    wide so that a loaded host's latency, or the emulation falling behind its wall-clock
    pacing, cannot move the RETIME into the other case."""
    width, old, new, count = 80_000, 480_000, 300_000, 10
    mcu, link = start_mcu()
    link.hello()
    assert configure(link, width=width, period=old, count=count).name == "ACK"
    assert link.command("ARM").name == "ACK"
    link.expect("TRIGGER", trigger_seq=3)
    time.sleep(delay_s)
    answer, taken_after, taken_before = bracketed_retime(link, period=new, divisor=12345)
    assert answer == "ACK"
    stopped = link.expect("STOPPED", timeout_s=8.0).values
    assert stopped == {"reason": StopReason.COUNT_DONE, "triggers": count}

    triggers = link.packets("TRIGGER")
    assert [t.values["trigger_seq"] for t in triggers] == list(range(1, count + 1))
    ticks = [t.values["tick"] for t in triggers]
    first_new = next(k for k, tick in enumerate(ticks) if tick + width > taken_after)
    assert ticks[first_new] + width > taken_before, "a falling edge within the bracket"
    if taken_during_a_pulse:
        assert ticks[first_new] < taken_after
    else:
        assert ticks[first_new - 1] + width < taken_after and taken_before < ticks[first_new]
    spacing = [old] * first_new + [new] * (count - 1 - first_new)
    assert [b - a for a, b in itertools.pairwise(ticks)] == spacing

    measured = pulses(mcu)
    assert len(measured) == count and mcu.edges()[-1][2] == 0
    assert all(abs((fall - rise) - width * TICK_NS) <= CYCLE_NS for rise, fall in measured)
    rises = [rise for rise, _ in measured]
    for (a, b), ticks_apart in zip(itertools.pairwise(rises), spacing, strict=True):
        assert abs((b - a) - ticks_apart * TICK_NS) <= CYCLE_NS

    assert link.command("ARM").name == "ACK"
    link.expect("STOPPED", timeout_s=8.0)
    second = pulses(mcu)[count:]
    assert len(second) == count
    for (a, _), (b, _) in itertools.pairwise(second):
        assert abs((b - a) - new * TICK_NS) <= CYCLE_NS


@pytest.mark.parametrize(
    ("new_divisor", "counts_per_s", "already_past"),
    [(300, 17_000.0, False), (5, 1_000.0, True)],
    ids=["from-the-last-trigger", "encoder-already-past-it"],
)
def test_retime_changes_the_encoder_divisor(start_mcu, new_divisor, counts_per_s, already_past):
    """Triggers every 200 counts from position 0; the encoder stops some counts after
    trigger 3 (at least the 8 counts of the TRIGGER packet's time on the line), RETIME sets a
    new divisor, and the encoder runs on. A larger divisor counts
    from the last trigger position; one the encoder is already past triggers on the next
    count, and the grid goes on from there in steps of the new divisor."""
    old_divisor, width = 200, 200
    mcu, link = start_mcu()
    link.hello()
    assert (
        configure(link, source=TriggerSource.ENCODER, width=width, divisor=old_divisor).name
        == "ACK"
    )
    assert link.command("ARM").name == "ACK"
    link.expect("TRIGGER", trigger_seq=1)
    mcu.set_encoder_rate(17_000.0)
    link.expect("TRIGGER", trigger_seq=3)
    mcu.set_encoder_rate(0.0)
    time.sleep(0.05)
    link.send("GET_POSITION")
    stopped_at = link.expect("POSITION").values["position"]
    before = [t.values["position"] for t in link.packets("TRIGGER")]
    assert before == [k * old_divisor for k in range(len(before))]
    moved = stopped_at - before[-1]
    assert 0 <= moved < old_divisor
    assert (moved >= new_divisor) == already_past

    assert retime(link, divisor=new_divisor, period=7).name == "ACK"
    mcu.set_encoder_rate(counts_per_s)
    link.expect("TRIGGER", trigger_seq=len(before) + 5, timeout_s=3.0)
    assert link.command("DISARM").name == "ACK"
    stopped = link.expect("STOPPED").values

    triggers = [t.values for t in link.packets("TRIGGER")]
    assert [t["trigger_seq"] for t in triggers] == list(range(1, len(triggers) + 1))
    assert len(triggers) == stopped["triggers"] == len(pulses(mcu))
    after = triggers[len(before) :]
    first = stopped_at + 1 if already_past else before[-1] + new_divisor
    assert [t["position"] for t in after] == [first + k * new_divisor for k in range(len(after))]
    expected_ticks = new_divisor / counts_per_s * 2_000_000
    gaps = [b["tick"] - a["tick"] for a, b in itertools.pairwise(after)]
    assert all(abs(gap - expected_ticks) <= 20 for gap in gaps), gaps


def test_retime_is_refused_unless_armed_and_a_bad_value_changes_nothing(start_mcu):
    mcu, link = start_mcu()
    link.hello()
    retime_id = BY_NAME["RETIME"].id
    seq = link.seq
    assert retime(link, period=4000).values == {
        "code": ErrorCode.BAD_STATE,
        "detail": retime_id,
        "rejected_seq": seq,
    }
    assert configure(link, width=200, period=2000).name == "ACK"
    assert retime(link, period=4000).values["code"] == ErrorCode.BAD_STATE
    assert link.command("ARM").name == "ACK"
    link.expect("TRIGGER", trigger_seq=3)
    for bad_period in (250, 200, 0, 0x80000001):
        seq = link.seq
        assert retime(link, period=bad_period, divisor=5).values == {
            "code": ErrorCode.BAD_VALUE,
            "detail": retime_id,
            "rejected_seq": seq,
        }
    link.expect("TRIGGER", trigger_seq=30)
    assert link.command("DISARM").name == "ACK"
    stopped = link.expect("STOPPED").values
    assert retime(link, period=4000).values["code"] == ErrorCode.BAD_STATE

    ticks = [t.values["tick"] for t in link.packets("TRIGGER")]
    assert len(ticks) == stopped["triggers"]
    assert {b - a for a, b in itertools.pairwise(ticks)} == {2000}
    rises = [rise for rise, _ in pulses(mcu)]
    assert len(rises) == stopped["triggers"]
    assert all(abs((b - a) - 2000 * TICK_NS) <= CYCLE_NS for a, b in itertools.pairwise(rises))

    assert configure(link, source=TriggerSource.ENCODER, width=200, divisor=100).name == "ACK"
    assert link.command("ARM").name == "ACK"
    for bad_divisor in (0, 0x80000000):
        assert retime(link, divisor=bad_divisor, period=4000).values["code"] == (
            ErrorCode.BAD_VALUE
        )
    assert link.command("DISARM").name == "ACK"


def test_dead_man_stops_a_silent_host(start_mcu):
    mcu, link = start_mcu()
    link.hello()
    assert link.command("SET_DEAD_MAN", timeout_ms=100).name == "ACK"
    assert configure(link, width=200, period=2000).name == "ACK"
    assert link.command("ARM").name == "ACK"
    stopped = link.expect("STOPPED", timeout_s=3.0).values
    assert stopped["reason"] == StopReason.DEAD_MAN
    measured = pulses(mcu)
    span_ms = (measured[-1][0] - measured[0][0]) / 1e6
    assert 97 <= span_ms <= 102, span_ms
    assert len(measured) == stopped["triggers"]
    assert mcu.edges()[-1][2] == 0


def test_disarm_stops_and_reports(start_mcu):
    mcu, link = start_mcu()
    link.hello()
    assert configure(link, width=1000, period=4000).name == "ACK"
    assert link.command("ARM").name == "ACK"
    for _ in range(5):
        link.expect("TRIGGER")
    assert configure(link).values["code"] == ErrorCode.BAD_STATE
    assert link.command("DISARM").name == "ACK"
    stopped = link.expect("STOPPED").values
    assert stopped["reason"] == StopReason.DISARMED
    time.sleep(0.05)
    link.poll()
    assert len(link.packets("TRIGGER")) == stopped["triggers"]
    edges_after_stop = mcu.edges()
    time.sleep(0.05)
    assert mcu.edges() == edges_after_stop
    assert edges_after_stop[-1][2] == 0
    assert len(pulses(mcu)) == stopped["triggers"]
    assert link.command("DISARM").name == "ACK"


def test_a_trigger_flood_loses_events_not_edges_or_control(start_mcu):
    """5 kHz triggers make more TRIGGER packets than the line carries: packets are dropped
    (gaps in trigger_seq), the edges stay exact and the host can still ping and disarm."""
    mcu, link = start_mcu()
    link.hello()
    assert configure(link, width=100, period=400).name == "ACK"
    assert link.command("ARM").name == "ACK"
    time.sleep(0.15)
    for token in range(3):
        link.send("PING", token=token)
        link.expect("PONG", token=token)
    assert link.command("DISARM").name == "ACK"
    stopped = link.expect("STOPPED").values
    seqs = [t.values["trigger_seq"] for t in link.packets("TRIGGER")]
    assert seqs == sorted(seqs) and len(seqs) < stopped["triggers"]
    measured = pulses(mcu)
    assert len(measured) == stopped["triggers"]
    for (rise0, fall0), (rise1, _) in itertools.pairwise(measured):
        assert abs((fall0 - rise0) - 100 * TICK_NS) <= CYCLE_NS
        assert abs((rise1 - rise0) - 400 * TICK_NS) <= CYCLE_NS


@pytest.mark.parametrize(
    "settings_",
    [
        {"width": 2000, "period": 2000},
        {"width": 200, "period": 0},
        {"width": 10, "period": 2000},
        {"width": 1990, "period": 2000},
        {"source": TriggerSource.ENCODER, "divisor": 0},
        {"source": 7},
    ],
    ids=[
        "width>=period",
        "zero-period",
        "width-too-short",
        "gap-too-short",
        "zero-divisor",
        "source",
    ],
)
def test_bad_values_are_refused(start_mcu, settings_):
    _, link = start_mcu()
    link.hello()
    seq = link.seq
    refused = configure(link, **settings_)
    assert refused.name == "ERROR"
    assert refused.values == {
        "code": ErrorCode.BAD_VALUE,
        "detail": BY_NAME["CONFIGURE"].id,
        "rejected_seq": seq,
    }
    assert link.command("ARM").values["code"] == ErrorCode.BAD_STATE


@pytest.fixture(scope="module")
def shared_link(binaries, tmp_path_factory) -> Iterator[Link]:
    mcu = SimulatedMcu(
        binaries["elf"], binaries["harness"], tmp_path_factory.mktemp("shared-mcu"), hold=True
    )
    with mcu:
        port = mcu.open_serial(timeout=0.01)
        try:
            yield Link(port)
        finally:
            port.close()


def _good_crc_then_bad(seq: int) -> bytes:
    packet = bytearray(encode("PING", seq, token=1))
    packet[-1] ^= 0x5A
    return bytes(packet)


@pytest.mark.parametrize(
    ("make", "code", "detail"),
    [
        (_good_crc_then_bad, ErrorCode.BAD_CRC, BY_NAME["PING"].id),
        (lambda seq: bytes([START_BYTE, 1]), ErrorCode.BAD_LENGTH, 1),
        (lambda seq: bytes([START_BYTE, 41]), ErrorCode.BAD_LENGTH, 41),
        (lambda seq: raw_packet(seq, 0x55), ErrorCode.UNKNOWN_MESSAGE, 0x55),
        (
            lambda seq: raw_packet(seq, BY_NAME["PONG"].id, bytes(12)),
            ErrorCode.UNKNOWN_MESSAGE,
            0x82,
        ),
        (
            lambda seq: raw_packet(seq, BY_NAME["PING"].id, b"\x01\x02\x03"),
            ErrorCode.BAD_PAYLOAD,
            0x02,
        ),
        (lambda seq: raw_packet(seq, BY_NAME["ARM"].id, b"\x00"), ErrorCode.BAD_PAYLOAD, 0x04),
        (lambda seq: encode("PING", (seq + 5) % 256, token=7), ErrorCode.OUT_OF_SEQUENCE, None),
        (lambda seq: encode("PING", seq, token=7)[:6], ErrorCode.BAD_LENGTH, 6),
    ],
    ids=[
        "bad-crc",
        "length-1",
        "length-41",
        "unknown-id",
        "to-host-id",
        "ping-3-bytes",
        "arm-with-payload",
        "out-of-sequence",
        "truncated",
    ],
)
def test_malformed_packets_get_their_error_and_the_stream_survives(shared_link, make, code, detail):
    link = shared_link
    link.hello()
    seq = link.seq
    link.send_raw(make(seq))
    error = link.expect("ERROR", code=int(code), timeout_s=2.0).values
    consumes_seq = code in (ErrorCode.UNKNOWN_MESSAGE, ErrorCode.BAD_PAYLOAD)
    if code == ErrorCode.OUT_OF_SEQUENCE:
        assert error == {"code": code, "detail": seq, "rejected_seq": (seq + 5) % 256}
    elif code == ErrorCode.BAD_LENGTH:
        assert error["detail"] == detail
    else:
        assert error == {"code": code, "detail": detail, "rejected_seq": seq}
    if consumes_seq:
        link.seq = (seq + 1) % 256
    token = 0xC0FFEE00 + link.seq
    link.send("PING", token=token)
    link.expect("PONG", token=token)


def test_pong_ticks_are_reception_ticks(shared_link):
    link = shared_link
    before = link.hello().values["tick"]
    ticks = []
    for token in range(5):
        link.send("PING", token=token)
        ticks.append(link.expect("PONG", token=token).values["tick"])
    after = link.hello(seq=3).values["tick"]
    assert before < ticks[0] and ticks == sorted(ticks) and ticks[-1] < after


@st.composite
def _garbage(draw) -> bytes:
    kind = draw(st.sampled_from(["noise", "truncated", "corrupted", "starts"]))
    if kind == "noise":
        return draw(st.binary(min_size=1, max_size=40))
    if kind == "starts":
        return bytes(draw(st.lists(st.sampled_from([START_BYTE, 2, 6, 40, 0, 0xFF]), max_size=12)))
    packet = bytearray(
        encode(
            "CONFIGURE",
            draw(st.integers(0, 255)),
            source=0,
            pulse_width_ticks=1,
            period_ticks=2,
            encoder_divisor=3,
            count=4,
            start_tick=5,
        )
        if draw(st.booleans())
        else encode("PING", draw(st.integers(0, 255)), token=draw(st.integers(0, 2**32 - 1)))
    )
    if kind == "truncated":
        return bytes(packet[: draw(st.integers(1, len(packet) - 1))])
    packet[draw(st.integers(1, len(packet) - 1))] ^= draw(st.integers(1, 255))
    return bytes(packet)


_tokens = itertools.count(1)


def _pongs_expected(stream: bytes, expected_seq: int) -> list[int]:
    """The PING tokens the firmware must answer for `stream`: the packets the host's reference
    decoder finds in it (a truncated packet can, rarely, be completed into a valid one by the
    next bytes; both parsers then agree on that), through the firmware's sequence rule."""
    decoder = PacketDecoder()
    packets = decoder.feed(stream)
    while decoder.pending():
        packets.extend(decoder.give_up_partial())
    tokens = []
    for packet in packets:
        if packet.name == "HELLO" and not packet.problem:
            expected_seq = (packet.seq + 1) % 256
        elif packet.seq == expected_seq:
            expected_seq = (expected_seq + 1) % 256
            if packet.name == "PING" and not packet.problem:
                tokens.append(packet.values["token"])
    return tokens


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(st.lists(st.tuples(_garbage(), st.booleans()), min_size=1, max_size=6))
def test_firmware_parser_survives_garbage(shared_link, pieces):
    """Garbage, truncated and corrupted packets interleaved with PINGs: the firmware answers
    exactly the PINGs the host's reference decoder finds (normally all of them), and nothing
    else, so the stream is never desynchronised."""
    link = shared_link
    link.hello(seq=0)
    stream = b""
    sent = []
    for garbage, ping_after in [*pieces, (b"", True)]:
        stream += garbage
        if ping_after:
            token = next(_tokens)
            sent.append(token)
            stream += encode("PING", link.seq, token=token)
            link.seq = (link.seq + 1) % 256
    expected = _pongs_expected(stream, 1)
    first = len(link.received)
    link.send_raw(stream)
    for token in expected:
        link.expect("PONG", token=token, timeout_s=2.0)
    link.hello(seq=0)
    answered = [
        f.values["token"]
        for f in link.received[first:]
        if f.name == "PONG" and f.values["token"] in sent
    ]
    assert answered == expected


def test_watchdog_resets_a_hung_firmware(start_mcu):
    mcu, link = start_mcu(test_build=True)
    assert link.expect("BOOT").values["cause"] == ResetCause.POWER_ON
    link.hello()
    assert configure(link, width=200, period=2000).name == "ACK"
    assert link.command("ARM").name == "ACK"
    link.expect("TRIGGER")
    mcu.drive_pin("C0", 0)
    boot = link.expect("BOOT", timeout_s=3.0)
    assert boot.values["cause"] == ResetCause.WATCHDOG and boot.seq == 0
    assert len(mcu.resets()) == 1
    wait_until(lambda: mcu.edges()[-1][2] == 0)
    link.hello()
    link.send("PING", token=99)
    link.expect("PONG", token=99)
    after_reset = mcu.edges()
    time.sleep(0.05)
    assert mcu.edges() == after_reset


def test_production_build_has_no_hang_pin(start_mcu):
    mcu, link = start_mcu()
    link.expect("BOOT")
    link.hello()
    mcu.drive_pin("C0", 0)
    time.sleep(0.3)
    link.send("PING", token=5)
    link.expect("PONG", token=5)
    assert mcu.resets() == []
    assert len(link.packets("BOOT")) == 1
