"""Reading a test recording front to back, up to any damage.

`RecordingReader` reads an MCAP file of `appliance.recording.format` sequentially (it never
needs the summary section at the end, so a file cut short by a crash reads up to its last
whole chunk) and checks every CRC the file carries: each chunk's, each attachment's, the data
section's and the summary section's. It gathers the metadata and the attachments, counts the
messages of every topic, and yields the samples one by one, each with every message recorded
for it.

Damage (`Damage`, one line each, in `damages`):

* A chunk that cannot be read (a CRC or decompression failure), a record whose length runs
  past the end of the file, or bytes that are not a record: reading stops there
  (`stopped_at`); every sample before it is read.
* An attachment that fails its CRC, or a metadata or index record that cannot be decoded
  while the records around it can: the record is left out and reading goes on after it (a
  damaged reference attachment leaves the reference frame recorded on `/camera/full`).
* The data section's CRC (the header, metadata and message indexes have no CRC of their own)
  does not match: the damage lies somewhere before; it is reported unless damage was already
  found there. The summary section's CRC (the index other MCAP tools use to seek) does not
  match: the damage lies in the summary or the footer.

A file that is not one recording is refused with `InputError` naming it: no MCAP magic, a
second MCAP file starting inside it (recordings joined with `cat`), or bytes after the
recording's end.
"""

from __future__ import annotations

import io
import json
import struct
import zlib
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.stream_reader import breakup_chunk

from appliance.errors import InputError
from appliance.recording import migration
from appliance.recording.format import (
    FORMAT_NAME,
    META_PREFIX,
    TOPIC_FULL,
    TOPIC_POINTS,
    TOPIC_STRAIN,
    TOPIC_TRIGGER,
    TOPIC_TRUTH,
    decode_json,
)

_MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEAD = struct.Struct("<BQ")
_CRC = struct.Struct("<I")
_MAX_CHUNK_BYTES = 1 << 31

_PARSERS: dict[int, Callable[[ReadDataStream], McapRecord]] = {
    Opcode.HEADER: Header.read,
    Opcode.FOOTER: Footer.read,
    Opcode.SCHEMA: Schema.read,
    Opcode.CHANNEL: Channel.read,
    Opcode.CHUNK: Chunk.read,
    Opcode.MESSAGE_INDEX: MessageIndex.read,
    Opcode.CHUNK_INDEX: ChunkIndex.read,
    Opcode.ATTACHMENT: Attachment.read,
    Opcode.ATTACHMENT_INDEX: AttachmentIndex.read,
    Opcode.STATISTICS: Statistics.read,
    Opcode.METADATA: Metadata.read,
    Opcode.METADATA_INDEX: MetadataIndex.read,
    Opcode.SUMMARY_OFFSET: SummaryOffset.read,
    Opcode.DATA_END: DataEnd.read,
}
"""Opcode -> reader of its record's fields (messages outside chunks are read apart)."""


@dataclass
class RecordedSample:
    """The messages recorded for one sample.

    Attributes:
        index: the sample index (the messages' sequence).
        log_time_ns: acquisition time, UNIX ns.
        points: the `/tracking/points` record.
        strain: the `/strain` record.
        machine: the machine's state record (`/machine/state`), or None.
        trigger: the `/camera/trigger` record, or None.
        truth: the `/sim/truth` record, or None.
        windows: mark -> serialised `foxglove.RawImage` of its window.
    """

    index: int
    log_time_ns: int
    points: dict[str, Any]
    strain: dict[str, Any]
    machine: dict[str, Any] | None = None
    trigger: dict[str, Any] | None = None
    truth: dict[str, Any] | None = None
    windows: dict[int, bytes] = field(default_factory=dict)


