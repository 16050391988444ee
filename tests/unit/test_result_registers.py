"""The result registers: where they are in the map, and a test's `results` object as their
values (every result of both standards served, in the register's unit, NaN when not
determined)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from appliance.live.modbus_map import (
    BY_NAME,
    RESULT_BLOCK,
    RESULT_VALUES,
    RESULTS_STANDARD_CODES,
    Access,
    RegisterType,
    ResultsStandard,
)
from appliance.live.result_registers import RESULT_SYMBOLS, result_register_values
from appliance.results import metals, rubber
from appliance.results import result as result_types
from appliance.results.result import Result
from appliance.results.series import TestSeries as Series


def test_the_result_block_sits_in_the_former_reserved_range_and_is_read_only():
    assert [(r.name, r.address, r.count) for r in RESULT_BLOCK[:3]] == [
        ("results_valid", 57, 1),
        ("results_counter", 58, 1),
        ("results_standard", 59, 1),
    ]
    floats = RESULT_BLOCK[3:]
    assert all(r.data_type is RegisterType.FLOAT32 for r in floats)
    assert [r.address for r in floats] == list(range(60, 90, 2))
    assert all(r.access is Access.READ for r in RESULT_BLOCK)
    assert BY_NAME["reserved"].address == 90 and BY_NAME["reserved"].end == 100
    assert RESULT_VALUES == RESULT_BLOCK[2:]
    assert set(RESULT_SYMBOLS) == {r.name for r in floats}
    for register in floats:
        assert "NaN: not determined" in register.description
    assert set(RESULTS_STANDARD_CODES) == {metals.STANDARD, rubber.STANDARD}


def _series(n: int = 3) -> Series:
    return Series.of(np.linspace(0.0, 0.01, n), np.full(n, np.nan))


def test_every_result_symbol_is_one_the_standards_give():
    symbols = {r.symbol for r in metals.metal_results(_series(), 25.0, broke=True).results}
    symbols |= {r.symbol for r in rubber.rubber_results(_series(), 12.4, broke=True).results}
    assert set(RESULT_SYMBOLS.values()) <= symbols


def test_values_are_converted_to_the_registers_units_and_missing_ones_are_nan():
    results = result_types.TestResults(
        "ISO 6892-1",
        25.0,
        [
            Result.determined("E", "modulus", "GPa", 209.5, (3, 40), "fit"),
            Result.determined("Rp0.2", "proof", "MPa", 355.04, (102, 103), "interp"),
            Result.determined("Ag", "Ag", "%", 14.83, (300, 320), "fit"),
            Result.determined("r", "r", "1", 1.774, (200, 260), "r_8-12"),
            Result.not_determined("n", "n", "1", "the test ended at 9 %"),
            Result.not_determined("A", "A", "%", "the test ended before the fracture"),
        ],
    ).as_dict()
    values = result_register_values(results)
    assert values["results_standard"] == ResultsStandard.ISO_6892_1
    assert values["result_modulus_mpa"] == pytest.approx(209500.0)
    assert values["result_rp02_mpa"] == 355.04
    assert values["result_ag"] == pytest.approx(0.1483)
    assert values["result_r_8_12"] == 1.774
    for name in ("result_n", "result_a", "result_rm_mpa", "result_tensile_strength_mpa"):
        assert math.isnan(values[name]), name
    assert set(values) == {r.name for r in RESULT_VALUES}


def test_a_test_without_results_and_a_unit_that_does_not_convert_give_nan():
    none = result_register_values({"standard": None, "not_determined": "no material"})
    assert none["results_standard"] == ResultsStandard.NONE
    assert all(math.isnan(v) for k, v in none.items() if k != "results_standard")
    odd = result_register_values(
        {"standard": "ISO 37", "TS": {"value": 20.0, "unit": "kN"}, "Eb": {"value": 612.0}}
    )
    assert odd["results_standard"] == ResultsStandard.ISO_37
    assert math.isnan(odd["result_tensile_strength_mpa"])
    assert math.isnan(odd["result_elongation_at_break"])
