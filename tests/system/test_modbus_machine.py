"""The Modbus machine client against real pymodbus servers on loopback (TCP) and a pty pair (RTU).

The simulated controller serves `TinyMachine` through the generic map; what the client reads
is compared with the machine's state just before and just after the read (so no timing
decides a result). The recorded controller serves a register table from a file, decoded here
independently (struct) and compared exactly. Timings appear only as generous upper bounds.
"""

from __future__ import annotations

import json
import struct
import time
import tomllib
from collections.abc import Iterator

import pytest

from appliance.sim.controller_server import ControllerServer
from hal.errors import (
    HardwareConfigError,
    HardwareConnectError,
    HardwareFault,
    HardwareTimeout,
)
from hal.machine import base as machine_base
from hal.machine.base import MachineState
from hal.machine.modbus import MAX_BACKOFF_S, ModbusMachine, RtuLink, TcpLink, parse_url
from hal.machine.register_map import GENERIC_CONTROLLER, RegisterMap
from hal.registry import machine_from_url
from tests.system.machine_controller_peers import (
    RECORDED_MAP,
    GarbageRtuPeer,
    RecordedController,
    SilentTcpPeer,
    SimulatedController,
    TinyMachine,
    bracketed,
    within,
)
from tests.system.modbus_peers import free_tcp_port, needs_socat, pty_pair

SLACK_S = 1.0
"""What a call may take beyond its timeout on a loaded 2-core host (an upper bound only)."""


@pytest.fixture
def clients() -> Iterator[list[ModbusMachine]]:
    made: list[ModbusMachine] = []
    yield made
    for client in made:
        client.close()


@pytest.fixture
def served() -> Iterator[tuple[SimulatedController, ControllerServer, int]]:
    controller = SimulatedController()
    port = free_tcp_port()
    with ControllerServer(controller) as server:
        server.serve_tcp(port)
        yield controller, server, port


def _client(clients: list[ModbusMachine], url: str, **kwargs) -> ModbusMachine:
    client = ModbusMachine(url, **kwargs)
    clients.append(client)
    return client


def _check_against_machine(client: ModbusMachine, machine: TinyMachine) -> MachineState:
    before_ns = time.monotonic_ns()
    state, before, after = bracketed(lambda: client.read_state(timeout_s=2.0), machine)
    after_ns = time.monotonic_ns()
    assert isinstance(state, MachineState)
    assert within(state.crosshead_mm, before["crosshead_mm"], after["crosshead_mm"])
    assert within(state.force_n, before["force_n"], after["force_n"])
    counts = sorted((before["encoder_counts"], after["encoder_counts"]))
    assert counts[0] <= state.encoder_counts <= counts[1]
    assert state.speed_mm_min in (before["speed_mm_min"], after["speed_mm_min"])
    assert state.running in (before["running"], after["running"])
    assert before_ns <= state.timestamp_ns <= after_ns
    return state


@pytest.mark.parametrize(
    ("url", "piece"),
    [
        ("modbus-tcp://", "host"),
        ("modbus-tcp://127.0.0.1:http", "port"),
        ("modbus-tcp://127.0.0.1:0", "port"),
        ("modbus-tcp://127.0.0.1:502?unit=300", "unit"),
        ("modbus-tcp://127.0.0.1:502?baud=9600", "baud"),
        ("modbus-tcp://127.0.0.1:502/x", "path"),
        ("modbus-tcp://127.0.0.1?unit=1&unit=2", "unit"),
        ("modbus-rtu://dev/ttyS0", "device"),
        ("modbus-rtu:///dev/ttyS0?parity=X", "parity"),
        ("modbus-rtu:///dev/ttyS0?stop_bits=3", "stop_bits"),
        ("modbus-rtu:///dev/ttyS0?baud=fast", "baud"),
        ("modbus-rtu:///dev/ttyS0?unit=0", "unit"),
        ("modbus-rtu:///dev/ttyS0?timeout=1", "timeout"),
    ],
)
def test_bad_url_pieces_are_named(url, piece):
    with pytest.raises(HardwareConfigError) as raised:
        ModbusMachine(url)
    message = str(raised.value)
    assert "\n" not in message
    assert repr(url) in message
    assert f": {piece}:" in message


