"""Property tests of the packet codec: garbage never costs a valid packet, splits never matter."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_bridge.messages import MAX_LEN, MESSAGES, START_BYTE, crc16
from firmware_bridge.packets import DecoderStatistics, PacketDecoder, PacketError, encode

RANGES = {
    "u8": (0, 2**8 - 1),
    "u16": (0, 2**16 - 1),
    "u32": (0, 2**32 - 1),
    "u64": (0, 2**64 - 1),
    "i32": (-(2**31), 2**31 - 1),
}


@st.composite
def valid_packets(draw) -> bytes:
    """One packet of any message in the table, any sequence number, any field values."""
    message = draw(st.sampled_from(MESSAGES))
    values = {name: draw(st.integers(*RANGES[kind])) for name, kind in message.fields}
    return encode(message.name, draw(st.integers(0, 255)), **values)


@st.composite
def truncated_packets(draw) -> bytes:
    packet = draw(valid_packets())
    return packet[: draw(st.integers(1, len(packet) - 1))]


@st.composite
def corrupted_packets(draw) -> bytes:
    packet = bytearray(draw(valid_packets()))
    index = draw(st.integers(1, len(packet) - 1))
    packet[index] ^= draw(st.integers(1, 255))
    return bytes(packet)


noise = st.binary(min_size=1, max_size=60)
start_heavy_noise = st.lists(
    st.sampled_from([START_BYTE, 0x02, 0x03, MAX_LEN, 0x00, 0xFF]), min_size=1, max_size=20
).map(bytes)
line_noise = st.one_of(noise, start_heavy_noise, corrupted_packets())
"""Damage within a stream that goes on: noise, start bytes, packets with wrong bytes."""
garbage = st.one_of(line_noise, truncated_packets())
"""Also packets cut short: what a sender leaves when it stops (reset, unplugged), so the line
is quiet after one (see test_a_truncated_packet_can_swallow_the_next_start_byte)."""


def drain(decoder: PacketDecoder) -> list[bytes]:
    """What a receiver does when the line goes quiet: give up partials until nothing is held."""
    packets = []
    while decoder.pending():
        packets.extend(f.raw for f in decoder.give_up_partial())
    return packets


def assert_none_lost(wanted: list[bytes], got: list[bytes]) -> None:
    """Every valid packet came out, in order, except where garbage completed into a packet with
    a good CRC that took some of its bytes: a packet is lost only to such an extra packet."""
    remaining = list(got)
    missing = 0
    position = 0
    for item in wanted:
        try:
            position = remaining.index(item, position) + 1
        except ValueError:
            missing += 1
    extra = len(got) - (len(wanted) - missing)
    assert missing <= extra, (wanted, got)


@settings(max_examples=300, deadline=None)
@given(
    chunks=st.lists(
        st.tuples(
            st.one_of(
                valid_packets().map(lambda f: (True, False, f)),
                line_noise.map(lambda g: (False, False, g)),
                truncated_packets().map(lambda g: (False, True, g)),
            ),
            st.booleans(),
        ),
        min_size=1,
        max_size=25,
    )
)
def test_every_valid_packet_after_garbage_is_received(chunks):
    """Chunks are whole valid packets or garbage; a quiet point (give_up_partial) may follow
    any chunk, and always follows a truncated packet. Every valid packet comes out, in order.
    Garbage may by chance form a packet with a good CRC (a corrupted packet can still check,
    noise can end like a packet cut short), and that packet may take bytes of the next one:
    extra packets are allowed, and a lost one only with such an extra packet."""
    decoder = PacketDecoder()
    wanted: list[bytes] = []
    got: list[bytes] = []
    for (is_valid, sender_stopped, data), quiet_after in chunks:
        if is_valid:
            wanted.append(data)
        got.extend(f.raw for f in decoder.feed(data))
        if quiet_after or sender_stopped:
            got.extend(f.raw for f in decoder.give_up_partial())
    got.extend(drain(decoder))
    assert_none_lost(wanted, got)
    assert decoder.statistics.packets == len(got)
    assert decoder.pending() == 0


@settings(max_examples=200, deadline=None)
@given(
    packets=st.lists(valid_packets(), min_size=1, max_size=10),
    garbage_pieces=st.lists(garbage, min_size=1, max_size=10),
)
def test_valid_packets_interleaved_with_garbage_without_quiet_points(packets, garbage_pieces):
    """A busy line (no quiet point until the end) still yields every valid packet but those
    garbage completed into a good-CRC packet (test_a_truncated_packet_can_swallow_...)."""
    stream = bytearray()
    for i, packet in enumerate(packets):
        stream += garbage_pieces[i % len(garbage_pieces)]
        stream += packet
    decoder = PacketDecoder()
    got = [f.raw for f in decoder.feed(bytes(stream))] + drain(decoder)
    assert_none_lost(packets, got)


@settings(max_examples=200, deadline=None)
@given(
    stream=st.lists(st.one_of(valid_packets(), garbage), max_size=15).map(b"".join),
    cuts=st.lists(st.integers(0, 2000), max_size=30),
)
def test_any_split_of_the_stream_gives_the_same_packets(stream, cuts):
    whole = PacketDecoder()
    expected = [f.raw for f in whole.feed(stream)] + drain(whole)
    pieces = sorted({c % (len(stream) + 1) for c in cuts} | {0, len(stream)})
    split = PacketDecoder()
    got: list[bytes] = []
    for begin, end in zip(pieces, pieces[1:], strict=False):
        got.extend(f.raw for f in split.feed(stream[begin:end]))
    got.extend(drain(split))
    assert got == expected
    assert split.statistics == whole.statistics


@settings(max_examples=200, deadline=None)
@given(
    stream=st.lists(st.one_of(valid_packets(), garbage), max_size=15).map(b"".join),
    cuts=st.lists(st.integers(0, 2000), max_size=30),
)
def test_quiet_points_inside_the_stream_do_not_change_the_packets(stream, cuts):
    """A pause at any byte (the receiver calls recover_behind_partial there) yields the same
    packets as the stream without pauses: a held start byte is dropped early only when the
    search the CRC check would make finds a whole packet behind it."""
    whole = PacketDecoder()
    expected = [f.raw for f in whole.feed(stream)] + drain(whole)
    pieces = sorted({c % (len(stream) + 1) for c in cuts} | {0, len(stream)})
    paused = PacketDecoder()
    got: list[bytes] = []
    for begin, end in zip(pieces, pieces[1:], strict=False):
        got.extend(f.raw for f in paused.feed(stream[begin:end]))
        got.extend(f.raw for f in paused.recover_behind_partial())
    got.extend(drain(paused))
    assert got == expected


@settings(max_examples=100, deadline=None)
@given(packet=valid_packets(), cut=st.integers(1, 1000), pauses=st.integers(1, 5))
def test_a_packet_whose_rest_is_late_is_kept_at_quiet_points(packet, cut, pauses):
    cut = 1 + cut % (len(packet) - 1)
    decoder = PacketDecoder()
    assert decoder.feed(packet[:cut]) == []
    for _ in range(pauses):
        assert decoder.recover_behind_partial() == []
    assert decoder.pending() == cut
    assert [f.raw for f in decoder.feed(packet[cut:])] == [packet]
    assert decoder.statistics == DecoderStatistics(packets=1)


def test_a_whole_packet_behind_a_noise_start_byte_is_taken_at_a_quiet_point():
    packet = encode("PING", 3, token=99)
    decoder = PacketDecoder()
    assert decoder.feed(bytes([START_BYTE, MAX_LEN]) + packet) == []
    assert [f.raw for f in decoder.recover_behind_partial()] == [packet]
    assert decoder.pending() == 0
    assert decoder.statistics.skipped_bytes == 2 and decoder.statistics.packets == 1


@settings(max_examples=200, deadline=None)
@given(data=st.binary(max_size=500), cuts=st.lists(st.integers(0, 500), max_size=10))
def test_random_bytes_never_raise(data, cuts):
    decoder = PacketDecoder()
    pieces = sorted({c % (len(data) + 1) for c in cuts} | {0, len(data)})
    for begin, end in zip(pieces, pieces[1:], strict=False):
        for packet in decoder.feed(data[begin:end]):
            assert packet.raw[0] == START_BYTE
        decoder.give_up_partial()
    drain(decoder)
    stats = decoder.statistics
    assert stats.skipped_bytes <= len(data)


@settings(max_examples=100, deadline=None)
@given(packet=valid_packets())
def test_a_packet_decodes_to_the_values_it_was_built_from(packet):
    (decoded,) = PacketDecoder().feed(packet)
    assert decoded.problem == ""
    assert decoded.raw == packet
    again = encode(decoded.name, decoded.seq, **decoded.values)
    assert again == packet


def test_a_truncated_packet_can_swallow_the_next_start_byte():
    """A limit of the packets, kept visible: a packet cut just before its last CRC byte,
    when that byte is 0xA5 (one packet in 256), is completed by the start byte of the packet
    that follows, and that packet is lost. A short pause in between does not save it (the
    rest of the cut packet might be late); a silence long enough for the receiver to give up
    the partial does."""
    cut = encode("ACK", 0x85, acked_seq=0xA9)
    assert cut[-1] == START_BYTE
    following = encode("HELLO", 0)
    busy = PacketDecoder()
    got = [f.raw for f in busy.feed(cut[:-1] + following)] + drain(busy)
    assert got == [cut]
    paused = PacketDecoder()
    assert paused.feed(cut[:-1]) == [] and paused.recover_behind_partial() == []
    assert [f.raw for f in paused.feed(following)] == [cut]
    quiet = PacketDecoder()
    assert quiet.feed(cut[:-1]) == []
    got = [f.raw for f in quiet.give_up_partial() + quiet.feed(following)]
    assert got == [following]


def _raw_packet(seq: int, message_id: int, payload: bytes) -> bytes:
    body = bytes([len(payload) + 2, seq, message_id]) + payload
    crc = crc16(body)
    return bytes([START_BYTE]) + body + bytes([crc & 0xFF, crc >> 8])


def test_good_crc_with_an_unknown_id_or_a_wrong_payload_is_returned_with_its_problem():
    unknown, short = PacketDecoder().feed(
        _raw_packet(7, 0x7E, b"") + _raw_packet(8, 0x02, b"\x01\x02")
    )
    assert unknown.problem == "unknown message" and unknown.name == "UNKNOWN_0x7e"
    assert short.problem == "bad payload" and short.name == "PING" and short.values == {}


def test_lengths_outside_the_limits_are_skipped():
    decoder = PacketDecoder()
    packet = encode("PING", 3, token=99)
    got = decoder.feed(bytes([START_BYTE, 1, START_BYTE, MAX_LEN + 1]) + packet)
    assert [f.raw for f in got] == [packet]
    assert decoder.statistics.length_errors == 2
    decoder.feed(bytes([START_BYTE, MAX_LEN]))
    assert decoder.pending() == 2 and decoder.statistics.length_errors == 2


@pytest.mark.parametrize(
    ("name", "seq", "values"),
    [
        ("NO_SUCH_MESSAGE", 0, {}),
        ("PING", 0, {}),
        ("PING", 0, {"token": 1, "extra": 2}),
        ("PING", -1, {"token": 1}),
        ("PING", 256, {"token": 1}),
        ("PING", 0, {"token": 2**32}),
        ("PING", 0, {"token": -1}),
        ("PING", 0, {"token": "one"}),
        ("SET_DEAD_MAN", 0, {"timeout_ms": 2**16}),
        ("TRIGGER", 0, {"trigger_seq": 0, "tick": 0, "position": 2**31}),
        ("TRIGGER", 0, {"trigger_seq": 0, "tick": 2**64, "position": 0}),
        ("CONFIGURE", 0, {"source": 0}),
    ],
)
def test_encode_refuses_bad_fields(name, seq, values):
    with pytest.raises(PacketError):
        encode(name, seq, **values)


def test_encode_lays_out_the_documented_wire_format():
    packet = encode("PING", 0x12, token=0x01020304)
    assert packet[:4] == bytes([START_BYTE, 6, 0x12, 0x02])
    assert packet[4:8] == struct.pack("<I", 0x01020304)
    assert int.from_bytes(packet[8:10], "little") == crc16(packet[1:8])
    assert crc16(b"123456789") == 0x29B1
