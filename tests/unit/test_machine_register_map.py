"""Register maps as data: parsing from config tables, errors, the read plan, the codec."""

from __future__ import annotations

import math

import pytest
from pymodbus.client.mixin import ModbusClientMixin

from hal.errors import HardwareConfigError
from hal.machine.register_map import (
    DATA_TYPES,
    ENTRIES,
    GENERIC_CONTROLLER,
    MAX_READ_REGISTERS,
    Register,
    RegisterMap,
)

DT = ModbusClientMixin.DATATYPE
WHERE = "run.toml: [machine.registers]"


def _encode(value, data_type, word_order="big"):
    return ModbusClientMixin.convert_to_registers(value, data_type, word_order=word_order)


def _map(**entries: Register) -> RegisterMap:
    base = {
        "crosshead_mm": Register(0, "input", "float32"),
        "speed_mm_min": Register(2, "input", "float32"),
        "force_n": Register(4, "input", "float32"),
    }
    return RegisterMap(**{**base, **entries})


def test_generic_preset_reads_everything_in_one_request():
    plan = GENERIC_CONTROLLER.read_plan()
    assert len(plan) == 1
    (span,) = plan
    assert (span.table, span.address, span.count) == ("input", 0, 9)
    assert [name for name, _ in span.entries] == [
        "crosshead_mm",
        "speed_mm_min",
        "force_n",
        "encoder_counts",
        "running",
    ]
    assert span.describe() == (
        "crosshead_mm, speed_mm_min, force_n, encoder_counts, running (input 0..8)"
    )
    assert set(GENERIC_CONTROLLER.entries()) == set(ENTRIES)


@pytest.mark.parametrize("word_order", ["big", "little"])
@pytest.mark.parametrize(
    ("data_type", "converter", "raw"),
    [
        ("int16", DT.INT16, -12345),
        ("uint16", DT.UINT16, 54321),
        ("int32", DT.INT32, -123456789),
        ("uint32", DT.UINT32, 3_000_000_000),
        ("float32", DT.FLOAT32, -1234.5),
    ],
)
def test_each_numeric_type_decodes_in_both_word_orders(data_type, converter, raw, word_order):
    words = _encode(raw, converter, word_order)
    plain = Register(10, "holding", data_type, word_order=word_order)
    assert plain.decode(words) == raw
    scaled = Register(10, "input", data_type, scale=0.01, offset=-5.0, word_order=word_order)
    assert scaled.decode(words) == raw * 0.01 - 5.0
    assert scaled.encode(raw * 0.01 - 5.0) == words
    assert plain.size == len(words)


def test_word_order_is_the_order_of_the_words():
    high_first = _encode(1.5, DT.FLOAT32, "big")
    assert high_first == [0x3FC0, 0x0000]
    assert Register(0, "holding", "float32", word_order="little").decode([0x0000, 0x3FC0]) == 1.5
    assert Register(0, "holding", "float32").decode([0x0000, 0x3FC0]) != 1.5


def test_bools_are_bits_of_registers_whole_registers_or_coils():
    status = 0b1010_0000_0000_0101
    assert Register(8, "input", "bool", bit=0).decode([status]) is True
    assert Register(8, "input", "bool", bit=1).decode([status]) is False
    assert Register(8, "input", "bool", bit=15).decode([status]) is True
    assert Register(8, "input", "bool").decode([0]) is False
    assert Register(8, "input", "bool").decode([7]) is True
    assert Register(3, "coil", "bool").decode([True]) is True
    assert Register(3, "discrete", "bool").decode([False]) is False
    assert Register(8, "holding", "bool", bit=3).encode(True) == [8]


def test_encoding_refuses_what_the_register_cannot_hold():
    with pytest.raises(ValueError, match="outside int16"):
        Register(0, "holding", "int16", scale=0.1).encode(4000.0)
    with pytest.raises(ValueError, match="not finite"):
        Register(0, "holding", "float32").encode(math.nan)
    with pytest.raises(ValueError, match="float32"):
        Register(0, "holding", "float32").encode(1e39)
    with pytest.raises(ValueError, match="is a bit"):
        Register(0, "coil", "bool").encode(True)
    assert Register(0, "holding", "uint16", scale=0.5).encode(10.2) == [20]


def test_coalescing_bridges_small_gaps_only():
    near = _map(encoder_counts=Register(6 + 8, "input", "int32"))
    assert [(s.address, s.count) for s in near.read_plan()] == [(0, 16)]
    far = _map(encoder_counts=Register(6 + 9, "input", "int32"))
    assert [(s.address, s.count) for s in far.read_plan()] == [(0, 6), (15, 2)]
    no_gap = RegisterMap(
        **{**far.entries(), "encoder_counts": Register(7, "input", "int32")}, max_gap=0
    )
    assert [(s.address, s.count) for s in no_gap.read_plan()] == [(0, 6), (7, 2)]


