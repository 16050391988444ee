"""GigE Vision camera through Aravis 0.8: the `Camera` protocol over a GenICam device.

URL: ``aravis://ADDRESS[?OPTION=VALUE&...]``, constructed as ``AravisCamera(url)`` (keyword
resources from the registry are ignored).

ADDRESS is the camera's IPv4 address, opened directly: Aravis sends unicast GVCP to that
address only, nothing is broadcast. ADDRESS may instead be an Aravis device id or a serial
number (``aravis://Basler-21234567``) for installations that name cameras by identity;
opening by id goes through Aravis' discovery, which **broadcasts** GVCP discovery packets on
every interface (and may resolve the name through DNS), so tests and isolated networks must
use addresses.

Options (bad or unknown ones raise `HardwareConfigError` naming the URL and the option):

==================  =========================================================================
``buffers``         buffers in the stream's pool (int >= 2, default 16)
``packet_size``     GigE stream packet size in bytes (int), or ``auto`` to let Aravis probe the
                    largest that passes; default: what the camera has
``packet_timeout_ms``   Aravis' wait for a missing packet before asking for it again (float)
``frame_retention_ms``  Aravis' wait for an incomplete frame before giving it up (float)
``packet_resend``   ``always`` or ``never``; default: Aravis' choice (it turns resend off for
                    cameras that do not announce it)
``trigger_line``    camera input of EXTERNAL triggers (default ``Line0``)
``gain_raw``        GainRaw in vendor units, for cameras that have no dB ``Gain`` (int);
                    default: the minimum
``liveness_ms``     period of the liveness probe while armed (float > 0, default 1000)
``reconnect_min_ms``, ``reconnect_max_ms``  reconnect backoff, doubling from min to max
                    (defaults 500 and 10000)
==================  =========================================================================

What it does:

* ``configure``: pixel format Mono8, Mono12 (unpacked, 12 bits in 16-bit words) or Mono16,
  refused, naming the formats the camera offers, when the camera does not list it; region
  rounded down to the camera's increments (the settings in force are returned); exposure
  (``ExposureTime`` or ``ExposureTimeAbs``, auto exposure switched off); gain in dB through
  the SFNC ``Gain`` feature (auto gain off). A camera with only ``GainRaw`` (vendor units,
  not dB; the Aravis fake camera is one) accepts ``gain_db = 0`` only and gets the URL's
  ``gain_raw`` or its minimum; asking it for dB is refused rather than guessed.
* ``prepare``: all triggers off first, then INTERNAL: the camera's frame rate
  (``AcquisitionFrameRate[Abs]``, refused outside its bounds); SOFTWARE: ``TriggerSelector
  = FrameStart``, ``TriggerMode = On``, then ``TriggerSource = Software``; EXTERNAL: the same
  with ``trigger_line`` and ``TriggerActivation = RisingEdge``. Mode is set before source, as
  GenICam cameras expect. ``frames > 0``: MultiFrame with ``AcquisitionFrameCount`` where
  the camera has it, else the backend counts and stops the acquisition itself; either way
  exactly that many frames are delivered, then `fetch` raises `HardwareTimeout`.
* ``arm``: a stream with a pool of ``buffers`` buffers, then AcquisitionStart.
* ``fetch``: every buffer is a lease from the pool (``_lease``): the pixels are copied into
  a new array owned by the frame and the buffer goes back to the stream whatever happens.
  Only complete buffers become frames; incomplete ones (missing packets, timeouts) are
  counted as lost. ``Frame.frame_id`` is the camera's block id unwrapped past the 16-bit
  GVSP wrap (ids run 1..65535, then 1), so a gap is a lost frame; it keeps increasing over
  the object's life, also across reconnects (the first frame after a reconnect follows the
  last one before it). ``Frame.timestamp_ns`` is the device timestamp (GVSP leader, converted
  to ns by Aravis from the camera's tick frequency; a camera that restarts restarts its
  clock). Metadata: ``device_frame_id`` (the raw block id) and ``system_timestamp_ns``
  (host real-time clock when Aravis received the frame). Mono12/16 arrive as uint16.
* ``statistics()``: what the backend saw and what Aravis' stream counted (see its docstring).

Camera outages: while armed, a watch thread reads the camera's Control Channel Privilege
register every ``liveness_ms``. When the read fails (the camera went away: Aravis gives up
after about 2.5 s) or shows that this host no longer controls the camera (it restarted), or
when Aravis' heartbeat reports the control lost, the session is lost: the next `fetch`
raises `HardwareConnectError` (one line naming the URL and the reason) and a background
thread retires the dead connection and reconnects with backoff (``reconnect_min_ms``
doubling to ``reconnect_max_ms``); on success it re-applies the settings and the trigger
preparation and re-arms. Every `fetch` meanwhile returns within its own timeout (plus a few
ms): with a frame, with `HardwareTimeout` (no frame yet, or not yet known to be lost), or
with `HardwareConnectError` (camera away, with the failed attempts so far and the time to
the next one). Before the loss is detected (up to ``liveness_ms`` + about 2.5 s), fetches
just time out.

Opening: a camera another application controls (GVCP control refused) is a
`HardwareConnectError`, not a read-only connection. `close` leaves control explicitly. Aravis
serialises opens within a process: an open of an absent camera (about 2.5 s) delays other
opens, including reconnects of other cameras, by up to that long. `frame_rate_bounds` and
`feature_value` read the camera for diagnostics.

What it does not do: chunk data (per-frame exposure or counters; ``Frame.exposure_us`` is the
exposure in force), PTP clock synchronisation, multicast, binning, colour formats, packed
12-bit formats, more than one stream channel, USB3 Vision specifics beyond what Aravis hides.
Blocking calls other than `fetch` and `open` (configure, prepare, trigger, disarm) are single
GVCP transactions and wait for Aravis' own timeout (about 2.5 s) when the camera has gone.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import functools
import math
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any, TypeVar
from urllib.parse import parse_qsl, unquote

import numpy as np

try:
    import gi

    gi.require_version("Aravis", "0.8")
    from gi.repository import Aravis, GLib
except (ImportError, ValueError) as exc:
    raise ImportError(f"Aravis 0.8 through PyGObject is not available: {exc}") from None

from hal.camera.base import (
    CameraSettings,
    Frame,
    PixelFormat,
    Region,
    TriggerInfo,
    TriggerMode,
)
from hal.errors import (
    HardwareConfigError,
    HardwareConnectError,
    HardwareError,
    HardwareFault,
    HardwareTimeout,
)
from hal.urls import split_url

_T = TypeVar("_T")

POLL_S = 0.05
"""Longest single wait for a buffer: how soon a waiting `fetch` notices a lost camera."""

_CCP_REGISTER = 0x0A00
"""GigE Vision bootstrap register: Control Channel Privilege (bit 0 exclusive, bit 1 control)."""

_CONNECTION_ERRORS = frozenset(
    int(code)
    for code in (
        Aravis.DeviceError.NOT_CONNECTED,
        Aravis.DeviceError.TRANSFER_ERROR,
        Aravis.DeviceError.TIMEOUT,
        Aravis.DeviceError.NOT_FOUND,
        Aravis.DeviceError.NOT_CONTROLLER,
    )
)
"""Aravis device errors that mean the camera cannot be reached or controlled."""

_STREAM_COUNTERS = {
    "n_completed_buffers": "completed_buffers",
    "n_failures": "failures",
    "n_underruns": "underruns",
    "n_timeouts": "timeouts",
    "n_aborted": "aborted",
    "n_missing_frames": "missing_frames",
    "n_size_mismatch_errors": "size_mismatch_errors",
    "n_received_packets": "received_packets",
    "n_missing_packets": "missing_packets",
    "n_error_packets": "error_packets",
    "n_ignored_packets": "ignored_packets",
    "n_resend_requests": "resend_requests",
    "n_resent_packets": "resent_packets",
    "n_duplicated_packets": "duplicated_packets",
    "n_transferred_bytes": "transferred_bytes",
}
"""Aravis stream statistics by their Aravis name -> the name `statistics()` gives them."""

_BACKEND_COUNTERS = (
    "frames_delivered",
    "frames_lost",
    "incomplete_buffers",
    "connection_losses",
    "reconnects",
    "reconnect_attempts",
)

_DTYPES = {PixelFormat.MONO8: np.dtype(np.uint8), PixelFormat.MONO12: np.dtype("<u2")}
_DTYPES[PixelFormat.MONO16] = np.dtype("<u2")


@dataclasses.dataclass(frozen=True)
class AravisOptions:
    """The URL's query options, parsed (see the module docstring for their meaning)."""

    buffers: int = 16
    packet_size: int | str | None = None
    packet_timeout_ms: float | None = None
    frame_retention_ms: float | None = None
    packet_resend: str | None = None
    trigger_line: str = "Line0"
    gain_raw: int | None = None
    liveness_ms: float = 1000.0
    reconnect_min_ms: float = 500.0
    reconnect_max_ms: float = 10000.0