@dataclass(frozen=True)
class Damage:
    """Where a recording is damaged.

    Attributes:
        offset: where the damage was found: the bytes before it read intact (`located`), or
            the end of the stretch a failed section CRC covers (not `located`).
        size: size of the file, bytes.
        reason: what is wrong there, one line.
        located: whether the damage starts at `offset` (False: somewhere before it).
    """

    offset: int
    size: int
    reason: str
    located: bool = True

    def describe(self) -> str:
        """One line: where and why."""
        where = "after" if self.located else "before"
        return f"damaged {where} byte {self.offset} of {self.size}: {self.reason}"


class _Stop(Exception):
    """Reading cannot go on past this point."""


class _AttachmentCrcError(ValueError):
    """An attachment whose contents fail its CRC."""

    def __init__(self, name: str, stored: int, computed: int) -> None:
        super().__init__(
            f"the attachment {name} fails its CRC (stored {stored:#010x}, computed "
            f"{computed:#010x})"
        )
        self.name = name


class RecordingReader:
    """Reads one recording.

    Attributes (after reading):
        metadata, attachments: by name; a damaged attachment is left out.
        message_counts: topic -> messages read.
        damages: every damage found, in file order; the last one is `stopped_at` when
            reading stopped at it.
        damaged_attachments: names of the attachments left out as damaged ("" for one
            whose name could not be read).
        stopped_at: the damage where reading stopped, or None when it reached the end.
        complete: the file ends with its footer and magic (summary present).
        reference_full_frame: (log time ns, serialised `foxglove.RawImage`) of the first
            `/camera/full` message of sequence 0 (the writer records the reference frame
            there as well as in the attachment), or None.
        profile, library: what the MCAP header names (None if it was not read).

    Args:
        path: the MCAP file.

    Raises:
        InputError: the file is missing, unreadable, or not an MCAP file.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            self._file: BinaryIO = self.path.open("rb")
            self.size = self.path.stat().st_size
        except FileNotFoundError:
            raise InputError(f"{self.path}: no such recording") from None
        except IsADirectoryError:
            raise InputError(f"{self.path}: is a directory, not a recording") from None
        except OSError as exc:
            raise InputError(f"{self.path}: cannot read the recording ({exc.strerror})") from None
        if self._file.read(len(_MAGIC)) != _MAGIC:
            self._file.close()
            raise InputError(f"{self.path}: not an MCAP file")
        self.metadata: dict[str, dict[str, str]] = {}
        self.attachments: dict[str, bytes] = {}
        self.message_counts: Counter[str] = Counter()
        self.topics: dict[int, tuple[str, str]] = {}
        self.schemas: dict[int, tuple[str, str]] = {}
        self.log_time_range_ns: tuple[int, int] | None = None
        self.complete = False
        self.damages: list[Damage] = []
        self.stopped_at: Damage | None = None
        self.reference_full_frame: tuple[int, bytes] | None = None
        self.damaged_attachments: list[str] = []
        self.profile: str | None = None
        self.library: str | None = None

    @property
    def damage(self) -> Damage | None:
        """The first damage found, or None."""
        return self.damages[0] if self.damages else None

    def describe_damage(self) -> str | None:
        """The damage as one line (the first damage, and where reading stopped when that
        is elsewhere), or None when the file is whole."""
        if not self.damages:
            return None
        text = self.damages[0].describe()
        if self.stopped_at is not None and self.stopped_at is not self.damages[0]:
            text += f"; reading stopped at byte {self.stopped_at.offset}: {self.stopped_at.reason}"
        return text

    def meta(self, name: str) -> dict[str, str] | None:
        """The `extensometer.<name>` metadata record, if read."""
        return self.metadata.get(META_PREFIX + name)

    def require(self, name: str) -> dict[str, str]:
        """The `extensometer.<name>` metadata; raises InputError when the recording has none."""
        record = self.meta(name)
        if record is None:
            raise InputError(f"{self.path}: no {META_PREFIX}{name} metadata")
        return record

    def check_format(self) -> None:
        """Raise InputError unless the recording says it is of this format, in a version this
        software reads (this one or an older one)."""
        record = self.meta("recording")
        if record is None or record.get("format") != FORMAT_NAME:
            written = f"written by {self.library!r}, profile {self.profile!r}"
            raise InputError(
                f"{self.path}: not an extensometer recording (no {FORMAT_NAME} "
                f"{META_PREFIX}recording metadata; {written})"
            )
        version = record.get("version", "")
        if not version.isdigit() or not 1 <= int(version) <= migration.CURRENT_VERSION:
            raise InputError(
                f"{self.path}: recording format version {version!r} is not one this software "
                f"reads (1 to {migration.CURRENT_VERSION})"
            )

    @property
    def version(self) -> int:
        """The recording's format version (the current one until its metadata is read)."""
        version = (self.meta("recording") or {}).get("version", "")
        if version.isdigit() and 1 <= int(version) <= migration.CURRENT_VERSION:
            return int(version)
        return migration.CURRENT_VERSION

    def samples(self) -> Iterator[RecordedSample]:
        """Every whole sample in order, up to the end or the damage where reading stops."""
        parts: dict[int, dict[str, Any]] = {}
        machine_topic = ""
        for topic, message in self._records():
            seq = message.sequence
            machine_topic = machine_topic or migration.machine_topic(self.version)
            try:
                if topic.startswith("/camera/window/"):
                    mark = int(topic.rsplit("/", 1)[1])
                    parts.setdefault(seq, {}).setdefault("windows", {})[mark] = message.data
                elif topic in (machine_topic, TOPIC_TRIGGER, TOPIC_TRUTH, TOPIC_POINTS):
                    parts.setdefault(seq, {})[topic] = _json_record(message.data)
                elif topic == TOPIC_STRAIN:
                    got = parts.pop(seq, {})
                    if TOPIC_POINTS not in got:
                        continue
                    yield RecordedSample(
                        index=seq,
                        log_time_ns=message.log_time,
                        points=got[TOPIC_POINTS],
                        strain=_json_record(message.data),
                        machine=got.get(machine_topic),
                        trigger=got.get(TOPIC_TRIGGER),
                        truth=got.get(TOPIC_TRUTH),
                        windows=got.get("windows", {}),
                    )
            except ValueError as exc:
                raise InputError(
                    f"{self.path}: the {topic} message of sample {seq} is not readable ({exc})"
                ) from None

    def read_all(self) -> None:
        """Read to the end (or the damage where reading stops), counting every message."""
        for _ in self._records():
            pass

    def close(self) -> None:
        """Close the file."""
        self._file.close()

    def _reset(self) -> None:
        self.metadata.clear()
        self.attachments.clear()
        self.message_counts.clear()
        self.topics.clear()
        self.schemas.clear()
        self.log_time_range_ns = None
        self.complete = False
        self.damages = []
        self.stopped_at = None
        self.reference_full_frame = None
        self.damaged_attachments = []
        self.profile = self.library = None

    def _damaged(self, offset: int, reason: str, *, located: bool = True) -> None:
        self.damages.append(Damage(offset, self.size, reason, located))

    def _stop(self, offset: int, reason: str) -> _Stop:
        self._damaged(offset, reason)
        self.stopped_at = self.damages[-1]
        return _Stop()

    def _records(self) -> Iterator[tuple[str, Message]]:
        self._reset()
        try:
            yield from self._read_records()
        except _Stop:
            return

    def _read_records(self) -> Iterator[tuple[str, Message]]:
        read = self._file
        read.seek(len(_MAGIC))
        offset = len(_MAGIC)
        data_crc: int | None = zlib.crc32(_MAGIC)
        summary_crc = 0
        while True:
            head = read.read(_RECORD_HEAD.size)
            if head[: len(_MAGIC)] == _MAGIC:
                raise InputError(
                    f"{self.path}: a second MCAP file starts at byte {offset} (recordings "
                    "joined into one file?); read each recording from a file of its own"
                )
            if not head:
                raise self._stop(offset, "the file ends before its footer (cut short)")
            if len(head) < _RECORD_HEAD.size:
                raise self._stop(offset, "the file ends inside a record")
            opcode, length = _RECORD_HEAD.unpack(head)
            left = self.size - offset - len(head)
            if length > left:
                raise self._stop(
                    offset,
                    f"the file ends inside a record ({_name(opcode)} of {length} bytes, "
                    f"{left} left)",
                )
            if opcode not in _PARSERS and opcode != Opcode.MESSAGE:
                raise self._stop(offset, f"no record starts here (opcode {opcode:#04x})")
            body = read.read(length)
            end = offset + len(head) + length
            if opcode == Opcode.HEADER and offset != len(_MAGIC):
                raise self._stop(offset, "a second MCAP header inside the file")
            if offset == len(_MAGIC) and opcode != Opcode.HEADER:
                raise self._stop(offset, "the file does not begin with an MCAP header")
            if opcode == Opcode.DATA_END:
                self._check_data_end(offset, body, data_crc)
                data_crc = None
            elif opcode == Opcode.FOOTER:
                self._check_footer(offset, head, body, summary_crc)
                self._check_end(end)
                return
            else:
                if data_crc is not None:
                    data_crc = zlib.crc32(body, zlib.crc32(head, data_crc))
                else:
                    summary_crc = zlib.crc32(body, zlib.crc32(head, summary_crc))
                yield from self._record(offset, opcode, body)
            offset = end

    def _record(self, offset: int, opcode: int, body: bytes) -> Iterator[tuple[str, Message]]:
        """The messages of one record (a chunk's, or a message outside chunks); takes in what
        the other records say."""
        stream = ReadDataStream(io.BytesIO(body))
        try:
            if opcode == Opcode.MESSAGE:
                record: McapRecord = Message.read(stream, len(body))
            else:
                record = _PARSERS[opcode](stream)
            if isinstance(record, Attachment):
                stored = _CRC.unpack_from(body, stream.count - _CRC.size)[0]
                computed = zlib.crc32(body[: stream.count - _CRC.size])
                if stored not in (0, computed):
                    raise _AttachmentCrcError(record.name, stored, computed)
        except Exception as exc:  # noqa: BLE001 - any decoding failure is damage
            if opcode in (Opcode.CHUNK, Opcode.MESSAGE):
                raise self._stop(offset, f"{_name(opcode)} not readable ({_why(exc)})") from None
            if isinstance(exc, _AttachmentCrcError):
                self.damaged_attachments.append(exc.name)
                what = str(exc)
            else:
                if opcode == Opcode.ATTACHMENT:
                    self.damaged_attachments.append("")
                what = f"{_name(opcode)} record not readable ({_why(exc)})"
            self._damaged(offset, f"{what}; the records after it were read")
            return
        if isinstance(record, Chunk):
            try:
                if record.uncompressed_size > _MAX_CHUNK_BYTES:
                    raise ValueError(f"{record.uncompressed_size} bytes uncompressed")
                inner = breakup_chunk(record, validate_crc=True)
            except Exception as exc:  # noqa: BLE001 - any decoding failure is damage
                raise self._stop(offset, f"chunk not readable ({_why(exc)})") from None
        else:
            inner = [record]
        for item in inner:
            if isinstance(item, Header):
                self.profile, self.library = item.profile, item.library
            elif isinstance(item, Schema):
                self.schemas[item.id] = (item.name, item.encoding)
            elif isinstance(item, Channel):
                schema = self.schemas.get(item.schema_id, ("", ""))[0]
                self.topics[item.id] = (item.topic, schema)
            elif isinstance(item, Metadata):
                self.metadata[item.name] = dict(item.metadata)
            elif isinstance(item, Attachment):
                self.attachments[item.name] = item.data
            elif isinstance(item, Message):
                yield self._message(item)

    def _message(self, message: Message) -> tuple[str, Message]:
        topic = self.topics.get(message.channel_id, (f"<channel {message.channel_id}>", ""))[0]
        self.message_counts[topic] += 1
        low, high = self.log_time_range_ns or (message.log_time, message.log_time)
        self.log_time_range_ns = (min(low, message.log_time), max(high, message.log_time))
        if topic == TOPIC_FULL and message.sequence == 0 and self.reference_full_frame is None:
            self.reference_full_frame = (message.log_time, message.data)
        return topic, message

    def _check_data_end(self, offset: int, body: bytes, data_crc: int | None) -> None:
        if len(body) < _CRC.size or data_crc is None:
            raise self._stop(offset, "the data section's end record is not readable")
        stored = _CRC.unpack_from(body)[0]
        if stored not in (0, data_crc) and not self.damages:
            self._damaged(
                offset,
                f"the data section's CRC does not match (stored {stored:#010x}, computed "
                f"{data_crc:#010x}): a record without a CRC of its own (the header, metadata or "
                "a message index) is damaged",
                located=False,
            )

    def _check_footer(self, offset: int, head: bytes, body: bytes, summary_crc: int) -> None:
        if len(body) < 20:
            raise self._stop(offset, "the footer is not readable")
        stored = _CRC.unpack_from(body, 16)[0]
        computed = zlib.crc32(body[:16], zlib.crc32(head, summary_crc))
        if stored not in (0, computed):
            self._damaged(
                offset,
                f"the summary section's CRC does not match (stored {stored:#010x}, computed "
                f"{computed:#010x}): the index other MCAP tools use to seek is damaged",
                located=False,
            )

    def _check_end(self, end: int) -> None:
        tail = self._file.read(len(_MAGIC))
        if tail != _MAGIC:
            raise self._stop(end, "the file does not end with the MCAP magic")
        after = end + len(_MAGIC)
        if after < self.size:
            following = self._file.read(len(_MAGIC))
            if following == _MAGIC:
                raise InputError(
                    f"{self.path}: a second MCAP file starts at byte {after} (recordings "
                    "joined into one file?); read each recording from a file of its own"
                )
            raise InputError(
                f"{self.path}: {self.size - after} bytes follow the end of the recording at "
                f"byte {after}; it is not one recording"
            )
        self.complete = True