def test_good_urls_and_the_registry():
    assert parse_url("modbus-tcp://127.0.0.1:5020?unit=3") == TcpLink("127.0.0.1", 5020, 3)
    assert parse_url("modbus-tcp://controller") == TcpLink("controller", 502, 1)
    assert parse_url("modbus-rtu:///dev/ttyUSB0?baud=115200&parity=E&stop_bits=2&unit=7") == (
        RtuLink("/dev/ttyUSB0", 115200, "E", 2, 7)
    )
    client = machine_from_url(
        "modbus-tcp://127.0.0.1:5020", machine=object(), clock=object(), accepts_commands=True
    )
    assert isinstance(client, ModbusMachine) and isinstance(client, machine_base.TestingMachine)
    assert client.register_map is GENERIC_CONTROLLER and client.accepts_commands
    with pytest.raises(HardwareConnectError, match="not open"):
        client.read_state(timeout_s=0.5)
    with pytest.raises(HardwareConfigError, match="timeout_s"):
        client.read_state(timeout_s=0)


def test_tcp_reads_the_simulated_machine_in_one_request(served, clients):
    controller, server, port = served
    client = _client(clients, f"modbus-tcp://127.0.0.1:{port}?unit=1")
    client.open(timeout_s=5.0)
    stopped = _check_against_machine(client, controller.machine)
    assert stopped.running is False and stopped.speed_mm_min == 0.0
    assert stopped.crosshead_mm == pytest.approx(10.0)
    controller.machine.start(30.0)
    requests_before = server.requests
    for _ in range(20):
        state = _check_against_machine(client, controller.machine)
        assert state.running is True and state.speed_mm_min == 30.0
    assert server.requests - requests_before == 20
    controller.machine.return_to_start(45.0)
    back = _check_against_machine(client, controller.machine)
    assert back.speed_mm_min == -45.0 and back.running
    statistics = client.statistics()
    assert statistics["reads"] == 22 and statistics["connected"] is True
    assert statistics["exceptions"] == statistics["transport_failures"] == 0
    assert statistics["last_latency_ms"] > 0


@needs_socat
def test_rtu_over_a_pty_pair_reads_and_commands(tmp_path, clients):
    controller = SimulatedController()
    with pty_pair(tmp_path) as (server_end, client_end), ControllerServer(controller) as server:
        server.serve_rtu(server_end, baud=115200)
        url = f"modbus-rtu://{client_end}?baud=115200&parity=N&stop_bits=1&unit=1"
        client = _client(clients, url, accepts_commands=True)
        client.open(timeout_s=5.0)
        client.start(12.5, timeout_s=2.0)
        assert controller.commands() == [("speed_setpoint_mm_min", 12.5), ("start", True)]
        for _ in range(5):
            state = _check_against_machine(client, controller.machine)
            assert state.running and state.speed_mm_min == 12.5
        client.close()


def _recorded_client(clients: list[ModbusMachine], port: int) -> ModbusMachine:
    with RECORDED_MAP.open("rb") as file:
        table = tomllib.load(file)["registers"]
    register_map = RegisterMap.from_table(table, f"{RECORDED_MAP.name}: [registers]")
    return _client(clients, f"modbus-tcp://127.0.0.1:{port}", register_map=register_map)


def _expected(row: dict[tuple[str, int], int]) -> dict[str, float | int | bool]:
    """The recorded row decoded the way its layout says, with struct (independent of hal)."""

    def words(*addresses: int) -> bytes:
        return struct.pack(">" + "H" * len(addresses), *(row["holding", a] for a in addresses))

    return {
        "crosshead_mm": struct.unpack(">i", words(101, 100))[0] * 0.001,
        "speed_mm_min": struct.unpack(">h", words(102))[0] * 0.01,
        "force_n": struct.unpack(">f", words(105, 104))[0] * 1000.0,
        "encoder_counts": struct.unpack(">I", words(107, 106))[0],
        "running": bool(row["discrete", 5]),
    }


