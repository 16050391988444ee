"""V4L2 camera (UVC webcams, simple industrial USB cameras) through OpenCV's V4L2 capture.

URL: ``v4l2:///dev/videoN[?OPTION=VALUE&...]`` (a symlink such as ``/dev/v4l/by-id/...`` is
resolved to its ``/dev/videoN``), constructed as ``V4l2Camera(url)``; keyword resources from
the registry are ignored. Options (bad or unknown ones raise `HardwareConfigError` naming the
URL and the option):

=============  ============================================================================
``queue``      frames held between the capture thread and `fetch` (int >= 1, default 4)
``fourcc``     the V4L2 pixel format to ask for (four characters), default ``GREY`` for
               Mono8 and ``Y16`` for Mono16
``gain``       the V4L2 gain control, in the device's own units (int); default: untouched
=============  ============================================================================

A thin backend, honest about what V4L2 and OpenCV give:

* Triggering: INTERNAL only (the camera's own frame rate, ``CAP_PROP_FPS``; the driver picks
  the nearest rate it supports). SOFTWARE and EXTERNAL are refused: UVC cameras have no
  trigger input and V4L2 no trigger control.
* Pixel formats: Mono8 from a ``GREY`` stream, or the luma (Y) plane of a ``YUYV`` stream
  (no colour conversion); Mono16 from a ``Y16`` stream. Compressed streams (MJPEG, H.264)
  are refused: lossy compression ruins correlation. Mono12 is refused.
* Region: size only (``CAP_PROP_FRAME_WIDTH/HEIGHT``; the driver picks the nearest size it
  supports, which `configure` returns); offsets are refused: V4L2 capture does not crop.
* Exposure: manual exposure (``CAP_PROP_AUTO_EXPOSURE = 1``, V4L2's "manual mode") and
  ``CAP_PROP_EXPOSURE`` in V4L2's exposure_absolute units of 100 us; the value read back is
  returned. Gain: V4L2 gain has device units, not dB, so `configure` accepts ``gain_db = 0``
  only; the URL option ``gain`` sets the raw control.
* Frames: a capture thread grabs frames into a queue of ``queue`` frames; when `fetch` falls
  behind, the oldest frame is dropped. ``Frame.frame_id`` counts the frames this backend
  grabbed (so a frame dropped from the queue leaves a gap), not the driver's sequence numbers,
  which OpenCV does not expose: frames the driver itself dropped are invisible.
  ``Frame.timestamp_ns`` is the V4L2 buffer timestamp (``CAP_PROP_POS_MSEC``; for most
  drivers CLOCK_MONOTONIC when the driver received the frame, UVC: start of reception, not
  start of exposure), or, when the driver gives none, the host's monotonic clock when the
  grab returned; ``metadata["timestamp_source"]`` says which (``v4l2-buffer`` or
  ``host-monotonic``).
* Errors: a grab that fails while armed (camera unplugged) ends the capture thread; `fetch`
  then raises `HardwareConnectError`. There is no reconnection.

Never exercised on the CI host (no V4L2 device exists there); the same protocol tests as
the other cameras run against it wherever ``/dev/video*`` exists.
"""

from __future__ import annotations

import collections
import dataclasses
import os
import re
import threading
import time
from typing import Any
from urllib.parse import parse_qsl

import cv2
import numpy as np

from hal.camera.base import CameraSettings, Frame, PixelFormat, Region, TriggerInfo, TriggerMode
from hal.errors import HardwareConfigError, HardwareConnectError, HardwareTimeout
from hal.urls import split_url

_MANUAL_EXPOSURE = 1
"""V4L2_EXPOSURE_MANUAL, the value OpenCV's V4L2 backend passes through for manual exposure."""

_EXPOSURE_UNIT_US = 100.0
"""V4L2 exposure_absolute unit."""

