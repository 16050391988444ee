"""A test's results as the values of the Modbus result registers.

When a test ends, the results wing (`appliance.results`) computes its results and the runner
hands them on as the summary's `results` object (what `summary.json` holds under `results`):

    {"standard": "ISO 6892-1", "cross_section_mm2": 25.0,
     "r": {"value": 1.77, "unit": "1", ...}, "Ag": {"value": 14.8, "unit": "%", ...}, ...}

`result_register_values` turns that object into the values of `modbus_map.RESULT_VALUES`: the
`results_standard` code and one float per result in the register's unit (E from GPa to MPa,
Ag, A and Eb from % to a fraction, 1 = 100 %), NaN for a result not determined, absent (a
result of the other standard) or in a unit the register cannot take. The live wing reads only
this documented object, never the results wing's code, so the two stay apart in the layers.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from appliance.live.modbus_map import (
    BY_NAME,
    RESULT_VALUES,
    RESULTS_STANDARD_CODES,
    RegisterType,
    ResultsStandard,
)

RESULT_SYMBOLS: Mapping[str, str] = {
    "result_modulus_mpa": "E",
    "result_rp02_mpa": "Rp0.2",
    "result_reh_mpa": "ReH",
    "result_rel_mpa": "ReL",
    "result_rm_mpa": "Rm",
    "result_ag": "Ag",
    "result_a": "A",
    "result_poisson_ratio": "nu",
    "result_r_8_12": "r",
    "result_n": "n",
    "result_tensile_strength_mpa": "TS",
    "result_elongation_at_break": "Eb",
    "result_s100_mpa": "S100",
    "result_s200_mpa": "S200",
    "result_s300_mpa": "S300",
}
"""Float register -> the symbol of the result it serves (a key of the `results` object)."""

UNIT_FACTORS: Mapping[tuple[str, str], float] = {
    ("MPa", "MPa"): 1.0,
    ("GPa", "MPa"): 1e3,
    ("%", "1"): 1e-2,
    ("1", "1"): 1.0,
}
"""(the result's unit, the register's unit) -> the factor from one to the other."""

CLEARED: Mapping[str, float | int] = {
    register.name: (
        math.nan if register.data_type is RegisterType.FLOAT32 else int(ResultsStandard.NONE)
    )
    for register in RESULT_VALUES
}
"""The values of the result registers that hold no test's results."""


def result_register_values(results: Mapping[str, Any]) -> dict[str, float | int]:
    """The values of `modbus_map.RESULT_VALUES` for a test's `results` object.

    Args:
        results: the summary's `results` object: `standard` (None when the test has no
            results at all) and, by symbol, `{"value": number or None, "unit": ...}`.

    Returns:
        register name -> value: `results_standard` its code, every float register its
        result in the register's unit, NaN where the result is not determined, absent or in
        a unit the register does not take.
    """
    values: dict[str, float | int] = dict(CLEARED)
    standard = results.get("standard")
    values["results_standard"] = int(
        RESULTS_STANDARD_CODES.get(standard, ResultsStandard.NONE)
        if isinstance(standard, str)
        else ResultsStandard.NONE
    )
    for name, symbol in RESULT_SYMBOLS.items():
        values[name] = _in_unit(results.get(symbol), BY_NAME[name].unit)
    return values


def _in_unit(result: Any, unit: str) -> float:
    """A result's value in `unit`; NaN when it has none or its unit does not convert."""
    if not isinstance(result, Mapping):
        return math.nan
    value = result.get("value")
    factor = UNIT_FACTORS.get((str(result.get("unit")), unit))
    if factor is None or not isinstance(value, int | float) or isinstance(value, bool):
        return math.nan
    converted = float(value) * factor
    return converted if math.isfinite(converted) else math.nan
