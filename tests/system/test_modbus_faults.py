"""The Modbus TCP server under the faults a plant network brings: idle and half-open
connections, connection floods, pipelined requests, functions it does not serve, garbage,
lying headers, many clients at once and a client that never reads.

Every server binds 127.0.0.1 on a free port; the clients are raw sockets speaking Modbus TCP
byte by byte. Each test is bounded by its own deadlines; the assertions are on what a
controller gets (answers, exception codes, closed connections) and on the log staying short,
with generous bounds on time for a loaded host, never timing targets.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import random
import re
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest

from appliance.config import ModbusConfig
from appliance.live.modbus_map import SERVED_FUNCTION_CODES
from appliance.live.modbus_server import StrainRegisterServer
from appliance.run.state import RunState
from tests.system.modbus_peers import (
    free_tcp_port,
    is_closed_by_peer,
    make_sample,
    mbap,
    read_registers_pdu,
    receive_frames,
    receive_until_closed,
    split_frames,
    timed_read,
    wait_closed_by_peer_unread,
)

ANSWER_BOUND_S = 3.0
"""The longest a controller's read may take under a fault on a loaded 2-core host."""

LOG_BOUND = 30
"""The most log records a whole fault test may leave (each a single line)."""

ILLEGAL_FUNCTION, ILLEGAL_ADDRESS, ILLEGAL_VALUE = 1, 2, 3


@pytest.fixture
def serve():
    """Factory: a started server on 127.0.0.1 and a free port -> (server, port); all closed."""
    servers: list[StrainRegisterServer] = []

    def start(**modbus) -> tuple[StrainRegisterServer, int]:
        port = free_tcp_port()
        config = ModbusConfig(tcp=f"127.0.0.1:{port}", **modbus)
        server = StrainRegisterServer(config, lambda name, value: True)
        servers.append(server)
        server.start(timeout_s=30.0)
        server.set_run_state(RunState.RUNNING)
        server.publish(make_sample(), None)
        return server, port

    yield start
    for server in servers:
        server.close()


@pytest.fixture
def log_records(caplog):
    """The warning-and-above records the test leaves, from every logger."""
    caplog.set_level(logging.WARNING)
    return caplog


def _assert_log_is_bounded(caplog) -> None:
    records = caplog.records
    assert len(records) <= LOG_BOUND, [r.getMessage() for r in records[:40]]
    for record in records:
        assert record.exc_info is None, record.getMessage()
        assert "\n" not in record.getMessage(), record.getMessage()


def _connect(port: int, timeout_s: float = 10.0) -> socket.socket:
    return socket.create_connection(("127.0.0.1", port), timeout=timeout_s)


def _exchange(port: int, payload: bytes, count: int, timeout_s: float = 10.0):
    with _connect(port) as sock:
        sock.sendall(payload)
        return receive_frames(sock, count, timeout_s)


def _exception_code(frame, function_code: int) -> int:
    _, protocol_id, _, pdu = frame
    assert protocol_id == 0 and len(pdu) == 2, frame
    assert pdu[0] == function_code | 0x80, frame
    return pdu[1]


def test_pipelined_requests_in_one_segment_are_all_answered_in_order(serve):
    _, port = serve()
    requests = [
        (11, read_registers_pdu(0, 2)),
        (12, read_registers_pdu(10, 4, function_code=4)),
        (13, struct.pack(">BHH", 6, 100, 3)),
        (14, read_registers_pdu(100, 3)),
        (15, read_registers_pdu(500, 1)),
        (16, read_registers_pdu(12, 2)),
    ]
    payload = b"".join(mbap(tid, pdu) for tid, pdu in requests)
    frames = _exchange(port, payload, len(requests))
    assert [frame[0] for frame in frames] == [tid for tid, _ in requests]
    assert frames[0][3][:2] == bytes((3, 4))
    assert frames[1][3][:2] == bytes((4, 8))
    assert frames[2][3] == struct.pack(">BHH", 6, 100, 3), "the write is echoed"
    assert frames[3][3] == bytes((3, 6)) + struct.pack(">HHH", 3, 1, 1), "it saw the write"
    assert _exception_code(frames[4], 3) == ILLEGAL_ADDRESS
    assert frames[5][3] == bytes((3, 4)) + struct.pack(">I", 70_000)


