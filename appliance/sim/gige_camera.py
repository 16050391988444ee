"""A GigE Vision camera on a loopback address whose frames this program draws.

`DrawnGigECamera` serves Aravis' fake GigE Vision camera (``Aravis.GvFakeCamera``) in this
process: it answers GVCP and sends GVSP on ADDRESS like any camera, and a client opens it by
that address (``aravis://127.0.0.1``) and drives it like Aravis' fake camera it is
(Width/Height/Offset, PixelFormat Mono8 or Mono16, AcquisitionFrameRate, software trigger).
Only the pixels are this program's: for every frame the camera sends, it calls `draw` with a
`FrameRequest` (the region, the frame id and the device timestamp the frame is sent with) and
copies the array `draw` returns into the frame.

The mapping to received frames is exact: the fake camera sets the buffer's frame id and
timestamp before it calls its fill pattern, and sends both in the GVSP leader, so a frame
received through ``hal.camera.aravis.AravisCamera`` has ``timestamp_ns`` equal to the
request's ``timestamp_ns`` (device time: the fake's real-time clock, microsecond resolution)
and ``metadata["device_frame_id"]`` equal to its ``frame_id`` (16 bits, wrapping after 65535
to 1).

The fake paces its frames itself: it sleeps to the next multiple of its frame period
(``AcquisitionFrameRate``, at most 1000 frames/s) on its own clock, then draws and sends. A
frame whose drawing and sending outlast the period skips the next multiple: the camera then
sends slower than asked, without a gap in its frame ids.

Why ctypes: setting the fill pattern through PyGObject with a Python callback crashes, so
``arv_fake_camera_set_fill_pattern`` is called through ctypes on the GvFakeCamera's
underlying ArvFakeCamera, with a ctypes callback kept referenced for the camera's life. The
callback uses the region's width * height (the buffer's data size is not set when the fill
pattern runs). ADDRESS must be an address of an interface (127.0.0.1, or one added to ``lo``
in a loopback-only network namespace). Aravis 0.8 through PyGObject is imported when the
camera starts, not with this module.
"""

from __future__ import annotations

import ctypes
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

MONO8 = 0x01080001
MONO16 = 0x01100007
"""GenICam PFNC codes of the pixel formats a drawn camera sends."""

FillPattern = ctypes.CFUNCTYPE(
    None, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint32, ctypes.c_uint32
)
"""ArvFakeCameraFillPattern: (buffer, user data, exposure_us, gain, pixel format)."""


def aravis_library() -> ctypes.CDLL:
    """libaravis-0.8 with the signatures of the buffer getters and the fill-pattern setter."""
    library = ctypes.CDLL("libaravis-0.8.so.0")
    getters = {
        "arv_buffer_get_image_width": ctypes.c_int,
        "arv_buffer_get_image_height": ctypes.c_int,
        "arv_buffer_get_image_x": ctypes.c_int,
        "arv_buffer_get_image_y": ctypes.c_int,
        "arv_buffer_get_frame_id": ctypes.c_uint64,
        "arv_buffer_get_timestamp": ctypes.c_uint64,
    }
    for name, result in getters.items():
        function = getattr(library, name)
        function.argtypes = [ctypes.c_void_p]
        function.restype = result
    library.arv_buffer_get_data.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_size_t)]
    library.arv_buffer_get_data.restype = ctypes.c_void_p
    library.arv_fake_camera_set_fill_pattern.argtypes = [
        ctypes.c_void_p,
        FillPattern,
        ctypes.c_void_p,
    ]
    library.arv_fake_camera_set_fill_pattern.restype = None
    return library


def fake_camera_pointer(fake_camera: Any) -> int:
    """The C address of a PyGObject-wrapped GObject (its ``__gpointer__`` capsule)."""
    get_pointer = ctypes.pythonapi.PyCapsule_GetPointer
    get_pointer.restype = ctypes.c_void_p
    get_pointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
    return int(get_pointer(fake_camera.__gpointer__, None))


