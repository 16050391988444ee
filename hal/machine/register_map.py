"""Register maps of tensile-machine controllers, as data: where each quantity lives and how.

A machine controller exposes the crosshead position, speed and force (and maybe a status word and
an encoder count) in Modbus registers, and takes commands in coils or registers. Where they
live differs from controller to controller, so the map is configuration, not code: one
`Register` per quantity (address, register table, data type, scale, offset, unit, word order),
gathered in a `RegisterMap`. `ModbusMachine` (hal/machine/modbus.py) reads and writes through it;
this module talks to no network.

Entries of a map (the names are the keys of `[machine.registers]` in the configuration):

* reads: `crosshead_mm`, `speed_mm_min`, `force_n` (required, numeric); `running` (optional,
  bool); `encoder_counts` (optional, an integer type);
* the set point `speed_setpoint_mm_min` (optional, numeric, holding registers): written before
  `start` and `return_to_start`;
* commands `start`, `stop`, `return_to_start` (optional): a coil (written ON), or a holding
  register of an integer type written with the entry's `value` (a command word: several
  commands may share one register with different values).

Register fields:

* `address`: zero-based protocol (PDU) address; a manual that counts from 1 (or writes 40001
  for holding register 0) needs 1 (or 40001) subtracted.
* `table`: "holding" (function 3, written with 6/16), "input" (function 4), "coil" (function 1,
  written with 5), "discrete" (function 2).
* `data_type`: "int16", "uint16" (1 register), "int32", "uint32", "float32" (2 registers),
  "bool". A bool on a coil or discrete input is that bit; a bool in a holding or input
  register is bit `bit` of it (0 = least significant), or the whole register (non-zero =
  True) when `bit` is not given. Numeric types live in holding or input registers only.
* `scale`, `offset`: value = raw * scale + offset (raw as the data type decodes it); not for
  bools or commands.
* `unit`: text, for people (the map does not convert units; the entry's name says the unit
  the appliance expects, and `scale` gets the controller's unit there).
* `word_order`: "big" (most significant word first, ABCD for a float) or "little" (CDAB);
  bytes within a register are big-endian as Modbus says. Ignored by 16-bit types.

Decoding and encoding go through pymodbus' own converters
(`ModbusClientMixin.convert_from_registers` / `convert_to_registers`); a bit of a register is
a shift and a mask.

The read plan (`RegisterMap.read_plan`): the read entries of each table, sorted by address,
are merged into spans that one request reads: the next entry joins the span when at most
`max_gap` unused registers (16 x `max_gap` bits for coils and discrete inputs) lie between,
and the span stays within 125 registers (2000 bits), the protocol's limits. Reading a few
unused registers costs less than a second round trip (a round trip is milliseconds on a
serial line, a register 0.17 ms at 115200 baud). A controller that answers exception 2 to
reads of unused addresses needs `max_gap = 0`.

`GENERIC_CONTROLLER`, the preset "generic", is a layout a controller can be configured to (and
the one the test peers and the benchmark serve); one read request (input 0 ... 8) takes the
whole state:

| entry                 | table   | address  | data type    | unit   | meaning                   |
|-----------------------|---------|----------|--------------|--------|---------------------------|
| crosshead_mm          | input   | 0 ... 1  | float32 ABCD | mm     | from start, + = opening   |
| speed_mm_min          | input   | 2 ... 3  | float32 ABCD | mm/min | + = opening               |
| force_n               | input   | 4 ... 5  | float32 ABCD | N      | load cell, + = tension    |
| encoder_counts        | input   | 6 ... 7  | int32 ABCD   | counts | crosshead encoder         |
| running               | input   | 8, bit 0 | bool         |        | status word bit 0: moving |
| speed_setpoint_mm_min | holding | 0 ... 1  | float32 ABCD | mm/min | of the next start/return  |
| start                 | coil    | 0        | bool, ON     |        | start at the set point    |
| stop                  | coil    | 1        | bool, ON     |        | stop the crosshead        |
| return_to_start       | coil    | 2        | bool, ON     |        | back to start, set point  |

Other bits of the status word are not read. A command coil is written ON every time (a
momentary command: the controller acts on the write and may clear the coil itself); the client
never writes it OFF.

Configuration (`RegisterMap.from_table`, the shape TOML gives): `preset` ("generic" or "none";
absent = "none", so nothing is inherited, least of all a command address, unless asked for),
`max_gap` (registers, default 8), and one sub-table per entry that overrides the preset's entry
key by key, or `false` to drop an optional entry of the preset::

    [machine.registers]
    preset = "generic"
    force_n = { address = 10, table = "holding", data_type = "int32", scale = 0.1, unit = "N" }
    return_to_start = false

A preset's `bit` (or `value`) is dropped when the override makes the entry something it does
not apply to (a coil, say); a `bit` or `value` the user gives is checked. Every error is one
line naming the place and the key (`run.toml: [machine.registers.force_n] data_type: must be
one of int16, uint16, int32, uint32, float32, bool, got 'float'`). `to_table` is the inverse
(the whole map, preset "none").

What this module does not do: talk to a controller, convert units, read strings, 64-bit types
or arrays, describe a command that needs several writes beyond "set point, then command", or
read a controller clock (the client time-stamps readings on the host).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

from pymodbus.client.mixin import ModbusClientMixin

from hal.errors import HardwareConfigError

Table = Literal["holding", "input", "coil", "discrete"]
DataType = Literal["int16", "uint16", "int32", "uint32", "float32", "bool"]
WordOrder = Literal["big", "little"]
Value = float | bool

TABLES: tuple[str, ...] = ("holding", "input", "coil", "discrete")
REGISTER_TABLES: tuple[str, ...] = ("holding", "input")
BIT_TABLES: tuple[str, ...] = ("coil", "discrete")
DATA_TYPES: tuple[str, ...] = ("int16", "uint16", "int32", "uint32", "float32", "bool")
INTEGER_TYPES: tuple[str, ...] = ("int16", "uint16", "int32", "uint32")
NUMERIC_TYPES: tuple[str, ...] = (*INTEGER_TYPES, "float32")
WORD_ORDERS: tuple[str, ...] = ("big", "little")

REQUIRED_READS: tuple[str, ...] = ("crosshead_mm", "speed_mm_min", "force_n")
READS: tuple[str, ...] = (*REQUIRED_READS, "running", "encoder_counts")
SETPOINTS: tuple[str, ...] = ("speed_setpoint_mm_min",)
COMMANDS: tuple[str, ...] = ("start", "stop", "return_to_start")
ENTRIES: tuple[str, ...] = (*READS, *SETPOINTS, *COMMANDS)
FIELDS: tuple[str, ...] = (
    "address",
    "table",
    "data_type",
    "scale",
    "offset",
    "unit",
    "word_order",
    "bit",
    "value",
)
PRESET_NAMES: tuple[str, ...] = ("generic", "none")

MAX_READ_REGISTERS = 125
"""Registers one read (function 3 or 4) may ask for."""
MAX_READ_BITS = 2000
"""Coils or discrete inputs one read (function 1 or 2) may ask for."""
DEFAULT_MAX_GAP = 8
"""Unused registers a read span may bridge (x 16 for bits)."""

_DATATYPE = ModbusClientMixin.DATATYPE
_CONVERTERS = {
    "int16": _DATATYPE.INT16,
    "uint16": _DATATYPE.UINT16,
    "int32": _DATATYPE.INT32,
    "uint32": _DATATYPE.UINT32,
    "float32": _DATATYPE.FLOAT32,
}
_WORDS = {"int16": 1, "uint16": 1, "int32": 2, "uint32": 2, "float32": 2, "bool": 1}
_INTEGER_RANGES = {
    "int16": (-(2**15), 2**15 - 1),
    "uint16": (0, 2**16 - 1),
    "int32": (-(2**31), 2**31 - 1),
    "uint32": (0, 2**32 - 1),
}

Problem = tuple[str, str]
"""(key, reason) of a bad setting."""


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _choices(options: Sequence[str]) -> str:
    return ", ".join(options)


@dataclass(frozen=True)
class Register:
    """Where one quantity lives in a controller and how it is coded.

    Args:
        address: zero-based protocol address (0 ... 65535; a 32-bit value takes `address` and
            `address + 1`).
        table: "holding", "input", "coil" or "discrete".
        data_type: "int16", "uint16", "int32", "uint32", "float32" or "bool".
        scale: value = raw * scale + offset; non-zero, finite.
        offset: see `scale`.
        unit: text for people (no conversion is made from it).
        word_order: "big" (high word first, ABCD) or "little" (CDAB).
        bit: for a bool in a holding or input register, its bit (0 = least significant);
            None = the whole register (non-zero = True).
        value: for a command in a holding register, the raw value written.

    Raises:
        HardwareConfigError: a field is out of range or does not fit the others (one line
            naming the register and the field).
    """

    address: int
    table: Table = "holding"
    data_type: DataType = "float32"
    scale: float = 1.0
    offset: float = 0.0
    unit: str = ""
    word_order: WordOrder = "big"
    bit: int | None = None
    value: int | None = None

    def __post_init__(self) -> None:
        problem = _register_problem(dataclasses.asdict(self))
        if problem is not None:
            key, reason = problem
            raise HardwareConfigError(f"register {self.table} {self.address}: {key}: {reason}")

    @property
    def size(self) -> int:
        """Registers (holding, input) or bits (coil, discrete) the entry occupies."""
        return 1 if self.table in BIT_TABLES else _WORDS[self.data_type]

    @property
    def end(self) -> int:
        """First address after the entry."""
        return self.address + self.size

    def describe(self) -> str:
        """Where it lives, for messages: "input 4..5", "coil 2", "input 8 bit 0"."""
        span = f"{self.address}" if self.size == 1 else f"{self.address}..{self.end - 1}"
        bit = f" bit {self.bit}" if self.bit is not None else ""
        return f"{self.table} {span}{bit}"

    def decode(self, raw: Sequence[int] | Sequence[bool]) -> Value:
        """The value of the entry's registers (`size` words) or bit (one bool).

        Returns a float (raw * scale + offset) for numeric types, a bool for "bool".
        """
        if self.table in BIT_TABLES:
            return bool(raw[0])
        if self.data_type == "bool":
            word = int(raw[0])
            return bool(word >> self.bit & 1) if self.bit is not None else word != 0
        number = ModbusClientMixin.convert_from_registers(
            [int(word) for word in raw[: self.size]],
            _CONVERTERS[self.data_type],
            word_order=self.word_order,
        )
        return float(number) * self.scale + self.offset

    def encode(self, value: float | bool) -> list[int]:
        """The register words that hold `value` (holding or input registers only).

        A numeric value is turned into raw = (value - offset) / scale, rounded for integer
        types. A bool in a register is its bit (or 1/0 for the whole register).

        Raises:
            ValueError: the entry is a coil or discrete input, or the value is not finite or
                does not fit the data type.
        """
        if self.table in BIT_TABLES:
            raise ValueError(f"{self.describe()} is a bit, not a register")
        if self.data_type == "bool":
            if self.bit is None:
                return [1 if value else 0]
            return [(1 << self.bit) if value else 0]
        number = float(value)
        if not math.isfinite(number):
            raise ValueError(f"{number} is not finite")
        raw = (number - self.offset) / self.scale
        if self.data_type == "float32":
            try:
                return ModbusClientMixin.convert_to_registers(
                    raw, _DATATYPE.FLOAT32, word_order=self.word_order
                )
            except OverflowError:
                raise ValueError(f"{number} does not fit a float32") from None
        low, high = _INTEGER_RANGES[self.data_type]
        rounded = round(raw)
        if not low <= rounded <= high:
            raise ValueError(f"{number} is raw {rounded}, outside {self.data_type} {low}..{high}")
        return ModbusClientMixin.convert_to_registers(
            rounded, _CONVERTERS[self.data_type], word_order=self.word_order
        )

    def command_words(self) -> list[int]:
        """The words a command register is written with (its `value`, in its data type)."""
        if self.value is None or self.data_type not in INTEGER_TYPES:
            raise ValueError(f"{self.describe()} is not a command register with a value")
        return ModbusClientMixin.convert_to_registers(
            self.value, _CONVERTERS[self.data_type], word_order=self.word_order
        )

    def to_table(self) -> dict[str, Any]:
        """The entry as a plain table, as `RegisterMap.from_table` reads it (no None fields)."""
        return {k: v for k, v in dataclasses.asdict(self).items() if v is not None}


def _register_problem(fields: Mapping[str, Any]) -> Problem | None:
    """What is wrong with a register's fields on their own (None: nothing)."""
    address = fields["address"]
    if not isinstance(address, int) or isinstance(address, bool) or not 0 <= address <= 65535:
        return "address", f"must be an integer 0 ... 65535, got {address!r}"
    table = fields["table"]
    if table not in TABLES:
        return "table", f"must be one of {_choices(TABLES)}, got {table!r}"
    data_type = fields["data_type"]
    if data_type not in DATA_TYPES:
        return "data_type", f"must be one of {_choices(DATA_TYPES)}, got {data_type!r}"
    for key in ("scale", "offset"):
        number = fields[key]
        if not _is_number(number) or not math.isfinite(number):
            return key, f"must be a finite number, got {number!r}"
    if fields["scale"] == 0:
        return "scale", "must not be 0"
    if not isinstance(fields["unit"], str):
        return "unit", f"must be text, got {fields['unit']!r}"
    if fields["word_order"] not in WORD_ORDERS:
        return "word_order", f"must be one of {_choices(WORD_ORDERS)}, got {fields['word_order']!r}"
    bit = fields["bit"]
    if bit is not None and (
        not isinstance(bit, int) or isinstance(bit, bool) or not 0 <= bit <= 15
    ):
        return "bit", f"must be an integer 0 ... 15, got {bit!r}"
    value = fields["value"]
    if value is not None and (not isinstance(value, int) or isinstance(value, bool)):
        return "value", f"must be an integer, got {value!r}"
    if table in BIT_TABLES and data_type != "bool":
        return "data_type", f"a {table} holds one bit: must be bool, got {data_type!r}"
    if bit is not None and (table in BIT_TABLES or data_type != "bool"):
        return "bit", "only for a bool in a holding or input register"
    if data_type == "bool" and (fields["scale"] != 1 or fields["offset"] != 0):
        key = "scale" if fields["scale"] != 1 else "offset"
        return key, "does not apply to a bool"
    if address + _WORDS[data_type] - 1 > 65535 and table in REGISTER_TABLES:
        return "address", f"a {data_type} at {address} runs past register 65535"
    if value is not None:
        if data_type not in INTEGER_TYPES:
            return "value", f"only for a command register of an integer type, not {data_type}"
        low, high = _INTEGER_RANGES[data_type]
        if not low <= value <= high:
            return "value", f"must fit {data_type} ({low} ... {high}), got {value}"
    return None