def test_recorded_table_is_served_and_decoded_exactly(clients):
    recorded = RecordedController()
    assert len(recorded.rows) >= 40
    port = free_tcp_port()
    with ControllerServer(recorded) as server:
        server.serve_tcp(port)
        client = _recorded_client(clients, port)
        client.open(timeout_s=5.0)
        assert len(client.read_plan) == 2
        speeds = set()
        for index, row in enumerate(recorded.rows):
            recorded.hold(index)
            state = client.read_state(timeout_s=2.0)
            expected = _expected(row)
            got = {name: getattr(state, name) for name in expected}
            assert got == expected, f"row {index}"
            speeds.add(state.speed_mm_min > 0)
            if state.speed_mm_min < 0:
                speeds.add("negative")
        assert speeds == {True, False, "negative"}
        recorded.play()
        decoded = [_expected(row) for row in recorded.rows]
        for _ in range(5):
            state = client.read_state(timeout_s=2.0)
            assert {name: getattr(state, name) for name in decoded[0]} in decoded
        with pytest.raises(HardwareConfigError, match="start"):
            client.start(5.0)
        assert recorded.writes == 0


def test_commands_are_refused_unless_configured(served, clients):
    controller, _, port = served
    url = f"modbus-tcp://127.0.0.1:{port}"
    client = _client(clients, url)
    client.open(timeout_s=5.0)
    for name, call in (
        ("start", lambda: client.start(10.0)),
        ("stop", client.stop),
        ("return_to_start", lambda: client.return_to_start(10.0)),
    ):
        with pytest.raises(HardwareConfigError) as raised:
            call()
        assert f"command {name} refused" in str(raised.value) and url in str(raised.value)
    assert controller.commands() == []
    assert client.statistics()["commands"] == 0


def test_commands_are_written_set_point_first_when_configured(served, clients):
    controller, _, port = served
    client = _client(clients, f"modbus-tcp://127.0.0.1:{port}", accepts_commands=True)
    client.open(timeout_s=5.0)
    client.start(30.0, timeout_s=2.0)
    assert controller.commands() == [("speed_setpoint_mm_min", 30.0), ("start", True)]
    moving = _check_against_machine(client, controller.machine)
    assert moving.running and moving.speed_mm_min == 30.0
    client.stop(timeout_s=2.0)
    assert controller.commands()[-1] == ("stop", True)
    stopped = _check_against_machine(client, controller.machine)
    assert not stopped.running and stopped.speed_mm_min == 0.0
    client.return_to_start(60.0, timeout_s=2.0)
    assert controller.commands()[-2:] == [
        ("speed_setpoint_mm_min", 60.0),
        ("return_to_start", True),
    ]
    returning = _check_against_machine(client, controller.machine)
    assert returning.running and returning.speed_mm_min == -60.0
    assert client.statistics()["commands"] == 3


def test_command_words_and_a_command_missing_from_the_map(clients):
    table = {
        "preset": "generic",
        "start": {"address": 10, "table": "holding", "data_type": "uint16", "value": 1},
        "stop": {"address": 10, "table": "holding", "data_type": "uint16", "value": 2},
        "return_to_start": False,
    }
    register_map = RegisterMap.from_table(table, "test: [machine.registers]")
    controller = SimulatedController(register_map)
    port = free_tcp_port()
    with ControllerServer(controller) as server:
        server.serve_tcp(port)
        url = f"modbus-tcp://127.0.0.1:{port}"
        client = _client(clients, url, register_map=register_map, accepts_commands=True)
        client.open(timeout_s=5.0)
        client.start(20.0)
        client.stop()
        assert controller.commands() == [
            ("speed_setpoint_mm_min", 20.0),
            ("start", 1),
            ("stop", 2),
        ]
        with pytest.raises(HardwareConfigError, match="no return_to_start entry") as raised:
            client.return_to_start(20.0)
        assert url in str(raised.value)
        with pytest.raises(HardwareConfigError, match="cannot hold"):
            client.start(float("nan"))
        assert len(controller.commands()) == 3


def test_an_exception_response_is_a_fault_not_a_connection_failure(served, clients):
    _, _, port = served
    beyond = RegisterMap.from_table(
        {"preset": "generic", "force_n": {"address": 200}}, "test: [machine.registers]"
    )
    url = f"modbus-tcp://127.0.0.1:{port}"
    client = _client(clients, url, register_map=beyond)
    with pytest.raises(HardwareFault) as at_open:
        client.open(timeout_s=5.0)
    assert not isinstance(at_open.value, HardwareConnectError | HardwareTimeout)
    assert str(at_open.value) == (
        f"{url}: reading force_n (input 200..201): exception 2 (illegal data address)"
    )
    for _ in range(3):
        with pytest.raises(HardwareFault, match="exception 2"):
            client.read_state(timeout_s=2.0)
    statistics = client.statistics()
    assert statistics["exceptions"] == 4 and statistics["transport_failures"] == 0
    assert statistics["connected"] is True and statistics["refused_while_disconnected"] == 0


