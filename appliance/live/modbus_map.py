"""The Modbus register map of the strain server, defined once as data.

`REGISTER_MAP` is the whole map: one `Register` per value (name, zero-based address, register
count, data type, access, unit, description, accepted values of a writable one). The server
(`appliance.live.modbus_server`) builds its register image and its write checks from it, the
integrator's table in appliance/live/README.md is rendered from it (`render_markdown_table`),
and the tests compare the two.

Conventions the map follows:

* Every register is a holding register (function 3) and, at the same address, an input
  register (function 4); both read the same image. Addresses are zero-based (PDU addresses;
  a tool that counts from 1 adds 1).
* float32, uint32 and uint64 values take 2, 2 and 4 registers in the configured word order:
  `big` puts the most significant word first (ABCD for a float), `little` the least
  significant first (CDAB). Bytes within a register are always big-endian, as Modbus says.
* uint16 values are the register itself; counters wrap to 0 after their largest value.
* The last test's results (57 ... 89, `RESULT_BLOCK`) follow the measurement block: a
  `results_valid` flag, a counter of results published and the standard, then the results as
  float32 (NaN: not determined). They are written in the same update as `exit_status` when a
  test ends, and cleared when the next one begins, so they always belong to the test that
  `exit_status` describes.
* The reserved block before the command block (90 ... 99) reads 0 and refuses writes, so a
  controller can read addresses 0 ... 104 in one request (105 <= 125 registers).
* A read may start or end in the middle of a multi-register value (it is a plain register
  read); a write must cover every writable value it touches completely.

* Functions: 3 and 4 read, 6 and 16 write, 22 (mask write) and 23 (read/write multiple)
  combine the two (`SERVED_FUNCTION_CODES`); the map has no coils or discrete inputs.

Exception codes a client gets:

* 1 (illegal function): a function not in `SERVED_FUNCTION_CODES` (coils, diagnostics,
  file records, FIFO, device identification, ...), a write from a TCP client not in
  `[modbus] allow_write_from` (when the list is not empty), or any write over RTU when the
  list is not empty (a serial line has no client address to check).
* 2 (illegal data address): an address outside the map, a write to a read-only register
  (reserved ones included), or a write that covers only part of a float (writing 103 alone).
* 3 (illegal data value): a command code not listed, a gauge length set point that is NaN,
  infinite or outside 1 ... 10000 mm, or a request of a served function that does not decode
  (too short, or a quantity the function does not allow: a read of 0 or more than 125
  registers).
* 4 (server device failure): the appliance failed while handling a command.

What this module does not do: it holds no state and talks to no network; it does not know
how the service reacts to a command (that is the server's `on_command` callback).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

from pymodbus.client.mixin import ModbusClientMixin

from appliance.run.state import ExitStatus, RunState

WordOrder = Literal["big", "little"]
WIDTH_STATIONS_SERVED = 8
"""Stations whose widths have registers of their own."""
Value = int | float

_DATATYPE = ModbusClientMixin.DATATYPE


class RegisterType(enum.Enum):
    """Data type of a register entry: (label, pymodbus converter type, registers per value).

    RESERVED has no value: its registers read 0 and its count is free.
    """

    UINT16 = ("uint16", _DATATYPE.UINT16, 1)
    UINT32 = ("uint32", _DATATYPE.UINT32, 2)
    UINT64 = ("uint64", _DATATYPE.UINT64, 4)
    FLOAT32 = ("float32", _DATATYPE.FLOAT32, 2)
    RESERVED = ("reserved", None, None)

    @property
    def label(self) -> str:
        """Name of the type in the table."""
        return self.value[0]

    @property
    def converter(self) -> ModbusClientMixin.DATATYPE | None:
        """pymodbus' converter type (None for RESERVED)."""
        return self.value[1]

    @property
    def registers(self) -> int | None:
        """Registers one value takes (None for RESERVED)."""
        return self.value[2]


class Access(enum.Enum):
    """What a client may do with a register."""

    READ = "r"
    READ_WRITE = "rw"


@dataclass(frozen=True)
class Register:
    """One entry of the map.

    Attributes:
        name: identifier of the value (snake_case, unit in the name where it has one).
        address: zero-based address of its first register.
        count: registers it takes.
        data_type: how its registers encode the value.
        access: read-only or writable.
        unit: unit of the value ("1" for a ratio, "" for a code, bits or counter).
        description: what it is, one sentence or a list of codes.
        minimum, maximum: accepted range of a writable float (None = not a range).
        choices: accepted values of a writable code (empty = not a code).
    """

    name: str
    address: int
    count: int
    data_type: RegisterType
    access: Access
    unit: str
    description: str
    minimum: float | None = None
    maximum: float | None = None
    choices: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        size = self.data_type.registers
        if size is not None and self.count != size:
            raise ValueError(f"{self.name}: {self.data_type.label} takes {size} registers")
        if not (0 <= self.address and self.address + self.count <= 0x10000 and self.count > 0):
            raise ValueError(f"{self.name}: address range outside 0 ... 65535")
        if self.access is Access.READ_WRITE and not (
            self.choices or (self.minimum is not None and self.maximum is not None)
        ):
            raise ValueError(f"{self.name}: a writable register needs choices or a range")

    @property
    def end(self) -> int:
        """One past its last register."""
        return self.address + self.count

    @property
    def writable(self) -> bool:
        """A client may write it."""
        return self.access is Access.READ_WRITE

    def accepts(self, value: Value) -> bool:
        """Whether a decoded value written by a client is in the accepted set or range."""
        if self.choices:
            return value in self.choices
        if self.minimum is None or self.maximum is None:
            return False
        return math.isfinite(value) and self.minimum <= value <= self.maximum


class StatusBit(enum.IntFlag):
    """Bits of the `status` register."""

    DATA_VALID = 1 << 0
    TRACKING = 1 << 1
    POINT_LOST = 1 << 2
    REFERENCE_UPDATED = 1 << 3
    CALIBRATING = 1 << 4
    FAULT = 1 << 5
    CAMERA_LOST = 1 << 6
    NO_CONTROLLER_DATA = 1 << 7
    FRAMES_DROPPED = 1 << 8


STATUS_BIT_MEANINGS: tuple[tuple[StatusBit, str], ...] = (
    (
        StatusBit.DATA_VALID,
        "data valid (the latest sample is valid, the camera is delivering and the run is "
        "running or stopping; any other run state, or a camera outage, clears it, so a stale "
        "strain is never flagged valid)",
    ),
    (StatusBit.TRACKING, "tracking (run state running)"),
    (
        StatusBit.POINT_LOST,
        "point lost (a point was lost in the latest sample; bits 2, 3 and 7 describe the "
        "latest sample while the run is running or stopping, and are clear otherwise)",
    ),
    (StatusBit.REFERENCE_UPDATED, "reference updated (in the latest sample)"),
    (StatusBit.CALIBRATING, "calibrating (run state armed: taking the reference)"),
    (StatusBit.FAULT, "fault (run state fault)"),
    (
        StatusBit.CAMERA_LOST,
        "camera lost (the camera went away during the test and is being reconnected)",
    ),
    (
        StatusBit.NO_CONTROLLER_DATA,
        "no controller data (the latest sample has no reading of the machine's controller: "
        "force and crosshead are NaN)",
    ),
    (
        StatusBit.FRAMES_DROPPED,
        "frames dropped (camera frames were dropped between the previous sample and the latest: "
        "a gap in the strain series; `frames_dropped` counts them)",
    ),
)

EXIT_STATUS_CODES: Mapping[ExitStatus, int] = {
    ExitStatus.COMPLETED: 1,
    ExitStatus.BREAK: 2,
    ExitStatus.STOPPED: 3,
    ExitStatus.ABORTED: 4,
    ExitStatus.FAULT: 5,
}
"""How the last test ended -> code of the `exit_status` register (0: none yet, or a test is
running)."""

RUN_STATE_CODES: Mapping[RunState, int] = {
    RunState.IDLE: 0,
    RunState.ARMED: 1,
    RunState.RUNNING: 2,
    RunState.STOPPING: 3,
    RunState.ABORTED: 4,
    RunState.FAULT: 5,
}
"""Run state -> code of the `run_state` register."""

COMMANDS: Mapping[int, str] = {1: "start", 2: "stop", 3: "zero"}
"""Code written to `command` -> the command handed to the server's `on_command`."""

GAUGE_LENGTH_COMMAND = "gauge_length"
"""The command handed to `on_command` (with the value) when the set point is written."""

SERVED_FUNCTION_CODES: Mapping[int, str] = {
    3: "read holding registers",
    4: "read input registers",
    6: "write single register",
    16: "write multiple registers",
    22: "mask write register",
    23: "read/write multiple registers",
}
"""The Modbus functions the server serves; every other function (coils, discrete inputs,
diagnostics, file records, FIFO, device identification, ...) gets exception 1."""


class CommandResult(enum.IntEnum):
    """Codes of the `command_result` register."""

    NONE = 0
    ACCEPTED = 1
    REFUSED = 2


COMMAND_RESULT_MEANINGS: Mapping[CommandResult, str] = {
    CommandResult.NONE: "none yet",
    CommandResult.ACCEPTED: "accepted",
    CommandResult.REFUSED: "refused in the current run state",
}


def _codes(pairs: Sequence[tuple[int, str]]) -> str:
    return ", ".join(f"{code} {text}" for code, text in pairs)


_STATUS_TEXT = "Bits: " + "; ".join(
    f"{bit.bit_length() - 1} {text}" for bit, text in STATUS_BIT_MEANINGS
)
_RUN_STATE_TEXT = "Run state: " + _codes([(c, s.value) for s, c in RUN_STATE_CODES.items()])
_EXIT_STATUS_TEXT = (
    "How the last test ended: "
    + _codes(
        [(0, "none yet, or a test is under way")]
        + [(c, s.value) for s, c in EXIT_STATUS_CODES.items()]
    )
    + " (stopped: by a stop command or the service's stop; the reason is in the recording "
    "and the summary)"
)
_COMMAND_TEXT = (
    "Write "
    + _codes(list(COMMANDS.items()))
    + " (zero: strain becomes 0 at the next frame); other values: exception 3. "
    "Reads the last command code written (0 none yet)"
)
_RESULT_TEXT = "Result of the last command or set point write: " + _codes(
    [(int(r), t) for r, t in COMMAND_RESULT_MEANINGS.items()]
)


class ResultsStandard(enum.IntEnum):
    """Codes of the `results_standard` register: the standard the test's results follow."""

    NONE = 0
    ISO_6892_1 = 1
    ISO_37 = 2


RESULTS_STANDARD_CODES: Mapping[str, ResultsStandard] = {
    "ISO 6892-1": ResultsStandard.ISO_6892_1,
    "ISO 37": ResultsStandard.ISO_37,
}
"""The summary's `results.standard` -> code of the `results_standard` register (anything
else: NONE)."""

_RESULTS_VALID_TEXT = (
    "1: the result registers (59 ... 89) hold the results of the test that ended last, the "
    "one `exit_status` describes (written in the same update as `exit_status`); 0: they hold "
    "none: no test has ended yet, a test is under way (they are cleared when it begins), or "
    "the last test ended without results (it did not start, or failed)"
)
_RESULTS_STANDARD_TEXT = "Standard of the results: " + _codes(
    [(0, "none (no results, or no `[specimen] material`)"), (1, "ISO 6892-1 (metal)")]
    + [(2, "ISO 37 (rubber)")]
)
_RESULT_FLOATS: tuple[tuple[str, str, str], ...] = (
    (
        "result_modulus_mpa",
        "MPa",
        "Modulus of elasticity E (ISO 6892-1): least-squares line of stress on strain through "
        "the loading samples between 10 % and 50 % of the yield strength",
    ),
    (
        "result_rp02_mpa",
        "MPa",
        "Proof strength Rp0.2 (ISO 6892-1): stress at 0.2 % plastic extension from the modulus "
        "line, interpolated between samples",
    ),
    (
        "result_reh_mpa",
        "MPa",
        "Upper yield strength ReH (ISO 6892-1), only with discontinuous yielding",
    ),
    (
        "result_rel_mpa",
        "MPa",
        "Lower yield strength ReL (ISO 6892-1), only with discontinuous yielding",
    ),
    (
        "result_rm_mpa",
        "MPa",
        "Tensile strength Rm (ISO 6892-1): the largest stress, once the force has fallen 0.5 % "
        "below it or the specimen broke",
    ),
    (
        "result_ag",
        "1",
        "Plastic extension at maximum force Ag (ISO 6892-1), 1 = 100 %",
    ),
    (
        "result_a",
        "1",
        "Elongation after fracture A from the extensometer (ISO 6892-1), 1 = 100 %: the "
        "plastic extension of the last valid sample before the fracture; only after a break",
    ),
    (
        "result_poisson_ratio",
        "1",
        "Poisson's ratio nu of a metal: minus the slope of transverse on axial strain over the "
        "samples E was fitted over (the elastic range)",
    ),
    (
        "result_r_8_12",
        "1",
        "Plastic strain ratio r_8-12 (ISO 10113, linear regression): plastic width strain on "
        "plastic length strain over 8 % to 12 % engineering strain, thickness strain by "
        "constant volume",
    ),
    (
        "result_n",
        "1",
        "Strain hardening exponent n (ISO 10275): slope of ln true stress on ln true plastic "
        "strain over 10 % to 20 % engineering strain, or from 10 % to the strain at maximum "
        "force when it comes first",
    ),
    (
        "result_tensile_strength_mpa",
        "MPa",
        "Tensile strength TS (ISO 37): the largest stress; only after a break",
    ),
    (
        "result_elongation_at_break",
        "1",
        "Elongation at break Eb (ISO 37), 1 = 100 %: the strain of the last valid sample "
        "before the break",
    ),
    *(
        (
            f"result_s{percent}_mpa",
            "MPa",
            f"Stress at {percent} % elongation S{percent} (ISO 37), interpolated between samples",
        )
        for percent in (100, 200, 300)
    ),
)
"""The test's results served as float32: (register name, unit, what it is and how taken)."""