def test_a_request_split_over_many_segments_is_answered_once_whole(serve):
    _, port = serve()
    frame = mbap(21, read_registers_pdu(0, 4)) + mbap(22, read_registers_pdu(4, 2))
    with _connect(port) as sock:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        for index in range(len(frame)):
            sock.sendall(frame[index : index + 1])
            time.sleep(0.002)
        frames = receive_frames(sock, 2)
    assert [(f[0], f[3][:2]) for f in frames] == [(21, bytes((3, 8))), (22, bytes((3, 4)))]


UNSERVED_REQUESTS = {
    1: struct.pack(">BHH", 1, 0, 8),
    2: struct.pack(">BHH", 2, 0, 8),
    5: struct.pack(">BHH", 5, 100, 0xFF00),
    7: bytes((7,)),
    8: struct.pack(">BHH", 8, 0, 0x1234),
    11: bytes((11,)),
    12: bytes((12,)),
    15: struct.pack(">BHHBB", 15, 0, 8, 1, 0xFF),
    17: bytes((17,)),
    20: bytes((20, 7, 6)) + struct.pack(">HHH", 1, 0, 1),
    21: bytes((21, 9, 6)) + struct.pack(">HHHH", 1, 0, 1, 7),
    24: struct.pack(">BH", 24, 0),
    43: bytes((43, 14, 1, 0)),
    65: bytes((65, 1, 2, 3)),
}


def test_functions_the_map_does_not_serve_get_illegal_function(serve):
    _, port = serve()
    assert set(UNSERVED_REQUESTS).isdisjoint(SERVED_FUNCTION_CODES)
    for function_code, pdu in UNSERVED_REQUESTS.items():
        frames = _exchange(port, mbap(function_code, pdu), 1)
        assert frames, f"function {function_code}: no answer"
        assert _exception_code(frames[0], function_code) == ILLEGAL_FUNCTION, function_code
    frames = _exchange(port, mbap(99, read_registers_pdu(0, 2)), 1)
    assert frames[0][3][:2] == bytes((3, 4)), "a served function still answers"


def test_malformed_requests_of_served_functions_get_illegal_data_value(serve):
    _, port = serve()
    malformed = {
        "quantity 65535": read_registers_pdu(0, 0xFFFF),
        "quantity 126": read_registers_pdu(0, 126),
        "quantity 0": read_registers_pdu(0, 0, function_code=4),
        "address only": struct.pack(">BH", 3, 0),
        "a read with a byte more": read_registers_pdu(0, 2) + b"\x00",
        "write single without value": struct.pack(">BH", 6, 100),
        "byte count 3 for 2 registers": struct.pack(">BHHB", 16, 103, 2, 3) + bytes(3),
        "4 bytes announced, 2 sent": struct.pack(">BHHB", 16, 103, 2, 4) + bytes(2),
        "write 0 registers": struct.pack(">BHHB", 16, 103, 0, 0),
        "read/write of 0 registers": struct.pack(">BHHHHB", 23, 0, 0, 100, 1, 2) + bytes(2),
    }
    for what, pdu in malformed.items():
        frames = _exchange(port, mbap(7, pdu), 1)
        assert frames, f"{what}: no answer"
        assert _exception_code(frames[0], pdu[0]) == ILLEGAL_VALUE, what
    assert timed_read(port) < ANSWER_BOUND_S


def test_idle_and_slowloris_connections_are_closed_after_the_idle_timeout(serve, log_records):
    _, port = serve(idle_timeout_s=1.0)
    partial = mbap(1, read_registers_pdu(0, 2))
    idle = [_connect(port) for _ in range(6)]
    header_only = [_connect(port) for _ in range(6)]
    body_missing = [_connect(port) for _ in range(6)]
    for sock in header_only:
        sock.sendall(partial[:3])
    for sock in body_missing:
        sock.sendall(partial[:9])
    controller = _connect(port)
    slow = idle + header_only + body_missing
    try:
        deadline = time.monotonic() + 15.0
        still_open = slow
        transaction_id = 0
        while still_open and time.monotonic() < deadline:
            transaction_id += 1
            controller.sendall(mbap(transaction_id, read_registers_pdu(0, 2)))
            answered = receive_frames(controller, 1, ANSWER_BOUND_S)
            assert [frame[0] for frame in answered] == [transaction_id]
            time.sleep(0.25)
            still_open = [sock for sock in still_open if not is_closed_by_peer(sock)]
        assert still_open == [], f"{len(still_open)} of {len(slow)} idle connections left open"
        assert transaction_id >= 3, "the idle ones closed before the timeout"
        assert not is_closed_by_peer(controller), "a polling controller is never idle"
    finally:
        for sock in (*slow, controller):
            sock.close()
    _assert_log_is_bounded(log_records)


