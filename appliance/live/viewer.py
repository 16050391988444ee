"""Live and remote monitoring of a test in a Rerun viewer: `RerunViewer` and `RerunService`.

`RerunViewer` is a `appliance.run.outputs.RunOutput` that follows test after test and streams
each to Rerun (rerun-sdk 0.41) through the sinks `[rerun]` chooses, in any combination:

    serve   = "HOST:PORT"   a gRPC server remote viewers connect to:
                            `rerun rerun+http://HOST:PORT/proxy`
    connect = URL           push to a viewer (or a `rerun --serve-grpc` proxy) listening at
                            `rerun+http://HOST:PORT/proxy`
    save    = PATH          an .rrd file per test ("{test}" in PATH becomes the test's id)

Every test is a recording of its own (an explicit `rr.RecordingStream`, never the global one),
with application id "extensometer" and the test's id (`RunFacts.facts["test_id"]`) as its
recording id and name. The server is opened by `start()` and closed by `close()`; `begin`
and `end` open and close one test's recording.

One server across tests
-----------------------
In rerun 0.41 a gRPC server exists only as the sink (`rr.GrpcServerSink`) of a recording stream:
replacing that stream's sinks or dropping the stream shuts the server down (rerun issue #12313,
"serve_grpc() should be possible to use independently of recording stream"). A server on each
test's stream would go down between tests and every viewer would lose its connection. So the
server lives on a stream of its own, `RerunService`, which holds nothing but a note and lasts as
long as the service; each test's stream is a *client* of that server (`rr.GrpcSink` to its
local URL), and the server relays every test to every connected viewer as a new recording. A
viewer that connects late still gets what the server kept (`server_memory_limit`; static data
is always kept). A `RerunViewer` opens its own `RerunService` (or takes one to share) at
`start()` and keeps it until `close()`, so one viewer serves every test of the service.

A quirk of rerun 0.41: the server shuts down gracefully, only once the last connected viewer has
hung up, so a viewer connected to a closed service keeps the port bound until the process ends.
A viewer's `rerun --save` therefore completes its file when the serving process exits.

Entity tree and timelines
-------------------------
    camera                  AnnotationContext: point classes tracked / reacquired / lost (static)
    camera/image            the frame, at `image_rate_hz`, scaled by `image_scale` (the
                            reference frame at frame -1); a static Transform3D scales it back to
                            sensor pixels, so every overlay is in sensor pixels
    camera/points           Points2D: tracked points, class id = `TrackStatus` (colour, label)
    camera/gauges           LineStrips2D: the axial (and transverse) gauge between mark
                            centroids, coloured red while the data is not valid
    strain/axial            Scalars: axial engineering strain
    strain/true             Scalars: axial true strain
    strain/transverse       Scalars: transverse engineering strain (with a transverse gauge)
    gauge/elongation_mm     Scalars: axial elongation, mm
    machine/force_n         Scalars (drawn as points): force, N
    machine/crosshead_mm    Scalars: crosshead position, mm
    status/points_lost      Scalars: points not measured in the frame
    status/state            TextDocument: run state, strain, data valid, points lost, viewer
                            counts (at most once per second of device time, and on changes)
    status/log              TextLog: start, data valid / not valid, points lost / found,
                            reference updates (debug), the exit status at the end
    status/result           AnyValues: exit status, reason, frame and viewer counts (static)
    facts/calibration       AnyValues: scale, gauge length, image size, points (static)
    facts/summary           TextDocument: the test's facts (static)

Timelines: `device_time` (timestamp: the device time of the exposure, mapped to UNIX time with
the run's epoch offset), `test_time` (duration since the reference frame, device clock),
`frame` (sequence: the sample index; the reference is -1) and `strain_ue` (sequence: the axial
engineering strain in microstrain, set when the strain is finite).

Force against strain. Rerun 0.41 has no XY plot (the abscissa of a time series view is the
timeline; rerun issue #8286 is open), and a curve in a 2D spatial view is drawn at aspect 1:1
(strains of 1e-3..6 against forces of 10..1e5 N) without axes. A strain timeline gives a real
plot with axes, zoom and hover: the force series on the `strain_ue` timeline *is* force
against strain, exact, one row per sample (no re-logging of a growing curve), and scrubbing
it shows the image and overlays at each strain. The viewer's x-axis follows the time panel's
timeline: the "force vs strain" view reads against strain once `strain_ue` is selected (and
against time otherwise). Force is drawn as points, so an unloading or the break, where strain
falls back, adds no false connecting lines.

The blueprint lays out the camera (image and overlays) on the left; strain against time,
force against strain and the status (state / events / facts as tabs) on the right; the time
panel starts on `test_time`. It is sent as the *default* blueprint, so a viewer whose user has
rearranged the layout keeps it from one test to the next.

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
"""

from __future__ import annotations

import dataclasses
import datetime
import ipaddress
import logging
import math
import queue
import socket
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from appliance.config import RerunConfig, parse_address
from appliance.errors import InputError
from appliance.measure.frame_measurer import StrainSample
from appliance.measure.gauges import Gauge
from appliance.measure.tracking import TrackStatus
from appliance.run.loop import LoopResult
from appliance.run.outputs import RunFacts
from appliance.run.state import ExitStatus

logger = logging.getLogger(__name__)

APPLICATION_ID = "extensometer"

DEVICE_TIME = "device_time"
TEST_TIME = "test_time"
FRAME = "frame"
STRAIN_TIMELINE = "strain_ue"

CAMERA = "camera"
IMAGE = "camera/image"
POINTS = "camera/points"
GAUGES = "camera/gauges"
AXIAL_STRAIN = "strain/axial"
TRUE_STRAIN = "strain/true"
TRANSVERSE_STRAIN = "strain/transverse"
ELONGATION = "gauge/elongation_mm"
FORCE = "machine/force_n"
CROSSHEAD = "machine/crosshead_mm"
POINTS_LOST = "status/points_lost"
STATE = "status/state"
EVENTS = "status/log"
RESULT = "status/result"
CALIBRATION = "facts/calibration"
FACTS = "facts/summary"

REFERENCE_FRAME = -1
"""`frame` of the reference image (sample indices start at 0)."""

_STATUS_PERIOD_NS = 1_000_000_000
_MAX_BATCH = 256
_QUEUE_POLL_S = 0.05
_LISTEN_WAIT_S = 2.0
_URL_SCHEMES = ("rerun://", "rerun+http://", "rerun+https://")

_STATUS_COLOURS = {
    TrackStatus.TRACKED: (40, 200, 60),
    TrackStatus.REACQUIRED: (250, 180, 0),
    TrackStatus.LOST: (230, 30, 30),
}
_AXIAL_COLOUR = (0, 190, 255)
_TRANSVERSE_COLOUR = (230, 80, 230)
_INVALID_COLOUR = (230, 30, 30)
_EXIT_LEVELS = {
    ExitStatus.COMPLETED: rr.TextLogLevel.INFO,
    ExitStatus.BREAK: rr.TextLogLevel.INFO,
    ExitStatus.ABORTED: rr.TextLogLevel.WARN,
    ExitStatus.FAULT: rr.TextLogLevel.ERROR,
}


def has_sinks(config: RerunConfig) -> bool:
    """Whether `[rerun]` asks for any sink (serve, connect or save): whether to make a viewer."""
    return bool(config.serve or config.connect or config.save)


def proxy_url(host: str, port: int) -> str:
    """The URL a viewer opens for a gRPC server at `host`:`port` (IPv6 in brackets)."""
    shown = f"[{host}]" if ":" in host else host
    return f"rerun+http://{shown}:{port}/proxy"


class RerunService:
    """A gRPC server that remote Rerun viewers connect to, up for as long as the service runs.

    The server is the only sink of a recording stream of its own (the "service" recording,
    which holds a note saying what this is); the viewer of each test connects its own stream
    to `local_url`, and the server relays every test to every viewer connected to `url`. See
    the module docstring for why (rerun 0.41 ties a server to a stream).

    Args:
        serve: "HOST:PORT" to listen on, HOST an IP address (`[rerun] serve`): 127.0.0.1 for
            viewers on this computer only (or through an SSH tunnel), 0.0.0.0 (or ::) for
            viewers on the lab network.
        application_id: the Rerun application id shared by the service and its tests.
        server_memory_limit: how much history the server keeps for viewers that connect
            late, in rerun's syntax ("512MiB", "10%"); the oldest goes first, static data
            stays.
        where: the configuration key named in errors.

    Raises:
        InputError: one line naming `where` and the address: the address is malformed, not
            an IP address, or not available ("[rerun] serve: cannot listen on
            127.0.0.1:9876 (Address already in use)").

    Attributes:
        host, port: the address listened on.
        url: what a remote viewer opens (`rerun <url>`).
        local_url: what this process's recordings connect to (loopback when listening on
            every interface).
    """

    def __init__(
        self,
        serve: str,
        *,
        application_id: str = APPLICATION_ID,
        server_memory_limit: str = "512MiB",
        where: str = "[rerun] serve",
    ) -> None:
        host, port = parse_address(serve, where)
        try:
            address = ipaddress.ip_address(host)
        except ValueError:
            raise InputError(f"{where}: HOST must be an IP address, got {host!r}") from None
        _check_can_listen(host, port, where)
        self.host = host
        self.port = port
        self.url = proxy_url(host, port)
        local = ("::1" if address.version == 6 else "127.0.0.1") if address.is_unspecified else host
        self.local_url = proxy_url(local, port)
        self._stream = rr.RecordingStream(
            application_id, recording_id=f"{application_id}-service", send_properties=False
        )
        self._stream.set_sinks(
            rr.GrpcServerSink(bind_ip=host, port=port, server_memory_limit=server_memory_limit)
        )
        if not _wait_listening(local, port, _LISTEN_WAIT_S):
            self._stream.disconnect()
            raise InputError(
                f"{where}: cannot listen on {_host_port(host, port)} (no server came up)"
            )
        self._stream.log(
            "service",
            rr.TextDocument(
                f"Extensometer service, serving on {self.url}. "
                "Every test arrives as a recording of its own."
            ),
            static=True,
        )
        self.closed = False

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop the server (idempotent); viewers still connected keep it up until they hang up."""
        if self.closed:
            return
        self.closed = True
        try:
            self._stream.flush(timeout_sec=timeout_s)
        except RuntimeError as exc:
            logger.warning("rerun service: %s", _one_line(exc))
        self._stream.disconnect()

    def __enter__(self) -> RerunService:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


class RerunViewer:
    """Streams every test to Rerun: a `RunOutput` that never slows the measurement.

    One viewer follows any number of tests in turn (`begin` ... `end`, then the next): each is
    a recording of its own, named by the test id of its facts (`facts.facts["test_id"]`, else
    "test-<UTC time of the reference frame>"). The gRPC server (`[rerun] serve`) is opened by
    `start()` (or by the first `begin`) and stays up across the tests, until `close()`.

        viewer = RerunViewer(config.rerun)
        viewer.start()                      # InputError naming the key if the port is taken
        for each test: viewer.begin(facts); viewer(sample)...; viewer.end(result)
        viewer.close()

    Args:
        config: `[rerun]`: the sinks, the image rate and scale, the queue size. In `save`,
            "{test}" is replaced by the test's recording id (one file per test); without it,
            each test overwrites the file.
        application_id: the Rerun application id.
        service: a gRPC server shared with other viewers; when given, `config.serve` is not
            opened again and `close()` leaves it running.
        close_timeout_s: the longest `end()` waits for the queue to drain and the test's
            stream to flush and close.

    Raises:
        ValueError: no sink at all (see `has_sinks`).
        InputError: a malformed `connect` URL, or a `save` directory that does not exist (one
            line naming the key).

    Attributes (of the test running, or the last one):
        recording_id: its recording id (None before the first `begin`).
        samples_shown: samples logged by the viewer thread.
        samples_dropped: samples dropped because the queue was full (or that came outside
            `begin` ... `end`).
        images_shown: camera images logged (the reference included).
        problem: the first problem met (a sink that failed, a viewer that went away), one
            line; None while all is well.
    """

    def __init__(
        self,
        config: RerunConfig,
        *,
        application_id: str = APPLICATION_ID,
        service: RerunService | None = None,
        close_timeout_s: float = 10.0,
    ) -> None:
        if service is None and not has_sinks(config):
            raise ValueError("[rerun] has no sink: set serve, connect or save")
        if config.connect and not _is_proxy_url(config.connect):
            raise InputError(
                f"[rerun] connect: must be rerun+http://HOST:PORT/proxy, got {config.connect!r}"
            )
        if config.save:
            folder = Path(config.save).parent
            if "{test}" not in str(folder) and not folder.is_dir():
                raise InputError(f"[rerun] save: {config.save}: no such directory {str(folder)!r}")
        self.config = config
        self.application_id = application_id
        self.close_timeout_s = close_timeout_s
        self._service = service
        self._owns_service = service is None and bool(config.serve)
        self._test: _TestStream | None = None
        self._outside_tests_dropped = 0

    @property
    def service(self) -> RerunService | None:
        """The gRPC server the tests go to (None before `start` or without `serve`)."""
        return self._service

    def start(self) -> None:
        """Open the gRPC server of `[rerun] serve`, if any (idempotent).

        Raises:
            InputError: the address is malformed or not available, naming `[rerun] serve`.
        """
        if self._owns_service and self._service is None:
            self._service = RerunService(self.config.serve, application_id=self.application_id)

    def close(self) -> None:
        """End a test still open and close the gRPC server this viewer opened (idempotent)."""
        test = self._test
        if test is not None and not test.ended:
            test.close(LoopResult(exit_status=ExitStatus.ABORTED, reason="viewer closed"))
        if self._owns_service and self._service is not None:
            self._service.close()

    def begin(self, facts: RunFacts) -> None:
        """Open the test's recording, log its facts and reference frame, start its thread.

        Raises:
            InputError: the server cannot listen (`[rerun] serve`) or the `save` file cannot
                be created (`[rerun] save`).
        """
        self.start()
        if self._test is not None and not self._test.ended:
            self._test.close(LoopResult(exit_status=ExitStatus.ABORTED, reason="next test began"))
        test_id = str(facts.facts.get("test_id") or "") or _default_recording_id(facts)
        urls = [self._service.local_url] if self._service is not None else []
        if self.config.connect and self.config.connect not in urls:
            urls.append(self.config.connect)
        save = Path(self.config.save.replace("{test}", test_id)) if self.config.save else None
        self._test = _TestStream(self, facts, test_id, urls, save)

    def __call__(self, sample: StrainSample) -> None:
        """Queue the sample for the viewer thread and return at once; drop it when full."""
        test = self._test
        if test is None:
            self._outside_tests_dropped += 1
            return
        test.offer(sample)

    def end(self, result: LoopResult) -> None:
        """Drain, log how the test ended, flush and close its stream (at most `close_timeout_s`).

        The gRPC server stays up for the next test. Never raises for a sink that failed or a
        viewer that went away: that is one warning on the `appliance.live.viewer` logger (and
        `problem`).
        """
        if self._test is not None:
            self._test.close(result)

    @property
    def recording_id(self) -> str | None:
        """The recording id of the test running, or of the last one (None before any)."""
        return self._test.recording_id if self._test is not None else None

    @property
    def samples_shown(self) -> int:
        """Samples of the test (running or last) logged by the viewer thread."""
        return self._test.samples_shown if self._test is not None else 0

    @property
    def samples_dropped(self) -> int:
        """Samples dropped on a full queue in the test (running or last), and outside tests."""
        test = self._test
        return self._outside_tests_dropped + (test.samples_dropped if test is not None else 0)

    @property
    def images_shown(self) -> int:
        """Camera images logged in the test (running or last), the reference included."""
        return self._test.images_shown if self._test is not None else 0

    @property
    def problem(self) -> str | None:
        """The first problem of the test (running or last), one line; None while all is well."""
        return self._test.problem if self._test is not None else None

    def stats(self) -> dict[str, Any]:
        """{}: the viewer's counts are shown in the viewer, not added to the summary."""
        return {}


