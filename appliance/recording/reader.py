"""Reading a test recording front to back, up to any damage.

`RecordingReader` reads an MCAP file of `appliance.recording.format` sequentially (it never
needs the summary section at the end, so a file cut short by a crash reads up to its last
whole chunk), validating chunk and data-section CRCs. It gathers the metadata and the
attachments, counts the messages of every topic, and yields the samples one by one, each
with every message recorded for it. Reading stops at the first damaged or missing byte;
`damage` then says where and why.
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

from mcap.records import Attachment, Channel, DataEnd, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from appliance.errors import InputError
from appliance.recording import migration
from appliance.recording.format import (
    FORMAT_NAME,
    META_PREFIX,
    TOPIC_POINTS,
    TOPIC_STRAIN,
    TOPIC_TRIGGER,
    TOPIC_TRUTH,
    decode_json,
)

_MAGIC = b"\x89MCAP0\r\n"


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
    """Where a recording stops being readable.

    Attributes:
        offset: bytes of the file read intact before the damage.
        size: size of the file, bytes.
        reason: what is wrong there, one line.
    """

    offset: int
    size: int
    reason: str

    def describe(self) -> str:
        """One line: where and why."""
        return f"damaged after byte {self.offset} of {self.size}: {self.reason}"


class RecordingReader:
    """Reads one recording.

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
        except OSError as exc:
            raise InputError(f"{self.path}: cannot read the recording ({exc.strerror})") from None
        if self._file.read(len(_MAGIC)) != _MAGIC:
            self._file.close()
            raise InputError(f"{self.path}: not an MCAP file")
        self._file.seek(0)
        self.metadata: dict[str, dict[str, str]] = {}
        self.attachments: dict[str, bytes] = {}
        self.message_counts: Counter[str] = Counter()
        self.topics: dict[int, tuple[str, str]] = {}
        self.schemas: dict[int, tuple[str, str]] = {}
        self.log_time_range_ns: tuple[int, int] | None = None
        self.complete = False
        self.damage: Damage | None = None

    def meta(self, name: str) -> dict[str, str] | None:
        """The `extensometer.<name>` metadata record, if read."""
        return self.metadata.get(META_PREFIX + name)

    def require(self, name: str) -> dict[str, str]:
        """The `extensometer.<name>` metadata; raises InputError when the recording has none."""
        record = self.meta(name)
        if record is None:
            where = f" ({self.damage.describe()})" if self.damage else ""
            raise InputError(f"{self.path}: no {META_PREFIX}{name} metadata{where}")
        return record

    def check_format(self) -> None:
        """Raise InputError unless the recording says it is of this format, in a version this
        software reads (this one or an older one)."""
        record = self.meta("recording")
        if record is None or record.get("format") != FORMAT_NAME:
            raise InputError(f"{self.path}: not an extensometer recording")
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
        return int(version) if version.isdigit() else migration.CURRENT_VERSION

    def samples(self) -> Iterator[RecordedSample]:
        """Every whole sample in order, up to the end or the damage (then `damage` is set)."""
        parts: dict[int, dict[str, Any]] = {}
        machine_topic = ""
        for topic, message in self._records():
            seq = message.sequence
            machine_topic = machine_topic or migration.machine_topic(self.version)
            if topic.startswith("/camera/window/"):
                parts.setdefault(seq, {}).setdefault("windows", {})[
                    int(topic.rsplit("/", 1)[1])
                ] = message.data
            elif topic in (machine_topic, TOPIC_TRIGGER, TOPIC_TRUTH, TOPIC_POINTS):
                parts.setdefault(seq, {})[topic] = decode_json(message.data)
            elif topic == TOPIC_STRAIN:
                got = parts.pop(seq, {})
                if TOPIC_POINTS not in got:
                    continue
                yield RecordedSample(
                    index=seq,
                    log_time_ns=message.log_time,
                    points=got[TOPIC_POINTS],
                    strain=decode_json(message.data),
                    machine=got.get(machine_topic),
                    trigger=got.get(TOPIC_TRIGGER),
                    truth=got.get(TOPIC_TRUTH),
                    windows=got.get("windows", {}),
                )

    def read_all(self) -> None:
        """Read to the end (or the damage), counting every message."""
        for _ in self._records():
            pass

    def close(self) -> None:
        """Close the file."""
        self._file.close()

    def _records(self) -> Iterator[tuple[str, Message]]:
        self._file.seek(0)
        self.metadata.clear()
        self.attachments.clear()
        self.message_counts.clear()
        self.complete = False
        self.damage = None
        reader = StreamReader(self._file, validate_crcs=True, record_size_limit=1 << 31)
        records = reader.records
        intact = 0
        while True:
            try:
                record = next(records)
            except StopIteration:
                return
            except Exception as exc:  # noqa: BLE001 - any decoding failure is damage
                reason = str(exc) or type(exc).__name__
                if self._file.tell() >= self.size:
                    reason = f"the file ends inside a record ({reason})"
                self.damage = Damage(intact, self.size, reason)
                return
            if isinstance(record, Schema):
                self.schemas[record.id] = (record.name, record.encoding)
            elif isinstance(record, Channel):
                schema = self.schemas.get(record.schema_id, ("", ""))[0]
                self.topics[record.id] = (record.topic, schema)
            elif isinstance(record, Metadata):
                self.metadata[record.name] = dict(record.metadata)
            elif isinstance(record, Attachment):
                self.attachments[record.name] = record.data
            elif isinstance(record, Message):
                topic = self.topics.get(record.channel_id, (f"<channel {record.channel_id}>", ""))
                self.message_counts[topic[0]] += 1
                low, high = self.log_time_range_ns or (record.log_time, record.log_time)
                self.log_time_range_ns = (min(low, record.log_time), max(high, record.log_time))
                yield topic[0], record
            elif isinstance(record, DataEnd | Footer):
                self.complete = isinstance(record, Footer) or self.complete
            intact = self._file.tell()


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