def test_the_service_unit_allows_more_descriptors_than_the_connections_can_take():
    unit = (Path(__file__).parents[2] / "systemd" / "extensometer.service").read_text("utf-8")
    limits = re.findall(r"^LimitNOFILE=(\d+)$", unit, re.MULTILINE)
    assert len(limits) == 1, "the unit sets no LimitNOFILE (the soft default is 1024)"
    most = {f.name: f for f in dataclasses.fields(ModbusConfig)}["max_connections"]
    assert int(limits[0]) >= most.metadata["maximum"] + 4096


def test_a_connection_flood_drops_the_oldest_idle_and_lets_the_controller_in(serve, log_records):
    server, port = serve()
    limit = server.config.max_connections
    controller = _connect(port)
    flood: list[socket.socket] = []
    worst_s = 0.0
    try:
        for index in range(1100):
            try:
                flood.append(_connect(port, timeout_s=5.0))
            except OSError:
                continue
            if index % 100 == 0:
                started = time.monotonic()
                controller.sendall(mbap(index, read_registers_pdu(0, 14)))
                answered = receive_frames(controller, 1, ANSWER_BOUND_S)
                assert [frame[0] for frame in answered] == [index], "the controller was dropped"
                worst_s = max(worst_s, time.monotonic() - started)
        assert len(flood) >= 1000, "the flood could not even connect"
        deadline = time.monotonic() + 15.0
        while True:
            still_open = [sock for sock in flood if not is_closed_by_peer(sock)]
            if len(still_open) < limit or time.monotonic() > deadline:
                break
            time.sleep(0.2)
        assert len(still_open) < limit, f"{len(still_open)} flood connections still open"
        assert timed_read(port) < ANSWER_BOUND_S
        assert worst_s < ANSWER_BOUND_S
    finally:
        for sock in (*flood, controller):
            sock.close()
        server.close()
    _assert_log_is_bounded(log_records)
    assert _events_counted(log_records, "dropped the oldest idle") >= len(flood) - limit


RUN_WITH_FEW_DESCRIPTORS = """
import logging, resource, sys, time
from appliance.config import ModbusConfig
from appliance.live.modbus_server import StrainRegisterServer
logging.basicConfig(level=logging.INFO, stream=sys.stderr)
resource.setrlimit(resource.RLIMIT_NOFILE, (64, resource.getrlimit(resource.RLIMIT_NOFILE)[1]))
config = ModbusConfig(tcp=sys.argv[1], max_connections=500, idle_timeout_s=1.0)
server = StrainRegisterServer(config, lambda name, value: True)
server.start(timeout_s=30.0)
print("serving", flush=True)
sys.stdin.read()
server.close()
"""


