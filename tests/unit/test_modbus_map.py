"""The Modbus register map as data: layout, codecs in both word orders, the integrator's table
(appliance/live/README.md)."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
from pymodbus.client.mixin import ModbusClientMixin

from appliance.live import modbus_map
from appliance.live.modbus_map import (
    BY_NAME,
    EXIT_STATUS_CODES,
    MAP_SIZE,
    MEASUREMENT_BLOCK,
    REGISTER_MAP,
    RUN_STATE_CODES,
    SERVED_FUNCTION_CODES,
    Access,
    Register,
    RegisterType,
    StatusBit,
)
from appliance.run.state import ExitStatus, RunState

README = Path(__file__).resolve().parents[2] / "appliance" / "live" / "README.md"
SECTION = "## Modbus register map"

FIXED_BLOCK = {
    "axial_strain": (0, 2, RegisterType.FLOAT32),
    "transverse_strain": (2, 2, RegisterType.FLOAT32),
    "true_strain": (4, 2, RegisterType.FLOAT32),
    "elongation_mm": (6, 2, RegisterType.FLOAT32),
    "gauge_length_mm": (8, 2, RegisterType.FLOAT32),
    "status": (10, 1, RegisterType.UINT16),
    "heartbeat": (11, 1, RegisterType.UINT16),
    "frame_counter": (12, 2, RegisterType.UINT32),
    "timestamp_unix_ns": (14, 4, RegisterType.UINT64),
    "poisson_ratio": (18, 2, RegisterType.FLOAT32),
    "crosshead_mm": (20, 2, RegisterType.FLOAT32),
    "force_n": (22, 2, RegisterType.FLOAT32),
    "time_since_reference_s": (24, 2, RegisterType.FLOAT32),
    "points_lost": (26, 1, RegisterType.UINT16),
    "run_state": (27, 1, RegisterType.UINT16),
    "latency_ms": (28, 2, RegisterType.FLOAT32),
    "command": (100, 1, RegisterType.UINT16),
    "command_counter": (101, 1, RegisterType.UINT16),
    "command_result": (102, 1, RegisterType.UINT16),
    "gauge_length_setpoint_mm": (103, 2, RegisterType.FLOAT32),
}


def test_entries_do_not_overlap_and_cover_the_map_without_gaps():
    addresses = [a for r in REGISTER_MAP for a in range(r.address, r.end)]
    assert addresses == list(range(MAP_SIZE))
    assert len({r.name for r in REGISTER_MAP}) == len(REGISTER_MAP)
    assert MAP_SIZE <= 125, "the whole map should be readable in one request"


def test_fixed_block_and_command_block_are_at_the_documented_addresses():
    for name, (address, count, kind) in FIXED_BLOCK.items():
        register = BY_NAME[name]
        assert (register.address, register.count, register.data_type) == (address, count, kind)
    exit_status = BY_NAME["exit_status"]
    assert (exit_status.address, exit_status.count, exit_status.access) == (30, 1, Access.READ)
    dropped = BY_NAME["frames_dropped"]
    assert (dropped.address, dropped.count, dropped.data_type) == (31, 2, RegisterType.UINT32)
    width = [(r.name, r.address, r.count) for r in modbus_map.WIDTH_BLOCK]
    assert width[:5] == [
        ("width_mm", 33, 2),
        ("width_transverse_strain", 35, 2),
        ("width_stations_seen", 37, 1),
        ("width_stations", 38, 1),
        ("width_poisson_ratio", 39, 2),
    ]
    assert width[5:] == [(f"width_{k}_mm", 39 + 2 * k, 2) for k in range(1, 9)]
    reserved = BY_NAME["reserved"]
    assert (reserved.address, reserved.end, reserved.access) == (90, 100, Access.READ)
    writable = {r.name for r in REGISTER_MAP if r.writable}
    assert writable == {"command", "gauge_length_setpoint_mm"}
    assert BY_NAME["command"].choices == (1, 2, 3)
    setpoint = BY_NAME["gauge_length_setpoint_mm"]
    assert (setpoint.minimum, setpoint.maximum) == (1.0, 10000.0)
    assert [r.name for r in MEASUREMENT_BLOCK][-1] == "latency_ms"
    assert modbus_map.register_at(13) is BY_NAME["frame_counter"]
    assert modbus_map.register_at(MAP_SIZE) is None


def test_codes_are_distinct_and_every_run_state_has_one():
    assert set(RUN_STATE_CODES) == set(RunState)
    assert sorted(RUN_STATE_CODES.values()) == list(range(6))
    assert set(EXIT_STATUS_CODES) == set(ExitStatus) - {ExitStatus.DAMAGED}
    assert sorted(EXIT_STATUS_CODES.values()) == list(range(1, 6))
    assert [int(bit) for bit in StatusBit] == [1, 2, 4, 8, 16, 32, 64, 128, 256]


@pytest.mark.parametrize("word_order", ["big", "little"])
@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("axial_strain", 0.123456),
        ("axial_strain", -7654.321),
        ("force_n", 1.0e-30),
        ("heartbeat", 65535),
        ("frame_counter", 4_000_000_001),
        ("timestamp_unix_ns", 1_767_225_600_123_456_789),
        ("gauge_length_setpoint_mm", 10000.0),
    ],
)
def test_encode_decode_round_trip(name, value, word_order):
    register = BY_NAME[name]
    words = modbus_map.encode(register, value, word_order)
    assert len(words) == register.count and all(0 <= w <= 0xFFFF for w in words)
    decoded = modbus_map.decode(register, words, word_order)
    if register.data_type is RegisterType.FLOAT32:
        assert decoded == float(np.float32(value))
    else:
        assert decoded == value


def test_word_orders_are_abcd_and_cdab_and_nan_survives():
    strain = BY_NAME["axial_strain"]
    big = modbus_map.encode(strain, 50.5, "big")
    assert big == [0x424A, 0x0000]
    assert modbus_map.encode(strain, 50.5, "little") == [0x0000, 0x424A]
    frame = BY_NAME["frame_counter"]
    assert modbus_map.encode(frame, 0x12345678, "big") == [0x1234, 0x5678]
    assert modbus_map.encode(frame, 0x12345678, "little") == [0x5678, 0x1234]
    stamp = BY_NAME["timestamp_unix_ns"]
    assert modbus_map.encode(stamp, 0x0001000200030004, "little") == [4, 3, 2, 1]
    assert math.isnan(modbus_map.decode(strain, modbus_map.encode(strain, math.nan)))


def test_counters_wrap_and_block_encoding_matches_entry_by_entry():
    assert modbus_map.encode(BY_NAME["heartbeat"], 65536) == [0]
    assert modbus_map.encode(BY_NAME["frame_counter"], 2**32 + 5) == [0, 5]
    values = {
        r.name: (i + 0.25 if r.data_type is RegisterType.FLOAT32 else i)
        for i, r in enumerate(MEASUREMENT_BLOCK)
    }
    for order in ("big", "little"):
        block = modbus_map.encode_block(MEASUREMENT_BLOCK, values, order)
        one_by_one = [
            w for r in MEASUREMENT_BLOCK for w in modbus_map.encode(r, values[r.name], order)
        ]
        assert block == one_by_one
        assert len(block) == BY_NAME["exit_status"].address
    with pytest.raises(ValueError, match="contiguous"):
        modbus_map.encode_block((BY_NAME["axial_strain"], BY_NAME["status"]), values)


def test_codec_is_pymodbus_own():
    strain = BY_NAME["axial_strain"]
    expected = ModbusClientMixin.convert_to_registers(
        0.25, ModbusClientMixin.DATATYPE.FLOAT32, word_order="little"
    )
    assert modbus_map.encode(strain, 0.25, "little") == expected


def test_writable_entries_accept_only_their_values():
    command, setpoint = BY_NAME["command"], BY_NAME["gauge_length_setpoint_mm"]
    assert [command.accepts(v) for v in (0, 1, 2, 3, 4)] == [False, True, True, True, False]
    for value, ok in (
        (1.0, True),
        (10000.0, True),
        (0.999, False),
        (10000.5, False),
        (math.nan, False),
        (math.inf, False),
        (-5.0, False),
    ):
        assert setpoint.accepts(value) is ok, value
    with pytest.raises(ValueError, match="takes 2 registers"):
        Register("x", 0, 1, RegisterType.FLOAT32, Access.READ, "", "")
    with pytest.raises(ValueError, match="needs choices or a range"):
        Register("x", 0, 1, RegisterType.UINT16, Access.READ_WRITE, "", "")


def test_markdown_table_has_one_row_per_entry():
    table = modbus_map.render_markdown_table()
    rows = table.splitlines()
    assert rows[0].startswith("| address | name |") and rows[1].startswith("|---")
    assert len(rows) == 2 + len(REGISTER_MAP)
    assert rows[2].startswith("| 0-1 | `axial_strain` | float32 | r | 1 |")
    assert "| 100 | `command` | uint16 | rw |" in table
    assert all(row.count("|") == 7 for row in rows)


def _readme_table(text: str) -> str | None:
    """The first table of the README's register-map section; None without the section."""
    if SECTION not in text:
        return None
    section = text.split(SECTION, 1)[1]
    section = re.split(r"^## ", section, maxsplit=1, flags=re.MULTILINE)[0]
    lines: list[str] = []
    for line in section.splitlines():
        if line.startswith("|"):
            lines.append(line)
        elif lines:
            break
    return "\n".join(lines) + "\n" if lines else ""


def test_readme_register_table_matches_the_map():
    table = _readme_table(README.read_text(encoding="utf-8"))
    assert table is not None, f"{README} has no {SECTION!r} section"
    assert table == modbus_map.render_markdown_table(), (
        f"{README}: register table differs from appliance.live.modbus_map; regenerate it with "
        "python -c 'from appliance.live.modbus_map import render_markdown_table as t; print(t())'"
    )


def test_the_served_functions_are_register_reads_and_writes_only_and_the_guide_names_them():
    assert set(SERVED_FUNCTION_CODES) == {3, 4, 6, 16, 22, 23}
    text = README.read_text(encoding="utf-8")
    bullet = " ".join(text[text.index("- **Functions.**") :].split("\n\n")[0].split())
    for code in (1, 2, 5, 8, 15, 17, 20, 21, 24, 43):
        assert re.search(rf"\b{code}\b", bullet), code
    assert bullet.endswith("gets exception 1."), bullet
