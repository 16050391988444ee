"""Fuzzing the configuration loader and the points file: a one-line error or a usable value.

Any TOML document, or any table a TOML document can hold, either loads as a configuration or is
refused with one `InputError` line naming the source; a configuration that loads can be planned
(optics, the simulated world, the exposure plan) without any other exception. Any text as a
points file is read or refused in one line naming the file. The tables are drawn from the
configuration's own keys, with values near and beyond each key's range as well as of the wrong
type, so most examples reach the checks behind the first one.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from appliance.cli.points_file import read_points
from appliance.config import Config, config_from_table, config_to_table, parse_config
from appliance.errors import InputError
from appliance.plan.exposure import exposure_for
from appliance.plan.optics import configured_optics
from appliance.sim.world import PRESETS, SimWorld

DEFAULTS = Config()
TABLES = {
    f.name: type(getattr(DEFAULTS, f.name))
    for f in dataclasses.fields(Config)
    if dataclasses.is_dataclass(getattr(DEFAULTS, f.name))
}

ANY_VALUE = st.one_of(
    st.booleans(),
    st.integers(-(2**63), 2**63 - 1),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
    st.lists(st.integers(-5, 5), max_size=3),
    st.dictionaries(st.text(max_size=4), st.integers(), max_size=2),
)


def _value_for(field: dataclasses.Field, *, wild: bool) -> st.SearchStrategy:
    """Values for one key: in its range or among its choices; `wild` adds values just beyond
    the range and of any type."""
    meta = field.metadata
    low, high = meta.get("minimum"), meta.get("maximum")
    fitting: list[st.SearchStrategy] = []
    if "choices" in meta:
        fitting.append(st.sampled_from(meta["choices"]))
    if low is not None and high is not None:
        integral = isinstance(field.default, int) or "int" in str(field.type)
        if integral and float(low).is_integer() and float(high).is_integer():
            fitting.append(st.integers(int(low), int(high)))
        else:
            fitting.append(st.floats(low, high, allow_nan=False))
        fitting.append(st.sampled_from([low, high]))
    if isinstance(field.default, (bool, int, float, str)):
        fitting.append(st.just(field.default))
    if "bool" in str(field.type):
        fitting.append(st.booleans())
    if not wild:
        return st.one_of(fitting) if fitting else st.nothing()
    wild_values = [ANY_VALUE]
    if low is not None and high is not None:
        span = max(abs(high - low), 1.0)
        wild_values.append(st.floats(low - 0.1 * span, high + 0.1 * span, allow_nan=False))
    return st.one_of(*fitting, *wild_values)


@st.composite
def config_tables(draw, *, wild: bool) -> dict:
    """A configuration table of known tables and keys; `wild` adds unknown tables and keys
    and values out of range or of the wrong type."""
    names = [*TABLES, "surprise"] if wild else [*TABLES]
    table: dict = {}
    for name in draw(st.lists(st.sampled_from(names), max_size=5, unique=True)):
        if name == "surprise":
            table[name] = {"key": draw(ANY_VALUE)}
            continue
        fields = {
            f.name: f
            for f in dataclasses.fields(TABLES[name])
            if f.metadata.get("configurable", True)
            and (wild or _value_for(f, wild=False) is not st.nothing())
        }
        keys = [*fields, "unknown_key"] if wild else [*fields]
        chosen = draw(st.lists(st.sampled_from(keys), max_size=5, unique=True))
        table[name] = {
            key: draw(ANY_VALUE if key == "unknown_key" else _value_for(fields[key], wild=wild))
            for key in chosen
        }
    if draw(st.booleans()):
        table.setdefault("sim", {})["sensor_width_px"] = 256
        table["sim"]["sensor_height_px"] = 512
    return table


def _one_line_naming(error: InputError, source: str) -> None:
    text = str(error)
    assert text and "\n" not in text and "Traceback" not in text
    assert text.startswith(source) or text.startswith("["), text


def _use(config: Config) -> None:
    """Plan a simulated test from `config`: only a one-line `InputError` may come out."""
    optics = configured_optics(config, PRESETS[config.sim.material].optics)
    world = SimWorld.from_config(config, optics)
    plan = exposure_for(config, optics, world.speed_mm_min)
    assert math.isfinite(plan.frame_period_s) and plan.frame_period_s > 0


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.one_of(config_tables(wild=True), config_tables(wild=False)))
def test_any_configuration_table_loads_or_is_refused_in_one_line(table):
    try:
        config = config_from_table(table, "fuzz.toml")
    except InputError as refused:
        _one_line_naming(refused, "fuzz.toml")
        return
    assert config_from_table(config_to_table(config), "again") == config
    try:
        _use(config)
    except InputError as refused:
        _one_line_naming(refused, "fuzz.toml")


@settings(max_examples=300, deadline=None)
@given(st.text(max_size=200))
def test_any_text_as_a_configuration_file_loads_or_is_refused_in_one_line(text):
    try:
        tomllib.loads(text)
    except tomllib.TOMLDecodeError:
        pass
    try:
        parse_config(text, "any.toml")
    except InputError as refused:
        assert "\n" not in str(refused) and str(refused).startswith("any.toml")


POINT_LINES = st.one_of(
    st.just("x,y"),
    st.just("x,y,u0,v0"),
    st.just("# comment"),
    st.just(""),
    st.lists(
        st.one_of(
            st.floats(allow_nan=True, allow_infinity=True).map(repr),
            st.integers(-(10**30), 10**30).map(str),
            st.text(alphabet="0123456789.,-+eE naif", max_size=8),
        ),
        min_size=1,
        max_size=5,
    ).map(",".join),
    st.text(max_size=20),
)


@settings(
    max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(lines=st.lists(POINT_LINES, max_size=8), data=st.binary(max_size=40), as_bytes=st.booleans())
def test_any_points_file_is_read_or_refused_in_one_line_naming_it(tmp_path, lines, data, as_bytes):
    path = tmp_path / "points.csv"
    if as_bytes:
        path.write_bytes(data)
    else:
        path.write_text("\n".join(lines), encoding="utf-8")
    try:
        points = read_points(path)
    except InputError as refused:
        assert "\n" not in str(refused) and str(path) in str(refused)
        return
    assert points.xy.ndim == 2 and points.xy.shape[1] == 2
    assert bool(((points.xy == points.xy) & (abs(points.xy) < float("inf"))).all())