REGISTER_MAP: tuple[Register, ...] = (
    Register(
        "axial_strain",
        0,
        2,
        RegisterType.FLOAT32,
        Access.READ,
        "1",
        "Axial engineering strain (L - L0) / L0 of the latest sample (1 = 100 %)",
    ),
    Register(
        "transverse_strain",
        2,
        2,
        RegisterType.FLOAT32,
        Access.READ,
        "1",
        "Transverse engineering strain (NaN without a transverse gauge)",
    ),
    Register(
        "true_strain",
        4,
        2,
        RegisterType.FLOAT32,
        Access.READ,
        "1",
        "True axial strain ln(1 + e)",
    ),
    Register(
        "elongation_mm",
        6,
        2,
        RegisterType.FLOAT32,
        Access.READ,
        "mm",
        "Elongation L - L0",
    ),
    Register(
        "gauge_length_mm",
        8,
        2,
        RegisterType.FLOAT32,
        Access.READ,
        "mm",
        "Current gauge length L",
    ),
    Register("status", 10, 1, RegisterType.UINT16, Access.READ, "", _STATUS_TEXT),
    Register(
        "heartbeat",
        11,
        1,
        RegisterType.UINT16,
        Access.READ,
        "",
        "Counts every register update and every idle tick of the service (wraps): it keeps "
        "moving while the appliance is alive",
    ),
    Register(
        "frame_counter",
        12,
        2,
        RegisterType.UINT32,
        Access.READ,
        "",
        "Camera frame id of the latest sample (wraps)",
    ),
    Register(
        "timestamp_unix_ns",
        14,
        4,
        RegisterType.UINT64,
        Access.READ,
        "ns",
        "Start of exposure of the latest sample, ns since the UNIX epoch (0 = unknown)",
    ),
    Register(
        "poisson_ratio",
        18,
        2,
        RegisterType.FLOAT32,
        Access.READ,
        "1",
        "Poisson's ratio -e_transverse / e_axial (NaN below 1e-4 axial strain or without a "
        "transverse gauge)",
    ),
    Register(
        "crosshead_mm",
        20,
        2,
        RegisterType.FLOAT32,
        Access.READ,
        "mm",
        "Crosshead position read with the frame (NaN when not read)",
    ),
    Register(
        "force_n",
        22,
        2,
        RegisterType.FLOAT32,
        Access.READ,
        "N",
        "Force read with the frame (NaN when not read)",
    ),
    Register(
        "time_since_reference_s",
        24,
        2,
        RegisterType.FLOAT32,
        Access.READ,
        "s",
        "Device time of the latest sample since the reference frame",
    ),
    Register(
        "points_lost",
        26,
        1,
        RegisterType.UINT16,
        Access.READ,
        "",
        "Points not measured in the latest sample",
    ),
    Register("run_state", 27, 1, RegisterType.UINT16, Access.READ, "", _RUN_STATE_TEXT),
    Register(
        "latency_ms",
        28,
        2,
        RegisterType.FLOAT32,
        Access.READ,
        "ms",
        "Processing latency of the latest sample: frame delivered to strain computed",
    ),
    Register("exit_status", 30, 1, RegisterType.UINT16, Access.READ, "", _EXIT_STATUS_TEXT),
    Register(
        "frames_dropped",
        31,
        2,
        RegisterType.UINT32,
        Access.READ,
        "",
        "Camera frames dropped in the current (or last) test: gaps in the camera's frame "
        "counter and frames the appliance had no time for; each is a gap in the strain series",
    ),
    Register(
        "width_mm",
        33,
        2,
        RegisterType.FLOAT32,
        Access.READ,
        "mm",
        "Specimen width at its edges, the mean of the stations seen (`[transverse] stations`; "
        "NaN when no width is measured or no station is seen)",
    ),
    Register(
        "width_transverse_strain",
        35,
        2,
        RegisterType.FLOAT32,
        Access.READ,
        "1",
        "Transverse engineering strain from the width, the mean of each seen station's "
        "w / w0 - 1 (NaN as `width_mm`)",
    ),
    Register(
        "width_stations_seen",
        37,
        1,
        RegisterType.UINT16,
        Access.READ,
        "",
        "Stations whose two edges were located in the latest sample (0 without a width)",
    ),
    Register(
        "width_stations",
        38,
        1,
        RegisterType.UINT16,
        Access.READ,
        "",
        "Stations the width is measured at (`[transverse] stations`; 0 = none)",
    ),
    Register(
        "width_poisson_ratio",
        39,
        2,
        RegisterType.FLOAT32,
        Access.READ,
        "1",
        "Contraction ratio from the width, -width_transverse_strain / e_axial: Poisson's "
        "ratio in the elastic range only (NaN below 1e-4 axial strain or without a width)",
    ),
    *(
        Register(
            f"width_{k}_mm",
            39 + 2 * k,
            2,
            RegisterType.FLOAT32,
            Access.READ,
            "mm",
            f"Width at station {k} from the first mark (NaN where it is flagged or not measured)",
        )
        for k in range(1, WIDTH_STATIONS_SERVED + 1)
    ),
    Register("results_valid", 57, 1, RegisterType.UINT16, Access.READ, "", _RESULTS_VALID_TEXT),
    Register(
        "results_counter",
        58,
        1,
        RegisterType.UINT16,
        Access.READ,
        "",
        "Counts the results published, one for every test that ended with its results "
        "(wraps; 0 none yet): a new value says the result registers hold a new test's results",
    ),
    Register(
        "results_standard", 59, 1, RegisterType.UINT16, Access.READ, "", _RESULTS_STANDARD_TEXT
    ),
    *(
        Register(
            name,
            60 + 2 * k,
            2,
            RegisterType.FLOAT32,
            Access.READ,
            unit,
            f"{text}; NaN: not determined in this test (the summary's `results` says why)",
        )
        for k, (name, unit, text) in enumerate(_RESULT_FLOATS)
    ),
    Register(
        "reserved",
        90,
        10,
        RegisterType.RESERVED,
        Access.READ,
        "",
        "Reserved: reads 0, writes get exception 2",
    ),
    Register(
        "command",
        100,
        1,
        RegisterType.UINT16,
        Access.READ_WRITE,
        "",
        _COMMAND_TEXT,
        choices=tuple(COMMANDS),
    ),
    Register(
        "command_counter",
        101,
        1,
        RegisterType.UINT16,
        Access.READ,
        "",
        "Counts every command and set point write the appliance took (accepted or refused; "
        "not those answered with an exception); wraps",
    ),
    Register("command_result", 102, 1, RegisterType.UINT16, Access.READ, "", _RESULT_TEXT),
    Register(
        "gauge_length_setpoint_mm",
        103,
        2,
        RegisterType.FLOAT32,
        Access.READ_WRITE,
        "mm",
        "Gauge length L0 for the next test, applied at the next start (write both registers "
        "in one request; NaN, infinite or out of range: exception 3). Reads the set point in "
        "force (NaN = the specimen's default)",
        minimum=1.0,
        maximum=10000.0,
    ),
)
"""The whole map, in address order."""

