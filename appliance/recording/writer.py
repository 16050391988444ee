"""The MCAP recording of a test, written on its own thread; exact enough to replay.

`McapRecorder` is an output (`appliance.run.outputs.RunOutput`) that writes one MCAP file per
test in the format of `appliance.recording.format`: ZSTD chunks, chunk CRCs and the data
section CRC on. Every record is encoded on the publishing thread and written by a writer
thread, so the file system never stalls the measurement directly.

Guarantees:

* Nothing is dropped silently. The windows, points, strain, controller state and events of
  every sample are always written. Full frames are the one optional record: when the writer
  falls behind by half of `backlog_mb`, the full-frame rate halves (and halves again while it
  stays behind; it recovers as the backlog clears); each change is recorded on
  `/recorder/status` and in `/log`, and the count of full frames not recorded is in the
  recording's `run_stop` metadata and the recorder's `stats`. Beyond `backlog_mb` the
  publishing thread waits for the disk (the loop then drops camera frames, which it counts).
* Crash safety: a record waits at most `flush_interval_s` before its chunk is closed and the
  file flushed (and fsync'ed when configured), so after a kill at any moment every chunk
  closed before it can be read and replayed.
* A recording is never overwritten: the file must not exist. (The file is synced only when
  it is a regular file; a pipe or a socket is flushed.)
* A write error (disk full) is raised at the next sample as `RecordingError`, which ends the
  test as a fault; what was written before stays readable. When the disk fills under another
  file of the test first, `abandon` stops the recording at once, so that the room left goes
  to the strain file and the summary.
"""

from __future__ import annotations

import json
import os
import queue
import stat
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from mcap.writer import CompressionType, Writer

from appliance import __version__
from appliance.config import RecordConfig, config_to_table
from appliance.errors import InputError
from appliance.measure.frame_measurer import StrainSample
from appliance.recording.calibration_record import calibration_metadata
from appliance.recording.format import (
    FORMAT_NAME,
    FORMAT_VERSION,
    META_PREFIX,
    PROFILE,
    REFERENCE_ATTACHMENT,
    TOPIC_FULL,
    TOPIC_LOG,
    TOPIC_MACHINE,
    TOPIC_POINTS,
    TOPIC_RECORDER,
    TOPIC_STRAIN,
    TOPIC_TRIGGER,
    TOPIC_TRUTH,
    TOPIC_WINDOW,
    encode_json,
    log_message,
    machine_record,
    message_encoding,
    png,
    points_record,
    raw_image,
    schema_data,
    schema_of,
    strain_record,
    trigger_record,
)
from appliance.recording.json_schemas import foxglove_time
from appliance.recording.overlays import (
    TOPIC_FULL_ANNOTATIONS,
    TOPIC_TRANSFORMS,
    TOPIC_WINDOW_ANNOTATIONS,
    full_frame_annotations,
    window_annotations,
    window_frame_id,
    window_transforms,
)
from appliance.run.loop import DeviceEvent, LoopResult
from appliance.run.outputs import RunFacts
from appliance.run.state import Transition

MAX_DEGRADATION_LEVEL = 10


class RecordingError(RuntimeError):
    """The recording could not be written (names the file and the cause)."""


