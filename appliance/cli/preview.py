"""`extensometer preview`: the live set-up view an installer aims, focuses and lights by.

    extensometer preview --camera URL [--config FILE] [--rate-hz 4] [--duration-s S]
                         [--exposure-us T] [--rerun-serve HOST:PORT] [--rerun-connect URL]
                         [--rerun-save FILE.rrd]

The camera free-runs at `--rate-hz`; every frame goes to a Rerun viewer
(`appliance.live.viewer.preview`) with the figures of `appliance.measure.speckle_quality`:
the focus (the sharpest tiles' weakest-direction gradient), the mean grey level, the
saturated and dark fractions, and in the subsets a test would track (`[tracking] subset_px`
about the gauge's points) the mean intensity gradient, the SSSIG and the speckle size, with
the frame rate by the device clock. Beside it, on a thread of its own, the specimen is
detected and the gauge placed exactly as a test places it on its reference frame
(`appliance.cli.detection_overlay.gauge_overlay`): the outline, the axis, the parallel
length's ends, the points, the marks and their subsets are drawn over the image, the newest
placement staying until the next (the gauge is placed again about once a second: a detection
takes longer than a frame). Nothing moves: no
machine is opened. `sim://` shows the simulated bench's camera with the preset's optics and
gauge length, in real time.

It runs until SIGINT or SIGTERM, or for `--duration-s`, then finishes a placement under way
(at most `PLACEMENT_FINISH_S`) and shows it, closes the camera and the viewer and prints one
summary line (frames, rate, the last frame's figures, the placement, what ended it); exit
status 0. 1 when the camera cannot be opened or stops sending; 2 for bad input (one line
naming it): no viewer sink, a bad URL, option or key. Without `--camera` the camera is
`[camera] url` (`sim://camera` by default).
"""

from __future__ import annotations

import argparse
import collections
import datetime
import math
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np

from appliance.cli import arguments, device_checks
from appliance.cli.detection_overlay import gauge_overlay, overlay_quality
from appliance.config import CameraConfig, Config
from appliance.errors import InputError
from appliance.measure.gauge_overlay import GaugeOverlay
from appliance.measure.speckle_quality import FrameQuality
from appliance.rig import gauge_centre_in
from appliance.run.object_plane import resolved_calibration_path
from hal.camera.base import Camera, CameraSettings, PixelFormat, TriggerInfo, TriggerMode
from hal.errors import HardwareConfigError, HardwareError, HardwareTimeout

CAMERA_OPTIONS = (("camera", "camera", "url"),)

DEFAULT_EXPOSURE_US = 1000.0
"""Exposure when neither `--exposure-us` nor `[camera] exposure_us` gives one (as
`camera-check`)."""

FETCH_TIMEOUTS_IN_A_ROW = 3
"""Fetches in a row that may time out before the camera counts as gone."""

PLACEMENT_PERIOD_S = 1.0
"""The gauge is placed again on a new frame at most this often, s: the specimen stands still
while the camera is set up, and a detection costs more than a frame."""

PLACEMENT_FINISH_S = 20.0
"""At the end, a placement under way is waited for at most this long, s, so the summary and
the viewer show the placement of a frame already streamed even on a busy host."""

RATE_WINDOW_FRAMES = 10
"""Frames the frame rate is taken over (device clock)."""


