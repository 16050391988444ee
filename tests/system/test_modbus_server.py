"""The Modbus strain server against real clients: mbpoll over TCP and over RTU on a pty pair.

Every server binds 127.0.0.1 on a free port. Samples are built with known numbers and
published; the tests assert what mbpoll prints (values, exception texts, exit status). The
torn-read test uses pymodbus' own client, which reads far faster than a process per poll.
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import math
import struct
import threading
import time

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient
from pymodbus.pdu import DecodePDU
from pymodbus.server import ModbusSerialServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.simulator import SimDevice
from pymodbus.simulator.simcore import SimCore

from appliance.bench.modbus import run_modbus_benchmark
from appliance.config import ModbusConfig
from appliance.errors import InputError
from appliance.live import modbus_map
from appliance.live.modbus_map import BY_NAME, RUN_STATE_CODES, StatusBit
from appliance.live.modbus_server import ServerStartError, StrainRegisterServer
from appliance.measure.edge_width import WidthReading
from appliance.measure.tracking import TrackStatus
from appliance.run.state import ExitStatus, RunState
from hal.machine.base import MachineState
from tests.system.modbus_peers import (
    free_tcp_port,
    make_facts,
    make_sample,
    mbpoll,
    mbpoll_read_tcp,
    mbpoll_tcp,
    needs_mbpoll,
    needs_socat,
    printed_values,
    pty_pair,
)

MACHINE = MachineState(
    crosshead_mm=3.25, speed_mm_min=10.0, force_n=1520.5, running=True, timestamp_ns=0
)


class Commands:
    """The server's on_command: records every call and answers `accept`."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, float | None]] = []
        self.accept = True

    def __call__(self, name: str, value: float | None) -> bool:
        self.calls.append((name, value))
        return self.accept


@pytest.fixture
def commands() -> Commands:
    return Commands()


@pytest.fixture
def serve(commands):
    """Factory: a started server on 127.0.0.1 and a free port -> (server, port); all closed."""
    servers: list[StrainRegisterServer] = []

    def start(*, tcp: bool = True, **modbus) -> tuple[StrainRegisterServer, int]:
        port = free_tcp_port()
        config = ModbusConfig(tcp=f"127.0.0.1:{port}" if tcp else "", **modbus)
        server = StrainRegisterServer(config, commands)
        servers.append(server)
        server.start(timeout_s=30.0)
        return server, port

    yield start
    for server in servers:
        server.close()


def _published(server: StrainRegisterServer, **sample) -> None:
    server.set_run_state(RunState.RUNNING)
    server.publish(make_sample(machine=MACHINE, **sample), make_facts())


def _floats(values: dict[int, str]) -> dict[int, float]:
    return {address: float(text) for address, text in values.items()}


def _failure(done) -> str:
    assert done.returncode != 0, done.stdout
    return done.stdout + done.stderr


@needs_mbpoll
def test_tcp_serves_the_whole_sample_in_big_word_order(serve):
    server, port = serve()
    _published(server, status=(0, int(TrackStatus.LOST), 0, 0), reference_updates=1)
    strains = _floats(mbpoll_read_tcp(port, "-r", "0", "-c", "5", "-t", "4:float", "-B"))
    assert strains == {
        0: pytest.approx(0.123456, rel=1e-5),
        2: pytest.approx(-0.0321, rel=1e-5),
        4: pytest.approx(math.log1p(0.123456), rel=1e-5),
        6: pytest.approx(6.1728, rel=1e-5),
        8: pytest.approx(56.1728, rel=1e-5),
    }
    more = _floats(mbpoll_read_tcp(port, "-r", "18", "-c", "4", "-t", "4:float", "-B"))
    assert more == {
        18: pytest.approx(0.26, rel=1e-5),
        20: pytest.approx(3.25),
        22: pytest.approx(1520.5),
        24: pytest.approx(12.5),
    }
    latency = _floats(mbpoll_read_tcp(port, "-r", "28", "-t", "4:float", "-B"))
    assert latency == {28: pytest.approx(1.25, rel=1e-5)}
    words = mbpoll_read_tcp(port, "-r", "10", "-c", "2", "-t", "4")
    expected_bits = (
        StatusBit.DATA_VALID
        | StatusBit.TRACKING
        | StatusBit.POINT_LOST
        | StatusBit.REFERENCE_UPDATED
    )
    assert int(words[10]) == int(expected_bits)
    assert int(words[11]) > 0
    assert mbpoll_read_tcp(port, "-r", "12", "-t", "4:int", "-B") == {12: "70000"}
    assert mbpoll_read_tcp(port, "-r", "26", "-c", "2", "-t", "4") == {26: "1", 27: "2"}
    stamp = mbpoll_read_tcp(port, "-r", "14", "-c", "4", "-t", "4")
    words = [int(stamp[address]) for address in range(14, 18)]
    expected_ns = make_facts().unix_time_ns(1_234_567_890)
    assert modbus_map.decode(BY_NAME["timestamp_unix_ns"], words) == expected_ns