class McapRecorder:
    """Records one test to an MCAP file.

    Args:
        path: the file to create (must not exist; its directory must).
        config: the [record] settings.
        truth: for simulated tests, (true engineering strain, true elongation mm) of a
            sample, recorded on `/sim/truth`; None = no truth.
        trigger_mode: how the camera is triggered, recorded with every exposure.
        stream: an open binary stream to write instead of creating `path` (a pipe to
            another host's storage, for instance); `path` then only names it in messages.
        wall_ns: UNIX wall clock, ns (publish times, log entries; injected for tests).

    Raises:
        InputError: the file exists or cannot be created.
    """

    def __init__(
        self,
        path: str | Path,
        config: RecordConfig,
        *,
        truth: Callable[[StrainSample], tuple[float, float]] | None = None,
        trigger_mode: str = "internal",
        stream: BinaryIO | None = None,
        wall_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self.path = Path(path)
        self.config = config
        self._truth = truth
        self._trigger_mode = trigger_mode
        self._wall_ns = wall_ns
        try:
            self._file = stream if stream is not None else self.path.open("xb")
        except FileExistsError:
            raise InputError(f"{self.path}: exists (a recording is never overwritten)") from None
        except OSError as exc:
            raise InputError(f"{self.path}: cannot create the recording ({exc.strerror})") from None
        self._writer = Writer(
            _Counted(self._file),
            chunk_size=config.chunk_size_kb * 1024,
            compression=CompressionType.ZSTD,
            enable_crcs=True,
            enable_data_crcs=True,
        )
        try:
            self._writer.start(profile=PROFILE, library=f"extensometer {__version__}")
            self._sync = config.fsync and stat.S_ISREG(os.fstat(self._file.fileno()).st_mode)
        except OSError as exc:
            self._file.close()
            raise InputError(f"{self.path}: cannot write the recording ({exc.strerror})") from None
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._queue: queue.Queue = queue.Queue()
        self._backlog = 0
        self._backlog_limit = int(config.backlog_mb * 1e6)
        self._backlog_changed = threading.Condition()
        self._error: BaseException | None = None
        self._abandoned = ""
        self._facts: RunFacts | None = None
        self._last_time_ns: int | None = None
        self._full_interval_ns = (
            int(1e9 / config.full_frame_rate_hz) if config.full_frame_rate_hz > 0 else None
        )
        self._last_nominal_ns: int | None = None
        self._last_full_ns: int | None = None
        self._level = 0
        self.samples_recorded = 0
        self.full_frames_recorded = 0
        self.full_frames_skipped = 0
        self.max_degradation_level = 0
        self.blocked_s = 0.0
        self._thread = threading.Thread(target=self._write_loop, name="recorder", daemon=True)
        self._thread.start()
        self._ended = False

    def stats(self) -> dict[str, Any]:
        """What was recorded: path, samples, full frames recorded and skipped, degradation."""
        return {
            "recording": str(self.path),
            "recording_samples": self.samples_recorded,
            "recording_full_frames": self.full_frames_recorded,
            "recording_full_frames_skipped": self.full_frames_skipped,
            "recording_max_degradation_level": self.max_degradation_level,
            "recording_blocked_s": self.blocked_s,
        }

    def begin(self, facts: RunFacts) -> None:
        """Write the run's metadata and the reference frame, and flush them to disk."""
        self._facts = facts
        reference = facts.reference
        image = reference.image
        started = self._wall_ns()
        self._metadata("recording", {"format": FORMAT_NAME, "version": FORMAT_VERSION})
        self._metadata(
            "run_start",
            {
                "test_id": str(facts.facts.get("test_id", "")),
                "started_unix_ns": str(started),
                "epoch_offset_ns": str(facts.epoch_offset_ns),
                "software_version": __version__,
                "reference_frame_id": str(reference.frame_id),
                "reference_timestamp_ns": str(reference.timestamp_ns),
                "reference_exposure_us": repr(float(reference.exposure_us)),
                "image_width": str(image.shape[1]),
                "image_height": str(image.shape[0]),
                "image_dtype": str(image.dtype),
                "facts": json.dumps(_jsonable(dict(facts.facts))),
            },
        )
        self._metadata("config", {"json": json.dumps(config_to_table(facts.config))})
        self._metadata("calibration", calibration_metadata(facts))
        layout = facts.layout
        self._metadata(
            "marks",
            {
                "points": json.dumps(facts.points.tolist()),
                "marks": json.dumps([list(m) for m in facts.marks]),
                "axial": json.dumps([list(layout.axial.first), list(layout.axial.second)]),
                "transverse": json.dumps(
                    None
                    if layout.transverse is None
                    else [list(layout.transverse.first), list(layout.transverse.second)]
                ),
            },
        )
        self._metadata("devices", {k: str(v) for k, v in facts.devices.items()})
        log_time = facts.unix_time_ns(reference.timestamp_ns)
        self._last_time_ns = log_time
        self._submit(("attachment", REFERENCE_ATTACHMENT, "image/png", png(image), log_time))
        self._message(TOPIC_FULL, log_time, 0, raw_image(image, log_time))
        reference_status = np.zeros(len(facts.points), dtype=np.int8)
        self._message(
            TOPIC_FULL_ANNOTATIONS,
            log_time,
            0,
            full_frame_annotations(log_time, None, facts.points, reference_status),
        )
        self.full_frames_recorded += 1
        self.log("INFO", "reference frame taken; measuring", log_time)
        self._submit(("flush",))

    def log(self, level: str, text: str, time_ns: int | None = None) -> None:
        """An entry in the recording's `/log` (run states, commands); nothing once the
        recording has failed (listeners of the run never fail with it).

        Its time defaults to the acquisition time of the latest frame recorded, so entries
        sit on the frames' timeline (also when a simulation runs faster than real time);
        before the reference frame, the wall clock.
        """
        when = time_ns if time_ns is not None else self._last_time_ns
        when = self._wall_ns() if when is None else when
        try:
            self._message(TOPIC_LOG, when, 0, log_message(when, level, text))
        except RecordingError:
            return

    def log_transition(self, transition: Transition) -> None:
        """A change of the run state, in `/log`."""
        reason = f": {transition.reason}" if transition.reason else ""
        self.log(
            "INFO",
            f"run state {transition.source.value} -> {transition.target.value}{reason}",
        )

    def log_device_event(self, event: DeviceEvent) -> None:
        """A device lost or back, in `/log` (the repeated "waiting" of an outage is not)."""
        if event.kind != "waiting":
            level = "INFO" if event.available else "WARNING"
            self.log(level, f"{event.device} {event.kind}: {event.url}: {event.text}")

    def __call__(self, sample: StrainSample) -> None:
        """Record one sample (publishing thread). Raises RecordingError after a write error."""
        facts = self._facts
        if facts is None:
            raise RecordingError(f"{self.path}: sample recorded before the run began")
        log_time = facts.unix_time_ns(sample.timestamp_ns)
        self._last_time_ns = log_time
        seq = sample.index
        positions, status = sample.positions, sample.status
        for k, window in enumerate(sample.windows):
            image = raw_image(window.pixels, log_time, window_frame_id(k))
            self._message(TOPIC_WINDOW.format(mark=k), log_time, seq, image)
            if k < len(facts.marks):
                overlay = window_annotations(
                    log_time, seq, window, positions, status, facts.marks[k]
                )
                self._message(TOPIC_WINDOW_ANNOTATIONS.format(mark=k), log_time, seq, overlay)
        self._message(TOPIC_TRANSFORMS, log_time, seq, window_transforms(log_time, sample.windows))
        if self._full_frame_due(sample.timestamp_ns) and sample.image is not None:
            self._message(TOPIC_FULL, log_time, seq, raw_image(sample.image, log_time))
            overlay = full_frame_annotations(log_time, seq, positions, status, sample.windows)
            self._message(TOPIC_FULL_ANNOTATIONS, log_time, seq, overlay)
            self.full_frames_recorded += 1
        self._json(TOPIC_TRIGGER, log_time, seq, trigger_record(sample, self._trigger_mode))
        if sample.machine is not None:
            self._json(TOPIC_MACHINE, log_time, seq, machine_record(sample.machine))
        self._json(TOPIC_POINTS, log_time, seq, points_record(sample, facts.points, sample.zeroed))
        if self._truth is not None:
            true_strain, true_elongation = self._truth(sample)
            self._json(
                TOPIC_TRUTH,
                log_time,
                seq,
                {
                    "index": seq,
                    "true_engineering_strain": true_strain,
                    "true_elongation_mm": true_elongation,
                },
            )
        self._json(TOPIC_STRAIN, log_time, seq, strain_record(sample))
        if sample.zeroed:
            self.log("INFO", f"strain zeroed at sample {seq}", log_time)
        self.samples_recorded += 1

    def end(self, result: LoopResult) -> None:
        """Write how the run ended, finish the file (summary and footer) and close it.

        Raises:
            RecordingError: the recording failed at some point (the file holds what was
                written before).
        """
        if self._ended:
            return
        self._ended = True
        level = "INFO" if result.exit_status.ended_normally else "ERROR"
        if self._facts is not None:
            self.log(level, f"run ended: {result.exit_status}: {result.reason}")
        self._metadata(
            "run_stop",
            {
                "exit_status": result.exit_status,
                "reason": result.reason,
                "stopped_unix_ns": str(self._wall_ns()),
                "frames_processed": str(result.frames_processed),
                "frames_dropped": str(result.frames_dropped),
                **{k: str(v) for k, v in self.stats().items() if k != "recording"},
            },
        )
        self._submit(("finish",), force=True)
        self._thread.join()
        if self._error is not None:
            raise RecordingError(f"{self.path}: recording failed: {self._error}")

    def abandon(self, why: str, timeout_s: float = 10.0) -> None:
        """Stop writing at once: records not yet on disk are dropped, the file keeps what was
        written (readable up to there), and `end` then only reports the failure. Waits up to
        `timeout_s` for the writer thread to stop (a disk that does not answer)."""
        self._abandoned = why
        self._queue.put((("finish",), 0))
        self._thread.join(timeout_s)

    def close(self) -> None:
        """Stop the writer without a run result (a run that never began); idempotent."""
        if not self._ended:
            self._ended = True
            self._submit(("finish",), force=True)
            self._thread.join()

    def _full_frame_due(self, timestamp_ns: int) -> bool:
        interval = self._full_interval_ns
        if interval is None:
            return False
        if self._last_nominal_ns is not None and timestamp_ns - self._last_nominal_ns < interval:
            return False
        self._last_nominal_ns = timestamp_ns
        behind = self._backlog > self._backlog_limit // 2
        if behind and self._level < MAX_DEGRADATION_LEVEL:
            self._set_level(self._level + 1, "the disk is behind")
        elif not behind and self._level > 0 and self._backlog < self._backlog_limit // 8:
            self._set_level(self._level - 1, "the disk caught up")
        spacing = interval << self._level
        if behind or (
            self._last_full_ns is not None and timestamp_ns - self._last_full_ns < spacing
        ):
            self.full_frames_skipped += 1
            return False
        self._last_full_ns = timestamp_ns
        return True

    def _set_level(self, level: int, reason: str) -> None:
        self._level = level
        self.max_degradation_level = max(self.max_degradation_level, level)
        interval_s = self._full_interval_ns * (1 << level) * 1e-9
        now = self._last_time_ns if self._last_time_ns is not None else self._wall_ns()
        self._json(
            TOPIC_RECORDER,
            now,
            0,
            {
                "full_frame_interval_s": interval_s,
                "degradation_level": level,
                "backlog_bytes": self._backlog,
                "full_frames_skipped": self.full_frames_skipped,
                "reason": reason,
            },
        )
        self.log(
            "WARNING" if level else "INFO",
            f"full frames every {interval_s:g} s ({reason}; "
            f"{self.full_frames_skipped} not recorded so far)",
            now,
        )

    def _metadata(self, name: str, data: dict[str, str]) -> None:
        self._submit(("metadata", META_PREFIX + name, data))

    def _json(self, topic: str, log_time: int, seq: int, record: dict[str, Any]) -> None:
        stamped = {"timestamp": foxglove_time(log_time), **record}
        self._message(topic, log_time, seq, encode_json(stamped))

    def _message(self, topic: str, log_time: int, seq: int, data: bytes) -> None:
        self._submit(("message", topic, log_time, seq, data))

    def _submit(self, op: tuple, *, force: bool = False) -> None:
        if self._error is not None and not force:
            raise RecordingError(f"{self.path}: recording failed: {self._error}")
        size = sum(len(x) for x in op if isinstance(x, bytes))
        with self._backlog_changed:
            if self._backlog + size > self._backlog_limit and not force:
                waited = time.monotonic()
                while self._backlog + size > self._backlog_limit and self._error is None:
                    self._backlog_changed.wait(0.1)
                self.blocked_s += time.monotonic() - waited
            self._backlog += size
        self._queue.put((op, size))

    def _channel(self, topic: str) -> int:
        channel = self._channels.get(topic)
        if channel is None:
            name = schema_of(topic)
            if name not in self._schemas:
                encoding, data = schema_data(name)
                self._schemas[name] = self._writer.register_schema(name, encoding, data)
            channel = self._writer.register_channel(
                topic, message_encoding(name), self._schemas[name]
            )
            self._channels[topic] = channel
        return channel

    def _apply(self, op: tuple) -> None:
        kind = op[0]
        if kind == "message":
            _, topic, log_time, seq, data = op
            self._writer.add_message(
                self._channel(topic), log_time, data, self._wall_ns(), sequence=seq
            )
        elif kind == "metadata":
            self._writer.add_metadata(op[1], op[2])
        elif kind == "attachment":
            _, name, media_type, data, log_time = op
            self._writer.add_attachment(self._wall_ns(), log_time, name, media_type, data)

    def _flush(self) -> None:
        self._writer.flush()
        if self._sync:
            os.fsync(self._file.fileno())

    def _write_loop(self) -> None:
        interval = self.config.flush_interval_s
        deadline: float | None = None
        try:
            while True:
                timeout = None if deadline is None else max(0.0, deadline - time.monotonic())
                try:
                    op, size = self._queue.get(timeout=timeout)
                except queue.Empty:
                    op, size = ("flush",), 0
                if self._abandoned:
                    raise RecordingError(f"abandoned: {self._abandoned}")
                if op[0] == "finish":
                    self._writer.finish()
                    self._file.flush()
                    if self._sync:
                        os.fsync(self._file.fileno())
                    return
                if op[0] == "flush":
                    if deadline is not None:
                        self._flush()
                        deadline = None
                else:
                    self._apply(op)
                    if deadline is None:
                        deadline = time.monotonic() + interval
                    elif time.monotonic() >= deadline:
                        self._flush()
                        deadline = None
                with self._backlog_changed:
                    self._backlog -= size
                    self._backlog_changed.notify_all()
        except BaseException as exc:  # noqa: BLE001 - any write failure ends the recording
            self._error = exc
            with self._backlog_changed:
                self._backlog_changed.notify_all()
        finally:
            self._file.close()


class _Counted:
    """A binary stream whose `tell` counts the bytes written (the MCAP writer asks for
    offsets, which a pipe cannot give)."""

    def __init__(self, stream: BinaryIO) -> None:
        self._stream = stream
        self._written = 0

    def write(self, data) -> int:
        view = memoryview(data)
        while view:
            done = self._stream.write(view)
            view = view[done if done is not None else len(view) :]
        self._written += len(data)
        return len(data)

    def tell(self) -> int:
        return self._written

    def flush(self) -> None:
        self._stream.flush()


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, float | int | str | bool) or value is None:
        return value
    return str(value)