BY_NAME: Mapping[str, Register] = {register.name: register for register in REGISTER_MAP}
"""Entries by name."""

MAP_SIZE = REGISTER_MAP[-1].end
"""Registers from address 0 to the end of the map."""

WIDTH_BLOCK: tuple[Register, ...] = tuple(r for r in REGISTER_MAP if r.name.startswith("width_"))
"""The specimen's width at its edges (33 ... 56), rewritten with every sample."""
MEASUREMENT_BLOCK: tuple[Register, ...] = tuple(
    r for r in REGISTER_MAP if r.end <= BY_NAME["exit_status"].address
)
"""The fixed block at 0 ... 29 that every sample rewrites (everything before `exit_status`)."""


RESULT_BLOCK: tuple[Register, ...] = tuple(r for r in REGISTER_MAP if r.name.startswith("result"))
"""The last test's results (57 ... 89): written when a test ends, in the same update as
`exit_status`, and cleared (NaN, `results_valid` 0) when the next test begins."""
RESULT_VALUES: tuple[Register, ...] = tuple(
    r for r in RESULT_BLOCK if r.name not in ("results_valid", "results_counter")
)
"""The part of `RESULT_BLOCK` that holds one test's results (59 ... 89): the standard and the
float32 values."""


def encode(register: Register, value: Value, word_order: WordOrder = "big") -> list[int]:
    """Registers of one value, with pymodbus' converters.

    Unsigned integers wrap modulo their size (counters); floats go to float32 (NaN kept).
    RESERVED entries encode to zeros whatever the value.
    """
    return encode_block((register,), {register.name: value}, word_order)


