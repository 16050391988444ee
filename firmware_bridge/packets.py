"""Packets of the trigger microcontroller's protocol: encoding, and a decoder that resyncs.

The wire format is in `firmware_bridge.messages`. `encode` builds one packet from a message
name, a sequence number and the payload's field values; `PacketDecoder.feed` takes bytes as
they arrive (any split, any garbage between packets) and returns the packets completed so far.

The decoder never loses a valid packet that follows garbage: on a start byte it waits for the
length, rejects a length outside 2 ... MAX_LEN, and on a CRC mismatch drops that start byte
only and searches again from the byte after it (a valid packet hidden inside a bad one is
found). A start byte and a plausible length from noise make the decoder wait for the bytes
of a packet that never comes. Two calls end the wait, for a receiver that sees the line go
quiet: `recover_behind_partial` (at any quiet point) drops that start byte only when a whole
packet already lies behind it, so a packet whose rest is merely late (a busy host, a USB
adapter's latency timer) is kept; `give_up_partial` (after a silence no packet has gaps of)
drops it whatever follows and looks at what was held. A packet with a good CRC whose id is
unknown or whose payload does not fit its message is returned as a `DecodedPacket` with
`problem` set, so the receiver can answer it (the firmware replies ERROR) instead of
dropping it silently.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Any

from firmware_bridge.messages import BY_ID, BY_NAME, MAX_LEN, START_BYTE, Message, crc16


class PacketError(ValueError):
    """A packet that cannot be built (unknown message, wrong fields, value out of range)."""


def encode(name: str, seq: int, **values: Any) -> bytes:
    """One packet of message `name` with sequence number `seq` (0 ... 255).

    Raises:
        PacketError: unknown message, missing or extra fields, or a value its type cannot
            hold.
    """
    message = BY_NAME.get(name)
    if message is None:
        raise PacketError(f"unknown message {name!r}")
    names = [n for n, _ in message.fields]
    if sorted(values) != sorted(names):
        raise PacketError(f"{name}: fields are {names}, got {sorted(values)}")
    if not 0 <= seq <= 255:
        raise PacketError(f"{name}: sequence number {seq} outside 0 ... 255")
    try:
        payload = struct.pack(message.struct_format, *(values[n] for n in names))
    except struct.error as exc:
        raise PacketError(f"{name}: {exc}") from None
    body = bytes([len(payload) + 2, seq, message.id]) + payload
    crc = crc16(body)
    return bytes([START_BYTE]) + body + bytes([crc & 0xFF, crc >> 8])


@dataclass(frozen=True)
class DecodedPacket:
    """A packet with a good CRC.

    Attributes:
        seq: its sequence number.
        message_id: its message id.
        message: the message type (None when the id is unknown).
        values: the payload's fields by name (empty when `problem` is set).
        problem: why the packet cannot be used ("unknown message", "bad payload"), or "".
        raw: the packet's bytes.
    """

    seq: int
    message_id: int
    message: Message | None
    values: dict[str, Any]
    problem: str
    raw: bytes

    @property
    def name(self) -> str:
        """The message's name, or UNKNOWN_0x.. ."""
        return self.message.name if self.message else f"UNKNOWN_{self.message_id:#04x}"


@dataclass
class DecoderStatistics:
    """What a decoder has seen: packets, bytes skipped while searching, CRC and length errors."""

    packets: int = 0
    skipped_bytes: int = 0
    crc_errors: int = 0
    length_errors: int = 0


@dataclass
class PacketDecoder:
    """Incremental decoder of a byte stream into packets."""

    statistics: DecoderStatistics = field(default_factory=DecoderStatistics)
    _buffer: bytearray = field(default_factory=bytearray)

    def feed(self, data: bytes) -> list[DecodedPacket]:
        """Add received bytes; the packets they complete, in order."""
        buffer = self._buffer
        buffer.extend(data)
        packets: list[DecodedPacket] = []
        stats = self.statistics
        while True:
            start = buffer.find(START_BYTE)
            if start < 0:
                stats.skipped_bytes += len(buffer)
                buffer.clear()
                return packets
            if start:
                stats.skipped_bytes += start
                del buffer[:start]
            if len(buffer) < 2:
                return packets
            length = buffer[1]
            if not 2 <= length <= MAX_LEN:
                stats.length_errors += 1
                stats.skipped_bytes += 1
                del buffer[:1]
                continue
            total = length + 4
            if len(buffer) < total:
                return packets
            body = bytes(buffer[1 : 2 + length])
            received = buffer[2 + length] | (buffer[3 + length] << 8)
            if crc16(body) != received:
                stats.crc_errors += 1
                stats.skipped_bytes += 1
                del buffer[:1]
                continue
            raw = bytes(buffer[:total])
            del buffer[:total]
            stats.packets += 1
            packets.append(_decoded(body, raw))

    def pending(self) -> int:
        """Bytes held waiting for the rest of a packet."""
        return len(self._buffer)

    def recover_behind_partial(self) -> list[DecodedPacket]:
        """The packets lying whole behind the start byte held at the front, if there are any.

        When the bytes after the held start byte already contain a complete packet with a
        good CRC, that start byte was noise: it is dropped, as `give_up_partial` would, and
        the packets found are returned. Otherwise nothing changes and [] is returned: the held
        bytes may be a real packet whose rest is still on its way.
        """
        if len(self._buffer) < 2:
            return []
        probe = PacketDecoder()
        packets = probe.feed(bytes(self._buffer[1:]))
        if not packets:
            return []
        stats = self.statistics
        stats.skipped_bytes += 1 + probe.statistics.skipped_bytes
        stats.crc_errors += probe.statistics.crc_errors
        stats.length_errors += probe.statistics.length_errors
        stats.packets += probe.statistics.packets
        self._buffer = probe._buffer
        return packets

    def give_up_partial(self) -> list[DecodedPacket]:
        """Treat the start byte of a packet that is waiting for its rest as garbage (call it
        when the line has been quiet longer than a packet takes): a start byte and length
        from noise would otherwise hold back a valid packet behind them until more bytes
        arrive. Returns the packets found in what was held."""
        if not self._buffer:
            return []
        held = bytes(self._buffer[1:])
        self._buffer.clear()
        self.statistics.skipped_bytes += 1
        return self.feed(held)


def _decoded(body: bytes, raw: bytes) -> DecodedPacket:
    seq, message_id, payload = body[1], body[2], body[3:]
    message = BY_ID.get(message_id)
    if message is None:
        return DecodedPacket(seq, message_id, None, {}, "unknown message", raw)
    if len(payload) != message.payload_size:
        return DecodedPacket(seq, message_id, message, {}, "bad payload", raw)
    values = dict(
        zip(
            (n for n, _ in message.fields),
            struct.unpack(message.struct_format, payload),
            strict=True,
        )
    )
    return DecodedPacket(seq, message_id, message, values, "", raw)
