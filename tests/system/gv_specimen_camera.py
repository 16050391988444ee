"""A GigE Vision camera that films a speckled specimen under uniaxial stretch, with a truth log.

Run as a program::

    python -m tests.system.gv_specimen_camera --address 127.0.0.2 --serial SPEC01 \\
        --width 512 --height 512 --strain-rate 0.01 --max-strain 0.1 --hold-s 0 \\
        --seed 7 --truth truth.jsonl

It serves an in-process ``Aravis.GvFakeCamera`` on ADDRESS (which must be an address of an
interface: add it to ``lo`` inside the test's namespace) and prints one line
``READY ADDRESS SERIAL WIDTHxHEIGHT`` on stdout once it answers GVCP. It runs until SIGTERM
or SIGINT, then restores the fake's own fill pattern, deletes the camera explicitly and exits
with status 0. Any client opens it by address (``aravis://127.0.0.2``) and drives it like the
fake camera it is (Width/Height/Offset, PixelFormat Mono8 or Mono16, AcquisitionFrameRate,
software trigger); ``tests.system.aravis_peers.specimen_camera`` starts and stops it.

The scene: a speckle coat (``appliance.dic.synthetic.dense_speckle``, speckle radius 2.5 px,
rendered analytically once at twice the resolution) on a WIDTH x HEIGHT sensor. At device
time t the specimen is stretched along the image's vertical axis about the centre row
``cy = (HEIGHT - 1) / 2``: the material point at reference row Y is seen at row
``cy + (Y - cy) * (1 + e(t))``, columns unchanged, with the engineering strain

    e(t) = min(max_strain, strain_rate * max(0, (t - t0) - hold_s)),

t0 being the device time of the first frame the camera renders. Each frame samples the coat
at the inverse-mapped positions (OpenCV bicubic remap; point samples, no noise, no blur) and
is quantised to Mono8 or Mono16 (the 8-bit grey value times 257).

The truth log (JSON lines, flushed line by line): a header ``{"kind": "header", ...}`` with
the parameters, then one record per rendered frame, written before the frame is sent::

    {"frame_id": 65401, "timestamp_ns": ..., "strain": ..., "region": [x, y, w, h],
     "pixel_format": "Mono8", "trigger_edge": null}

(``trigger_edge``: with a trigger wire, the number of the firmware pulse the frame answers.)

The mapping to received frames is exact: Aravis' fake camera sets the buffer's frame id and
timestamp before it calls the fill pattern (the callback reads them through
``arv_buffer_get_frame_id`` and ``arv_buffer_get_timestamp``), and sends both in the GVSP
leader, so a frame received through ``hal.camera.aravis.AravisCamera`` has
``timestamp_ns`` equal to the record's ``timestamp_ns`` (device time: the fake's real-time
clock, microsecond resolution) and ``metadata["device_frame_id"]`` equal to its
``frame_id`` (16 bits, wrapping after 65535 to 1; the timestamp is the unambiguous key).

Trigger wire (``--trigger-wire EDGE_LOG``): Aravis' fake camera has no line input; in trigger
mode it sends a frame only when its software trigger register is set (it looks every
millisecond: its trigger frequency is set to 1 kHz). The wire follows the edge log of the
trigger firmware under simavr (``firmware_bridge.simulator``; one line per pin change, written
as it happens) and sets that register at every rising edge of the trigger output PB1, so the
camera exposes on the firmware's pulses as a camera on a trigger cable would (a pulse while
the last one is not taken yet is lost, as a busy camera ignores one). The client selects
``TriggerSource = Software`` as the camera's trigger line (``aravis://...?trigger_line=Software``
with EXTERNAL triggering) and never sends a software trigger itself. The latency from edge to
exposure (the log, this process's polling, the camera's millisecond) is a few ms; frames keep
their device timestamps, so the truth log stays exact.

Why ctypes: setting the fill pattern through PyGObject with a Python callback crashes, so
``arv_fake_camera_set_fill_pattern`` is called through ctypes on the GvFakeCamera's
underlying ArvFakeCamera, with a ctypes callback kept referenced for the camera's life. The
callback uses the region's width * height (the buffer's data size is not set when the fill
pattern runs).
"""

from __future__ import annotations

import argparse
import ctypes
import json
import signal
import sys
import threading
import time
from pathlib import Path
from typing import IO, Any

