"""The last test's results on Modbus and in Rerun, from a served simulated sheet metal test.

`extensometer serve` runs as a real process (under a fake NOTIFY_SOCKET, as systemd would)
with the simulated devices; a pymodbus client reads the whole map (0 ... 104, one request)
over TCP on loopback and writes the start commands. A short metal test with the width at its
edges (`[transverse] stations`) to 13 % strain at 60 mm/min determines r_8-12 and n, and too
few elastic samples for E (so nu, Rp0.2 and the rest are not determined): the result
registers must hold the summary's values as float32, NaN where the summary has none, be
flagged valid in the same read as the exit status, and read NaN / not valid while the next
test runs. The viewer's saved recording holds the same results.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient

from appliance.config import ModbusConfig
from appliance.live import modbus_map
from appliance.live.modbus_map import BY_NAME, MAP_SIZE, RESULT_VALUES, ResultsStandard
from appliance.live.modbus_server import StrainRegisterServer
from appliance.live.result_registers import (
    RESULT_SYMBOLS,
    UNIT_FACTORS,
    result_register_values,
)
from appliance.live.viewer import RESULT
from appliance.run.state import ExitStatus
from tests.system import rerun_peers
from tests.system.modbus_peers import free_tcp_port
from tests.system.notify_harness import NotifyHarness

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))
RUN_STATE_IDLE = 0
EXIT_COMPLETED = 1


def _config(tmp_path: Path, port: int) -> Path:
    path = tmp_path / "service.toml"
    path.write_text(
        f'[modbus]\ntcp = "127.0.0.1:{port}"\n'
        f'[service]\nstate_directory = "{tmp_path / "state"}"\n'
        "[run]\nuntil_strain = 0.13\nspeed_mm_min = 60\n"
        '[sim]\nmaterial = "metal"\nsensor_width_px = 400\n'
        "[transverse]\nstations = 3\n"
        f'[rerun]\nsave = "{tmp_path / "{test}.rrd"}"\nimage_rate_hz = 0\n'
    )
    return path


def _read_map(client: ModbusTcpClient, word_order: str = "big") -> dict[str, float | int]:
    """Every value of the map from one read request (one register image)."""
    response = client.read_holding_registers(0, count=MAP_SIZE)
    assert not response.isError(), response
    words = response.registers
    return {
        r.name: modbus_map.decode(r, words[r.address : r.end], word_order)
        for r in modbus_map.REGISTER_MAP
        if r.data_type is not modbus_map.RegisterType.RESERVED
    }


def _wait_map(client: ModbusTcpClient, condition, timeout_s: float) -> dict[str, float | int]:
    deadline = time.monotonic() + timeout_s
    while True:
        values = _read_map(client)
        if condition(values):
            return values
        assert time.monotonic() < deadline, f"registers never matched: {values}"
        time.sleep(0.1)


def _float_results(values: dict[str, float | int]) -> dict[str, float]:
    return {r.name: values[r.name] for r in RESULT_VALUES if r.name in RESULT_SYMBOLS}


def _expected(results: dict, name: str) -> float:
    """The summary's result served by register `name`, in the register's unit (float64)."""
    entry = results.get(RESULT_SYMBOLS[name])
    if entry is None or entry["value"] is None:
        return math.nan
    return entry["value"] * UNIT_FACTORS[(entry["unit"], BY_NAME[name].unit)]


def test_a_served_metal_test_leaves_its_results_on_modbus_until_the_next_test(tmp_path):
    port = free_tcp_port()
    config = _config(tmp_path, port)
    with NotifyHarness([EXTENSOMETER, "serve", "--config", str(config)]) as service:
        service.wait_for("READY=1", timeout=180)
        client = ModbusTcpClient("127.0.0.1", port=port, timeout=10)
        assert client.connect()
        try:
            before = _read_map(client)
            assert (before["results_valid"], before["results_counter"]) == (0, 0)
            assert before["results_standard"] == ResultsStandard.NONE
            assert all(math.isnan(v) for v in _float_results(before).values())

            assert not client.write_register(100, 1).isError()
            ended = _wait_map(client, lambda v: v["exit_status"] != 0, 300)
            assert ended["exit_status"] == EXIT_COMPLETED
            assert (ended["results_valid"], ended["results_counter"]) == (1, 1)
            assert ended["results_standard"] == ResultsStandard.ISO_6892_1

            deadline = time.monotonic() + 60
            while not (summaries := sorted((tmp_path / "state").glob("*.summary.json"))):
                assert time.monotonic() < deadline, "no summary written"
                time.sleep(0.1)
            results = json.loads(summaries[0].read_text())["results"]
            test_id = summaries[0].name.removesuffix(".summary.json")
            assert results["r"]["value"] is not None and results["n"]["value"] is not None
            assert results["E"]["value"] is None
            served = _float_results(ended)
            for name, value in served.items():
                expected = _expected(results, name)
                if math.isnan(expected):
                    assert math.isnan(value), name
                else:
                    assert value == float(np.float32(expected)), name
            assert 1.0 < served["result_r_8_12"] < 3.0 and 0.05 < served["result_n"] < 0.5

            assert not client.write_register(100, 1).isError()
            running = _wait_map(client, lambda v: v["run_state"] != RUN_STATE_IDLE, 120)
            assert running["exit_status"] == 0
            assert (running["results_valid"], running["results_counter"]) == (0, 1)
            assert running["results_standard"] == ResultsStandard.NONE
            assert all(math.isnan(v) for v in _float_results(running).values())
        finally:
            client.close()
        assert service.terminate(timeout=60) == 0

    store = rerun_peers.recordings(tmp_path / f"{test_id}.rrd")[test_id]
    shown = rerun_peers.latest(store, RESULT)
    assert shown["exit_status"] == "completed"
    for name in RESULT_SYMBOLS:
        expected = _expected(results, name)
        if math.isnan(expected):
            assert math.isnan(shown[name]), name
        else:
            assert shown[name] == pytest.approx(expected, rel=1e-12), name


def test_results_are_written_with_the_exit_status_counted_and_cleared():
    """The server alone, in the little word order (CDAB; the served test reads ABCD)."""
    port = free_tcp_port()
    server = StrainRegisterServer(
        ModbusConfig(tcp=f"127.0.0.1:{port}", word_order="little"), lambda *_: False
    )
    server.start(timeout_s=30.0)
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=10)
    assert client.connect()
    rubber = {
        "standard": "ISO 37",
        "TS": {"value": 21.5, "unit": "MPa"},
        "Eb": {"value": 612.25, "unit": "%"},
        "S100": {"value": None, "unit": "MPa"},
    }
    try:
        server.set_exit_status(ExitStatus.BREAK, result_register_values(rubber))
        first = _read_map(client, "little")
        assert (first["exit_status"], first["results_valid"], first["results_counter"]) == (2, 1, 1)
        assert first["results_standard"] == ResultsStandard.ISO_37
        assert first["result_tensile_strength_mpa"] == 21.5
        assert first["result_elongation_at_break"] == float(np.float32(6.1225))
        assert math.isnan(first["result_s100_mpa"]) and math.isnan(first["result_r_8_12"])
        refused = client.write_registers(BY_NAME["result_r_8_12"].address, [0, 0])
        assert refused.isError() and refused.exception_code == 2

        server.set_exit_status(None)
        cleared = _read_map(client, "little")
        assert (cleared["exit_status"], cleared["results_valid"]) == (0, 0)
        assert cleared["results_counter"] == 1
        assert math.isnan(cleared["result_tensile_strength_mpa"])

        server.set_exit_status(ExitStatus.FAULT)
        failed = _read_map(client, "little")
        assert (failed["exit_status"], failed["results_valid"]) == (5, 0)
        assert failed["results_counter"] == 1
        server.set_exit_status(ExitStatus.COMPLETED, result_register_values(rubber))
        assert _read_map(client, "little")["results_counter"] == 2
    finally:
        client.close()
        server.close()