_UNCOMPRESSED = {"GREY": PixelFormat.MONO8, "YUYV": PixelFormat.MONO8, "Y16 ": PixelFormat.MONO16}
"""Stream formats this backend decodes, and the pixel format each delivers."""

_DEVICE = re.compile(r"^/dev/video(\d+)$")


@dataclasses.dataclass(frozen=True)
class V4l2Options:
    """The URL's query options, parsed (see the module docstring)."""

    queue: int = 4
    fourcc: str | None = None
    gain: int | None = None


def parse_v4l2_url(url: str) -> tuple[str, int, V4l2Options]:
    """The device path, its /dev/videoN index and the options of a ``v4l2://`` URL."""
    parts = split_url(url, "camera")
    if parts.scheme != "v4l2" or not parts.path:
        raise HardwareConfigError(f"camera URL {url!r}: expected v4l2:///dev/videoN")
    path = parts.path
    match = _DEVICE.match(os.path.realpath(path))
    if match is None:
        raise HardwareConfigError(f"camera URL {url!r}: {path} is not a /dev/videoN device")
    values: dict[str, Any] = {}
    for key, text in parse_qsl(parts.query, keep_blank_values=True):
        if key == "queue":
            if not text.isdigit() or int(text) < 1:
                raise HardwareConfigError(
                    f"camera URL {url!r}: option queue={text!r} is not an integer >= 1"
                )
            values[key] = int(text)
        elif key == "fourcc":
            if not 1 <= len(text) <= 4:
                raise HardwareConfigError(
                    f"camera URL {url!r}: option fourcc={text!r} is not a four-character code"
                )
            values[key] = text.ljust(4)
        elif key == "gain":
            try:
                values[key] = int(text)
            except ValueError:
                raise HardwareConfigError(
                    f"camera URL {url!r}: option gain={text!r} is not an integer"
                ) from None
        else:
            raise HardwareConfigError(
                f"camera URL {url!r}: unknown option {key!r} (queue, fourcc, gain)"
            )
    return path, int(match.group(1)), V4l2Options(**values)


def _fourcc_text(code: float) -> str:
    value = int(code)
    return "".join(chr((value >> (8 * i)) & 0xFF) for i in range(4))


@dataclasses.dataclass(frozen=True)
class _Grabbed:
    image: np.ndarray
    frame_id: int
    timestamp_ns: int
    source: str