def test_running_out_of_descriptors_costs_one_log_line_and_heals(tmp_path):
    port = free_tcp_port()
    process = subprocess.Popen(
        [sys.executable, "-c", RUN_WITH_FEW_DESCRIPTORS, f"127.0.0.1:{port}"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=(tmp_path / "log").open("w"),
        text=True,
        cwd=Path(__file__).parents[2],
    )
    flood: list[socket.socket] = []
    try:
        assert process.stdout is not None and process.stdout.readline() == "serving\n"
        for _ in range(150):
            flood.append(_connect(port, timeout_s=5.0))
        time.sleep(3.0)
        for sock in flood:
            sock.close()
        assert timed_read(port, timeout_s=10.0) < 10.0, "accepting never resumed"
    finally:
        for sock in flood:
            sock.close()
        assert process.stdin is not None
        process.stdin.close()
        process.wait(timeout=30)
    log = (tmp_path / "log").read_text(encoding="utf-8")
    assert "Traceback" not in log, log[:2000]
    assert 1 <= log.count("out of system resource") <= 3, log[:2000]
    assert len(log.splitlines()) <= LOG_BOUND, log[:2000]


def _events_counted(caplog, what: str) -> int:
    """Events the throttled lines about `what` stand for: each line and the count it gives."""
    total = 0
    for record in caplog.records:
        message = record.getMessage()
        if what not in message:
            continue
        more = re.search(r"\(and (\d+) more like it", message)
        held = re.search(r"\((\d+) like it", message)
        total += 1 + int(more.group(1)) if more else int(held.group(1)) if held else 1
    return total


def test_garbage_and_lying_headers_never_stop_the_server(serve, log_records):
    _, port = serve(idle_timeout_s=1.0)
    rng = random.Random(20261202)
    for _ in range(20):
        with _connect(port) as sock:
            sock.sendall(rng.randbytes(rng.randrange(1, 600)))
            _, closed = receive_until_closed(sock, 5.0)
            assert closed, "garbage left a connection open past the idle timeout"
    lies = {
        "protocol id 1": mbap(1, read_registers_pdu(0, 2), protocol_id=1),
        "length 0": struct.pack(">HHHB", 1, 0, 0, 1) + read_registers_pdu(0, 2),
        "length 1": struct.pack(">HHHB", 1, 0, 1, 1) + read_registers_pdu(0, 2),
        "length 60000": struct.pack(">HHHB", 1, 0, 60000, 1) + bytes(300),
        "length 200, 5 bytes sent": struct.pack(">HHHB", 1, 0, 200, 1) + bytes(5),
        "truncated header": mbap(1, read_registers_pdu(0, 2))[:5],
    }
    for what, payload in lies.items():
        with _connect(port) as sock:
            sock.sendall(payload)
            data, closed = receive_until_closed(sock, 5.0)
        assert closed, f"{what}: the connection stayed open"
        assert data == b"", f"{what}: answered {data!r}"
        assert timed_read(port) < ANSWER_BOUND_S, what
    short_by_two = struct.pack(">HHHB", 5, 0, 4, 1) + read_registers_pdu(0, 2)
    frames = _exchange(port, short_by_two, 1, timeout_s=3.0)
    assert len(frames) <= 1 and all(frame[1] == 0 for frame in frames)
    assert timed_read(port) < ANSWER_BOUND_S
    _assert_log_is_bounded(log_records)


def test_fifty_clients_at_once_are_all_answered(serve, log_records):
    _, port = serve(max_connections=64)
    clients, reads = 50, 20

    async def client(number: int) -> list[float]:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        took = []
        try:
            for index in range(reads):
                tid = number * 100 + index
                started = time.monotonic()
                writer.write(mbap(tid, read_registers_pdu(0, 14)))
                header = await asyncio.wait_for(reader.readexactly(7), ANSWER_BOUND_S * 3)
                length = struct.unpack(">HHHB", header)[2]
                pdu = await asyncio.wait_for(reader.readexactly(length - 1), ANSWER_BOUND_S)
                assert struct.unpack(">H", header[:2])[0] == tid and pdu[:2] == bytes((3, 28))
                took.append(time.monotonic() - started)
        finally:
            writer.close()
        return took

    async def all_clients() -> list[list[float]]:
        return await asyncio.gather(*(client(n) for n in range(clients)))

    results = asyncio.run(asyncio.wait_for(all_clients(), 60.0))
    assert sum(len(took) for took in results) == clients * reads
    assert max(max(took) for took in results) < ANSWER_BOUND_S * 3
    assert timed_read(port) < ANSWER_BOUND_S
    _assert_log_is_bounded(log_records)


def test_a_client_that_never_reads_is_cut_off_and_the_rest_are_served(serve, log_records):
    _, port = serve(idle_timeout_s=1.0)
    greedy = _connect(port)
    greedy.setblocking(False)
    request = mbap(1, read_registers_pdu(0, 125)) * 256
    sent = 0
    try:
        deadline = time.monotonic() + 5.0
        blocked_since = None
        while sent < 8_000_000 and time.monotonic() < deadline:
            try:
                sent += greedy.send(request)
                blocked_since = None
            except BlockingIOError:
                blocked_since = blocked_since or time.monotonic()
                if time.monotonic() - blocked_since > 0.5:
                    break
                time.sleep(0.01)
            except ConnectionError:
                break
        for _ in range(3):
            assert timed_read(port) < ANSWER_BOUND_S
        assert wait_closed_by_peer_unread(greedy, 15.0), "a client that never reads stays"
        assert timed_read(port) < ANSWER_BOUND_S
    finally:
        greedy.close()
    _assert_log_is_bounded(log_records)


def test_responses_are_well_formed_frames_for_the_unit_ids_answered(serve):
    _, port = serve(unit_id=7)
    with _connect(port) as sock:
        sock.sendall(
            mbap(1, read_registers_pdu(0, 2), unit_id=7)
            + mbap(2, read_registers_pdu(0, 2), unit_id=8)
            + mbap(3, read_registers_pdu(0, 2), unit_id=0)
            + mbap(4, read_registers_pdu(0, 2), unit_id=255)
        )
        frames = receive_frames(sock, 3)
    assert [(f[0], f[2]) for f in frames] == [(1, 7), (3, 0), (4, 255)]
    data = b"".join(mbap(f[0], f[3], f[2]) for f in frames)
    assert split_frames(data) == (frames, b"")