def add_parser(commands: argparse._SubParsersAction) -> None:
    """The `preview` command."""
    preview = commands.add_parser(
        "preview",
        help="stream the live camera image with focus, exposure, speckle and the gauge to Rerun",
        description=(
            "Free-run the camera and stream every frame to a Rerun viewer with the focus, the "
            "saturated and dark fractions, the speckle's quality in the subsets a test would "
            "track (mean intensity gradient, SSSIG, speckle size), the frame rate, and the "
            "specimen and gauge a test would place, until SIGINT or SIGTERM (or "
            "--duration-s); then one summary line. For aiming, focusing and lighting the "
            "camera before a test."
        ),
    )
    preview.add_argument("--camera", metavar="URL", help="camera URL ([camera] url)")
    preview.add_argument("--config", type=Path, metavar="FILE", help="TOML configuration")
    preview.add_argument(
        "--rate-hz",
        type=arguments.within(float, 0.1, 100.0),
        default=4.0,
        help="frames per second shown (4)",
    )
    preview.add_argument(
        "--duration-s",
        type=arguments.positive_float,
        help="stop after this long, s (default: until SIGINT or SIGTERM)",
    )
    preview.add_argument(
        "--exposure-us",
        type=arguments.like_key(CameraConfig, "exposure_us"),
        help="exposure, us ([camera] exposure_us, else 1000)",
    )
    arguments.add_rerun_options(preview)
    preview.set_defaults(handler=preview_command)


def preview_configuration(args: argparse.Namespace) -> Config:
    """`preview`'s configuration: the file's (or the defaults) with the options applied; for a
    `sim://` camera, the simulated bench's optics and gauge length where none is configured.

    Raises:
        InputError: no camera, or a bad key or option (naming it).
    """
    config = arguments.configuration(
        args.config, args, arguments.option_overrides(args, CAMERA_OPTIONS)
    )
    config = resolved_calibration_path(config, args.config)
    if not config.camera.url:
        raise InputError("preview: no camera: give --camera URL ([camera] url)")
    if config.camera.url.startswith("sim://"):
        config = device_checks.simulated_setup(config)
    gauge_centre_in(config, "frame")
    return config


def preview_command(args: argparse.Namespace) -> int:
    """Run `preview`: exit status 0 when stopped by a signal or its duration, 1 when the
    camera cannot be opened or stops sending."""
    from appliance.live.viewer import has_sinks
    from appliance.live.viewer.preview import PreviewViewer

    config = preview_configuration(args)
    if not has_sinks(config.rerun):
        raise InputError(
            "preview: no viewer: give --rerun-serve HOST:PORT, --rerun-connect URL or "
            "--rerun-save FILE.rrd ([rerun] serve, connect or save)"
        )
    try:
        camera = device_checks.camera_for_check(config, config.camera.url)
    except HardwareConfigError as error:
        raise InputError(f"preview: {error}") from None
    recording_id = f"preview-{datetime.datetime.now(datetime.UTC):%Y%m%dT%H%M%SZ}"
    viewer = PreviewViewer(config.rerun, recording_id)
    if viewer.url is not None:
        print(f"extensometer: preview: viewers open {viewer.url}", file=sys.stderr, flush=True)
    stop = _StopOnSignals()
    session = PreviewSession(camera, config, viewer, args.rate_hz, args.exposure_us)
    problem: str | None = None
    try:
        with stop:
            session.run(stop.event, args.duration_s)
    except HardwareConfigError as error:
        problem = f"preview: {error}"
        viewer.close(f"{recording_id}: refused: {error}")
        raise InputError(problem) from None
    except HardwareError as error:
        problem = f"preview: {error}"
    ended_by = stop.signal_name or ("the camera" if problem else "its duration")
    summary = session.summary(ended_by)
    viewer_problem = viewer.close(f"{recording_id}: {summary}")
    if problem is not None:
        print(f"extensometer: {problem}", file=sys.stderr)
    if viewer_problem is not None:
        print(f"extensometer: warning: viewer: {viewer_problem}", file=sys.stderr)
    print(f"preview: {summary}", flush=True)
    return 1 if problem is not None else 0


