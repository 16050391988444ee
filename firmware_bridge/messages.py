"""The one message table of the trigger microcontroller, shared by host and firmware.

This module is the single source: the firmware's C header (`firmware/messages.h`) is
generated from it (`python -m firmware_bridge.gen_header`), and a test checks that the header
in the tree is what this table generates. The handshake returns the table's hash
(`TABLE_HASH`), so a host refuses to run against firmware built from another table.

Wire format of a packet (both directions)::

    0xA5 | LEN | SEQ | ID | PAYLOAD (LEN - 2 bytes) | CRC16 (little-endian)

`LEN` counts SEQ, ID and the payload (2 ... `MAX_LEN`); the CRC is CRC-16/CCITT-FALSE
(polynomial 0x1021, initial 0xFFFF, no reflection, no final xor) over LEN ... PAYLOAD.
Numbers in payloads are little-endian; `u8 u16 u32 u64 i32` as in C. A receiver that finds a
bad length or CRC drops the start byte only and looks for the next 0xA5, so garbage never
desynchronises the stream.

Sequence numbers: each side numbers its own packets, +1 mod 256 per packet. The firmware
expects the host's next number; a packet with another number is rejected with
`ERROR(OUT_OF_SEQUENCE, expected)` and not acted on. `HELLO` is accepted with any number and
sets the expectation to its number + 1 (how a host starts or resynchronises). The host sees
gaps in the firmware's numbers as lost packets.

Clock: the firmware's tick is its Timer1 at F_CPU / 8 (2 MHz on a 16 MHz ATmega328P),
extended in software to 64 bits. Every time on the wire is in ticks.
"""

from __future__ import annotations

import enum
import struct
import zlib
from dataclasses import dataclass

START_BYTE = 0xA5
MAX_LEN = 40
"""Largest LEN: sequence, id and a payload of at most 38 bytes."""
PROTOCOL_VERSION = (1, 1)
"""(major, minor) of the protocol; the firmware reports it in HELLO_REPLY."""

FIELD_FORMATS = {"u8": "B", "u16": "H", "u32": "I", "u64": "Q", "i32": "i"}
"""Field type -> struct code (little-endian)."""


class Direction(enum.Enum):
    """Who sends a message."""

    TO_MCU = "to_mcu"
    TO_HOST = "to_host"


@dataclass(frozen=True)
class Message:
    """One message type: id, name, direction, and its payload fields (name, type) in order."""

    id: int
    name: str
    direction: Direction
    fields: tuple[tuple[str, str], ...] = ()
    doc: str = ""

    @property
    def struct_format(self) -> str:
        """The payload's struct format (little-endian)."""
        return "<" + "".join(FIELD_FORMATS[kind] for _, kind in self.fields)

    @property
    def payload_size(self) -> int:
        """Payload bytes."""
        return struct.calcsize(self.struct_format)


class ErrorCode(enum.IntEnum):
    """`ERROR.code`: why the firmware rejected a packet or a command."""

    BAD_CRC = 1
    BAD_LENGTH = 2
    OUT_OF_SEQUENCE = 3
    UNKNOWN_MESSAGE = 4
    BAD_PAYLOAD = 5
    BAD_STATE = 6
    BAD_VALUE = 7


class StopReason(enum.IntEnum):
    """`STOPPED.reason`: why triggering ended."""

    COUNT_DONE = 0
    DISARMED = 1
    DEAD_MAN = 2


class ResetCause(enum.IntEnum):
    """`BOOT.cause`: what reset the microcontroller (from MCUSR)."""

    POWER_ON = 0
    EXTERNAL = 1
    BROWN_OUT = 2
    WATCHDOG = 3
    OTHER = 4


class TriggerSource(enum.IntEnum):
    """`CONFIGURE.source`: what times the trigger pulses."""

    PERIOD = 0
    ENCODER = 1


D_MCU, D_HOST = Direction.TO_MCU, Direction.TO_HOST