import cv2
import numpy as np

OVERSAMPLE = 2
SPECKLE_RADIUS_PX = 2.5
SPECKLE_DENSITY = 0.25
"""Speckles per square pixel at camera scale (`dense_speckle`'s default)."""

MONO8 = 0x01080001
MONO16 = 0x01100007
"""GenICam PFNC codes of the pixel formats the camera renders."""

FillPattern = ctypes.CFUNCTYPE(
    None, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint32, ctypes.c_uint32
)
"""ArvFakeCameraFillPattern: (buffer, user data, exposure_us, gain, pixel format)."""


class StretchedSpecimen:
    """The speckle coat and the stretch: renders the sensor region at a given strain.

    Args:
        width, height: sensor size, px.
        seed: seed of the speckle pattern.
    """

    def __init__(self, width: int, height: int, seed: int) -> None:
        from appliance.dic import synthetic

        fine_width, fine_height = OVERSAMPLE * width, OVERSAMPLE * height
        pattern = synthetic.dense_speckle(
            fine_width,
            fine_height,
            seed=seed,
            radius=OVERSAMPLE * SPECKLE_RADIUS_PX,
            density=SPECKLE_DENSITY / OVERSAMPLE**2,
        )
        self.coat = synthetic.render(pattern, fine_height, fine_width).astype(np.float32)
        self.width = width
        self.height = height
        self.centre_y = (height - 1) / 2.0

    def render(self, x: int, y: int, width: int, height: int, strain: float) -> np.ndarray:
        """Grey values (8-bit scale, float32) of the region at `strain`.

        Sensor pixel (X, Y) shows reference point (X, cy + (Y - cy) / (1 + strain)); a camera
        pixel centre c lies at OVERSAMPLE * c + (OVERSAMPLE - 1) / 2 on the fine coat.
        """
        half = (OVERSAMPLE - 1) / 2.0
        columns = OVERSAMPLE * np.arange(x, x + width, dtype=np.float32) + half
        rows = np.arange(y, y + height, dtype=np.float64)
        reference_rows = self.centre_y + (rows - self.centre_y) / (1.0 + strain)
        fine_rows = (OVERSAMPLE * reference_rows + half).astype(np.float32)
        map_x = np.broadcast_to(columns[None, :], (height, width))
        map_y = np.broadcast_to(fine_rows[:, None], (height, width))
        return cv2.remap(
            self.coat,
            np.ascontiguousarray(map_x),
            np.ascontiguousarray(map_y),
            cv2.INTER_CUBIC,
            borderMode=cv2.BORDER_REFLECT,
        )


def _aravis_library() -> ctypes.CDLL:
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


class SpecimenFill:
    """The fill pattern: renders each frame at the strain of its device time, logs the truth."""

    def __init__(
        self,
        library: ctypes.CDLL,
        specimen: StretchedSpecimen,
        truth: IO[str],
        *,
        strain_rate_per_s: float,
        max_strain: float,
        hold_s: float,
    ) -> None:
        self._library = library
        self._specimen = specimen
        self._truth = truth
        self._rate = strain_rate_per_s
        self._max = max_strain
        self._hold_s = hold_s
        self._t0_ns: int | None = None
        self.wire: TriggerWire | None = None
        self.callback = FillPattern(self._fill)

    def strain_at(self, timestamp_ns: int) -> float:
        """e(t) of the module docstring; the first call fixes t0."""
        if self._t0_ns is None:
            self._t0_ns = timestamp_ns
        elapsed_s = (timestamp_ns - self._t0_ns) * 1e-9
        return min(self._max, self._rate * max(0.0, elapsed_s - self._hold_s))

    def _fill(self, buffer: int, _data: int, _exposure: int, _gain: int, pixel_format: int) -> None:
        if pixel_format not in (MONO8, MONO16):
            return
        library = self._library
        width = library.arv_buffer_get_image_width(buffer)
        height = library.arv_buffer_get_image_height(buffer)
        x, y = library.arv_buffer_get_image_x(buffer), library.arv_buffer_get_image_y(buffer)
        frame_id = int(library.arv_buffer_get_frame_id(buffer))
        timestamp_ns = int(library.arv_buffer_get_timestamp(buffer))
        strain = self.strain_at(timestamp_ns)
        grey = np.clip(np.rint(self._specimen.render(x, y, width, height, strain)), 0, 255)
        if pixel_format == MONO8:
            pixels = np.ascontiguousarray(grey, dtype=np.uint8)
            name = "Mono8"
        else:
            pixels = np.ascontiguousarray(grey * 257, dtype="<u2")
            name = "Mono16"
        size = ctypes.c_size_t(0)
        destination = library.arv_buffer_get_data(buffer, ctypes.byref(size))
        record = {
            "frame_id": frame_id,
            "timestamp_ns": timestamp_ns,
            "strain": strain,
            "region": [x, y, width, height],
            "pixel_format": name,
            "trigger_edge": self.wire.take() if self.wire is not None else None,
        }
        self._truth.write(json.dumps(record) + "\n")
        self._truth.flush()
        ctypes.memmove(destination, pixels.ctypes.data, pixels.nbytes)


TRIGGER_SOFTWARE_REGISTER = 0x30C
"""The fake camera's TriggerSoftware command register (ARV_FAKE_CAMERA_REGISTER_TRIGGER_
SOFTWARE in arvfakecamera.h)."""


class TriggerWire:
    """Presses the fake camera's trigger at every rising edge of PB1 in a firmware edge log.

    Each press is numbered (1 = the first rising edge of the log, i.e. the firmware's
    TRIGGER sequence number when it was armed once) and queued; the fill pattern `take`s the
    queue when it renders a frame: the frame answers the earliest press, later ones were lost
    while the camera was busy. With `miss_every` = N, every Nth pulse is not passed on (a
    camera that misses pulses, for the host's re-synchronisation). With `first_delay_s`, the
    first pulse is passed on that late (a camera slow to take its first trigger, so the
    host's first frame sets too late a latency baseline).
    """

    def __init__(
        self,
        fake_camera: Any,
        edge_log: Path,
        stop: threading.Event,
        miss_every: int = 0,
        first_delay_s: float = 0.0,
    ) -> None:
        self.fake_camera = fake_camera
        self.edge_log = edge_log
        self.stop = stop
        self.miss_every = miss_every
        self.first_delay_s = first_delay_s
        self.pressed = 0
        self._pending: list[int] = []
        self._lock = threading.Lock()
        self.thread = threading.Thread(target=self._follow, name="trigger-wire", daemon=True)

    def take(self) -> int | None:
        """The number of the earliest press not answered yet (None: none); clears them all."""
        with self._lock:
            pending, self._pending = self._pending, []
        return pending[0] if pending else None

    def start(self) -> None:
        self.fake_camera.set_trigger_frequency(1000.0)
        self.thread.start()

    def _follow(self) -> None:
        while not self.edge_log.exists():
            if self.stop.wait(0.01):
                return
        with self.edge_log.open(encoding="ascii", errors="replace") as log:
            pending = ""
            while not self.stop.is_set():
                chunk = log.readline()
                if not chunk:
                    time.sleep(0.001)
                    continue
                pending += chunk
                if not pending.endswith("\n"):
                    continue
                fields, pending = pending.split(), ""
                if len(fields) >= 3 and fields[1] == "PB1" and fields[2] == "1":
                    self.pressed += 1
                    if self.miss_every and self.pressed % self.miss_every == 0:
                        continue
                    if (
                        self.pressed == 1
                        and self.first_delay_s > 0
                        and self.stop.wait(self.first_delay_s)
                    ):
                        return
                    with self._lock:
                        self._pending.append(self.pressed)
                    self.fake_camera.write_register(TRIGGER_SOFTWARE_REGISTER, 1)