class _StopOnSignals:
    """A context in which SIGINT and SIGTERM set `event` (and `signal_name`) instead of ending
    the process; the previous handlers come back on exit."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.signal_name: str | None = None
        self._previous: dict[int, object] = {}

    def _handle(self, number: int, _frame: object) -> None:
        self.signal_name = signal.Signals(number).name
        self.event.set()

    def __enter__(self) -> _StopOnSignals:
        for number in (signal.SIGINT, signal.SIGTERM):
            self._previous[number] = signal.signal(number, self._handle)
        return self

    def __exit__(self, *exc_info: object) -> None:
        for number, handler in self._previous.items():
            signal.signal(number, handler)  # type: ignore[arg-type]


class _PlacementWorker:
    """Places the gauge on the newest frame offered, on a thread of its own: a detection takes
    longer than a frame, so the stream does not wait for it."""

    def __init__(self, config: Config) -> None:
        self._config = config
        self._wanted = threading.Condition()
        self._image: np.ndarray | None = None
        self._done: GaugeOverlay | None = None
        self._closing = False
        self._thread = threading.Thread(target=self._run, name="preview-placement", daemon=True)
        self._thread.start()

    def offer(self, image: np.ndarray) -> None:
        """Place the gauge on `image` next, unless a placement is under way."""
        with self._wanted:
            if self._image is None:
                self._image = image
                self._wanted.notify()

    def take(self) -> GaugeOverlay | None:
        """The placement finished since the last call, or None."""
        with self._wanted:
            done, self._done = self._done, None
            return done

    def finish(self, timeout_s: float) -> GaugeOverlay | None:
        """The placement under way or finished and not yet taken, waited for at most
        `timeout_s`; None when there is none (or it did not finish in time)."""
        deadline = time.monotonic() + timeout_s
        with self._wanted:
            while self._image is not None and self._done is None:
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._wanted.wait(left)
            done, self._done = self._done, None
            return done

    def close(self, timeout_s: float = 10.0) -> None:
        with self._wanted:
            self._closing = True
            self._wanted.notify()
        self._thread.join(timeout_s)

    def _run(self) -> None:
        while True:
            with self._wanted:
                while self._image is None and not self._closing:
                    self._wanted.wait()
                if self._closing:
                    return
                image = self._image
            overlay = gauge_overlay(image, self._config)
            with self._wanted:
                self._done = overlay
                self._image = None
                self._wanted.notify_all()


class PreviewSession:
    """One set-up view: a free-running camera streamed with its figures and placement.

    Args:
        camera: a constructed, not opened, camera (closed again when `run` returns).
        config: gain, region, pixel format and exposure (`[camera]`), the gauge (`[gauge]`,
            `[optics]`) and the subset size (`[tracking] subset_px`).
        viewer: where frames, figures and placements go (`PreviewViewer`).
        rate_hz: the camera's frame rate.
        exposure_us: exposure override, us.

    Attributes (after `run`):
        frames: frames shown.
        lost: frames the camera counted that never arrived (frame-id gaps).
        placements: placements shown.
        elapsed_s: from the first frame to the last.
    """

    def __init__(
        self,
        camera: Camera,
        config: Config,
        viewer,
        rate_hz: float,
        exposure_us: float | None,
    ) -> None:
        self.camera = camera
        self.config = config
        self.viewer = viewer
        self.rate_hz = rate_hz
        self.exposure_us = exposure_us or config.camera.exposure_us or DEFAULT_EXPOSURE_US
        self.frames = 0
        self.lost = 0
        self.placements = 0
        self.elapsed_s = 0.0
        self.last_quality: FrameQuality | None = None
        self.last_placement: GaugeOverlay | None = None
        self._stamps: collections.deque[int] = collections.deque(maxlen=RATE_WINDOW_FRAMES)

    def run(self, stop: threading.Event, duration_s: float | None) -> None:
        """Stream frames until `stop` is set or `duration_s` has passed.

        Raises:
            HardwareConfigError: the camera refuses a setting.
            HardwareError: it cannot be opened, or sends nothing for three fetches in a row.
        """
        from appliance.live.viewer.preview import figures_of

        c = self.config.camera
        settings = CameraSettings(
            exposure_us=self.exposure_us,
            gain_db=c.gain_db,
            region=c.region(),
            pixel_format=PixelFormat(c.pixel_format),
        )
        fetch_timeout_s = max(2.0, 3.0 / self.rate_hz)
        worker = _PlacementWorker(self.config)
        self.camera.open()
        try:
            full_scale = self.camera.configure(settings).pixel_format.max_value
            self.camera.prepare(TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=self.rate_hz))
            self.camera.arm()
            try:
                started = time.monotonic()
                next_placement = started
                timeouts = 0
                last_id: int | None = None
                while not stop.is_set():
                    if duration_s is not None and time.monotonic() - started >= duration_s:
                        break
                    try:
                        frame = self.camera.fetch(fetch_timeout_s)
                    except HardwareTimeout:
                        timeouts += 1
                        self.viewer.note(f"no frame within {fetch_timeout_s:g} s", warning=True)
                        if timeouts >= FETCH_TIMEOUTS_IN_A_ROW:
                            raise
                        continue
                    timeouts = 0
                    if last_id is not None and 1 < frame.frame_id - last_id < 1000:
                        self.lost += frame.frame_id - last_id - 1
                    last_id = frame.frame_id
                    image = np.asarray(frame.image)
                    self._show(worker.take())
                    if time.monotonic() >= next_placement:
                        worker.offer(image)
                        next_placement = time.monotonic() + PLACEMENT_PERIOD_S
                    overlay = self.last_placement or GaugeOverlay(lines=(), refused=True)
                    quality = overlay_quality(image, full_scale, self.config, overlay)
                    self._stamps.append(frame.timestamp_ns)
                    self.elapsed_s = time.monotonic() - started
                    self.viewer.show_frame(
                        self.frames, self.elapsed_s, image, figures_of(quality, self.frame_rate_hz)
                    )
                    self.last_quality = quality
                    self.frames += 1
                self._show(worker.finish(PLACEMENT_FINISH_S))
            finally:
                self.camera.disarm()
        finally:
            worker.close()
            self.camera.close()

    def _show(self, placed: GaugeOverlay | None) -> None:
        """Stream a finished placement (nothing for None) and keep it for the summary."""
        if placed is None:
            return
        self.last_placement = placed
        self.placements += 1
        self.viewer.show_placement(placed, self.config.tracking.subset_px)

    @property
    def frame_rate_hz(self) -> float | None:
        """Frames per second over the last frames, by the device clock (None before two)."""
        if len(self._stamps) < 2:
            return None
        span_s = (self._stamps[-1] - self._stamps[0]) * 1e-9
        return (len(self._stamps) - 1) / span_s if span_s > 0 else None

    def summary(self, ended_by: str) -> str:
        """One line: frames, rate, the last frame's figures and placement, what ended it."""
        shown_hz = (self.frames - 1) / self.elapsed_s if self.frames > 1 and self.elapsed_s else 0
        parts = [
            f"{self.frames} frames in {self.elapsed_s:.1f} s ({shown_hz:.1f} Hz shown, "
            f"{self.lost} lost), {self.placements} placements"
        ]
        q = self.last_quality
        if q is not None:
            parts.append(
                f"focus {q.focus_gradient:.2f} grey levels/px, mean grey {q.mean_grey:.1f}, "
                f"saturated {q.saturated_fraction * 100:.2f} %, dark {q.dark_fraction * 100:.2f} %"
            )
            if q.subsets is not None:
                s = q.subsets
                size = "-" if math.isnan(s.speckle_size_px) else f"{s.speckle_size_px:.2f} px"
                parts.append(
                    f"subsets MIG {s.mean_intensity_gradient:.2f}, SSSIG {s.sssig:.3g}, "
                    f"speckle {size}"
                )
        if self.last_placement is not None and self.last_placement.lines:
            parts.append(self.last_placement.lines[-1])
        parts.append(f"ended by {ended_by}")
        return "; ".join(parts)