def test_coalescing_keeps_within_the_protocol_limits_and_tables_apart():
    wide = RegisterMap(
        crosshead_mm=Register(0, "holding", "float32"),
        speed_mm_min=Register(60, "holding", "float32"),
        force_n=Register(124, "holding", "float32"),
        running=Register(10, "discrete", "bool"),
        encoder_counts=Register(0, "input", "uint16"),
        max_gap=120,
    )
    plan = [(s.table, s.address, s.count) for s in wide.read_plan()]
    assert plan == [("holding", 0, 62), ("holding", 124, 2), ("input", 0, 1), ("discrete", 10, 1)]
    assert all(s.count <= MAX_READ_REGISTERS for s in wide.read_plan())
    bits = _map(
        running=Register(0, "coil", "bool"),
        start=Register(1, "coil", "bool"),
    )
    assert [(s.table, s.count) for s in bits.read_plan()] == [("input", 6), ("coil", 1)]


def test_a_span_decodes_each_of_its_entries():
    values = {
        "crosshead_mm": 12.5,
        "speed_mm_min": -30.0,
        "force_n": 4321.0,
        "encoder_counts": -12500,
        "running": True,
    }
    image = GENERIC_CONTROLLER.register_image(values)
    (span,) = GENERIC_CONTROLLER.read_plan()
    raw = [image["input"].get(a, 0) for a in range(span.address, span.address + span.count)]
    assert span.decode(raw) == values
    assert image["input"][8] == 1
    with pytest.raises(ValueError, match="8 values for 9"):
        span.decode(raw[:8])


def test_bits_of_one_status_word_share_it():
    shared = _map(
        running=Register(8, "input", "bool", bit=0),
        encoder_counts=Register(9, "input", "uint16"),
    )
    table = shared.to_table()
    both = RegisterMap.from_table({**table, "running": {**table["running"], "bit": 4}}, WHERE)
    assert both.running.bit == 4
    image = both.register_image(
        {"crosshead_mm": 0, "speed_mm_min": 0, "force_n": 0, "running": True, "encoder_counts": 3}
    )
    assert image["input"][8] == 16


def test_preset_overrides_key_by_key_and_drops_optional_entries():
    table = {
        "preset": "generic",
        "force_n": {"address": 20, "table": "holding", "data_type": "int32", "scale": 0.1},
        "running": {"table": "discrete", "address": 3},
        "return_to_start": False,
        "max_gap": 4,
    }
    parsed = RegisterMap.from_table(table, WHERE)
    assert parsed.force_n == Register(20, "holding", "int32", scale=0.1, unit="N")
    assert parsed.running == Register(3, "discrete", "bool")
    assert parsed.return_to_start is None and parsed.max_gap == 4
    assert parsed.crosshead_mm == GENERIC_CONTROLLER.crosshead_mm
    assert RegisterMap.from_table({"preset": "generic"}, WHERE) == GENERIC_CONTROLLER


def test_maps_round_trip_through_plain_tables():
    for register_map in (
        GENERIC_CONTROLLER,
        _map(
            running=Register(7, "holding", "bool", bit=2),
            start=Register(30, "holding", "uint16", value=1),
            stop=Register(30, "holding", "uint16", value=2),
            speed_setpoint_mm_min=Register(
                40, "holding", "int32", scale=0.001, word_order="little"
            ),
        ),
    ):
        table = register_map.to_table()
        assert table["preset"] == "none"
        assert RegisterMap.from_table(table, WHERE) == register_map
        for entry in table.values():
            if isinstance(entry, dict):
                assert all(isinstance(v, str | int | float) for v in entry.values())


def _error(table) -> str:
    with pytest.raises(HardwareConfigError) as raised:
        RegisterMap.from_table(table, WHERE)
    message = str(raised.value)
    assert "\n" not in message
    return message