MESSAGES: tuple[Message, ...] = (
    Message(0x01, "HELLO", D_MCU, (), "handshake; any sequence number, resets the expectation"),
    Message(0x02, "PING", D_MCU, (("token", "u32"),), "round trip for clock sync"),
    Message(
        0x03,
        "CONFIGURE",
        D_MCU,
        (
            ("source", "u8"),
            ("pulse_width_ticks", "u32"),
            ("period_ticks", "u32"),
            ("encoder_divisor", "u32"),
            ("count", "u32"),
            ("start_tick", "u64"),
        ),
        "trigger set-up (only while disarmed); count 0 = until disarmed; start_tick 0 = at ARM",
    ),
    Message(0x04, "ARM", D_MCU, (), "start triggering as configured"),
    Message(0x05, "DISARM", D_MCU, (), "stop triggering (STOPPED follows)"),
    Message(0x06, "GET_POSITION", D_MCU, (), "encoder position now"),
    Message(
        0x07,
        "SET_DEAD_MAN",
        D_MCU,
        (("timeout_ms", "u16"),),
        "stop triggering when no valid packet arrives for this long; 0 = off",
    ),
    Message(
        0x08,
        "RETIME",
        D_MCU,
        (("period_ticks", "u32"), ("encoder_divisor", "u32")),
        "new spacing for the armed trigger, kept for later ARMs (only while armed); PERIOD "
        "source: period_ticks from the rise whose successor is not yet programmed, "
        "encoder_divisor ignored; ENCODER: encoder_divisor from the last trigger position, "
        "period_ticks ignored",
    ),
    Message(
        0x81,
        "HELLO_REPLY",
        D_HOST,
        (
            ("version_major", "u8"),
            ("version_minor", "u8"),
            ("table_hash", "u32"),
            ("tick_hz", "u32"),
            ("tick", "u64"),
        ),
        "protocol version, table hash, tick rate and the tick at the reply",
    ),
    Message(
        0x82,
        "PONG",
        D_HOST,
        (("token", "u32"), ("tick", "u64")),
        "PING's token and the tick at which the PING was received",
    ),
    Message(0x83, "ACK", D_HOST, (("acked_seq", "u8"),), "the command with that number is done"),
    Message(
        0x86,
        "POSITION",
        D_HOST,
        (("position", "i32"), ("tick", "u64")),
        "encoder counts and the tick of the reading",
    ),
    Message(
        0x90,
        "TRIGGER",
        D_HOST,
        (("trigger_seq", "u32"), ("tick", "u64"), ("position", "i32")),
        "a trigger pulse began at tick; its number (1 = the first pulse after ARM) and the "
        "encoder position",
    ),
    Message(
        0x91,
        "STOPPED",
        D_HOST,
        (("reason", "u8"), ("triggers", "u32")),
        "triggering ended (StopReason) after that many pulses",
    ),
    Message(0x92, "BOOT", D_HOST, (("cause", "u8"),), "sent once after reset (ResetCause)"),
    Message(
        0xE0,
        "ERROR",
        D_HOST,
        (("code", "u8"), ("detail", "u8"), ("rejected_seq", "u8")),
        "a packet or command rejected (ErrorCode); detail: the expected sequence number for "
        "OUT_OF_SEQUENCE, the message id otherwise",
    ),
)
"""Every message, in id order within each direction."""

BY_NAME: dict[str, Message] = {m.name: m for m in MESSAGES}
BY_ID: dict[int, Message] = {m.id: m for m in MESSAGES}


def table_text() -> str:
    """The canonical text of the table the hash is taken over: one line per message."""
    lines = [f"protocol {PROTOCOL_VERSION[0]}.{PROTOCOL_VERSION[1]} max_len {MAX_LEN}"]
    for m in MESSAGES:
        fields = " ".join(f"{name}:{kind}" for name, kind in m.fields)
        lines.append(f"{m.id:#04x} {m.name} {m.direction.value} {fields}".rstrip())
    for enum_type in (ErrorCode, StopReason, ResetCause, TriggerSource):
        values = " ".join(f"{e.name}={int(e)}" for e in enum_type)
        lines.append(f"{enum_type.__name__} {values}")
    return "\n".join(lines) + "\n"


TABLE_HASH = zlib.crc32(table_text().encode("ascii"))
"""CRC-32 of `table_text()`: returned by the firmware in HELLO_REPLY."""


def crc16(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE of `data` (poly 0x1021, init 0xFFFF); check value of b"123456789"
    is 0x29B1."""
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc
