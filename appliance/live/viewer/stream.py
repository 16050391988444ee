"""One test's recording in the viewer: its stream, its bounded queue and the thread that logs.

Never slowing the measurement
-----------------------------
`__call__` runs on the loop's publishing thread and only puts the sample in a bounded queue
(`queue_size`); a full queue drops the sample and counts it (`samples_dropped`). Samples whose
image is not due drop their pixels before they are queued, so the queue holds at most the
images it will show. A thread of the viewer logs: the scalar series of every batch it takes
from the queue go out as columns (`send_columns`), images and overlays row by row. `end()`
lets the thread drain the queue, log the exit status and the counts, flush and close the
stream, and waits for it at most `close_timeout_s`; a viewer that went away (a remote viewer
that hung up, a proxy that is down) costs one warning on the `appliance.live.viewer` logger, never
an exception.

Nothing static
--------------
A test logs no static data and no recording properties (`send_properties=False`, no recording
name: the recording id is the test id): its facts, series styles, annotation context and image
transform are logged at the reference frame's time on every timeline, its result at its last
sample's. The gRPC server of `extensometer serve` keeps a recording's static messages beside its
history and evicts them only once the history itself is gone, and each one it keeps holds on to
far more of the process's memory than its own size (by measurement, 0.35 to 1.8 MB per
test's static messages with a 64 MB history): with static data per test the service's memory
grew with every test and did not level off; without it, it stays flat once the history is full.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import queue
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path

import cv2
import numpy as np
import rerun as rr

from appliance.config import RerunConfig
from appliance.errors import InputError
from appliance.live.viewer.layout import (
    AXIAL_COLOUR,
    AXIAL_STRAIN,
    CALIBRATION,
    CAMERA,
    CROSSHEAD,
    DEVICE_TIME,
    ELONGATION,
    EVENTS,
    EXIT_LEVELS,
    FACTS,
    FORCE,
    FRAME,
    GAUGES,
    IMAGE,
    INVALID_COLOUR,
    POINTS,
    POINTS_LOST,
    REFERENCE_FRAME,
    RESULT,
    STATE,
    STATUS_COLOURS,
    STRAIN_TIMELINE,
    TEST_TIME,
    TRANSVERSE_COLOUR,
    TRANSVERSE_STRAIN,
    TRUE_STRAIN,
    WIDTH_STRAIN,
    viewer_blueprint,
)
from appliance.live.viewer.server import one_line
from appliance.measure.frame_measurer import StrainSample
from appliance.measure.gauges import Gauge
from appliance.measure.tracking import TrackStatus
from appliance.run.loop import LoopResult
from appliance.run.outputs import RunFacts

logger = logging.getLogger("appliance.live.viewer")

_STATUS_PERIOD_NS = 1_000_000_000
_MAX_BATCH = 256
_QUEUE_POLL_S = 0.05


def _set_sinks_with_blueprint(
    stream: rr.RecordingStream, sinks: Sequence, application_id: str
) -> None:
    """Give `stream` its sinks, with the viewer's layout as the application's default blueprint.

    `RecordingStream.set_sinks(default_blueprint=...)` of rerun-sdk 0.41 logs the blueprint on a
    stream of its own into a memory sink that refers back to that stream, so neither is ever
    freed: two threads and their buffers per test under `serve`. The blueprint is logged here
    the same way on a stream this function holds, which it disconnects once the blueprint has
    been handed to `stream`'s sinks; that breaks the cycle. (rerun-sdk is pinned to 0.41: the
    blueprint stream and `_log_to_stream` are its own internals.)

    Raises:
        RuntimeError: a sink cannot be opened (a file sink's path).
    """
    blueprint_stream = rr.RecordingStream._from_native(
        rr.bindings.new_blueprint(
            application_id=application_id,
            make_default=False,
            make_thread_default=False,
            default_enabled=True,
        )
    )
    try:
        blueprint_stream.set_time("blueprint", sequence=0)
        viewer_blueprint().to_blueprint()._log_to_stream(blueprint_stream)
        blueprint = blueprint_stream.memory_recording()
        rr.bindings.set_sinks(
            list(sinks), default_blueprint=blueprint.storage, recording=stream.to_native()
        )
    finally:
        blueprint_stream.disconnect()


def _release_closed_streams() -> None:
    """End the threads and free the buffers of recording streams nothing refers to any more.

    rerun-sdk 0.41 keeps every Python-made `RecordingStream` alive in its registry after
    `disconnect()` and after the last Python reference goes: its `RecordingStream` and
    `ChunkBatcher` threads and buffers stay until the process ends (rerun issue #2116,
    "Dropped unused python recordings"), two threads and a few MB per test under `serve`.
    `flush_and_cleanup_orphaned_recordings` is what `rr.init` calls to free them; streams still
    referenced (the service's server, another test's) are left alone.
    """
    rr.bindings.flush_and_cleanup_orphaned_recordings()


class OneTestStream:
    """One test's recording: its stream, its queue and the thread that logs.

    Args:
        config: `[rerun]` (image rate and scale, queue size).
        application_id: the Rerun application id.
        close_timeout_s: the longest `close` waits for the queue to drain and the stream to
            flush.
        facts: the test's facts.
        recording_id: the test's recording id.
        urls: gRPC servers to send to (the service's, a `connect` URL).
        save: an .rrd file to write, or None.

    Raises:
        InputError: the `save` file cannot be created (naming `[rerun] save`).
    """

    def __init__(
        self,
        config: RerunConfig,
        application_id: str,
        close_timeout_s: float,
        facts: RunFacts,
        recording_id: str,
        urls: Sequence[str],
        save: Path | None,
    ) -> None:
        self.config = config
        self.facts = facts
        self.recording_id = recording_id
        self.close_timeout_s = close_timeout_s
        self.samples_shown = 0
        self.samples_dropped = 0
        self.images_shown = 0
        self.problem: str | None = None
        self.ended = False
        rate = config.image_rate_hz
        self._image_period_ns = round(1e9 / rate) if rate > 0 else None
        self._next_image_ns: int | None = None
        self._queue: queue.Queue[StrainSample] = queue.Queue(maxsize=config.queue_size)
        self._ending = threading.Event()
        self._result: LoopResult | None = None
        self._results: dict[str, float | int] = {}
        self._last_sample: StrainSample | None = None
        self._last_valid = True
        self._last_lost = 0
        self._last_dropped = 0
        self._next_status_ns = 0
        self._reference_updates = 0
        height, width = facts.reference.image.shape[:2]
        scale = config.image_scale
        self._image_size = (max(1, round(width * scale)), max(1, round(height * scale)))
        sinks: list = [rr.GrpcSink(url) for url in urls]
        if save is not None:
            sinks.append(rr.FileSink(save))
        stream = rr.RecordingStream(
            application_id, recording_id=recording_id, send_properties=False
        )
        try:
            _set_sinks_with_blueprint(stream, sinks, application_id)
        except RuntimeError as exc:
            self.ended = True
            stream.disconnect()
            del stream
            _release_closed_streams()
            raise InputError(f"[rerun] save: {save}: {one_line(exc)}") from None
        self._stream = stream
        self._set_reference_time()
        self._log_facts()
        self._log_reference()
        self._thread = threading.Thread(target=self._run, name="rerun-viewer", daemon=True)
        self._thread.start()

    def offer(self, sample: StrainSample) -> None:
        if self._ending.is_set():
            self.samples_dropped += 1
            return
        show_image = (
            self._image_period_ns is not None
            and sample.image is not None
            and (self._next_image_ns is None or sample.timestamp_ns >= self._next_image_ns)
        )
        if not show_image:
            sample = dataclasses.replace(sample, image=None, windows=())
        try:
            self._queue.put_nowait(sample)
        except queue.Full:
            self.samples_dropped += 1
            return
        if show_image:
            self._next_image_ns = sample.timestamp_ns + self._image_period_ns

    def set_results(self, values: Mapping[str, float | int]) -> None:
        """The test's results, logged with how it ended (before `close`)."""
        if not self.ended:
            self._results = dict(values)

    def close(self, result: LoopResult) -> None:
        if self.ended:
            return
        self.ended = True
        self._result = result
        self._ending.set()
        self._thread.join(self.close_timeout_s)
        if self._thread.is_alive():
            self._warn(f"gave up waiting for the stream to close after {self.close_timeout_s:g} s")

    def _run(self) -> None:
        try:
            while True:
                try:
                    first = self._queue.get(timeout=_QUEUE_POLL_S)
                except queue.Empty:
                    if self._ending.is_set():
                        break
                    continue
                batch = [first]
                while len(batch) < _MAX_BATCH:
                    try:
                        batch.append(self._queue.get_nowait())
                    except queue.Empty:
                        break
                try:
                    self._show(batch)
                except Exception as exc:
                    self._warn(f"logging failed: {type(exc).__name__}: {one_line(exc)}")
                self.samples_shown += len(batch)
            if self._result is not None:
                self._show_end(self._result)
        except Exception as exc:
            self._warn(f"logging failed: {type(exc).__name__}: {one_line(exc)}")
        finally:
            self._close_stream()

    def _close_stream(self) -> None:
        try:
            self._stream.flush(timeout_sec=0.5 * self.close_timeout_s)
        except RuntimeError as exc:
            self._warn(
                f"a viewer went away; the rest of the test is not shown there ({one_line(exc)})"
            )
        self._stream.disconnect()
        self._stream = None
        _release_closed_streams()

    def _warn(self, message: str) -> None:
        if self.problem is None:
            self.problem = message
            logger.warning("rerun viewer, %s: %s", self.recording_id, message)

    def _log_facts(self) -> None:
        facts, stream = self.facts, self._stream
        height, width = facts.reference.image.shape[:2]
        shown_width, shown_height = self._image_size
        stream.log(
            CAMERA,
            rr.AnnotationContext(
                [
                    (int(status), status.name.lower(), colour)
                    for status, colour in STATUS_COLOURS.items()
                ]
            ),
        )
        stream.log(
            IMAGE,
            rr.Transform3D(
                translation=[-0.5, -0.5, 0.0],
                scale=[width / shown_width, height / shown_height, 1.0],
            ),
        )
        series = [
            (AXIAL_STRAIN, rr.SeriesLines(names="axial (engineering)", colors=[AXIAL_COLOUR])),
            (TRUE_STRAIN, rr.SeriesLines(names="axial (true)", colors=[(0, 90, 200)])),
            (ELONGATION, rr.SeriesLines(names="elongation [mm]")),
            (FORCE, rr.SeriesPoints(names="force [N]", marker_sizes=[1.5])),
            (CROSSHEAD, rr.SeriesLines(names="crosshead [mm]")),
            (POINTS_LOST, rr.SeriesLines(names="points lost", colors=[INVALID_COLOUR])),
        ]
        if facts.layout.transverse is not None:
            series.append(
                (
                    TRANSVERSE_STRAIN,
                    rr.SeriesLines(names="transverse (engineering)", colors=[TRANSVERSE_COLOUR]),
                )
            )
        if facts.facts.get("width_stations"):
            series.append(
                (
                    WIDTH_STRAIN,
                    rr.SeriesLines(names="transverse (width at the edges)", colors=[(200, 120, 0)]),
                )
            )
        for entity, style in series:
            stream.log(entity, style)
        stream.log(
            CALIBRATION,
            rr.AnyValues(
                scale_mm_per_px=facts.calibration.scale_mm_per_px,
                gauge_length_mm=facts.gauge_length_mm,
                image_width_px=width,
                image_height_px=height,
                image_scale=self.config.image_scale,
                points=len(facts.points),
                marks=len(facts.marks),
                epoch_offset_ns=facts.epoch_offset_ns,
            ),
        )
        stream.log(
            FACTS,
            rr.TextDocument(
                _facts_markdown(facts, self.recording_id), media_type=rr.MediaType.MARKDOWN
            ),
        )

    def _set_reference_time(self) -> None:
        facts, stream = self.facts, self._stream
        stream.set_time(FRAME, sequence=REFERENCE_FRAME)
        stream.set_time(TEST_TIME, duration=np.timedelta64(0, "ns"))
        stream.set_time(
            DEVICE_TIME,
            timestamp=np.datetime64(facts.unix_time_ns(facts.reference.timestamp_ns), "ns"),
        )
        stream.set_time(STRAIN_TIMELINE, sequence=0)

    def _log_reference(self) -> None:
        facts, stream = self.facts, self._stream
        reference = facts.reference
        stream.log(IMAGE, rr.Image(self._scaled(reference.image)))
        self.images_shown += 1
        points = np.asarray(facts.points, dtype=np.float64)
        self._log_overlays(points, np.full(len(points), int(TrackStatus.TRACKED)), True)
        stream.log(
            EVENTS,
            rr.TextLog(
                f"test {self.recording_id} started: L0 = {facts.gauge_length_mm:.3f} mm, "
                f"{len(points)} points in {len(facts.marks)} marks, "
                f"{facts.calibration.scale_mm_per_px:.5g} mm/px",
                level=rr.TextLogLevel.INFO,
            ),
        )
        stream.log(STATE, self._state_document("RUNNING", None))
        stream.reset_time()

    def _show(self, batch: Sequence[StrainSample]) -> None:
        clocks = _Clocks.of(batch, self.facts)
        readings = [sample.reading for sample in batch]
        self._send_series(AXIAL_STRAIN, [r.engineering_strain for r in readings], clocks)
        self._send_series(TRUE_STRAIN, [r.true_strain for r in readings], clocks)
        if self.facts.layout.transverse is not None:
            self._send_series(TRANSVERSE_STRAIN, [r.transverse_strain for r in readings], clocks)
        if self.facts.facts.get("width_stations"):
            self._send_series(
                WIDTH_STRAIN,
                [s.width.transverse_strain if s.width else math.nan for s in batch],
                clocks,
            )
        self._send_series(ELONGATION, [r.elongation_mm for r in readings], clocks)
        machines = [sample.machine for sample in batch]
        self._send_series(FORCE, [m.force_n if m else math.nan for m in machines], clocks)
        self._send_series(CROSSHEAD, [m.crosshead_mm if m else math.nan for m in machines], clocks)
        lost = [s.points_lost for s in batch]
        self._send_series(POINTS_LOST, lost, clocks)
        for sample, lost_points in zip(batch, lost, strict=True):
            self._show_sample(sample, lost_points)

    def _show_sample(self, sample: StrainSample, lost_points: int) -> None:
        stream = self._stream
        events = self._events(sample, lost_points)
        state_due = bool(events) or sample.timestamp_ns >= self._next_status_ns
        self._last_sample = sample
        if not (state_due or sample.image is not None):
            return
        self._set_time(sample)
        for text, level in events:
            stream.log(EVENTS, rr.TextLog(text, level=level))
        if sample.image is not None:
            stream.log(IMAGE, rr.Image(self._scaled(sample.image)))
            self._log_overlays(sample.positions, sample.status, sample.data_valid)
            self.images_shown += 1
        if state_due:
            stream.log(STATE, self._state_document("RUNNING", sample))
            self._next_status_ns = sample.timestamp_ns + _STATUS_PERIOD_NS

    def _events(self, sample: StrainSample, lost_points: int) -> list[tuple[str, str]]:
        where = f"frame {sample.index} (t = {sample.time_s:.3f} s)"
        events = []
        if sample.data_valid != self._last_valid:
            events.append(
                (f"{where}: data valid again", rr.TextLogLevel.INFO)
                if sample.data_valid
                else (f"{where}: data not valid", rr.TextLogLevel.WARN)
            )
            self._last_valid = sample.data_valid
        if lost_points != self._last_lost:
            total = len(sample.status)
            events.append(
                (f"{where}: {lost_points} of {total} points lost", rr.TextLogLevel.WARN)
                if lost_points
                else (f"{where}: all {total} points tracked again", rr.TextLogLevel.INFO)
            )
            self._last_lost = lost_points
        if sample.frames_dropped > self._last_dropped:
            dropped = sample.frames_dropped - self._last_dropped
            events.append(
                (
                    f"{where}: {dropped} camera frames dropped before it "
                    f"({sample.frames_dropped} in all)",
                    rr.TextLogLevel.WARN,
                )
            )
            self._last_dropped = sample.frames_dropped
        if sample.reference_updates:
            self._reference_updates += sample.reference_updates
            events.append(
                (f"{where}: {sample.reference_updates} reference(s) updated", rr.TextLogLevel.DEBUG)
            )
        return events

    def _show_end(self, result: LoopResult) -> None:
        stream = self._stream
        if self._last_sample is not None:
            self._set_time(self._last_sample)
        else:
            self._set_reference_time()
        summary = (
            f"test {result.exit_status}: {result.reason or 'no reason given'}; "
            f"{result.frames_processed} frames measured, {result.frames_dropped} lost before "
            f"measuring; viewer showed {self.samples_shown} samples and dropped "
            f"{self.samples_dropped}"
        )
        level = EXIT_LEVELS.get(result.exit_status, rr.TextLogLevel.WARN)
        stream.log(EVENTS, rr.TextLog(summary, level=level))
        stream.log(
            STATE, self._state_document(result.exit_status.upper(), self._last_sample, result)
        )
        stream.log(
            RESULT,
            rr.AnyValues(
                exit_status=result.exit_status,
                reason=result.reason,
                frames_processed=result.frames_processed,
                frames_dropped=result.frames_dropped,
                viewer_samples_shown=self.samples_shown,
                viewer_samples_dropped=self.samples_dropped,
                **self._results,
            ),
        )

    def _set_time(self, sample: StrainSample) -> None:
        stream, facts = self._stream, self.facts
        stream.set_time(FRAME, sequence=sample.index)
        stream.set_time(
            TEST_TIME,
            duration=np.timedelta64(sample.timestamp_ns - facts.reference.timestamp_ns, "ns"),
        )
        stream.set_time(
            DEVICE_TIME, timestamp=np.datetime64(facts.unix_time_ns(sample.timestamp_ns), "ns")
        )
        strain = sample.reading.engineering_strain
        if math.isfinite(strain):
            stream.set_time(STRAIN_TIMELINE, sequence=round(strain * 1e6))
        else:
            stream.disable_timeline(STRAIN_TIMELINE)

    def _send_series(self, entity: str, values: Sequence[float], clocks: _Clocks) -> None:
        values = np.asarray(values, dtype=np.float64)
        finite = np.isfinite(values)
        for rows, with_strain in (
            (finite & clocks.strain_known, True),
            (finite & ~clocks.strain_known, False),
        ):
            if rows.any():
                self._stream.send_columns(
                    entity,
                    indexes=clocks.columns(rows, with_strain),
                    columns=rr.Scalars.columns(scalars=values[rows]),
                )

    def _log_overlays(self, positions: np.ndarray, status: np.ndarray, valid: bool) -> None:
        layout = self.facts.layout
        gauges: list[tuple[Gauge, str, tuple[int, int, int]]] = [
            (layout.axial, "axial", AXIAL_COLOUR)
        ]
        if layout.transverse is not None:
            gauges.append((layout.transverse, "transverse", TRANSVERSE_COLOUR))
        strips = [
            [positions[list(gauge.first)].mean(axis=0), positions[list(gauge.second)].mean(axis=0)]
            for gauge, _, _ in gauges
        ]
        self._stream.log(
            POINTS,
            rr.Points2D(
                positions,
                class_ids=np.asarray(status, dtype=np.uint16),
                radii=rr.Radius.ui_points(4.0),
            ),
        )
        self._stream.log(
            GAUGES,
            rr.LineStrips2D(
                strips,
                colors=[colour if valid else INVALID_COLOUR for _, _, colour in gauges],
                labels=[name for _, name, _ in gauges],
                radii=rr.Radius.ui_points(1.5),
            ),
        )

    def _scaled(self, image: np.ndarray) -> np.ndarray:
        size = self._image_size
        if size == (image.shape[1], image.shape[0]):
            return image
        return cv2.resize(image, size, interpolation=cv2.INTER_AREA)

    def _state_document(
        self, state: str, sample: StrainSample | None, result: LoopResult | None = None
    ) -> rr.TextDocument:
        facts = self.facts
        lines = [f"## {self.recording_id}: {state}", ""]
        if result is not None and result.reason:
            lines += [result.reason, ""]
        rows = [("gauge length L0", f"{facts.gauge_length_mm:.3f} mm")]
        if sample is None:
            rows.append(("frame", "reference"))
        else:
            reading = sample.reading
            strain = reading.engineering_strain
            lost = sample.points_lost
            rows += [
                ("frame", f"{sample.index} (t = {sample.time_s:.3f} s)"),
                ("axial strain", f"{strain:.6f} ({100 * strain:.3f} %)"),
                ("true strain", f"{reading.true_strain:.6f}"),
                ("elongation", f"{reading.elongation_mm:.4f} mm"),
            ]
            if facts.layout.transverse is not None:
                rows += [
                    ("transverse strain", f"{reading.transverse_strain:.6f}"),
                    ("Poisson's ratio", f"{reading.poisson_ratio:.4f}"),
                ]
            if sample.machine is not None:
                rows += [
                    ("force", f"{sample.machine.force_n:.2f} N"),
                    ("crosshead", f"{sample.machine.crosshead_mm:.3f} mm"),
                ]
            rows += [
                ("data valid", "yes" if sample.data_valid else "**no**"),
                ("points lost", f"{lost} of {len(sample.status)}"),
                ("frames dropped", str(sample.frames_dropped)),
            ]
        rows += [
            ("reference updates", str(self._reference_updates)),
            ("viewer", f"{self.samples_shown} samples shown, {self.samples_dropped} dropped"),
        ]
        if result is not None:
            rows += [
                ("frames measured", str(result.frames_processed)),
                ("frames lost before measuring", str(result.frames_dropped)),
            ]
            rows += [
                (name, f"{value:.6g}")
                for name, value in self._results.items()
                if name.startswith("result_") and math.isfinite(value)
            ]
        lines += ["| | |", "|---|---|"] + [f"| {name} | {value} |" for name, value in rows]
        return rr.TextDocument("\n".join(lines), media_type=rr.MediaType.MARKDOWN)


@dataclasses.dataclass(frozen=True)
class _Clocks:
    """The timelines of a batch of samples, as columns."""

    frame: np.ndarray
    test_ns: np.ndarray
    device_ns: np.ndarray
    strain_ue: np.ndarray
    strain_known: np.ndarray

    @classmethod
    def of(cls, batch: Sequence[StrainSample], facts: RunFacts) -> _Clocks:
        stamps = np.array([sample.timestamp_ns for sample in batch], dtype=np.int64)
        strain = np.array([s.reading.engineering_strain for s in batch], dtype=np.float64)
        known = np.isfinite(strain)
        return cls(
            frame=np.array([sample.index for sample in batch], dtype=np.int64),
            test_ns=stamps - facts.reference.timestamp_ns,
            device_ns=stamps + facts.epoch_offset_ns,
            strain_ue=np.where(known, np.round(np.where(known, strain, 0.0) * 1e6), 0).astype(
                np.int64
            ),
            strain_known=known,
        )

    def columns(self, rows: np.ndarray, with_strain: bool) -> list[rr.TimeColumn]:
        columns = [
            rr.TimeColumn(FRAME, sequence=self.frame[rows]),
            rr.TimeColumn(TEST_TIME, duration=self.test_ns[rows].astype("timedelta64[ns]")),
            rr.TimeColumn(DEVICE_TIME, timestamp=self.device_ns[rows].astype("datetime64[ns]")),
        ]
        if with_strain:
            columns.append(rr.TimeColumn(STRAIN_TIMELINE, sequence=self.strain_ue[rows]))
        return columns


def _facts_markdown(facts: RunFacts, recording_id: str) -> str:
    reference = facts.reference
    height, width = reference.image.shape[:2]
    layout = facts.layout
    lines = [
        f"## Test {recording_id}",
        "",
        "| | |",
        "|---|---|",
        f"| gauge length L0 | {facts.gauge_length_mm:.4f} mm |",
        f"| scale | {facts.calibration.scale_mm_per_px:.6g} mm/px |",
        f"| image | {width} x {height} px, {reference.image.dtype} |",
        f"| points | {len(facts.points)} in {len(facts.marks)} marks |",
        f"| axial gauge | points {list(layout.axial.first)} to {list(layout.axial.second)} |",
    ]
    if layout.transverse is not None:
        lines.append(
            f"| transverse gauge | points {list(layout.transverse.first)} to "
            f"{list(layout.transverse.second)} |"
        )
    lines.append(
        f"| reference frame | {reference.frame_id}, exposure {reference.exposure_us:g} us |"
    )
    lines += [f"| {name} | {value} |" for name, value in facts.devices.items()]
    lines += [f"| {name} | {value} |" for name, value in facts.facts.items()]
    return "\n".join(lines)