@dataclass(frozen=True)
class FrameRequest:
    """The frame the camera is about to send.

    Attributes:
        frame_id: its GVSP block id (16 bits, 1 ... 65535).
        timestamp_ns: its device timestamp, ns.
        x, y, width, height: the sensor region, px.
        pixel_format: its PFNC code (`MONO8`, `MONO16`, or another the client chose).
    """

    frame_id: int
    timestamp_ns: int
    x: int
    y: int
    width: int
    height: int
    pixel_format: int


Draw = Callable[[FrameRequest], "np.ndarray | None"]
"""Returns the frame's pixels (height x width, uint8 for Mono8, little-endian uint16 for
Mono16), or None to leave the buffer as it is (a pixel format it does not draw)."""


class DrawnGigECamera:
    """Aravis' fake GigE Vision camera serving frames drawn by `draw`; see the module.

    Args:
        address: the interface address it serves GVCP on.
        serial: its serial number.
        width, height: its sensor size and default region, px.
        draw: called on the camera's sending thread for every frame; must be fast next to
            the frame period (the camera sends slower otherwise) and must not raise.
    """

    def __init__(self, address: str, serial: str, width: int, height: int, draw: Draw) -> None:
        self.address = address
        self.serial = serial
        self.width = width
        self.height = height
        self._draw = draw
        self._library: ctypes.CDLL | None = None
        self._callback = FillPattern(self._fill)
        self._gv_camera: Any = None
        self._pointer: int | None = None
        self.fake_camera: Any = None
        """The underlying ``Aravis.FakeCamera`` while serving (registers, trigger frequency)."""

    def start(self) -> None:
        """Serve on `address`.

        Raises:
            RuntimeError: the camera cannot serve there (not an interface address, or the
                GVCP port taken).
        """
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis

        self._library = aravis_library()
        gv_camera = Aravis.GvFakeCamera.new(self.address, self.serial)
        if not gv_camera.is_running():
            del gv_camera
            raise RuntimeError(f"cannot serve on {self.address} (not an interface address?)")
        fake_camera = gv_camera.get_fake_camera()
        for register, value in (
            (Aravis.FAKE_CAMERA_REGISTER_SENSOR_WIDTH, self.width),
            (Aravis.FAKE_CAMERA_REGISTER_SENSOR_HEIGHT, self.height),
            (Aravis.FAKE_CAMERA_REGISTER_WIDTH, self.width),
            (Aravis.FAKE_CAMERA_REGISTER_HEIGHT, self.height),
        ):
            fake_camera.write_register(register, value)
        self._pointer = fake_camera_pointer(fake_camera)
        self._library.arv_fake_camera_set_fill_pattern(self._pointer, self._callback, None)
        self._gv_camera, self.fake_camera = gv_camera, fake_camera

    def stop(self) -> None:
        """Restore the fake's own fill pattern and delete the camera explicitly; idempotent."""
        if self._gv_camera is None:
            return
        assert self._library is not None
        self._library.arv_fake_camera_set_fill_pattern(
            self._pointer, ctypes.cast(None, FillPattern), None
        )
        self.fake_camera = None
        self._gv_camera = None
        self._pointer = None

    def __enter__(self) -> DrawnGigECamera:
        self.start()
        return self

    def __exit__(self, *_: Any) -> None:
        self.stop()

    def _fill(self, buffer: int, _data: int, _exposure: int, _gain: int, pixel_format: int) -> None:
        library = self._library
        assert library is not None
        request = FrameRequest(
            frame_id=int(library.arv_buffer_get_frame_id(buffer)),
            timestamp_ns=int(library.arv_buffer_get_timestamp(buffer)),
            x=library.arv_buffer_get_image_x(buffer),
            y=library.arv_buffer_get_image_y(buffer),
            width=library.arv_buffer_get_image_width(buffer),
            height=library.arv_buffer_get_image_height(buffer),
            pixel_format=int(pixel_format),
        )
        pixels = self._draw(request)
        if pixels is None:
            return
        pixels = np.ascontiguousarray(pixels)
        size = ctypes.c_size_t(0)
        destination = library.arv_buffer_get_data(buffer, ctypes.byref(size))
        ctypes.memmove(destination, pixels.ctypes.data, pixels.nbytes)