def encode_block(
    registers: Sequence[Register], values: Mapping[str, Value], word_order: WordOrder = "big"
) -> list[int]:
    """Registers of consecutive entries (no gaps), one pymodbus call per run of one type.

    Args:
        registers: contiguous entries in address order.
        values: value of every entry by name (RESERVED entries need none).
        word_order: "big" (most significant word first) or "little".

    Raises:
        ValueError: the entries are not contiguous.
    """
    words: list[int] = []
    run: list[Value] = []
    run_type: RegisterType | None = None
    expected = registers[0].address if registers else 0
    for register in registers:
        if register.address != expected:
            raise ValueError(f"{register.name}: not contiguous with the entry before it")
        expected = register.end
        kind = register.data_type
        if kind is not run_type and run:
            words += _convert(run, run_type, word_order)
            run = []
        run_type = kind
        if kind is RegisterType.RESERVED:
            words += [0] * register.count
            run_type = None
            continue
        value = values[register.name]
        if kind is RegisterType.FLOAT32:
            run.append(float(value))
        else:
            run.append(int(value) % (1 << (16 * register.count)))
    if run:
        words += _convert(run, run_type, word_order)
    return words


def _convert(values: list[Value], kind: RegisterType | None, word_order: WordOrder) -> list[int]:
    if kind is None or kind.converter is None:
        raise ValueError("reserved registers have no value to convert")
    return ModbusClientMixin.convert_to_registers(values, kind.converter, word_order=word_order)


def decode(register: Register, words: Sequence[int], word_order: WordOrder = "big") -> Value:
    """The value of one entry from its registers, with pymodbus' converters.

    Raises:
        ValueError: wrong number of registers, or a RESERVED entry (it has no value).
    """
    if len(words) != register.count:
        raise ValueError(f"{register.name}: needs {register.count} registers, got {len(words)}")
    converter = register.data_type.converter
    if converter is None:
        raise ValueError(f"{register.name}: reserved registers have no value")
    value = ModbusClientMixin.convert_from_registers(list(words), converter, word_order=word_order)
    if not isinstance(value, int | float):
        raise ValueError(f"{register.name}: registers decode to {value!r}, not one number")
    return value


def register_at(address: int) -> Register | None:
    """The entry holding an address, or None outside the map."""
    for register in REGISTER_MAP:
        if register.address <= address < register.end:
            return register
    return None


def render_markdown_table() -> str:
    """The map as a Markdown table (what the "Modbus register map" section of
    appliance/live/README.md holds)."""
    lines = [
        "| address | name | type | access | unit | description |",
        "|---|---|---|---|---|---|",
    ]
    for register in REGISTER_MAP:
        span = (
            str(register.address)
            if register.count == 1
            else f"{register.address}-{register.end - 1}"
        )
        description = register.description
        if register.minimum is not None and register.maximum is not None:
            description += f". Accepted: {register.minimum:g} ... {register.maximum:g}"
        lines.append(
            f"| {span} | `{register.name}` | {register.data_type.label} | "
            f"{register.access.value} | {register.unit or '-'} | {description} |"
        )
    return "\n".join(lines) + "\n"
