"""A GigE Vision camera that films a speckled specimen under uniaxial stretch, with a truth log.

Run as a program::

    python -m tests.system.gv_specimen_camera --address 127.0.0.2 --serial SPEC01 \\
        --width 512 --height 512 --strain-rate 0.01 --max-strain 0.1 --hold-s 0 \\
        --seed 7 --truth truth.jsonl

It serves an in-process ``Aravis.GvFakeCamera`` whose frames it draws
(``appliance.sim.gige_camera.DrawnGigECamera``) on ADDRESS (which must be an address of an
interface: add it to ``lo`` inside the test's namespace) and prints one line
``READY ADDRESS SERIAL WIDTHxHEIGHT`` on stdout once it answers GVCP. It runs until SIGTERM
or SIGINT, then restores the fake's own fill pattern, deletes the camera explicitly and exits
with status 0. Any client opens it by address (``aravis://127.0.0.2``) and drives it like the
fake camera it is (Width/Height/Offset, PixelFormat Mono8 or Mono16, AcquisitionFrameRate,
software trigger); ``tests.system.aravis_peers.specimen_camera`` starts and stops it.

The scene (``appliance.sim.stretched_speckle.StretchedSpecimen``): a speckle coat
(``appliance.dic.synthetic.dense_speckle``, speckle radius 2.5 px, rendered analytically once
at twice the resolution) on a WIDTH x HEIGHT sensor. At device
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

The mapping to received frames is exact (``appliance.sim.gige_camera``): Aravis' fake camera
sets the buffer's frame id and timestamp before it asks for the pixels, and sends both in the
GVSP leader, so a frame received through ``hal.camera.aravis.AravisCamera`` has
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
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time
from pathlib import Path
from typing import IO, Any

import numpy as np

from appliance.sim.gige_camera import MONO8, MONO16, DrawnGigECamera, FrameRequest
from appliance.sim.stretched_speckle import StretchedSpecimen


class SpecimenFill:
    """Draws each frame at the strain of its device time and logs the truth before it is sent
    (the `draw` of `appliance.sim.gige_camera.DrawnGigECamera`)."""

    def __init__(
        self,
        specimen: StretchedSpecimen,
        truth: IO[str],
        *,
        strain_rate_per_s: float,
        max_strain: float,
        hold_s: float,
    ) -> None:
        self._specimen = specimen
        self._truth = truth
        self._rate = strain_rate_per_s
        self._max = max_strain
        self._hold_s = hold_s
        self._t0_ns: int | None = None
        self.wire: TriggerWire | None = None

    def strain_at(self, timestamp_ns: int) -> float:
        """e(t) of the module docstring; the first call fixes t0."""
        if self._t0_ns is None:
            self._t0_ns = timestamp_ns
        elapsed_s = (timestamp_ns - self._t0_ns) * 1e-9
        return min(self._max, self._rate * max(0.0, elapsed_s - self._hold_s))

    def __call__(self, request: FrameRequest) -> np.ndarray | None:
        if request.pixel_format not in (MONO8, MONO16):
            return None
        strain = self.strain_at(request.timestamp_ns)
        region = [request.x, request.y, request.width, request.height]
        grey = np.clip(np.rint(self._specimen.render(*region, strain)), 0, 255)
        if request.pixel_format == MONO8:
            pixels = np.ascontiguousarray(grey, dtype=np.uint8)
            name = "Mono8"
        else:
            pixels = np.ascontiguousarray(grey * 257, dtype="<u2")
            name = "Mono16"
        record = {
            "frame_id": request.frame_id,
            "timestamp_ns": request.timestamp_ns,
            "strain": strain,
            "region": region,
            "pixel_format": name,
            "trigger_edge": self.wire.take() if self.wire is not None else None,
        }
        self._truth.write(json.dumps(record) + "\n")
        self._truth.flush()
        return pixels


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


def main(argv: list[str] | None = None) -> int:
    """Serve the specimen camera until SIGTERM/SIGINT; 0 on a clean stop, 2 if it cannot serve."""
    arguments = _arguments(argv)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())

    specimen = StretchedSpecimen(arguments.width, arguments.height, arguments.seed)
    specimen.render(0, 0, arguments.width, arguments.height, 0.0)
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
            specimen,
            truth,
            strain_rate_per_s=arguments.strain_rate,
            max_strain=arguments.max_strain,
            hold_s=arguments.hold_s,
        )
        camera = DrawnGigECamera(
            arguments.address, arguments.serial, arguments.width, arguments.height, fill
        )
        try:
            camera.start()
        except RuntimeError as exc:
            print(str(exc), file=sys.stderr)
            return 2
        if arguments.trigger_wire is not None:
            fill.wire = TriggerWire(
                camera.fake_camera,
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
        camera.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