def _role_problem(name: str, register: Register) -> Problem | None:
    """What is wrong with `register` as the entry `name` (None: nothing)."""
    is_command = name in COMMANDS
    if register.value is not None and not is_command:
        return "value", "only for a command (start, stop, return_to_start)"
    if name in REQUIRED_READS and register.data_type == "bool":
        return "data_type", f"must be one of {_choices(NUMERIC_TYPES)} (a number), got 'bool'"
    if name == "running" and register.data_type != "bool":
        return "data_type", f"must be 'bool', got {register.data_type!r}"
    if name == "encoder_counts" and register.data_type not in INTEGER_TYPES:
        return (
            "data_type",
            f"must be one of {_choices(INTEGER_TYPES)}, got {register.data_type!r}",
        )
    if name in SETPOINTS:
        if register.table != "holding":
            return "table", f"a set point is written: must be 'holding', got {register.table!r}"
        if register.data_type == "bool":
            return "data_type", f"must be one of {_choices(NUMERIC_TYPES)}, got 'bool'"
    if is_command:
        if register.table not in ("coil", "holding"):
            return "table", f"a command is written: must be coil or holding, got {register.table!r}"
        if register.scale != 1 or register.offset != 0:
            return ("scale" if register.scale != 1 else "offset"), "does not apply to a command"
        if register.table == "holding":
            if register.data_type not in INTEGER_TYPES:
                return (
                    "data_type",
                    f"a command register must be one of {_choices(INTEGER_TYPES)}, "
                    f"got {register.data_type!r}",
                )
            if register.value is None:
                return "value", "missing: the value a command register is written with"
    return None