@needs_mbpoll
def test_input_registers_read_the_same_image(serve):
    server, port = serve()
    _published(server)
    holding = mbpoll_read_tcp(port, "-r", "0", "-c", "14", "-t", "4")
    inputs = mbpoll_read_tcp(port, "-r", "0", "-c", "14", "-t", "3")
    assert inputs == holding and len(inputs) == 14
    strains = _floats(mbpoll_read_tcp(port, "-r", "0", "-c", "2", "-t", "3:float", "-B"))
    assert strains == {0: pytest.approx(0.123456, rel=1e-5), 2: pytest.approx(-0.0321, rel=1e-5)}
    assert mbpoll_read_tcp(port, "-r", "12", "-t", "3:int", "-B") == {12: "70000"}


@needs_mbpoll
def test_little_word_order_reads_as_cdab(serve):
    server, port = serve(word_order="little")
    _published(server)
    little = _floats(mbpoll_read_tcp(port, "-r", "0", "-t", "4:float"))
    assert little == {0: pytest.approx(0.123456, rel=1e-5)}
    big = _floats(mbpoll_read_tcp(port, "-r", "0", "-t", "4:float", "-B"))
    assert big[0] != pytest.approx(0.123456, rel=1e-2)
    assert mbpoll_read_tcp(port, "-r", "12", "-t", "4:int") == {12: "70000"}
    setpoint = mbpoll_tcp(port, "-r", "103", "-t", "4:float", write=["250.25"])
    assert setpoint.returncode == 0, setpoint.stdout + setpoint.stderr
    assert _floats(mbpoll_read_tcp(port, "-r", "103", "-t", "4:float")) == {103: 250.25}


@needs_mbpoll
def test_heartbeat_moves_with_every_update_and_tick(serve):
    server, port = serve()
    first = int(mbpoll_read_tcp(port, "-r", "11", "-t", "4")[11])
    server.tick()
    server.tick()
    assert int(mbpoll_read_tcp(port, "-r", "11", "-t", "4")[11]) == (first + 2) % 65536
    server.publish(make_sample(), None)
    server.set_run_state(RunState.ARMED)
    assert int(mbpoll_read_tcp(port, "-r", "11", "-t", "4")[11]) == (first + 4) % 65536