def _name(opcode: int) -> str:
    try:
        return Opcode(opcode).name.lower().replace("_", " ")
    except ValueError:
        return f"opcode {opcode:#04x}"


def _why(exc: BaseException) -> str:
    text = str(exc).splitlines()[0] if str(exc) else ""
    return text or type(exc).__name__


def _json_record(data: bytes) -> dict[str, Any]:
    record = decode_json(data)
    if not isinstance(record, dict):
        raise ValueError("not a JSON object")
    return record


def config_table(reader: RecordingReader) -> dict[str, Any]:
    """The recorded configuration as tables, in the current format's names (raises
    InputError if missing or malformed)."""
    record = reader.require("config")
    try:
        table = json.loads(record["json"])
    except (KeyError, ValueError):
        raise InputError(f"{reader.path}: the recorded configuration is not readable") from None
    if not isinstance(table, dict):
        raise InputError(f"{reader.path}: the recorded configuration is not a table")
    return migration.config_table(table, reader.version)


def run_facts(reader: RecordingReader) -> dict[str, Any]:
    """The run facts recorded at the start, in the current format's names ({} when the run's
    start was not recorded). Raises InputError when they are not readable."""
    start = reader.meta("run_start") or {}
    try:
        facts = json.loads(start.get("facts", "{}"))
    except ValueError:
        raise InputError(f"{reader.path}: the recorded run facts are not readable") from None
    if not isinstance(facts, dict):
        raise InputError(f"{reader.path}: the recorded run facts are not a table")
    return migration.run_facts(facts, reader.version)


def recorded_devices(reader: RecordingReader) -> dict[str, str]:
    """The device identities recorded at the start, in the current format's names."""
    return migration.devices(dict(reader.meta("devices") or {}), reader.version)