def _overlap_allowed(first: tuple[str, Register], second: tuple[str, Register]) -> bool:
    (name_a, a), (name_b, b) = first, second
    if (
        a.data_type == b.data_type == "bool"
        and a.table in REGISTER_TABLES
        and a.address == b.address
        and a.bit is not None
        and b.bit is not None
        and a.bit != b.bit
        and name_a in READS
        and name_b in READS
    ):
        return True
    return (
        name_a in COMMANDS
        and name_b in COMMANDS
        and a.value is not None
        and b.value is not None
        and a.value != b.value
        and (a.address, a.table, a.data_type, a.word_order)
        == (b.address, b.table, b.data_type, b.word_order)
    )


def _map_problem(entries: Mapping[str, Register], max_gap: object) -> tuple[str, str, str] | None:
    """(entry, key, reason) of the first problem of a whole map (entry "" = the map itself)."""
    if not isinstance(max_gap, int) or isinstance(max_gap, bool) or not 0 <= max_gap <= 120:
        return "", "max_gap", f"must be an integer 0 ... 120 (registers), got {max_gap!r}"
    for name in REQUIRED_READS:
        if entries.get(name) is None:
            return name, "", "missing (crosshead_mm, speed_mm_min and force_n are required)"
    present = [(name, entries[name]) for name in ENTRIES if entries.get(name) is not None]
    for name, register in present:
        problem = _role_problem(name, register)
        if problem is not None:
            return name, *problem
    for index, (name, register) in enumerate(present):
        for other_name, other in present[:index]:
            if other.table != register.table:
                continue
            if register.address >= other.end or other.address >= register.end:
                continue
            if _overlap_allowed((other_name, other), (name, register)):
                continue
            return (
                name,
                "address",
                f"{register.describe()} overlaps {other_name} ({other.describe()})",
            )
    return None