def test_status_bits_and_run_state_code_follow_the_state_and_the_latest_sample(commands):
    server = StrainRegisterServer(ModbusConfig(), commands)
    status, run_state = BY_NAME["status"].address, BY_NAME["run_state"].address

    def state_words() -> tuple[int, int]:
        return server.read_registers(status, 1)[0], server.read_registers(run_state, 1)[0]

    strain = BY_NAME["axial_strain"]
    assert math.isnan(modbus_map.decode(strain, server.read_registers(0, 2)))
    assert state_words() == (0, RUN_STATE_CODES[RunState.IDLE])
    server.set_run_state(RunState.ARMED)
    assert state_words() == (int(StatusBit.CALIBRATING), 1)
    server.set_run_state(RunState.RUNNING)
    server.publish(
        make_sample(status=(0, int(TrackStatus.LOST)), reference_updates=2, machine=MACHINE), None
    )
    every_sample_bit = StatusBit.DATA_VALID | StatusBit.POINT_LOST | StatusBit.REFERENCE_UPDATED
    assert state_words() == (int(every_sample_bit | StatusBit.TRACKING), 2)
    server.set_camera_lost(True)
    lost_camera = StatusBit.CAMERA_LOST | StatusBit.POINT_LOST | StatusBit.REFERENCE_UPDATED
    assert state_words() == (int(lost_camera | StatusBit.TRACKING), 2)
    server.set_camera_lost(False)
    assert state_words() == (int(every_sample_bit | StatusBit.TRACKING), 2)
    server.set_run_state(RunState.STOPPING)
    assert state_words() == (int(every_sample_bit), 3)
    server.set_run_state(RunState.IDLE)
    assert state_words() == (0, 0), "the latest sample's bits are cleared once no test runs"
    server.set_run_state(RunState.RUNNING)
    server.publish(make_sample(data_valid=False, machine=MACHINE), None)
    assert state_words() == (int(StatusBit.TRACKING), 2)
    server.set_run_state(RunState.FAULT)
    assert state_words() == (int(StatusBit.FAULT), 5)
    server.set_run_state(RunState.ABORTED)
    assert state_words() == (0, 4)
    server.set_run_state(RunState.RUNNING)
    server.publish(make_sample(machine=None), None)
    no_controller = StatusBit.DATA_VALID | StatusBit.NO_CONTROLLER_DATA | StatusBit.TRACKING
    assert state_words() == (int(no_controller), 2)
    server.set_camera_lost(True)
    server.set_run_state(RunState.ARMED)
    assert state_words()[0] & StatusBit.CAMERA_LOST == 0
    server.close()


def test_the_exit_status_register_says_how_the_last_test_ended(commands):
    server = StrainRegisterServer(ModbusConfig(), commands)
    exit_status = BY_NAME["exit_status"].address
    assert server.read_registers(exit_status, 1) == [0]
    for status, code in ((ExitStatus.STOPPED, 3), (ExitStatus.BREAK, 2), (ExitStatus.FAULT, 5)):
        server.set_exit_status(status)
        assert server.read_registers(exit_status, 1) == [code]
    server.set_exit_status(None)
    assert server.read_registers(exit_status, 1) == [0]
    server.close()


@needs_mbpoll
def test_commands_are_handed_on_and_their_result_is_readable(serve, commands):
    _, port = serve()
    assert mbpoll_tcp(port, "-r", "100", "-t", "4", write=["1"]).returncode == 0
    assert commands.calls == [("start", None)]
    assert mbpoll_read_tcp(port, "-r", "100", "-c", "3") == {100: "1", 101: "1", 102: "1"}
    commands.accept = False
    assert mbpoll_tcp(port, "-r", "100", "-t", "4", write=["2"]).returncode == 0
    assert mbpoll_read_tcp(port, "-r", "100", "-c", "3") == {100: "2", 101: "2", 102: "2"}
    commands.accept = True
    assert mbpoll_tcp(port, "-r", "100", "-t", "4", write=["3"]).returncode == 0
    assert commands.calls == [("start", None), ("stop", None), ("zero", None)]
    assert mbpoll_read_tcp(port, "-r", "100", "-c", "3") == {100: "3", 101: "3", 102: "1"}
    for value in ("0", "4", "65535"):
        assert "Illegal data value" in _failure(
            mbpoll_tcp(port, "-r", "100", "-t", "4", write=[value])
        )
    assert len(commands.calls) == 3
    assert mbpoll_read_tcp(port, "-r", "101") == {101: "3"}