class _TestStream:
    """One test's recording: its stream, its queue and the thread that logs."""

    def __init__(
        self,
        viewer: RerunViewer,
        facts: RunFacts,
        recording_id: str,
        urls: Sequence[str],
        save: Path | None,
    ) -> None:
        config = viewer.config
        self.config = config
        self.facts = facts
        self.recording_id = recording_id
        self.close_timeout_s = viewer.close_timeout_s
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
        self._last_sample: StrainSample | None = None
        self._last_valid = True
        self._last_lost = 0
        self._next_status_ns = 0
        self._reference_updates = 0
        height, width = facts.reference.image.shape[:2]
        scale = config.image_scale
        self._image_size = (max(1, round(width * scale)), max(1, round(height * scale)))
        sinks: list = [rr.GrpcSink(url) for url in urls]
        if save is not None:
            sinks.append(rr.FileSink(save))
        stream = rr.RecordingStream(viewer.application_id, recording_id=recording_id)
        try:
            stream.set_sinks(*sinks, default_blueprint=viewer_blueprint())
        except RuntimeError as exc:
            self.ended = True
            raise InputError(f"[rerun] save: {save}: {_one_line(exc)}") from None
        stream.send_recording_name(recording_id)
        self._stream = stream
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
                    self._warn(f"logging failed: {type(exc).__name__}: {_one_line(exc)}")
                self.samples_shown += len(batch)
            if self._result is not None:
                self._show_end(self._result)
        except Exception as exc:
            self._warn(f"logging failed: {type(exc).__name__}: {_one_line(exc)}")
        finally:
            self._close_stream()

    def _close_stream(self) -> None:
        try:
            self._stream.flush(timeout_sec=0.5 * self.close_timeout_s)
        except RuntimeError as exc:
            self._warn(
                f"a viewer went away; the rest of the test is not shown there ({_one_line(exc)})"
            )
        self._stream.disconnect()

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
                    for status, colour in _STATUS_COLOURS.items()
                ]
            ),
            static=True,
        )
        stream.log(
            IMAGE,
            rr.Transform3D(
                translation=[-0.5, -0.5, 0.0],
                scale=[width / shown_width, height / shown_height, 1.0],
            ),
            static=True,
        )
        series = [
            (AXIAL_STRAIN, rr.SeriesLines(names="axial (engineering)", colors=[_AXIAL_COLOUR])),
            (TRUE_STRAIN, rr.SeriesLines(names="axial (true)", colors=[(0, 90, 200)])),
            (ELONGATION, rr.SeriesLines(names="elongation [mm]")),
            (FORCE, rr.SeriesPoints(names="force [N]", marker_sizes=[1.5])),
            (CROSSHEAD, rr.SeriesLines(names="crosshead [mm]")),
            (POINTS_LOST, rr.SeriesLines(names="points lost", colors=[_INVALID_COLOUR])),
        ]
        if facts.layout.transverse is not None:
            series.append(
                (
                    TRANSVERSE_STRAIN,
                    rr.SeriesLines(names="transverse (engineering)", colors=[_TRANSVERSE_COLOUR]),
                )
            )
        for entity, style in series:
            stream.log(entity, style, static=True)
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
            static=True,
        )
        stream.log(
            FACTS,
            rr.TextDocument(
                _facts_markdown(facts, self.recording_id), media_type=rr.MediaType.MARKDOWN
            ),
            static=True,
        )

    def _log_reference(self) -> None:
        facts, stream = self.facts, self._stream
        reference = facts.reference
        stream.set_time(FRAME, sequence=REFERENCE_FRAME)
        stream.set_time(TEST_TIME, duration=np.timedelta64(0, "ns"))
        stream.set_time(
            DEVICE_TIME, timestamp=np.datetime64(facts.unix_time_ns(reference.timestamp_ns), "ns")
        )
        stream.set_time(STRAIN_TIMELINE, sequence=0)
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
            stream.set_time(FRAME, sequence=REFERENCE_FRAME)
        summary = (
            f"test {result.exit_status}: {result.reason or 'no reason given'}; "
            f"{result.frames_processed} frames measured, {result.frames_dropped} lost before "
            f"measuring; viewer showed {self.samples_shown} samples and dropped "
            f"{self.samples_dropped}"
        )
        level = _EXIT_LEVELS.get(result.exit_status, rr.TextLogLevel.WARN)
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
            ),
            static=True,
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
            (layout.axial, "axial", _AXIAL_COLOUR)
        ]
        if layout.transverse is not None:
            gauges.append((layout.transverse, "transverse", _TRANSVERSE_COLOUR))
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
                colors=[colour if valid else _INVALID_COLOUR for _, _, colour in gauges],
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
        lines += ["| | |", "|---|---|"] + [f"| {name} | {value} |" for name, value in rows]
        return rr.TextDocument("\n".join(lines), media_type=rr.MediaType.MARKDOWN)