def test_a_lost_controller_is_reported_at_once_and_reconnected_after_backoff(served, clients):
    controller, server, port = served
    client = _client(clients, f"modbus-tcp://127.0.0.1:{port}")
    client.open(timeout_s=5.0)
    client.read_state(timeout_s=2.0)
    server.stop()
    started = time.monotonic()
    with pytest.raises(HardwareConnectError, match="connection lost"):
        client.read_state(timeout_s=2.0)
    assert time.monotonic() - started < 2.0 + SLACK_S
    started = time.monotonic()
    with pytest.raises(HardwareConnectError, match="next attempt in"):
        client.read_state(timeout_s=2.0)
    assert time.monotonic() - started < SLACK_S
    time.sleep(0.15)
    with pytest.raises(HardwareConnectError, match="connection refused"):
        client.read_state(timeout_s=2.0)
    assert client.statistics()["backoff_s"] == pytest.approx(0.4)
    server.serve_tcp(port)
    deadline = time.monotonic() + 10 * MAX_BACKOFF_S
    state = None
    while state is None and time.monotonic() < deadline:
        try:
            state = client.read_state(timeout_s=2.0)
        except HardwareConnectError:
            time.sleep(0.02)
    assert state is not None
    _check_against_machine(client, controller.machine)
    statistics = client.statistics()
    assert statistics["reconnects"] == 1 and statistics["connected"] is True
    assert statistics["transport_failures"] >= 2 and statistics["refused_while_disconnected"] >= 1
    assert statistics["backoff_s"] == pytest.approx(0.1)


def test_a_silent_controller_times_out_within_the_timeout(clients):
    port = free_tcp_port()
    with SilentTcpPeer(port):
        client = _client(clients, f"modbus-tcp://127.0.0.1:{port}")
        started = time.monotonic()
        with pytest.raises(HardwareConnectError, match="no valid reply"):
            client.open(timeout_s=0.3)
        assert time.monotonic() - started < 0.3 + SLACK_S
        time.sleep(0.12)
        started = time.monotonic()
        with pytest.raises(HardwareTimeout, match="no valid reply"):
            client.read_state(timeout_s=0.3)
        assert time.monotonic() - started < 0.3 + SLACK_S
        statistics = client.statistics()
        assert statistics["timeouts"] == 2 and statistics["exceptions"] == 0


@needs_socat
def test_garbage_on_the_rtu_line_is_a_timeout(tmp_path, clients):
    with pty_pair(tmp_path) as (server_end, client_end), GarbageRtuPeer(server_end) as peer:
        client = _client(clients, f"modbus-rtu://{client_end}?baud=115200")
        started = time.monotonic()
        with pytest.raises(HardwareConnectError, match="no valid reply"):
            client.open(timeout_s=0.3)
        assert time.monotonic() - started < 0.3 + SLACK_S
        time.sleep(0.12)
        started = time.monotonic()
        with pytest.raises(HardwareTimeout):
            client.read_state(timeout_s=0.3)
        assert time.monotonic() - started < 0.3 + SLACK_S
        assert peer.answers >= 2
        client.close()


def test_a_missing_serial_device_is_a_connect_error(tmp_path, clients):
    missing = tmp_path / "ttyNone"
    client = _client(clients, f"modbus-rtu://{missing}")
    with pytest.raises(HardwareConnectError, match="cannot connect to .*ttyNone"):
        client.open(timeout_s=1.0)
    with pytest.raises(HardwareConnectError, match="next attempt in"):
        client.read_state(timeout_s=1.0)


def test_the_benchmark_runs_and_writes_its_report(tmp_path, capsys):
    from appliance.bench.machine_client import run_machine_benchmark

    out = tmp_path / "results"
    assert run_machine_benchmark(out, True, duration_s=0.3) == 0
    figures = json.loads((out / "machine.json").read_text(encoding="utf-8"))["figures"]
    assert json.loads(capsys.readouterr().out) == figures
    for phase in ("as_fast_as_possible", "paced"):
        assert figures[phase]["reads"] > 0 and figures[phase]["failures"] == {}
        assert figures[phase]["latency_ms"]["p99"] > 0
    assert figures["client_statistics"]["transport_failures"] == 0