@needs_mbpoll
def test_gauge_length_set_point_is_range_checked_and_reads_back(serve, commands):
    _, port = serve()
    assert math.isnan(float(mbpoll_read_tcp(port, "-r", "103", "-t", "4:float", "-B")[103]))
    done = mbpoll_tcp(port, "-r", "103", "-t", "4:float", "-B", write=["120.5"])
    assert done.returncode == 0, done.stdout + done.stderr
    assert commands.calls == [("gauge_length", 120.5)]
    assert _floats(mbpoll_read_tcp(port, "-r", "103", "-t", "4:float", "-B")) == {103: 120.5}
    assert mbpoll_read_tcp(port, "-r", "103", "-c", "2", "-t", "4") == {103: "17137", 104: "0"}
    commands.accept = False
    assert mbpoll_tcp(port, "-r", "103", "-t", "4:float", "-B", write=["80"]).returncode == 0
    assert commands.calls[-1] == ("gauge_length", 80.0)
    assert _floats(mbpoll_read_tcp(port, "-r", "103", "-t", "4:float", "-B")) == {103: 120.5}
    assert mbpoll_read_tcp(port, "-r", "102") == {102: "2"}
    commands.accept = True
    for edge in ("1", "10000"):
        assert mbpoll_tcp(port, "-r", "103", "-t", "4:float", "-B", write=[edge]).returncode == 0
    calls = len(commands.calls)
    for bad in ("-5", "0.5", "10000.5", "nan"):
        failure = _failure(mbpoll_tcp(port, "-r", "103", "-t", "4:float", "-B", write=[bad]))
        assert "Illegal data value" in failure, bad
    for nan_or_inf in (["32704", "0"], ["32640", "0"], ["65408", "0"]):
        raw = _failure(mbpoll_tcp(port, "-r", "103", "-t", "4", write=nan_or_inf))
        assert "Illegal data value" in raw, nan_or_inf
    for half in ("103", "104"):
        failure = _failure(mbpoll_tcp(port, "-r", half, "-t", "4", write=["17000"]))
        assert "Illegal data address" in failure, half
    assert len(commands.calls) == calls
    assert _floats(mbpoll_read_tcp(port, "-r", "103", "-t", "4:float", "-B")) == {103: 10000.0}


@needs_mbpoll
def test_read_only_and_unmapped_addresses_refuse_writes(serve, commands):
    _, port = serve()
    for address in ("0", "10", "101", "102", "50", "105", "2000"):
        failure = _failure(mbpoll_tcp(port, "-r", address, "-t", "4", write=["1"]))
        assert "Illegal data address" in failure, address
    whole = mbpoll_read_tcp(port, "-r", "0", "-c", "105", "-t", "4")
    assert len(whole) == 105
    assert all(
        whole[address] == "0" for address in (*range(30, 33), *range(57, 60), *range(90, 100))
    )
    assert whole[37] == whole[38] == "0"
    assert "Illegal data address" in _failure(mbpoll_tcp(port, "-1", "-r", "104", "-c", "2"))
    assert "Illegal function" in _failure(mbpoll_tcp(port, "-1", "-r", "100", "-t", "0"))
    assert commands.calls == []


@needs_mbpoll
def test_allow_list_refuses_writes_from_other_clients_but_serves_reads(serve, commands):
    server, port = serve(allow_write_from=("127.0.0.2",))
    _published(server)
    failure = _failure(mbpoll_tcp(port, "-r", "100", "-t", "4", write=["1"]))
    assert "Illegal function" in failure
    reads = _floats(mbpoll_read_tcp(port, "-r", "0", "-t", "4:float", "-B"))
    assert reads == {0: pytest.approx(0.123456, rel=1e-5)}
    assert commands.calls == []
    client = ModbusTcpClient("127.0.0.1", port=port, source_address=("127.0.0.2", 0), timeout=10)
    try:
        assert client.connect()
        written = client.write_register(100, 1, device_id=1)
        assert not written.isError(), written
    finally:
        client.close()
    assert commands.calls == [("start", None)]
    _, open_port = serve(allow_write_from=("127.0.0.1",))
    assert mbpoll_tcp(open_port, "-r", "100", "-t", "4", write=["2"]).returncode == 0
    assert commands.calls[-1] == ("stop", None)