def viewer_blueprint() -> rrb.Blueprint:
    """The viewer's layout: camera with overlays; strain, force vs strain and status; time panel."""
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial2DView(name="camera", origin=f"/{CAMERA}"),
            rrb.Vertical(
                rrb.TimeSeriesView(name="strain vs time", origin="/strain"),
                rrb.TimeSeriesView(
                    name=f"force vs strain (timeline {STRAIN_TIMELINE})",
                    origin="/machine",
                    contents=[f"/{FORCE}"],
                ),
                rrb.Tabs(
                    rrb.TextDocumentView(name="status", origin=f"/{STATE}"),
                    rrb.TextLogView(name="events", origin=f"/{EVENTS}"),
                    rrb.TextDocumentView(name="facts", origin=f"/{FACTS}"),
                ),
                row_shares=[3, 3, 2],
            ),
            column_shares=[2, 3],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline=TEST_TIME),
    )


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


def _default_recording_id(facts: RunFacts) -> str:
    unix_ns = facts.unix_time_ns(facts.reference.timestamp_ns)
    when = datetime.datetime.fromtimestamp(unix_ns / 1e9, tz=datetime.UTC)
    return f"test-{when:%Y%m%dT%H%M%S.%f}Z"


def _is_proxy_url(url: str) -> bool:
    return url.startswith(_URL_SCHEMES) and url.endswith("/proxy")


def _host_port(host: str, port: int) -> str:
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def _check_can_listen(host: str, port: int, where: str) -> None:
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    try:
        with socket.socket(family, socket.SOCK_STREAM) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            probe.bind((host, port))
    except OSError as exc:
        reason = exc.strerror or str(exc)
        raise InputError(f"{where}: cannot listen on {_host_port(host, port)} ({reason})") from None


def _wait_listening(host: str, port: int, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with socket.create_connection((host, port), timeout=0.2):
                return True
        except OSError:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.01)


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())