@pytest.mark.parametrize(
    ("override", "expected"),
    [
        (
            {"force_n": {"data_type": "float"}},
            "run.toml: [machine.registers.force_n] data_type: must be one of "
            f"{', '.join(DATA_TYPES)}, got 'float'",
        ),
        (
            {"force_n": {"table": "coil"}},
            "run.toml: [machine.registers.force_n] data_type: a coil holds one bit: must be bool, "
            "got 'float32'",
        ),
        (
            {"force_n": {"adress": 3}},
            "run.toml: [machine.registers.force_n] adress: unknown key",
        ),
        (
            {"force_n": {"address": 70000}},
            "run.toml: [machine.registers.force_n] address: must be an integer 0 ... 65535, "
            "got 70000",
        ),
        (
            {"force_n": {"address": "4"}},
            "run.toml: [machine.registers.force_n] address: must be an integer",
        ),
        (
            {"force_n": {"address": True}},
            "run.toml: [machine.registers.force_n] address: must be an integer",
        ),
        (
            {"force_n": {"address": 65535}},
            "run.toml: [machine.registers.force_n] address: a float32 at 65535 runs past",
        ),
        ({"force_n": {"scale": 0}}, "run.toml: [machine.registers.force_n] scale: must not be 0"),
        (
            {"force_n": {"scale": "1"}},
            "run.toml: [machine.registers.force_n] scale: must be a finite number",
        ),
        (
            {"force_n": {"word_order": "middle"}},
            "run.toml: [machine.registers.force_n] word_order: must be one of big, little",
        ),
        (
            {"force_n": {"data_type": "bool"}},
            "run.toml: [machine.registers.force_n] data_type: must be one of int16, uint16, int32, "
            "uint32, float32 (a number), got 'bool'",
        ),
        (
            {"running": {"bit": 16}},
            "run.toml: [machine.registers.running] bit: must be an integer 0 ... 15, got 16",
        ),
        (
            {"running": {"data_type": "uint16"}},
            "run.toml: [machine.registers.running] data_type: must be 'bool', got 'uint16'",
        ),
        (
            {"force_n": {"bit": 3}},
            "run.toml: [machine.registers.force_n] bit: only for a bool in a holding or input",
        ),
        (
            {"encoder_counts": {"data_type": "float32"}},
            "run.toml: [machine.registers.encoder_counts] data_type: must be one of int16",
        ),
        (
            {"encoder_counts": {"address": 5}},
            "run.toml: [machine.registers.encoder_counts] address: input 5..6 overlaps force_n "
            "(input 4..5)",
        ),
        (
            {"speed_setpoint_mm_min": {"table": "input"}},
            "run.toml: [machine.registers.speed_setpoint_mm_min] table: a set point is written",
        ),
        (
            {"start": {"table": "discrete"}},
            "run.toml: [machine.registers.start] table: a command is written",
        ),
        (
            {"start": {"table": "holding", "data_type": "uint16", "address": 9}},
            "run.toml: [machine.registers.start] value: missing",
        ),
        (
            {"start": {"table": "holding", "data_type": "uint16", "address": 9, "value": -1}},
            "run.toml: [machine.registers.start] value: must fit uint16 (0 ... 65535), got -1",
        ),
        (
            {"stop": {"address": 0}},
            "run.toml: [machine.registers.stop] address: coil 0 overlaps start (coil 0)",
        ),
        ({"force_n": {"value": 3}}, "run.toml: [machine.registers.force_n] value: only for"),
        ({"force_n": False}, "run.toml: [machine.registers.force_n]: required, cannot be dropped"),
        ({"force_n": 4}, "run.toml: [machine.registers.force_n]: must be a table"),
        ({"forse_n": {}}, "run.toml: [machine.registers] forse_n: unknown entry"),
        ({"max_gap": 500}, "run.toml: [machine.registers] max_gap: must be an integer 0 ... 120"),
        ({"preset": "acme"}, "run.toml: [machine.registers] preset: must be one of generic, none"),
    ],
)
def test_bad_settings_are_named_in_one_line(override, expected):
    assert _error({"preset": "generic", **override}).startswith(expected)


def test_without_a_preset_entries_are_complete_and_required():
    assert _error({}) == (
        "run.toml: [machine.registers.crosshead_mm]: missing "
        "(crosshead_mm, speed_mm_min and force_n are required)"
    )
    assert _error({"crosshead_mm": {"address": 0, "table": "input"}}).startswith(
        "run.toml: [machine.registers.crosshead_mm] data_type: missing"
    )
    parsed = RegisterMap.from_table(
        {
            "crosshead_mm": {"address": 0, "table": "input", "data_type": "float32"},
            "speed_mm_min": {"address": 2, "table": "input", "data_type": "float32"},
            "force_n": {"address": 4, "table": "input", "data_type": "float32"},
        },
        WHERE,
    )
    assert parsed.running is None and parsed.start is None


def test_overlaps_allowed_for_distinct_bits_and_command_values_only():
    _map(
        running=Register(8, "input", "bool", bit=0),
        start=Register(20, "holding", "uint16", value=1),
        stop=Register(20, "holding", "uint16", value=2),
    )
    with pytest.raises(HardwareConfigError, match=r"\[stop\] address: holding 20 overlaps start"):
        _map(
            start=Register(20, "holding", "uint16", value=1),
            stop=Register(20, "holding", "uint16", value=1),
        )
    with pytest.raises(HardwareConfigError, match="overlaps"):
        _map(running=Register(4, "input", "bool", bit=0))
    assert Register(5, "holding", "float32").describe() == "holding 5..6"


def test_a_register_checks_itself_when_built_in_code():
    with pytest.raises(HardwareConfigError, match="register coil 3: data_type: a coil holds"):
        Register(3, "coil", "float32")
    with pytest.raises(HardwareConfigError, match="scale: does not apply to a bool"):
        Register(3, "discrete", "bool", scale=2.0)
    with pytest.raises(HardwareConfigError, match=r"register map \[force_n\] data_type"):
        _map(force_n=Register(4, "input", "bool"))