@needs_mbpoll
@needs_socat
def test_rtu_on_a_pty_pair_serves_the_same_image_as_tcp(serve, commands, tmp_path):
    with pty_pair(tmp_path) as (server_end, client_end):
        server, port = serve(rtu_device=server_end, unit_id=7, rtu_baud=115200)
        _published(server)
        rtu = ("-m", "rtu", "-b", "115200", "-P", "none", "-a", "7", "-0")

        def read(*args: str) -> dict[int, str]:
            done = mbpoll(*rtu, "-1", *args, client_end)
            assert done.returncode == 0, done.stdout + done.stderr
            return printed_values(done.stdout)

        strains = _floats(read("-r", "0", "-c", "2", "-t", "4:float", "-B"))
        assert strains == {
            0: pytest.approx(0.123456, rel=1e-5),
            2: pytest.approx(-0.0321, rel=1e-5),
        }
        assert read("-r", "12", "-t", "3:int", "-B") == {12: "70000"}
        assert read("-r", "10", "-c", "4", "-t", "4") == mbpoll_read_tcp(
            port, "-a", "7", "-r", "10", "-c", "4", "-t", "4"
        )
        assert mbpoll(*rtu, "-r", "100", "-t", "4", client_end, "--", "1").returncode == 0
        assert commands.calls == [("start", None)]
        assert read("-r", "100", "-c", "3") == {100: "1", 101: "1", 102: "1"}
        assert mbpoll_read_tcp(port, "-a", "7", "-r", "101") == {101: "1"}
        assert "timed out" in _failure(mbpoll_tcp(port, "-1", "-a", "1", response_timeout_s=0.5))
        read_only = _failure(mbpoll(*rtu, "-r", "0", "-t", "4", client_end, "--", "1"))
        assert "Illegal data address" in read_only
        bad_value = _failure(mbpoll(*rtu, "-r", "100", "-t", "4", client_end, "--", "9"))
        assert "Illegal data value" in bad_value
        other_unit = mbpoll(
            "-m",
            "rtu",
            "-b",
            "115200",
            "-P",
            "none",
            "-a",
            "8",
            "-0",
            "-1",
            "-r",
            "0",
            client_end,
            response_timeout_s=0.5,
        )
        assert "timed out" in _failure(other_unit)
        assert read("-r", "0", "-t", "4:float", "-B") == {0: "0.123456"}


@needs_mbpoll
@needs_socat
def test_rtu_writes_are_refused_when_an_allow_list_is_set(serve, commands, tmp_path):
    with pty_pair(tmp_path) as (server_end, client_end):
        serve(tcp=False, rtu_device=server_end, allow_write_from=("127.0.0.1",))
        rtu = ("-m", "rtu", "-b", "115200", "-P", "none", "-a", "1", "-0")
        refused = _failure(mbpoll(*rtu, "-r", "100", "-t", "4", client_end, "--", "1"))
        assert "Illegal function" in refused
        assert mbpoll(*rtu, "-1", "-r", "100", client_end).returncode == 0
    assert commands.calls == []


@needs_mbpoll
@needs_socat
def test_coil_functions_get_illegal_function_over_tcp_and_rtu(serve, commands, tmp_path):
    with pty_pair(tmp_path) as (server_end, client_end):
        _, port = serve(rtu_device=server_end, rtu_baud=115200)
        rtu = ("-m", "rtu", "-b", "115200", "-P", "none", "-a", "1", "-0")
        for kind in ("0", "1"):
            over_rtu = _failure(mbpoll(*rtu, "-1", "-r", "100", "-t", kind, client_end))
            assert "Illegal function" in over_rtu, kind
            assert "Illegal function" in _failure(mbpoll_tcp(port, "-1", "-r", "100", "-t", kind))
        single_coil = _failure(mbpoll(*rtu, "-r", "100", "-t", "0", client_end, "--", "1"))
        assert "Illegal function" in single_coil
        over_tcp = _failure(mbpoll_tcp(port, "-r", "100", "-t", "0", write=["1"]))
        assert "Illegal function" in over_tcp
        assert mbpoll(*rtu, "-1", "-r", "100", client_end).returncode == 0
    assert commands.calls == []