def _arguments(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m tests.system.gv_specimen_camera",
        description="GigE Vision camera filming a stretched speckle specimen (see the module).",
    )
    parser.add_argument("--address", default="127.0.0.2", help="loopback address to serve on")
    parser.add_argument("--serial", default="SPEC01", help="serial number")
    parser.add_argument("--width", type=int, default=512, help="sensor width, px")
    parser.add_argument("--height", type=int, default=512, help="sensor height, px")
    parser.add_argument(
        "--strain-rate", type=float, default=0.01, help="engineering strain per second"
    )
    parser.add_argument("--max-strain", type=float, default=0.1, help="strain cap")
    parser.add_argument(
        "--hold-s", type=float, default=0.0, help="seconds at zero strain after the first frame"
    )
    parser.add_argument("--seed", type=int, default=7, help="seed of the speckle pattern")
    parser.add_argument("--truth", type=Path, required=True, help="truth log (JSON lines)")
    parser.add_argument(
        "--trigger-wire", type=Path, help="firmware edge log whose PB1 pulses trigger the camera"
    )
    parser.add_argument(
        "--miss-every", type=int, default=0, help="the wire drops every Nth pulse (0 = none)"
    )
    parser.add_argument(
        "--first-delay-s", type=float, default=0.0, help="the wire passes the first pulse late"
    )
    arguments = parser.parse_args(argv)
    if arguments.width < 16 or arguments.height < 16:
        parser.error("--width and --height must be >= 16")
    if arguments.strain_rate < 0 or arguments.max_strain < 0 or arguments.hold_s < 0:
        parser.error("--strain-rate, --max-strain and --hold-s must be >= 0")
    return arguments


def _fake_camera_pointer(fake_camera: Any) -> int:
    """The C address of a PyGObject-wrapped GObject (its ``__gpointer__`` capsule)."""
    get_pointer = ctypes.pythonapi.PyCapsule_GetPointer
    get_pointer.restype = ctypes.c_void_p
    get_pointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
    return int(get_pointer(fake_camera.__gpointer__, None))


def main(argv: list[str] | None = None) -> int:
    """Serve the specimen camera until SIGTERM/SIGINT; 0 on a clean stop, 2 if it cannot serve."""
    arguments = _arguments(argv)
    import gi

    gi.require_version("Aravis", "0.8")
    from gi.repository import Aravis

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())

    specimen = StretchedSpecimen(arguments.width, arguments.height, arguments.seed)
    specimen.render(0, 0, arguments.width, arguments.height, 0.0)
    library = _aravis_library()
    with arguments.truth.open("w", encoding="utf-8") as truth:
        header = {
            "kind": "header",
            "address": arguments.address,
            "serial": arguments.serial,
            "width": arguments.width,
            "height": arguments.height,
            "centre_y": specimen.centre_y,
            "strain_rate_per_s": arguments.strain_rate,
            "max_strain": arguments.max_strain,
            "hold_s": arguments.hold_s,
            "seed": arguments.seed,
            "mapping": "row = centre_y + (reference_row - centre_y) * (1 + strain); columns fixed",
            "time_origin": "device timestamp of the first rendered frame",
        }
        truth.write(json.dumps(header) + "\n")
        truth.flush()
        fill = SpecimenFill(
            library,
            specimen,
            truth,
            strain_rate_per_s=arguments.strain_rate,
            max_strain=arguments.max_strain,
            hold_s=arguments.hold_s,
        )
        gv_camera = Aravis.GvFakeCamera.new(arguments.address, arguments.serial)
        if not gv_camera.is_running():
            print(
                f"cannot serve on {arguments.address} (not an interface address?)", file=sys.stderr
            )
            del gv_camera
            return 2
        fake_camera = gv_camera.get_fake_camera()
        for register, value in (
            (Aravis.FAKE_CAMERA_REGISTER_SENSOR_WIDTH, arguments.width),
            (Aravis.FAKE_CAMERA_REGISTER_SENSOR_HEIGHT, arguments.height),
            (Aravis.FAKE_CAMERA_REGISTER_WIDTH, arguments.width),
            (Aravis.FAKE_CAMERA_REGISTER_HEIGHT, arguments.height),
        ):
            fake_camera.write_register(register, value)
        pointer = _fake_camera_pointer(fake_camera)
        library.arv_fake_camera_set_fill_pattern(pointer, fill.callback, None)
        if arguments.trigger_wire is not None:
            fill.wire = TriggerWire(
                fake_camera,
                arguments.trigger_wire,
                stop,
                miss_every=arguments.miss_every,
                first_delay_s=arguments.first_delay_s,
            )
            fill.wire.start()
        print(
            f"READY {arguments.address} {arguments.serial} {arguments.width}x{arguments.height}",
            flush=True,
        )
        while not stop.wait(0.2):
            pass
        library.arv_fake_camera_set_fill_pattern(pointer, ctypes.cast(None, FillPattern), None)
        del fake_camera
        del gv_camera
    return 0


if __name__ == "__main__":
    sys.exit(main())