@dataclass(frozen=True)
class ReadSpan:
    """One read request of a plan: `count` registers (or bits) of `table` from `address`.

    Attributes:
        entries: the (name, register) pairs it decodes, by address.
    """

    table: str
    address: int
    count: int
    entries: tuple[tuple[str, Register], ...]

    def describe(self) -> str:
        """The entries and the span, for messages: "force_n (input 4..5)"."""
        names = ", ".join(name for name, _ in self.entries)
        last = self.address + self.count - 1
        where = f"{self.address}" if self.count == 1 else f"{self.address}..{last}"
        return f"{names} ({self.table} {where})"

    def decode(self, raw: Sequence[int] | Sequence[bool]) -> dict[str, Value]:
        """Each entry's value from the span's registers or bits (at least `count` of them)."""
        if len(raw) < self.count:
            raise ValueError(f"{self.describe()}: {len(raw)} values for {self.count}")
        values: dict[str, Value] = {}
        for name, register in self.entries:
            start = register.address - self.address
            values[name] = register.decode(raw[start : start + register.size])
        return values


@dataclass(frozen=True)
class RegisterMap:
    """A controller's register map: one `Register` per entry the appliance uses.

    Args:
        crosshead_mm, speed_mm_min, force_n: the required reads (numeric).
        running: bool read (None: the client takes "speed is not 0").
        encoder_counts: integer read.
        speed_setpoint_mm_min: holding register(s) written before start / return_to_start.
        start, stop, return_to_start: commands (coil, or holding register with `value`).
        max_gap: unused registers a read span may bridge (see the module docstring).

    Raises:
        HardwareConfigError: an entry does not fit its role, entries overlap, or `max_gap` is
            out of range (one line naming the entry and the key).
    """

    crosshead_mm: Register
    speed_mm_min: Register
    force_n: Register
    running: Register | None = None
    encoder_counts: Register | None = None
    speed_setpoint_mm_min: Register | None = None
    start: Register | None = None
    stop: Register | None = None
    return_to_start: Register | None = None
    max_gap: int = DEFAULT_MAX_GAP

    def __post_init__(self) -> None:
        problem = _map_problem(self.entries(), self.max_gap)
        if problem is not None:
            name, key, reason = problem
            place = f"register map [{name}]" if name else "register map"
            raise HardwareConfigError(_message(place, key, reason))

    def entries(self) -> dict[str, Register]:
        """The entries present, reads first, by name."""
        found = {name: getattr(self, name) for name in ENTRIES}
        return {name: register for name, register in found.items() if register is not None}

    def reads(self) -> dict[str, Register]:
        """The read entries present, by name."""
        return {name: r for name, r in self.entries().items() if name in READS}

    def read_plan(self) -> tuple[ReadSpan, ...]:
        """The requests that read every read entry: coalesced spans, tables in TABLES order."""
        spans: list[ReadSpan] = []
        reads = self.reads()
        for table in TABLES:
            in_table = sorted(
                ((n, r) for n, r in reads.items() if r.table == table),
                key=lambda item: (item[1].address, item[1].end),
            )
            if table in BIT_TABLES:
                gap, limit = 16 * self.max_gap, MAX_READ_BITS
            else:
                gap, limit = self.max_gap, MAX_READ_REGISTERS
            current: list[tuple[str, Register]] = []
            start = end = 0
            for name, register in in_table:
                joined_end = max(end, register.end)
                if current and register.address - end <= gap and joined_end - start <= limit:
                    current.append((name, register))
                    end = joined_end
                    continue
                if current:
                    spans.append(ReadSpan(table, start, end - start, tuple(current)))
                current, start, end = [(name, register)], register.address, register.end
            if current:
                spans.append(ReadSpan(table, start, end - start, tuple(current)))
        return tuple(spans)

    def register_image(self, values: Mapping[str, Value]) -> dict[str, dict[int, int | bool]]:
        """What a controller serving this map holds for `values` (one per read entry).

        Returns {table: {address: word (registers) or bool (bits)}}; bools that are bits of
        one register are combined into its word. For simulated controllers and tests.

        Raises:
            KeyError: a read entry of the map has no value.
            ValueError: a value does not fit its register.
        """
        image: dict[str, dict[int, int | bool]] = {table: {} for table in TABLES}
        for name, register in self.reads().items():
            value = values[name]
            cells = image[register.table]
            if register.table in BIT_TABLES:
                cells[register.address] = bool(value)
                continue
            for index, word in enumerate(register.encode(value)):
                address = register.address + index
                cells[address] = int(cells.get(address, 0)) | word
        return image

    @classmethod
    def from_table(cls, table: Mapping[str, Any], where: str) -> RegisterMap:
        """A map from the plain tables TOML gives (see the module docstring for the keys).

        Args:
            table: {"preset": "generic" | "none", "max_gap": int, ENTRY: {FIELD: value} |
                False, ...}.
            where: how the user names `table` in messages, e.g. "run.toml: [machine.registers]";
                an entry is then named "run.toml: [machine.registers.force_n]".

        Raises:
            HardwareConfigError: one line naming `where`, the entry and the key.
        """
        if not isinstance(table, Mapping):
            raise HardwareConfigError(f"{where}: must be a table, got {table!r}")
        preset_name = table.get("preset", "none")
        if preset_name not in PRESET_NAMES:
            raise HardwareConfigError(
                f"{where} preset: must be one of {_choices(PRESET_NAMES)}, got {preset_name!r}"
            )
        preset = PRESETS.get(preset_name)
        base = preset.entries() if preset is not None else {}
        max_gap = table.get("max_gap", preset.max_gap if preset is not None else DEFAULT_MAX_GAP)
        entries: dict[str, Register] = dict(base)
        for name, given in table.items():
            if name in ("preset", "max_gap"):
                continue
            if name not in ENTRIES:
                raise HardwareConfigError(
                    f"{where} {name}: unknown entry (known: preset, max_gap, {_choices(ENTRIES)})"
                )
            place = _entry_where(where, name)
            if given is False:
                if name in REQUIRED_READS:
                    raise HardwareConfigError(f"{place}: required, cannot be dropped")
                entries.pop(name, None)
                continue
            if not isinstance(given, Mapping):
                raise HardwareConfigError(
                    f"{place}: must be a table of {_choices(FIELDS)} (or false), got {given!r}"
                )
            entries[name] = _entry_from_table(given, base.get(name), place)
        problem = _map_problem(entries, max_gap)
        if problem is not None:
            name, key, reason = problem
            place = _entry_where(where, name) if name else where
            raise HardwareConfigError(_message(place, key, reason))
        return cls(**entries, max_gap=max_gap)

    def to_table(self) -> dict[str, Any]:
        """The map as plain tables, preset "none" (the inverse of `from_table`)."""
        table: dict[str, Any] = {"preset": "none", "max_gap": self.max_gap}
        table.update({name: register.to_table() for name, register in self.entries().items()})
        return table