def test_start_names_the_culprit_and_close_releases_everything(commands, tmp_path):
    port = free_tcp_port()
    first = StrainRegisterServer(ModbusConfig(tcp=f"127.0.0.1:{port}"), commands)
    first.start(timeout_s=30.0)
    try:
        second = StrainRegisterServer(ModbusConfig(tcp=f"127.0.0.1:{port}"), commands)
        with pytest.raises(ServerStartError) as taken:
            second.start(timeout_s=30.0)
        assert str(taken.value) == f"[modbus] tcp 127.0.0.1:{port}: address already in use"
        second.close()
    finally:
        first.close()
        first.close()
    again = StrainRegisterServer(ModbusConfig(tcp=f"127.0.0.1:{port}"), commands)
    again.start(timeout_s=30.0)
    again.close()
    missing = tmp_path / "no-such-tty"
    both = StrainRegisterServer(
        ModbusConfig(tcp=f"127.0.0.1:{port}", rtu_device=str(missing)), commands
    )
    with pytest.raises(ServerStartError) as absent:
        both.start(timeout_s=30.0)
    assert str(absent.value) == f"[modbus] rtu_device {missing}: no such file or directory"
    after = StrainRegisterServer(ModbusConfig(tcp=f"127.0.0.1:{port}"), commands)
    after.start(timeout_s=30.0)
    after.close()
    idle = StrainRegisterServer(ModbusConfig(), commands)
    assert not idle.enabled
    idle.start()
    idle.close()


def test_bad_allow_list_entry_is_named(commands):
    with pytest.raises(InputError, match=r"\[modbus\] allow_write_from: 'controller'"):
        StrainRegisterServer(ModbusConfig(allow_write_from=("controller",)), commands)


def test_a_reader_never_sees_a_torn_float_or_a_mixed_update(serve):
    server, port = serve()
    even = make_sample(strain=0.123456, gauge_length_mm=56.1728, elongation_mm=6.1728)
    odd = make_sample(strain=-7654.321, gauge_length_mm=1.0e-3, elongation_mm=-98765.4)
    stop = threading.Event()
    published = [0]

    def publish_in_a_tight_loop() -> None:
        frame = 0
        while not stop.is_set():
            frame += 1
            server.publish(dataclasses.replace(odd if frame % 2 else even, frame_id=frame), None)
        published[0] = frame

    def as_float32(value: float) -> float:
        return float(np.float32(value))

    expected = {
        parity: tuple(
            as_float32(v)
            for v in (
                sample.reading.engineering_strain,
                sample.reading.elongation_mm,
                sample.reading.gauge_length_mm,
            )
        )
        for parity, sample in ((0, even), (1, odd))
    }
    writer = threading.Thread(target=publish_in_a_tight_loop, daemon=True)
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=10)
    frames_seen = set()
    reads = 0
    writer.start()
    try:
        assert client.connect()
        deadline = time.monotonic() + 20.0
        while reads < 400 and time.monotonic() < deadline:
            result = client.read_holding_registers(0, count=14, device_id=1)
            assert not result.isError(), result
            words = result.registers
            frame = modbus_map.decode(BY_NAME["frame_counter"], words[12:14])
            values = tuple(
                modbus_map.decode(BY_NAME[name], words[a : a + 2])
                for name, a in (("axial_strain", 0), ("elongation_mm", 6), ("gauge_length_mm", 8))
            )
            assert values == expected[frame % 2], (frame, values)
            frames_seen.add(frame)
            reads += 1
    finally:
        stop.set()
        writer.join(timeout=30)
        client.close()
    assert reads >= 50
    assert len(frames_seen) > 10, "the publisher did not run while reading"
    assert published[0] > len(frames_seen)


def test_pymodbus_internals_the_server_relies_on_are_there():
    handler = inspect.signature(ServerRequestHandler.__init__)
    assert list(handler.parameters) == [
        "self",
        "owner",
        "trace_packet",
        "trace_pdu",
        "trace_connect",
    ]
    assert inspect.iscoroutinefunction(ServerRequestHandler.handle_request)
    assert callable(ModbusSerialServer.callback_new_connection)
    serve_forever = inspect.signature(ModbusSerialServer.serve_forever)
    assert serve_forever.parameters["background"].kind is inspect.Parameter.KEYWORD_ONLY
    assert "action" in {f.name for f in dataclasses.fields(SimDevice)}
    assert list(inspect.signature(SimCore).parameters) == ["devices"]
    request = DecodePDU(True).decode(struct.pack(">BHH", 3, 0, 2))
    assert request is not None and (request.address, request.count) == (0, 2)
    assert inspect.iscoroutinefunction(request.datastore_update)
    assert list(inspect.signature(request.datastore_update).parameters) == [
        "context",
        "device_id",
    ]
    assert DecodePDU(True).decode(struct.pack(">BHH", 3, 0, 126)) is None


