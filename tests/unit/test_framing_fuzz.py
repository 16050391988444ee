"""Property tests of the frame codec: garbage never costs a valid frame, splits never matter."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_bridge.framing import DecoderStatistics, FrameDecoder, FramingError, encode
from firmware_bridge.messages import MAX_LEN, MESSAGES, START_BYTE, crc16

RANGES = {
    "u8": (0, 2**8 - 1),
    "u16": (0, 2**16 - 1),
    "u32": (0, 2**32 - 1),
    "u64": (0, 2**64 - 1),
    "i32": (-(2**31), 2**31 - 1),
}


@st.composite
def valid_frames(draw) -> bytes:
    """One frame of any message in the table, any sequence number, any field values."""
    message = draw(st.sampled_from(MESSAGES))
    values = {name: draw(st.integers(*RANGES[kind])) for name, kind in message.fields}
    return encode(message.name, draw(st.integers(0, 255)), **values)


@st.composite
def truncated_frames(draw) -> bytes:
    frame = draw(valid_frames())
    return frame[: draw(st.integers(1, len(frame) - 1))]


@st.composite
def corrupted_frames(draw) -> bytes:
    frame = bytearray(draw(valid_frames()))
    index = draw(st.integers(1, len(frame) - 1))
    frame[index] ^= draw(st.integers(1, 255))
    return bytes(frame)


noise = st.binary(min_size=1, max_size=60)
start_heavy_noise = st.lists(
    st.sampled_from([START_BYTE, 0x02, 0x03, MAX_LEN, 0x00, 0xFF]), min_size=1, max_size=20
).map(bytes)
line_noise = st.one_of(noise, start_heavy_noise, corrupted_frames())
"""Damage within a stream that goes on: noise, start bytes, frames with wrong bytes."""
garbage = st.one_of(line_noise, truncated_frames())
"""Also frames cut short: what a sender leaves when it stops (reset, unplugged), so the line
is quiet after one (see test_a_truncated_frame_can_swallow_the_next_start_byte)."""


def drain(decoder: FrameDecoder) -> list[bytes]:
    """What a receiver does when the line goes quiet: give up partials until nothing is held."""
    frames = []
    while decoder.pending():
        frames.extend(f.raw for f in decoder.give_up_partial())
    return frames


def assert_none_lost(wanted: list[bytes], got: list[bytes]) -> None:
    """Every valid frame came out, in order, except where garbage completed into a frame with
    a good CRC that took some of its bytes: a frame is lost only to such an extra frame."""
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
                valid_frames().map(lambda f: (True, False, f)),
                line_noise.map(lambda g: (False, False, g)),
                truncated_frames().map(lambda g: (False, True, g)),
            ),
            st.booleans(),
        ),
        min_size=1,
        max_size=25,
    )
)
def test_every_valid_frame_after_garbage_is_received(chunks):
    """Chunks are whole valid frames or garbage; a quiet point (give_up_partial) may follow
    any chunk, and always follows a truncated frame. Every valid frame comes out, in order.
    Garbage may by chance form a frame with a good CRC (a corrupted frame can still check,
    noise can end like a frame cut short), and that frame may take bytes of the next one:
    extra frames are allowed, and a lost one only with such an extra frame."""
    decoder = FrameDecoder()
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
    assert decoder.statistics.frames == len(got)
    assert decoder.pending() == 0


@settings(max_examples=200, deadline=None)
@given(
    frames=st.lists(valid_frames(), min_size=1, max_size=10),
    garbage_pieces=st.lists(garbage, min_size=1, max_size=10),
)
def test_valid_frames_interleaved_with_garbage_without_quiet_points(frames, garbage_pieces):
    """A busy line (no quiet point until the end) still yields every valid frame but those
    garbage completed into a good-CRC frame (test_a_truncated_frame_can_swallow_...)."""
    stream = bytearray()
    for i, frame in enumerate(frames):
        stream += garbage_pieces[i % len(garbage_pieces)]
        stream += frame
    decoder = FrameDecoder()
    got = [f.raw for f in decoder.feed(bytes(stream))] + drain(decoder)
    assert_none_lost(frames, got)


@settings(max_examples=200, deadline=None)
@given(
    stream=st.lists(st.one_of(valid_frames(), garbage), max_size=15).map(b"".join),
    cuts=st.lists(st.integers(0, 2000), max_size=30),
)
def test_any_split_of_the_stream_gives_the_same_frames(stream, cuts):
    whole = FrameDecoder()
    expected = [f.raw for f in whole.feed(stream)] + drain(whole)
    pieces = sorted({c % (len(stream) + 1) for c in cuts} | {0, len(stream)})
    split = FrameDecoder()
    got: list[bytes] = []
    for begin, end in zip(pieces, pieces[1:], strict=False):
        got.extend(f.raw for f in split.feed(stream[begin:end]))
    got.extend(drain(split))
    assert got == expected
    assert split.statistics == whole.statistics


@settings(max_examples=200, deadline=None)
@given(
    stream=st.lists(st.one_of(valid_frames(), garbage), max_size=15).map(b"".join),
    cuts=st.lists(st.integers(0, 2000), max_size=30),
)
def test_quiet_points_inside_the_stream_do_not_change_the_frames(stream, cuts):
    """A pause at any byte (the receiver calls recover_behind_partial there) yields the same
    frames as the stream without pauses: a held start byte is dropped early only when the
    search the CRC check would make finds a whole frame behind it."""
    whole = FrameDecoder()
    expected = [f.raw for f in whole.feed(stream)] + drain(whole)
    pieces = sorted({c % (len(stream) + 1) for c in cuts} | {0, len(stream)})
    paused = FrameDecoder()
    got: list[bytes] = []
    for begin, end in zip(pieces, pieces[1:], strict=False):
        got.extend(f.raw for f in paused.feed(stream[begin:end]))
        got.extend(f.raw for f in paused.recover_behind_partial())
    got.extend(drain(paused))
    assert got == expected


@settings(max_examples=100, deadline=None)
@given(frame=valid_frames(), cut=st.integers(1, 1000), pauses=st.integers(1, 5))
def test_a_frame_whose_rest_is_late_is_kept_at_quiet_points(frame, cut, pauses):
    cut = 1 + cut % (len(frame) - 1)
    decoder = FrameDecoder()
    assert decoder.feed(frame[:cut]) == []
    for _ in range(pauses):
        assert decoder.recover_behind_partial() == []
    assert decoder.pending() == cut
    assert [f.raw for f in decoder.feed(frame[cut:])] == [frame]
    assert decoder.statistics == DecoderStatistics(frames=1)


def test_a_whole_frame_behind_a_noise_start_byte_is_taken_at_a_quiet_point():
    frame = encode("PING", 3, token=99)
    decoder = FrameDecoder()
    assert decoder.feed(bytes([START_BYTE, MAX_LEN]) + frame) == []
    assert [f.raw for f in decoder.recover_behind_partial()] == [frame]
    assert decoder.pending() == 0
    assert decoder.statistics.skipped_bytes == 2 and decoder.statistics.frames == 1


@settings(max_examples=200, deadline=None)
@given(data=st.binary(max_size=500), cuts=st.lists(st.integers(0, 500), max_size=10))
def test_random_bytes_never_raise(data, cuts):
    decoder = FrameDecoder()
    pieces = sorted({c % (len(data) + 1) for c in cuts} | {0, len(data)})
    for begin, end in zip(pieces, pieces[1:], strict=False):
        for frame in decoder.feed(data[begin:end]):
            assert frame.raw[0] == START_BYTE
        decoder.give_up_partial()
    drain(decoder)
    stats = decoder.statistics
    assert stats.skipped_bytes <= len(data)


@settings(max_examples=100, deadline=None)
@given(frame=valid_frames())
def test_a_frame_decodes_to_the_values_it_was_built_from(frame):
    (decoded,) = FrameDecoder().feed(frame)
    assert decoded.problem == ""
    assert decoded.raw == frame
    again = encode(decoded.name, decoded.seq, **decoded.values)
    assert again == frame


def test_a_truncated_frame_can_swallow_the_next_start_byte():
    """A limit of the framing, kept visible: a frame cut just before its last CRC byte,
    when that byte is 0xA5 (one frame in 256), is completed by the start byte of the frame
    that follows, and that frame is lost. A short pause in between does not save it (the
    rest of the cut frame might be late); a silence long enough for the receiver to give up
    the partial does."""
    cut = encode("ACK", 0x85, acked_seq=0xA9)
    assert cut[-1] == START_BYTE
    following = encode("HELLO", 0)
    busy = FrameDecoder()
    got = [f.raw for f in busy.feed(cut[:-1] + following)] + drain(busy)
    assert got == [cut]
    paused = FrameDecoder()
    assert paused.feed(cut[:-1]) == [] and paused.recover_behind_partial() == []
    assert [f.raw for f in paused.feed(following)] == [cut]
    quiet = FrameDecoder()
    assert quiet.feed(cut[:-1]) == []
    got = [f.raw for f in quiet.give_up_partial() + quiet.feed(following)]
    assert got == [following]


def _raw_frame(seq: int, message_id: int, payload: bytes) -> bytes:
    body = bytes([len(payload) + 2, seq, message_id]) + payload
    crc = crc16(body)
    return bytes([START_BYTE]) + body + bytes([crc & 0xFF, crc >> 8])


def test_good_crc_with_an_unknown_id_or_a_wrong_payload_is_returned_with_its_problem():
    unknown, short = FrameDecoder().feed(
        _raw_frame(7, 0x7E, b"") + _raw_frame(8, 0x02, b"\x01\x02")
    )
    assert unknown.problem == "unknown message" and unknown.name == "UNKNOWN_0x7e"
    assert short.problem == "bad payload" and short.name == "PING" and short.values == {}


def test_lengths_outside_the_limits_are_skipped():
    decoder = FrameDecoder()
    frame = encode("PING", 3, token=99)
    got = decoder.feed(bytes([START_BYTE, 1, START_BYTE, MAX_LEN + 1]) + frame)
    assert [f.raw for f in got] == [frame]
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
    with pytest.raises(FramingError):
        encode(name, seq, **values)


def test_encode_lays_out_the_documented_wire_format():
    frame = encode("PING", 0x12, token=0x01020304)
    assert frame[:4] == bytes([START_BYTE, 6, 0x12, 0x02])
    assert frame[4:8] == struct.pack("<I", 0x01020304)
    assert int.from_bytes(frame[8:10], "little") == crc16(frame[1:8])
    assert crc16(b"123456789") == 0x29B1