def parse_aravis_url(url: str) -> tuple[str, AravisOptions]:
    """The camera address (or device id) and the options of an ``aravis://`` URL.

    Raises HardwareConfigError naming the URL and the bad option.
    """
    parts = split_url(url, "camera")
    if parts.scheme != "aravis":
        raise HardwareConfigError(f"camera URL {url!r}: not an aravis:// URL")
    address = unquote(parts.netloc or parts.path.strip("/"))
    if not address:
        raise HardwareConfigError(f"camera URL {url!r}: no camera address (aravis://ADDRESS)")
    fields = {field.name: field for field in dataclasses.fields(AravisOptions)}
    values: dict[str, Any] = {}
    for key, text in parse_qsl(parts.query, keep_blank_values=True):
        if key not in fields:
            known = ", ".join(fields)
            raise HardwareConfigError(f"camera URL {url!r}: unknown option {key!r} ({known})")
        values[key] = _option_value(url, key, text)
    options = AravisOptions(**values)
    if options.reconnect_max_ms < options.reconnect_min_ms:
        raise HardwareConfigError(
            f"camera URL {url!r}: option reconnect_max_ms={options.reconnect_max_ms:g} is "
            f"below reconnect_min_ms={options.reconnect_min_ms:g}"
        )
    return address, options


def _option_value(url: str, key: str, text: str) -> Any:
    def bad(expected: str) -> HardwareConfigError:
        return HardwareConfigError(f"camera URL {url!r}: option {key}={text!r} is not {expected}")

    if key in ("buffers", "gain_raw"):
        try:
            value = int(text)
        except ValueError:
            raise bad("an integer") from None
        if key == "buffers" and value < 2:
            raise bad("an integer >= 2")
        return value
    if key == "packet_size":
        if text == "auto":
            return text
        try:
            value = int(text)
        except ValueError:
            raise bad("an integer number of bytes or 'auto'") from None
        if value <= 0:
            raise bad("a positive number of bytes or 'auto'")
        return value
    if key == "packet_resend":
        if text not in ("always", "never"):
            raise bad("'always' or 'never'")
        return text
    if key == "trigger_line":
        if not text:
            raise bad("a line name (e.g. Line0)")
        return text
    try:
        value = float(text)
    except ValueError:
        raise bad("a number") from None
    if not (math.isfinite(value) and value > 0):
        raise bad("a positive number")
    return value


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _translate(url: str, what: str, exc: GLib.Error) -> HardwareError:
    """An Aravis/GLib error as the hardware error of its phase."""
    message = f"{url}: {what}: {_one_line(exc.message)}"
    if exc.domain == "arv-device-error-quark" and exc.code in _CONNECTION_ERRORS:
        return HardwareConnectError(message)
    return HardwareConfigError(message)


def _call(url: str, what: str, function: Callable[..., _T], *args: Any) -> _T:
    try:
        return function(*args)
    except GLib.Error as exc:
        raise _translate(url, what, exc) from None