def test_latency_benchmark_runs_and_writes_its_report(tmp_path, capsys):
    out = tmp_path / "results"
    assert run_modbus_benchmark(out, True, frames=10) == 0
    figures = json.loads((out / "modbus.json").read_text(encoding="utf-8"))["figures"]
    assert json.loads(capsys.readouterr().out) == figures
    assert figures["verdict"] in ("met", "missed") and figures["setup"]["points"] == 10
    for key in ("without_client", "with_polling_client"):
        run = figures[key]
        assert run["frames"] == 10 and run["exit_status"] == "completed"
        assert run["delivery_to_register_ms"]["n"] == 10
        assert set(run["stages_ms"]) == {
            "queue_to_tracking_thread",
            "tracker_track",
            "gauges_read",
            "rest_of_measure",
            "publish",
        }
        assert run["max_abs_strain_error"] < 1e-3
        ratio = run["in_tracker_medians"]
        stages = run["stages_ms"]
        assert ratio["p50"] == pytest.approx(
            run["delivery_to_register_ms"]["p50"] / stages["tracker_track"]["p50"]
        )
        assert ratio["p50"] >= 1.0 and ratio["p99"] >= ratio["p50"]
    assert figures["with_polling_client"]["client"]["frames_seen"] > 0


def test_the_registers_count_drops_and_flag_the_sample_after_a_gap(commands):
    server = StrainRegisterServer(ModbusConfig(), commands)
    status, counter = BY_NAME["status"], BY_NAME["frames_dropped"]
    server.set_run_state(RunState.ARMED)
    server.set_run_state(RunState.RUNNING)
    for dropped, flagged in ((0, False), (3, True), (3, False), (4, True)):
        server.publish(make_sample(frames_dropped=dropped), None)
        bits = server.read_registers(status.address, 1)[0]
        assert bool(bits & StatusBit.FRAMES_DROPPED) is flagged, dropped
        words = server.read_registers(counter.address, counter.count)
        assert modbus_map.decode(counter, words) == dropped
    server.set_run_state(RunState.ARMED)
    assert modbus_map.decode(counter, server.read_registers(counter.address, counter.count)) == 0
    server.close()


@needs_mbpoll
def test_the_width_registers_carry_each_station_and_read_nan_without_a_width(serve):
    server, port = serve()
    _published(server)
    empty = _floats(mbpoll_read_tcp(port, "-r", "33", "-c", "2", "-t", "4:float", "-B"))
    assert all(math.isnan(value) for value in empty.values())
    assert mbpoll_read_tcp(port, "-r", "37", "-c", "2", "-t", "4") == {37: "0", 38: "0"}
    width = WidthReading(
        widths_mm=(12.25, math.nan, 12.5),
        seen=(True, False, True),
        mean_width_mm=12.375,
        transverse_strain=-0.01,
    )
    server.set_run_state(RunState.RUNNING)
    server.publish(
        dataclasses.replace(make_sample(machine=MACHINE, strain=0.04), width=width), make_facts()
    )
    mean = _floats(mbpoll_read_tcp(port, "-r", "33", "-c", "2", "-t", "4:float", "-B"))
    assert mean == {33: pytest.approx(12.375), 35: pytest.approx(-0.01, rel=1e-6)}
    assert mbpoll_read_tcp(port, "-r", "37", "-c", "2", "-t", "4") == {37: "2", 38: "3"}
    poisson = _floats(mbpoll_read_tcp(port, "-r", "39", "-t", "4:float", "-B"))
    assert poisson == {39: pytest.approx(0.25, rel=1e-6)}
    stations = _floats(mbpoll_read_tcp(port, "-r", "41", "-c", "8", "-t", "4:float", "-B"))
    assert stations[41] == pytest.approx(12.25) and stations[45] == pytest.approx(12.5)
    assert math.isnan(stations[43]) and all(math.isnan(stations[a]) for a in range(47, 57, 2))