def _message(place: str, key: str, reason: str) -> str:
    return f"{place} {key}: {reason}" if key else f"{place}: {reason}"


def _entry_where(where: str, name: str) -> str:
    if where.endswith("]"):
        return f"{where[:-1]}.{name}]"
    return f"{where} [{name}]"


def _entry_from_table(given: Mapping[str, Any], inherited: Register | None, place: str) -> Register:
    unknown = [key for key in given if key not in FIELDS]
    if unknown:
        raise HardwareConfigError(f"{place} {unknown[0]}: unknown key (known: {_choices(FIELDS)})")
    if inherited is None:
        for key in ("address", "table", "data_type"):
            if key not in given:
                raise HardwareConfigError(
                    f"{place} {key}: missing (an entry not in the preset needs address, "
                    "table and data_type)"
                )
        fields: dict[str, Any] = {f.name: f.default for f in dataclasses.fields(Register)}
    else:
        fields = dataclasses.asdict(inherited)
    fields.update(given)
    is_register_bool = fields["data_type"] == "bool" and fields["table"] in REGISTER_TABLES
    if "bit" not in given and not is_register_bool:
        fields["bit"] = None
    is_command_register = fields["table"] == "holding" and fields["data_type"] in INTEGER_TYPES
    if "value" not in given and not is_command_register:
        fields["value"] = None
    problem = _register_problem(fields)
    if problem is not None:
        key, reason = problem
        raise HardwareConfigError(f"{place} {key}: {reason}")
    return Register(**fields)


GENERIC_CONTROLLER = RegisterMap(
    crosshead_mm=Register(0, "input", "float32", unit="mm"),
    speed_mm_min=Register(2, "input", "float32", unit="mm/min"),
    force_n=Register(4, "input", "float32", unit="N"),
    encoder_counts=Register(6, "input", "int32", unit="counts"),
    running=Register(8, "input", "bool", bit=0),
    speed_setpoint_mm_min=Register(0, "holding", "float32", unit="mm/min"),
    start=Register(0, "coil", "bool"),
    stop=Register(1, "coil", "bool"),
    return_to_start=Register(2, "coil", "bool"),
)
"""The preset "generic": the layout in the module docstring."""

PRESETS: dict[str, RegisterMap] = {"generic": GENERIC_CONTROLLER}
"""Preset name -> map ("none" is no preset)."""