class V4l2Camera:
    """A V4L2 camera through OpenCV (see the module docstring for what it can and cannot do).

    Args:
        url: ``v4l2:///dev/videoN[?options]``; other keyword arguments are ignored.
    """

    def __init__(self, url: str, **_: Any) -> None:
        self.url = url
        self.path, self._index, self.options = parse_v4l2_url(url)
        self._capture: cv2.VideoCapture | None = None
        self._settings: CameraSettings | None = None
        self._fourcc = ""
        self._trigger = TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=30.0)
        self._armed = False
        self._queue: collections.deque[_Grabbed] = collections.deque()
        self._ready = threading.Condition()
        self._device_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._error = ""
        self._grabbed = 0
        self._delivered = 0
        self._dropped = 0

    def open(self, timeout_s: float = 5.0) -> None:
        """Open the device (a local ioctl; `timeout_s` is not needed). Raises
        HardwareConnectError when it cannot be opened."""
        if self._capture is not None:
            return
        capture = cv2.VideoCapture(self._index, cv2.CAP_V4L2)
        if not capture.isOpened():
            capture.release()
            raise HardwareConnectError(f"{self.url}: cannot open {self.path}")
        self._capture = capture

    def close(self) -> None:
        """Stop capturing and release the device; safe to call twice."""
        self.disarm()
        capture, self._capture = self._capture, None
        if capture is not None:
            capture.release()

    def configure(self, settings: CameraSettings) -> CameraSettings:
        """Apply `settings` (see the module docstring); returns the settings in force."""
        if self._armed:
            raise HardwareConfigError(f"{self.url}: cannot configure while armed")
        capture = self._require_open()
        if settings.pixel_format is PixelFormat.MONO12:
            raise HardwareConfigError(f"{self.url}: pixel format Mono12 is not offered over V4L2")
        if settings.gain_db != 0:
            raise HardwareConfigError(
                f"{self.url}: gain_db={settings.gain_db:g} refused: V4L2 gain has device units, "
                f"not dB (use the URL option gain)"
            )
        region = settings.region
        if region is not None and (region.x or region.y):
            raise HardwareConfigError(f"{self.url}: V4L2 capture has no region offset ({region})")
        wanted = self.options.fourcc or (
            "GREY" if settings.pixel_format is PixelFormat.MONO8 else "Y16 "
        )
        capture.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*wanted))
        if region is not None:
            capture.set(cv2.CAP_PROP_FRAME_WIDTH, region.width)
            capture.set(cv2.CAP_PROP_FRAME_HEIGHT, region.height)
        fourcc = _fourcc_text(capture.get(cv2.CAP_PROP_FOURCC))
        if _UNCOMPRESSED.get(fourcc) is not settings.pixel_format:
            raise HardwareConfigError(
                f"{self.url}: asked for {wanted.strip()}, the device delivers "
                f"{fourcc.strip() or 'an unknown format'}, "
                f"which is not {settings.pixel_format.value}"
            )
        capture.set(cv2.CAP_PROP_CONVERT_RGB, 0)
        if self.options.gain is not None and not capture.set(cv2.CAP_PROP_GAIN, self.options.gain):
            raise HardwareConfigError(f"{self.url}: the device refuses gain={self.options.gain}")
        exposure = self._apply_exposure(capture, settings.exposure_us)
        width = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH))
        height = int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
        self._fourcc = fourcc
        self._settings = CameraSettings(
            exposure_us=exposure,
            gain_db=0.0,
            region=Region(0, 0, width, height),
            pixel_format=settings.pixel_format,
        )
        return self._settings

    def prepare(self, trigger: TriggerInfo) -> None:
        """INTERNAL triggering at `rate_hz`; SOFTWARE and EXTERNAL raise HardwareConfigError."""
        if self._armed:
            raise HardwareConfigError(f"{self.url}: cannot prepare while armed")
        if trigger.mode is not TriggerMode.INTERNAL:
            raise HardwareConfigError(
                f"{self.url}: {trigger.mode.value} triggering refused: UVC/V4L2 cameras have no "
                f"trigger (use INTERNAL)"
            )
        capture = self._require_open()
        capture.set(cv2.CAP_PROP_FPS, float(trigger.rate_hz or 0.0))
        if trigger.exposure_us is not None and self._settings is not None:
            exposure = self._apply_exposure(capture, trigger.exposure_us)
            self._settings = dataclasses.replace(self._settings, exposure_us=exposure)
        self._trigger = trigger

    def set_exposure(self, exposure_us: float) -> float:
        """Set the exposure between two grabs of the capture thread (armed or not); returns
        the exposure read back, us."""
        capture = self._require_open()
        if self._settings is None:
            raise HardwareConfigError(f"{self.url}: configure before set_exposure")
        with self._device_lock:
            exposure = self._apply_exposure(capture, exposure_us)
        self._settings = dataclasses.replace(self._settings, exposure_us=exposure)
        return exposure

    def arm(self) -> None:
        """Start the capture thread."""
        if self._armed:
            return
        capture = self._require_open()
        if self._settings is None:
            raise HardwareConfigError(f"{self.url}: configure before arm")
        self._queue.clear()
        self._error = ""
        self._delivered = 0
        self._stop.clear()
        self._thread = threading.Thread(
            target=self._capture_loop, args=(capture,), name="v4l2-capture", daemon=True
        )
        self._armed = True
        self._thread.start()

    def disarm(self) -> None:
        """Stop the capture thread (waits up to 2 s for a grab in progress)."""
        self._armed = False
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(timeout=2.0)
        with self._ready:
            self._queue.clear()

    def trigger(self) -> None:
        """Always refused: there is no software trigger over V4L2."""
        raise HardwareConfigError(f"{self.url}: UVC/V4L2 cameras have no software trigger")

    def fetch(self, timeout_s: float) -> Frame:
        """The oldest frame in the queue. Raises HardwareTimeout when none arrives in time (or
        all `frames` were delivered), HardwareConnectError when capturing failed."""
        if not self._armed:
            raise HardwareConfigError(f"{self.url}: fetch while not armed")
        frames = self._trigger.frames
        if frames and self._delivered >= frames:
            raise HardwareTimeout(f"{self.url}: all {frames} frames delivered")
        deadline = time.monotonic() + max(0.0, timeout_s)
        with self._ready:
            while not self._queue:
                if self._error:
                    raise HardwareConnectError(f"{self.url}: {self._error}")
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise HardwareTimeout(f"{self.url}: no frame within {timeout_s:g} s")
                self._ready.wait(remaining)
            grabbed = self._queue.popleft()
        self._delivered += 1
        assert self._settings is not None
        return Frame(
            image=grabbed.image,
            frame_id=grabbed.frame_id,
            timestamp_ns=grabbed.timestamp_ns,
            exposure_us=self._settings.exposure_us,
            metadata={"timestamp_source": grabbed.source, "fourcc": self._fourcc.strip()},
        )

    def statistics(self) -> dict[str, int]:
        """``frames_grabbed``, ``frames_delivered`` (this acquisition) and ``frames_dropped``
        (from the queue because `fetch` fell behind; frames the driver dropped are unknown)."""
        return {
            "frames_grabbed": self._grabbed,
            "frames_delivered": self._delivered,
            "frames_dropped": self._dropped,
        }

    def _require_open(self) -> cv2.VideoCapture:
        if self._capture is None:
            raise HardwareConfigError(f"{self.url}: the camera is not open")
        return self._capture

    def _apply_exposure(self, capture: cv2.VideoCapture, exposure_us: float) -> float:
        capture.set(cv2.CAP_PROP_AUTO_EXPOSURE, _MANUAL_EXPOSURE)
        if not capture.set(cv2.CAP_PROP_EXPOSURE, exposure_us / _EXPOSURE_UNIT_US):
            raise HardwareConfigError(f"{self.url}: the device refuses exposure_us={exposure_us:g}")
        return float(capture.get(cv2.CAP_PROP_EXPOSURE)) * _EXPOSURE_UNIT_US

    def _capture_loop(self, capture: cv2.VideoCapture) -> None:
        while not self._stop.is_set():
            with self._device_lock:
                grabbed_ok = capture.grab()
                host_ns = time.monotonic_ns()
                stamp_ms = float(capture.get(cv2.CAP_PROP_POS_MSEC))
                ok, image = capture.retrieve() if grabbed_ok else (False, None)
            if not grabbed_ok:
                if not self._stop.is_set():
                    with self._ready:
                        self._error = f"grabbing from {self.path} failed (unplugged?)"
                        self._ready.notify_all()
                return
            if not ok or image is None:
                continue
            if self._fourcc == "YUYV":
                image = image.reshape(image.shape[0], -1, 2)[:, :, 0]
            elif image.ndim == 3:
                image = image[:, :, 0]
            image = np.ascontiguousarray(image)
            frame_id = self._grabbed
            self._grabbed += 1
            grabbed = _Grabbed(
                image=image,
                frame_id=frame_id,
                timestamp_ns=int(round(stamp_ms * 1e6)) if stamp_ms > 0 else host_ns,
                source="v4l2-buffer" if stamp_ms > 0 else "host-monotonic",
            )
            with self._ready:
                if len(self._queue) >= self.options.queue:
                    self._queue.popleft()
                    self._dropped += 1
                self._queue.append(grabbed)
                self._ready.notify_all()