def _short_traceback(method: Callable[..., _T]) -> Callable[..., _T]:
    """Raise a public method's hardware errors with a traceback that starts at the method.

    The frames below it hold Aravis objects in their locals; an error kept by the caller
    (logged, stored) would keep the camera alive through its traceback, and Aravis leaves
    control of a camera, which may block for its GVCP timeout, only when the last
    reference goes.
    """

    @functools.wraps(method)
    def wrapper(*args: Any, **kwargs: Any) -> _T:
        try:
            return method(*args, **kwargs)
        except HardwareError as exc:
            exc.__context__ = None
            raise exc.with_traceback(None) from None

    return wrapper


@contextlib.contextmanager
def _lease(stream: Aravis.Stream, buffer: Aravis.Buffer) -> Iterator[Aravis.Buffer]:
    """A buffer borrowed from the stream's pool: it goes back to the stream whatever happens."""
    try:
        yield buffer
    finally:
        stream.push_buffer(buffer)


class _LostFlag:
    """Set once when a session is lost, with the reason and the moment (monotonic s)."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.reason = ""
        self.at_s = 0.0

    def set(self, reason: str) -> None:
        if not self.event.is_set():
            self.reason = reason
            self.at_s = time.monotonic()
            self.event.set()

    def on_control_lost(self, *_: Any) -> None:
        self.set("Aravis' heartbeat lost control of the camera")


@dataclasses.dataclass(frozen=True)
class _Features:
    """What one camera offers, read once per connection."""

    sensor: tuple[int, int]
    pixel_formats: tuple[str, ...]
    has_gain_db: bool
    has_gain_raw: bool
    has_exposure_auto: bool
    has_gain_auto: bool
    has_frame_rate: bool
    has_frame_rate_enable: bool
    has_frame_count: bool
    has_acquisition_mode: bool
    has_trigger_activation: bool
    trigger_selectors: tuple[str, ...]
    trigger_sources: tuple[str, ...]


class _Session:
    """One connection to the camera: the Aravis objects, the stream while armed, a liveness watch.

    Sessions are not repaired: a lost one is retired and a new one opened. The watch thread
    and Aravis' heartbeat only ever set the session's `_LostFlag`.
    """

    def __init__(self, url: str, camera: Aravis.Camera, probe_period_s: float) -> None:
        self.camera = camera
        self.device = camera.get_device()
        self.is_gv = bool(camera.is_gv_device())
        self.stream: Aravis.Stream | None = None
        self.lost = _LostFlag()
        self.features = _read_features(url, camera)
        self._probe_period_s = probe_period_s
        self._watch: threading.Thread | None = None
        self._stop_watch = threading.Event()
        self._handler = self.device.connect("control-lost", self.lost.on_control_lost)

    def start_watch(self) -> None:
        """Probe the camera every period until `stop_watch` (GigE Vision devices only)."""
        if not self.is_gv or self._watch is not None:
            return
        self._stop_watch.clear()
        self._watch = threading.Thread(
            target=self._watch_loop, args=(self.device,), name="aravis-liveness", daemon=True
        )
        self._watch.start()

    def stop_watch(self) -> None:
        self._stop_watch.set()
        watch, self._watch = self._watch, None
        if watch is not None and not self.lost.event.is_set():
            watch.join(timeout=1.0)

    def _watch_loop(self, device: Aravis.Device) -> None:
        while not self._stop_watch.wait(self._probe_period_s):
            try:
                privilege = device.read_register(_CCP_REGISTER)
            except GLib.Error as exc:
                self.lost.set(f"no answer to a register read ({_one_line(exc.message)})")
                return
            if not int(privilege) & 0x3:
                self.lost.set("this host no longer controls the camera (it restarted?)")
                return

    def detach_stream(self) -> tuple[Aravis.Stream | None, dict[str, int]]:
        """Take the stream out of the session, with its final counters."""
        stream, self.stream = self.stream, None
        return stream, _stream_counters(stream)

    def release(self) -> None:
        """Give up control of a live camera, then drop the stream and the camera.

        Control is left explicitly: Aravis would leave it when the device is finalized, but
        a Python reference kept elsewhere (an exception's traceback holds the frames that
        used the camera) would delay that for as long as the reference lives.
        """
        self.stop_watch()
        if self.is_gv and not self.lost.event.is_set() and self.device is not None:
            with contextlib.suppress(GLib.Error):
                self.device.leave_control()
        with contextlib.suppress(Exception):
            self.device.disconnect(self._handler)
        self.stream = None
        self.device = None
        self.camera = None


def _stream_counters(stream: Aravis.Stream | None) -> dict[str, int]:
    if stream is None:
        return {}
    counters: dict[str, int] = {}
    for index in range(stream.get_n_infos()):
        name = stream.get_info_name(index)
        if name in _STREAM_COUNTERS:
            counters[_STREAM_COUNTERS[name]] = int(stream.get_info_uint64(index))
    return counters


def _release_in_background(session: _Session, stream: list[Aravis.Stream | None]) -> None:
    stream.clear()
    session.release()


def _read_features(url: str, camera: Aravis.Camera) -> _Features:
    def available(name: str) -> bool:
        return bool(_call(url, f"look up {name}", camera.is_feature_available, name))

    def entries(name: str) -> tuple[str, ...]:
        if not available(name):
            return ()
        return tuple(_call(url, f"list {name}", camera.dup_available_enumerations_as_strings, name))

    width, height = _call(url, "read the sensor size", camera.get_sensor_size)
    return _Features(
        sensor=(int(width), int(height)),
        pixel_formats=tuple(
            _call(url, "list pixel formats", camera.dup_available_pixel_formats_as_strings)
        ),
        has_gain_db=available("Gain"),
        has_gain_raw=available("GainRaw"),
        has_exposure_auto=available("ExposureAuto"),
        has_gain_auto=available("GainAuto"),
        has_frame_rate=bool(_call(url, "look up the frame rate", camera.is_frame_rate_available)),
        has_frame_rate_enable=available("AcquisitionFrameRateEnable"),
        has_frame_count=available("AcquisitionFrameCount"),
        has_acquisition_mode=available("AcquisitionMode"),
        has_trigger_activation=available("TriggerActivation"),
        trigger_selectors=entries("TriggerSelector"),
        trigger_sources=entries("TriggerSource"),
    )


def _round_down(value: int, minimum: int, increment: int) -> int:
    increment = max(1, increment)
    return minimum + max(0, (value - minimum) // increment) * increment


def _frame_id_step(last: int, new: int) -> int:
    """Exposures from block id `last` to `new`: GVSP 1.x ids run 1..65535, then wrap to 1."""
    if new > last:
        return new - last
    if last - new > 0x7FFF and last <= 0xFFFF:
        return new + 0xFFFF - last
    return 1


class _Reconnector:
    """Opens a new session after a loss, with backoff, on its own thread.

    `connect` opens, restores and arms a session (it raises HardwareError on failure).
    The first attempt starts `min_s` after the loss; the pause after a failed attempt doubles
    up to `max_s`. `ready` is set when `session` holds the new connection. `cancel` stops
    further attempts and hands over a session already opened (None otherwise); one opened
    after the cancel is released at once.
    """

    def __init__(
        self,
        connect: Callable[[], _Session],
        *,
        min_s: float,
        max_s: float,
        on_attempt: Callable[[], None],
    ) -> None:
        self._connect = connect
        self._min_s = min_s
        self._max_s = max_s
        self._on_attempt = on_attempt
        self._lock = threading.Lock()
        self._cancelled = threading.Event()
        self.ready = threading.Event()
        self.session: _Session | None = None
        self.attempts = 0
        self.last_error = ""
        self.next_attempt_s = time.monotonic() + min_s
        self._thread = threading.Thread(target=self._run, name="aravis-reconnect", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        pause = self._min_s
        while not self._cancelled.wait(max(0.0, self.next_attempt_s - time.monotonic())):
            self.attempts += 1
            self._on_attempt()
            try:
                session = self._connect()
            except HardwareError as exc:
                self.last_error = str(exc)
                pause = min(self._max_s, pause * 2.0)
                self.next_attempt_s = time.monotonic() + pause
                continue
            with self._lock:
                if not self._cancelled.is_set():
                    self.session = session
                    self.ready.set()
                    return
            session.release()
            return

    def cancel(self) -> _Session | None:
        with self._lock:
            self._cancelled.set()
            return self.session


class AravisCamera:
    """A GigE Vision camera through Aravis (see the module docstring for URL and behaviour).

    Args:
        url: ``aravis://ADDRESS[?options]``; other keyword arguments are ignored.

    Raises HardwareConfigError (at construction) for a bad URL.
    """

    def __init__(self, url: str, **_: Any) -> None:
        self.url = url
        self._address, self.options = parse_aravis_url(url)
        self._lock = threading.Lock()
        self._session: _Session | None = None
        self._opened = False
        self._settings: CameraSettings | None = None
        self._trigger = TriggerInfo(mode=TriggerMode.SOFTWARE)
        self._armed = False
        self._reconnector: _Reconnector | None = None
        self._retiring: list[threading.Thread] = []
        self._delivered = 0
        self._stopped_after_count = False
        self._frame_id = -1
        self._last_device_id: int | None = None
        self._counts: collections.Counter[str] = collections.Counter()
        self._retired_stream_counts: collections.Counter[str] = collections.Counter()

    @property
    def address(self) -> str:
        """The camera's address (or device id) from the URL."""
        return self._address

    @property
    def sensor_size(self) -> tuple[int, int]:
        """Sensor (width, height), px. Raises HardwareConfigError when not open."""
        return self._require_session().features.sensor

    @property
    def settings(self) -> CameraSettings | None:
        """The settings in force; None while the camera's own pixel format is not one of ours."""
        return self._settings

    @_short_traceback
    def frame_rate_bounds(self) -> tuple[float, float]:
        """The camera's frame rate range for INTERNAL triggering now, frames/s."""
        session = self._require_session()
        low, high = _call(
            self.url, "read the frame rate bounds", session.camera.get_frame_rate_bounds
        )
        return float(low), float(high)

    @_short_traceback
    def feature_value(self, name: str) -> str:
        """The current value of a GenICam feature, as text (for diagnostics and tests).

        Raises HardwareConfigError for a feature the camera does not have.
        """
        session = self._require_session()
        camera = session.camera
        if not _call(self.url, f"look up {name}", camera.is_feature_available, name):
            raise HardwareConfigError(f"{self.url}: the camera has no feature {name}")
        node = _call(self.url, f"look up {name}", session.device.get_feature, name)
        return str(_call(self.url, f"read {name}", node.get_value_as_string))

    @_short_traceback
    def open(self, timeout_s: float = 5.0) -> None:
        """Connect to the camera and take control of it. Raises HardwareConnectError.

        Returns within `timeout_s`: an Aravis open of an absent camera takes about 2.5 s;
        one that outlasts the timeout finishes in the background and is released.
        """
        if self._session is not None:
            return
        self._session = self._open_within(timeout_s)
        self._opened = True
        if self._settings is None:
            self._settings = self._read_settings(self._session)

    def close(self) -> None:
        """Disarm and release the camera; safe to call twice.

        Waits (up to 10 s in all) for lost connections still being torn down in the
        background, so their Aravis threads end before the caller's process does.
        """
        self.disarm()
        session = self._session
        if session is not None:
            self._retire(session)
        deadline = time.monotonic() + 10.0
        for thread in self._retiring:
            thread.join(timeout=max(0.0, deadline - time.monotonic()))
        self._retiring = [thread for thread in self._retiring if thread.is_alive()]
        self._opened = False

    @_short_traceback
    def configure(self, settings: CameraSettings) -> CameraSettings:
        """Apply `settings`; returns the settings in force (region rounded to increments).

        Raises HardwareConfigError for a setting the camera cannot take, or when armed;
        HardwareConnectError when the camera cannot be reached.
        """
        if self._armed:
            raise HardwareConfigError(f"{self.url}: cannot configure while armed")
        session = self._require_session()
        self._settings = self._apply_settings(session, settings)
        if self._trigger.exposure_us is not None:
            self._trigger = dataclasses.replace(self._trigger, exposure_us=None)
        return self._settings

    @_short_traceback
    def prepare(self, trigger: TriggerInfo) -> None:
        """Set up the next acquisition (see the module docstring). Raises HardwareConfigError."""
        if self._armed:
            raise HardwareConfigError(f"{self.url}: cannot prepare while armed")
        session = self._require_session()
        self._apply_trigger(session, trigger)
        self._trigger = trigger
        if trigger.exposure_us is not None and self._settings is not None:
            exposure = self._apply_exposure(session, trigger.exposure_us)
            self._settings = dataclasses.replace(self._settings, exposure_us=exposure)

    @_short_traceback
    def set_exposure(self, exposure_us: float) -> float:
        """Write the exposure, armed or not (GenICam cameras take ExposureTime while
        acquiring); returns the exposure read back, us. Raises HardwareConfigError outside the
        camera's bounds, HardwareConnectError when it cannot be reached."""
        if self._settings is None:
            raise HardwareConfigError(f"{self.url}: configure before set_exposure")
        session = self._require_session()
        exposure = self._apply_exposure(session, exposure_us)
        self._settings = dataclasses.replace(self._settings, exposure_us=exposure)
        if self._trigger.exposure_us is not None:
            self._trigger = dataclasses.replace(self._trigger, exposure_us=None)
        return exposure

    @_short_traceback
    def arm(self) -> None:
        """Create the stream with its buffer pool and start acquiring as prepared.

        Raises HardwareConfigError when not open, or when the camera's pixel format is not
        one the appliance accepts (configure first); HardwareConnectError when the camera
        cannot be reached.
        """
        if self._armed:
            return
        if not self._opened:
            raise HardwareConfigError(f"{self.url}: arm before open")
        if self._settings is None:
            raise HardwareConfigError(
                f"{self.url}: configure before arm (the camera's pixel format is not one of "
                f"{', '.join(f.value for f in PixelFormat)})"
            )
        session = self._require_session()
        self._apply_trigger(session, self._trigger)
        self._start_stream(session)
        self._armed = True
        self._delivered = 0
        self._stopped_after_count = False
        self._last_device_id = None

    @_short_traceback
    def disarm(self) -> None:
        """Stop acquiring and drop the stream; frames not fetched yet are discarded."""
        reconnector, self._reconnector = self._reconnector, None
        if reconnector is not None:
            adopted = reconnector.cancel()
            if adopted is not None:
                with self._lock:
                    self._session = adopted
        self._armed = False
        session = self._session
        if session is None:
            return
        if session.lost.event.is_set():
            self._retire(session)
            return
        session.stop_watch()
        if session.stream is not None:
            with contextlib.suppress(GLib.Error):
                session.camera.stop_acquisition()
        with self._lock:
            stream, counters = session.detach_stream()
            self._retired_stream_counts.update(counters)
        del stream

    @_short_traceback
    def trigger(self) -> None:
        """Software trigger (SOFTWARE mode, armed). Raises HardwareConfigError otherwise,
        HardwareConnectError while the camera is away."""
        if self._trigger.mode is not TriggerMode.SOFTWARE:
            raise HardwareConfigError(
                f"{self.url}: software trigger in {self._trigger.mode.value} mode"
            )
        if not self._armed:
            raise HardwareConfigError(f"{self.url}: software trigger while not armed")
        session = self._session
        if self._reconnector is not None or session is None or session.lost.event.is_set():
            raise HardwareConnectError(f"{self.url}: software trigger while the camera is away")
        _call(self.url, "software trigger", session.camera.software_trigger)

    @_short_traceback
    def fetch(self, timeout_s: float) -> Frame:
        """Next complete frame. Returns within `timeout_s` (plus a few ms) in every case; a
        frame already waiting when the time is up (this thread was held up) is still taken.

        Raises HardwareTimeout when none arrives in time (or all `frames` were delivered),
        HardwareConnectError while the camera is lost or reconnecting (see the module
        docstring), HardwareFault when a buffer does not match the settings in force,
        HardwareConfigError when not armed.
        """
        if not self._armed:
            raise HardwareConfigError(f"{self.url}: fetch while not armed")
        deadline = time.monotonic() + max(0.0, timeout_s)
        if self._reconnector is not None:
            self._await_reconnect(deadline)
        frames = self._trigger.frames
        if frames and self._delivered >= frames:
            self._stop_after_count()
            raise HardwareTimeout(f"{self.url}: all {frames} frames delivered")
        session = self._session
        assert session is not None and session.stream is not None
        stream = session.stream
        while True:
            if session.lost.event.is_set():
                del stream
                error = self._begin_reconnect(session)
                del session
                raise error
            remaining = deadline - time.monotonic()
            if remaining > 0:
                buffer = stream.timeout_pop_buffer(max(1, int(min(remaining, POLL_S) * 1e6)))
            else:
                buffer = stream.try_pop_buffer()
                if buffer is None:
                    del stream
                    raise HardwareTimeout(f"{self.url}: no frame within {timeout_s:g} s")
            if buffer is None:
                continue
            with _lease(stream, buffer):
                frame = self._frame_from(buffer)
            if frame is not None:
                self._delivered += 1
                self._counts["frames_delivered"] += 1
                return frame

    def statistics(self) -> dict[str, Any]:
        """Counters since construction, as honest as Aravis allows.

        Backend counts: ``frames_delivered``; ``frames_lost`` (block-id gaps plus incomplete
        buffers: exactly the gaps `Frame.frame_id` shows); ``incomplete_buffers`` (by Aravis
        buffer status in ``incomplete_by_status``, e.g. ``missing-packets``, ``timeout``);
        ``connection_losses``, ``reconnect_attempts``, ``reconnects``.

        Aravis' stream counts, summed over every stream this object armed (the stream of a
        lost connection counts up to its loss): ``completed_buffers``, ``failures``,
        ``underruns`` (a frame arrived with no free buffer in the pool), ``timeouts``,
        ``aborted``, ``missing_frames``, ``size_mismatch_errors``, ``received_packets``,
        ``missing_packets``, ``error_packets``, ``ignored_packets``, ``resend_requests``,
        ``resent_packets``, ``duplicated_packets``, ``transferred_bytes``. Aravis counts
        ``missing_packets`` each time it notices a packet missing, so it may exceed the
        packets actually lost.

        States: ``connected`` (a live session), ``armed``, ``reconnecting``.
        """
        with self._lock:
            session = self._session
            stream_counts = collections.Counter(self._retired_stream_counts)
            if session is not None:
                stream_counts.update(_stream_counters(session.stream))
            counts = collections.Counter(self._counts)
        figures: dict[str, Any] = {name: counts[name] for name in _BACKEND_COUNTERS}
        figures["incomplete_by_status"] = {
            key.removeprefix("status:"): value
            for key, value in counts.items()
            if key.startswith("status:")
        }
        figures.update({name: stream_counts[name] for name in _STREAM_COUNTERS.values()})
        figures["connected"] = session is not None and not session.lost.event.is_set()
        figures["armed"] = self._armed
        figures["reconnecting"] = self._reconnector is not None
        return figures

    def _require_session(self) -> _Session:
        """The live session; reopens (within 5 s) one lost while not armed."""
        if not self._opened:
            raise HardwareConfigError(f"{self.url}: the camera is not open")
        session = self._session
        if session is not None and not session.lost.event.is_set():
            return session
        if session is not None:
            self._retire(session)
        session = self._open_within(5.0)
        self._restore(session, arm=False)
        self._session = session
        return session

    def _open_within(self, timeout_s: float) -> _Session:
        lock = threading.Lock()
        outcome: dict[str, Any] = {}
        done = threading.Event()

        def attempt() -> None:
            try:
                session = self._open_session()
            except HardwareError as exc:
                outcome["error"] = exc
                done.set()
                return
            with lock:
                if outcome.get("abandoned"):
                    session.release()
                else:
                    outcome["session"] = session
                done.set()

        threading.Thread(target=attempt, name="aravis-open", daemon=True).start()
        done.wait(max(0.0, timeout_s))
        with lock:
            if not done.is_set():
                outcome["abandoned"] = True
                raise HardwareConnectError(f"{self.url}: no answer within {timeout_s:g} s")
        if "error" in outcome:
            raise outcome["error"]
        return outcome["session"]

    def _open_session(self) -> _Session:
        try:
            camera = Aravis.Camera.new(self._address)
        except GLib.Error as exc:
            raise HardwareConnectError(
                f"{self.url}: cannot open the camera: {_one_line(exc.message)}"
            ) from None
        session = _Session(self.url, camera, self.options.liveness_ms / 1000.0)
        if session.is_gv and not session.device.is_controller():
            session.lost.set("another application controls the camera")
            thread = threading.Thread(target=session.release, name="aravis-retire", daemon=True)
            thread.start()
            self._retiring.append(thread)
            raise HardwareConnectError(
                f"{self.url}: another application controls the camera (GVCP control refused)"
            )
        packet_size = self.options.packet_size
        if session.is_gv and packet_size == "auto":
            _call(self.url, "negotiate the packet size", camera.gv_auto_packet_size)
        elif session.is_gv and packet_size is not None:
            _call(
                self.url, f"set packet_size={packet_size}", camera.gv_set_packet_size, packet_size
            )
        return session

    def _restore(self, session: _Session, *, arm: bool) -> None:
        """Bring a new connection to the state of the last one: settings, trigger, stream."""
        try:
            if self._settings is not None:
                self._apply_settings(session, self._settings)
            self._apply_trigger(session, self._trigger)
            if self._trigger.exposure_us is not None:
                self._apply_exposure(session, self._trigger.exposure_us)
            if arm:
                self._start_stream(session)
        except HardwareError:
            session.release()
            raise

    def _read_settings(self, session: _Session) -> CameraSettings | None:
        camera = session.camera
        name = _call(self.url, "read PixelFormat", camera.get_pixel_format_as_string)
        if name not in {f.value for f in PixelFormat}:
            return None
        x, y, width, height = _call(self.url, "read the region", camera.get_region)
        exposure = _call(self.url, "read the exposure", camera.get_exposure_time)
        gain = 0.0
        if session.features.has_gain_db:
            gain = max(0.0, float(_call(self.url, "read Gain", camera.get_float, "Gain")))
        return CameraSettings(
            exposure_us=float(exposure),
            gain_db=gain,
            region=Region(int(x), int(y), int(width), int(height)),
            pixel_format=PixelFormat(name),
        )

    def _apply_settings(self, session: _Session, settings: CameraSettings) -> CameraSettings:
        camera, features = session.camera, session.features
        name = settings.pixel_format.value
        if name not in features.pixel_formats:
            offered = ", ".join(features.pixel_formats) or "none"
            raise HardwareConfigError(
                f"{self.url}: pixel format {name} is not offered by the camera "
                f"(it offers {offered})"
            )
        _call(self.url, f"set PixelFormat={name}", camera.set_pixel_format_from_string, name)
        region = self._apply_region(session, settings.region)
        exposure = self._apply_exposure(session, settings.exposure_us)
        gain = self._apply_gain(session, settings.gain_db)
        return CameraSettings(
            exposure_us=exposure, gain_db=gain, region=region, pixel_format=settings.pixel_format
        )

    def _apply_region(self, session: _Session, wanted: Region | None) -> Region:
        camera = session.camera
        sensor_width, sensor_height = session.features.sensor
        region = wanted or Region(0, 0, sensor_width, sensor_height)
        if region.x + region.width > sensor_width or region.y + region.height > sensor_height:
            raise HardwareConfigError(
                f"{self.url}: region {region} exceeds the {sensor_width}x{sensor_height} sensor"
            )
        width_min, _ = _call(self.url, "read the Width bounds", camera.get_width_bounds)
        height_min, _ = _call(self.url, "read the Height bounds", camera.get_height_bounds)
        if region.width < width_min or region.height < height_min:
            raise HardwareConfigError(
                f"{self.url}: region {region} is smaller than the camera's minimum "
                f"{width_min}x{height_min}"
            )
        width = _round_down(region.width, width_min, camera.get_width_increment())
        height = _round_down(region.height, height_min, camera.get_height_increment())
        x, y = region.x, region.y
        if camera.is_region_offset_available():
            x = _round_down(x, 0, camera.get_x_offset_increment())
            y = _round_down(y, 0, camera.get_y_offset_increment())
        elif x or y:
            raise HardwareConfigError(f"{self.url}: the camera has no region offset ({region})")
        _call(self.url, f"set the region to {region}", camera.set_region, x, y, width, height)
        x, y, width, height = _call(self.url, "read the region", camera.get_region)
        return Region(int(x), int(y), int(width), int(height))

    def _apply_exposure(self, session: _Session, exposure_us: float) -> float:
        camera = session.camera
        low, high = _call(self.url, "read the exposure bounds", camera.get_exposure_time_bounds)
        if not low <= exposure_us <= high:
            raise HardwareConfigError(
                f"{self.url}: exposure_us={exposure_us:g} outside the camera's {low:g}..{high:g} us"
            )
        if session.features.has_exposure_auto:
            _call(self.url, "set ExposureAuto=Off", camera.set_exposure_time_auto, Aravis.Auto.OFF)
        _call(self.url, f"set exposure {exposure_us:g} us", camera.set_exposure_time, exposure_us)
        return float(_call(self.url, "read the exposure", camera.get_exposure_time))

    def _apply_gain(self, session: _Session, gain_db: float) -> float:
        camera, features = session.camera, session.features
        if features.has_gain_db:
            if features.has_gain_auto:
                _call(self.url, "set GainAuto=Off", camera.set_gain_auto, Aravis.Auto.OFF)
            low, high = _call(self.url, "read the Gain bounds", camera.get_float_bounds, "Gain")
            if not low <= gain_db <= high:
                raise HardwareConfigError(
                    f"{self.url}: gain_db={gain_db:g} outside the camera's {low:g}..{high:g} dB"
                )
            _call(self.url, f"set Gain={gain_db:g} dB", camera.set_float, "Gain", gain_db)
            return max(0.0, float(_call(self.url, "read Gain", camera.get_float, "Gain")))
        if gain_db != 0:
            only_raw = " (only GainRaw, in vendor units: see the URL option gain_raw)"
            raise HardwareConfigError(
                f"{self.url}: gain_db={gain_db:g} refused: the camera has no Gain in dB"
                f"{only_raw if features.has_gain_raw else ''}"
            )
        if features.has_gain_raw:
            low, high = _call(
                self.url, "read the GainRaw bounds", camera.get_integer_bounds, "GainRaw"
            )
            raw = low if self.options.gain_raw is None else self.options.gain_raw
            if not low <= raw <= high:
                raise HardwareConfigError(
                    f"{self.url}: option gain_raw={raw} outside the camera's {low}..{high}"
                )
            _call(self.url, f"set GainRaw={raw}", camera.set_integer, "GainRaw", raw)
        return 0.0

    def _trigger_source(self, session: _Session, mode: TriggerMode) -> str:
        features = session.features
        if "FrameStart" not in features.trigger_selectors:
            raise HardwareConfigError(
                f"{self.url}: {mode.value} triggering needs TriggerSelector FrameStart, which "
                f"the camera does not offer"
            )
        source = "Software" if mode is TriggerMode.SOFTWARE else self.options.trigger_line
        if source not in features.trigger_sources:
            offered = ", ".join(features.trigger_sources) or "none"
            raise HardwareConfigError(
                f"{self.url}: trigger source {source} is not offered by the camera "
                f"(it offers {offered})"
            )
        return source

    def _apply_trigger(self, session: _Session, trigger: TriggerInfo) -> None:
        camera, features = session.camera, session.features
        rate = float(trigger.rate_hz or 0.0)
        if trigger.mode is TriggerMode.INTERNAL:
            self._check_frame_rate(session, rate)
            source = ""
        else:
            source = self._trigger_source(session, trigger.mode)
        if features.trigger_selectors:
            _call(self.url, "switch the triggers off", camera.clear_triggers)
        if trigger.mode is TriggerMode.INTERNAL:
            if features.has_frame_rate_enable:
                _call(
                    self.url,
                    "set AcquisitionFrameRateEnable",
                    camera.set_boolean,
                    "AcquisitionFrameRateEnable",
                    True,
                )
            _call(self.url, f"set the frame rate to {rate:g}/s", camera.set_frame_rate, rate)
        else:
            for feature, value in (
                ("TriggerSelector", "FrameStart"),
                ("TriggerMode", "On"),
                ("TriggerSource", source),
            ):
                _call(self.url, f"set {feature}={value}", camera.set_string, feature, value)
            if trigger.mode is TriggerMode.EXTERNAL and features.has_trigger_activation:
                _call(
                    self.url,
                    "set TriggerActivation=RisingEdge",
                    camera.set_string,
                    "TriggerActivation",
                    "RisingEdge",
                )
        if features.has_acquisition_mode:
            counted = trigger.frames > 0 and features.has_frame_count
            modes = Aravis.AcquisitionMode
            mode = modes.MULTI_FRAME if counted else modes.CONTINUOUS
            _call(self.url, "set AcquisitionMode", camera.set_acquisition_mode, mode)
            if counted:
                _call(self.url, "set AcquisitionFrameCount", camera.set_frame_count, trigger.frames)

    def _check_frame_rate(self, session: _Session, rate_hz: float) -> None:
        if not session.features.has_frame_rate:
            raise HardwareConfigError(f"{self.url}: the camera has no frame rate control")
        low, high = _call(
            self.url, "read the frame rate bounds", session.camera.get_frame_rate_bounds
        )
        if not low <= rate_hz <= high:
            raise HardwareConfigError(
                f"{self.url}: rate_hz={rate_hz:g} outside the camera's {low:g}..{high:g} frames/s"
            )

    def _start_stream(self, session: _Session) -> None:
        camera = session.camera
        stream = _call(self.url, "create the stream", camera.create_stream, None, None)
        if stream is None:
            raise HardwareFault(f"{self.url}: Aravis created no stream")
        if session.is_gv:
            self._apply_stream_options(stream)
        payload = int(_call(self.url, "read the payload size", camera.get_payload))
        for _ in range(self.options.buffers):
            stream.push_buffer(Aravis.Buffer.new_allocate(payload))
        session.stream = stream
        _call(self.url, "start the acquisition", camera.start_acquisition)
        session.start_watch()

    def _apply_stream_options(self, stream: Aravis.Stream) -> None:
        options = self.options
        if options.packet_timeout_ms is not None:
            stream.set_property("packet-timeout", int(options.packet_timeout_ms * 1000))
        if options.frame_retention_ms is not None:
            stream.set_property("frame-retention", int(options.frame_retention_ms * 1000))
        if options.packet_resend is not None:
            resend = Aravis.GvStreamPacketResend
            value = resend.ALWAYS if options.packet_resend == "always" else resend.NEVER
            stream.set_property("packet-resend", value)

    def _frame_from(self, buffer: Aravis.Buffer) -> Frame | None:
        """The frame a buffer holds (pixels copied), or None for an incomplete one (counted)."""
        device_id = int(buffer.get_frame_id())
        status = buffer.get_status()
        if status != Aravis.BufferStatus.SUCCESS:
            self._counts["incomplete_buffers"] += 1
            self._counts[f"status:{status.value_nick}"] += 1
        if device_id or status == Aravis.BufferStatus.SUCCESS:
            step = (
                1
                if self._last_device_id is None
                else _frame_id_step(self._last_device_id, device_id)
            )
            self._last_device_id = device_id
            self._frame_id += step
            self._counts["frames_lost"] += step - 1
        if status != Aravis.BufferStatus.SUCCESS:
            self._counts["frames_lost"] += 1
            return None
        settings = self._settings
        assert settings is not None and settings.region is not None
        region, fmt = settings.region, settings.pixel_format
        width, height = int(buffer.get_image_width()), int(buffer.get_image_height())
        if (width, height) != (region.width, region.height):
            raise HardwareFault(
                f"{self.url}: frame {device_id} is {width}x{height}, the region in force is "
                f"{region.width}x{region.height}"
            )
        dtype = _DTYPES[fmt]
        row_bytes = width * dtype.itemsize
        stride = row_bytes + int(buffer.get_image_padding()[0])
        data = np.frombuffer(buffer.get_image_data(), dtype=np.uint8)
        if data.size < stride * (height - 1) + row_bytes:
            raise HardwareFault(
                f"{self.url}: frame {device_id} holds {data.size} bytes, {width}x{height} "
                f"{fmt.value} needs {row_bytes * height}"
            )
        rows = np.lib.stride_tricks.as_strided(
            data, shape=(height, row_bytes), strides=(stride, 1), writeable=False
        )
        image = np.array(rows.view(dtype), dtype=dtype.newbyteorder("="))
        return Frame(
            image=image,
            frame_id=self._frame_id,
            timestamp_ns=int(buffer.get_timestamp()),
            exposure_us=settings.exposure_us,
            metadata={
                "device_frame_id": device_id,
                "system_timestamp_ns": int(buffer.get_system_timestamp()),
            },
        )

    def _stop_after_count(self) -> None:
        session = self._session
        if self._stopped_after_count or session is None:
            return
        self._stopped_after_count = True
        if not session.features.has_frame_count:
            with contextlib.suppress(GLib.Error):
                session.camera.stop_acquisition()

    def _begin_reconnect(self, session: _Session) -> HardwareConnectError:
        """The session is lost: retire it and start reconnecting; the error `fetch` raises."""
        self._counts["connection_losses"] += 1
        self._retire(session)
        self._reconnector = _Reconnector(
            self._reconnect_once,
            min_s=self.options.reconnect_min_ms / 1000.0,
            max_s=self.options.reconnect_max_ms / 1000.0,
            on_attempt=self._count_attempt,
        )
        return HardwareConnectError(f"{self.url}: camera lost: {session.lost.reason}; reconnecting")

    def _count_attempt(self) -> None:
        with self._lock:
            self._counts["reconnect_attempts"] += 1

    def _reconnect_once(self) -> _Session:
        session = self._open_session()
        self._restore(session, arm=True)
        return session

    def _await_reconnect(self, deadline: float) -> None:
        reconnector = self._reconnector
        assert reconnector is not None
        if reconnector.ready.wait(max(0.0, deadline - time.monotonic())):
            with self._lock:
                self._session = reconnector.session
                self._counts["reconnects"] += 1
            self._reconnector = None
            self._last_device_id = None
            return
        detail = f"; last: {reconnector.last_error}" if reconnector.last_error else ""
        next_s = max(0.0, reconnector.next_attempt_s - time.monotonic())
        raise HardwareConnectError(
            f"{self.url}: camera away, reconnecting ({reconnector.attempts} attempt(s) so far"
            f"{detail}; next in {next_s:.1f} s)"
        )

    def _retire(self, session: _Session) -> None:
        """Drop a session: fold in its stream counters and release it (a lost one, whose
        Aravis teardown waits for timeouts, in the background)."""
        alive = not session.lost.event.is_set()
        if alive and session.stream is not None:
            session.stop_watch()
            with contextlib.suppress(GLib.Error):
                session.camera.stop_acquisition()
        with self._lock:
            if self._session is session:
                self._session = None
            stream, counters = session.detach_stream()
            self._retired_stream_counts.update(counters)
        if alive:
            del stream
            session.release()
            return
        thread = threading.Thread(
            target=_release_in_background,
            args=(session, [stream]),
            name="aravis-retire",
            daemon=True,
        )
        del stream
        thread.start()
        self._retiring = [t for t in self._retiring if t.is_alive()] + [thread]
