"""Fuzzing the Modbus TCP server's request handling with hypothesis, over a real socket.

Any byte string sent on a connection, followed by the client's end of stream, gets well-formed
Modbus TCP answers (a served function's response or an exception 1 ... 4, for a unit id the
server answers) or none, and then the server closes the connection; it never crashes and
always answers a well-formed read on a fresh connection afterwards. The inputs are raw bytes,
sequences of MBAP frames with true or lying lengths and protocol ids, random PDUs behind
valid headers, and mixtures of these.
"""

from __future__ import annotations

import socket
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.config import ModbusConfig
from appliance.live.modbus_map import SERVED_FUNCTION_CODES
from appliance.live.modbus_server import StrainRegisterServer
from tests.system.modbus_peers import (
    free_tcp_port,
    make_sample,
    receive_until_closed,
    split_frames,
    timed_read,
)

UNIT_ID = 7
ANSWERED_UNIT_IDS = {UNIT_ID, 0, 255}

function_codes = st.one_of(st.sampled_from(sorted(SERVED_FUNCTION_CODES)), st.integers(0, 255))
pdus = st.one_of(
    st.tuples(function_codes, st.binary(max_size=260)).map(lambda p: bytes((p[0],)) + p[1]),
    st.builds(
        lambda fc, address, count: struct.pack(">BHH", fc, address, count),
        st.sampled_from((3, 4, 6)),
        st.integers(0, 0xFFFF),
        st.integers(0, 0xFFFF),
    ),
)


@st.composite
def frames(draw) -> bytes:
    """One MBAP frame: a PDU behind a header whose length and protocol id may lie."""
    pdu = draw(pdus)
    length = draw(st.one_of(st.just(len(pdu) + 1), st.integers(0, 0xFFFF)))
    protocol_id = draw(st.sampled_from((0, 0, 0, 1, 0xFFFF)))
    unit_id = draw(st.sampled_from((UNIT_ID, UNIT_ID, 0, 255, 1, 8)))
    tid = draw(st.integers(0, 0xFFFF))
    return struct.pack(">HHHB", tid, protocol_id, length, unit_id) + pdu


streams = st.one_of(
    st.binary(max_size=600),
    st.lists(frames(), min_size=1, max_size=6).map(b"".join),
    st.tuples(st.lists(frames(), max_size=3), st.binary(max_size=40)).map(
        lambda p: b"".join(p[0]) + p[1]
    ),
)


@pytest.fixture(scope="module")
def port():
    number = free_tcp_port()
    config = ModbusConfig(tcp=f"127.0.0.1:{number}", unit_id=UNIT_ID, idle_timeout_s=5.0)
    server = StrainRegisterServer(config, lambda name, value: True)
    server.start(timeout_s=30.0)
    server.publish(make_sample(), None)
    yield number
    server.close()


@settings(max_examples=200, deadline=None)
@given(data=streams)
def test_any_bytes_get_valid_answers_or_a_close_and_never_stop_the_server(port, data):
    with socket.create_connection(("127.0.0.1", port), timeout=10.0) as sock:
        try:
            sock.sendall(data)
            sock.shutdown(socket.SHUT_WR)
        except ConnectionError:
            pass
        received, closed = receive_until_closed(sock, 10.0)
    assert closed, "the server kept a connection open after the client's end of stream"
    answers, rest = split_frames(received)
    assert rest == b"", f"a partial answer: {received!r}"
    for _, protocol_id, unit_id, pdu in answers:
        assert protocol_id == 0 and unit_id in ANSWERED_UNIT_IDS, (protocol_id, unit_id)
        if pdu[0] & 0x80:
            assert len(pdu) == 2 and pdu[1] in (1, 2, 3, 4), pdu
        else:
            assert pdu[0] in SERVED_FUNCTION_CODES, pdu
    timed_read(port, timeout_s=10.0, unit_id=UNIT_ID)
