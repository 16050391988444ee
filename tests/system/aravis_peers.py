"""Real GigE Vision peers for the camera tests: Aravis' fake camera and the specimen camera.

Both serve GVCP/GVSP on a loopback address inside the test's network namespace:

* `FakeGvCamera` runs ``arv-fake-gv-camera-0.8 -i ADDRESS -s SERIAL`` (Aravis' own fake: a
  diagonal ramp image, GainRaw, software and Line0 triggers) as a subprocess that a test can
  kill and start again, to take the camera away and bring it back.
* `specimen_camera` runs ``python -m tests.system.gv_specimen_camera`` (see that module): a
  GigE Vision camera whose images are a rendered speckle specimen under uniaxial stretch, with
  a truth log; `SpecimenTruth` reads the log and gives the true strain of a received frame.

Network discipline: nothing here broadcasts. Cameras are opened by IP address only, and the
peers are skipped (`needs_gige`) unless the tests run in a network namespace whose only
interface is loopback (``unshare --net``, as ``.ci/test`` does). Addresses other than
127.0.0.1 are added to that namespace's loopback (`ensure_loopback_address`); Aravis' fake
camera needs its address to belong to an interface.

Every process started here is ended by the context manager or method that started it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import select
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import pytest

from appliance.bench.camera import gvcp_port_bound

FAKE_GV_CAMERA = shutil.which("arv-fake-gv-camera-0.8")
IP = shutil.which("ip")
GVCP_PORT = 3956
REPO_ROOT = Path(__file__).resolve().parents[2]


def _aravis_importable() -> bool:
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis  # noqa: F401
    except (ImportError, ValueError):
        return False
    return True


def isolated_network() -> bool:
    """True inside a network namespace whose only interface is loopback."""
    return [name for _, name in socket.if_nameindex()] == ["lo"]


def _gige_skip_reason() -> str | None:
    if not _aravis_importable():
        return "Aravis 0.8 through PyGObject is not installed (gir1.2-aravis-0.8, pygobject)"
    if FAKE_GV_CAMERA is None:
        return "arv-fake-gv-camera-0.8 is not installed (apt-get install aravis-tools)"
    if not isolated_network():
        return "GigE Vision tests run only in a loopback-only network namespace (unshare --net)"
    return None


GIGE_SKIP_REASON = _gige_skip_reason()
needs_gige = pytest.mark.skipif(GIGE_SKIP_REASON is not None, reason=GIGE_SKIP_REASON or "")


def ensure_loopback_address(address: str) -> None:
    """Make `address` (in 127.0.0.0/8) an address of `lo`; only in an isolated namespace."""
    if address == "127.0.0.1":
        return
    if not isolated_network() or IP is None:
        raise RuntimeError(f"cannot add {address} to lo outside a loopback-only namespace")
    shown = subprocess.run(
        [IP, "-o", "-4", "addr", "show", "dev", "lo"], capture_output=True, text=True, check=True
    ).stdout
    if f"inet {address}/" in shown:
        return
    subprocess.run(
        [IP, "addr", "add", f"{address}/8", "dev", "lo"], capture_output=True, text=True, check=True
    )


def _wait_for(condition: Any, timeout_s: float, what: str, process: subprocess.Popen) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if process.poll() is not None:
            raise RuntimeError(f"{what}: the process exited with status {process.returncode}")
        if time.monotonic() > deadline:
            raise RuntimeError(f"{what}: not ready within {timeout_s:g} s")
        time.sleep(0.02)


def _end(process: subprocess.Popen, *, timeout_s: float = 10.0) -> int:
    """SIGTERM, then SIGKILL if it does not exit; the exit status."""
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=timeout_s)
    return process.returncode


class FakeGvCamera:
    """Aravis' fake GigE Vision camera as a subprocess on a loopback address.

    Args:
        address: where it serves GVCP (added to `lo` when not 127.0.0.1).
        serial: its serial number.
        lost_per_thousand: GVSP packets it drops on purpose (its ``-r`` option), or None.
    """

    def __init__(
        self, address: str = "127.0.0.1", serial: str = "GV01", lost_per_thousand: int | None = None
    ) -> None:
        self.address = address
        self.serial = serial
        self.lost_per_thousand = lost_per_thousand
        self.process: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        """The camera's URL for `hal.camera.aravis.AravisCamera` (no options)."""
        return f"aravis://{self.address}"

    def start(self, timeout_s: float = 10.0) -> None:
        """Start the camera and wait until it holds its GVCP port."""
        assert FAKE_GV_CAMERA is not None and self.process is None
        ensure_loopback_address(self.address)
        command = [FAKE_GV_CAMERA, "-i", self.address, "-s", self.serial]
        if self.lost_per_thousand is not None:
            command += ["-r", str(self.lost_per_thousand)]
        self.process = subprocess.Popen(
            command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        _wait_for(
            lambda: gvcp_port_bound(self.address),
            timeout_s,
            f"arv-fake-gv-camera on {self.address}",
            self.process,
        )

    def kill(self) -> None:
        """Take the camera away at once (SIGKILL): no goodbye on the wire."""
        process, self.process = self.process, None
        if process is not None:
            process.kill()
            process.wait(timeout=10)

    def stop(self) -> None:
        """End the camera (SIGTERM, then SIGKILL)."""
        process, self.process = self.process, None
        if process is not None:
            _end(process)

    def __enter__(self) -> FakeGvCamera:
        self.start()
        return self

    def __exit__(self, *_: Any) -> None:
        self.stop()


@dataclasses.dataclass(frozen=True)
class TruthRecord:
    """One frame the specimen camera rendered (a line of its truth log).

    Attributes:
        frame_id: the GVSP block id the frame was sent with (`Frame.metadata["device_frame_id"]`).
        timestamp_ns: its device timestamp (exactly `Frame.timestamp_ns` as Aravis delivers it).
        strain: true engineering strain of the specimen in this frame (along y, about the centre).
        region: (x, y, width, height) of the sensor region rendered.
        pixel_format: name of the pixel format rendered (Mono8 or Mono16).
        trigger_edge: with a trigger wire, the number of the firmware pulse (rising edge of
            the edge log, from 1) the frame answers; None without.
    """

    frame_id: int
    timestamp_ns: int
    strain: float
    region: tuple[int, int, int, int]
    pixel_format: str
    trigger_edge: int | None = None


class SpecimenTruth:
    """The specimen camera's truth log: the header and one record per rendered frame.

    The log is read when constructed; `reload` reads what was appended since. The header
    (`header`) holds the camera's parameters: ``width``, ``height``, ``centre_y`` (the row
    about which the stretch acts), ``strain_rate_per_s``, ``max_strain``, ``hold_s``,
    ``seed`` and ``mapping`` (the deformation as text).
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.header: dict[str, Any] = {}
        self._by_timestamp: dict[int, TruthRecord] = {}
        self._by_frame_id: dict[int, TruthRecord] = {}
        self.reload()

    def reload(self) -> None:
        """Read the log again (the camera appends a line before it sends each frame)."""
        header: dict[str, Any] = {}
        by_timestamp: dict[int, TruthRecord] = {}
        by_frame_id: dict[int, TruthRecord] = {}
        with self.path.open(encoding="utf-8") as lines:
            for line in lines:
                if not line.endswith("\n"):
                    break
                entry = json.loads(line)
                if entry.get("kind") == "header":
                    header = entry
                    continue
                record = TruthRecord(
                    frame_id=int(entry["frame_id"]),
                    timestamp_ns=int(entry["timestamp_ns"]),
                    strain=float(entry["strain"]),
                    region=tuple(entry["region"]),
                    pixel_format=str(entry["pixel_format"]),
                    trigger_edge=entry.get("trigger_edge"),
                )
                by_timestamp[record.timestamp_ns] = record
                by_frame_id[record.frame_id] = record
        self.header, self._by_timestamp, self._by_frame_id = header, by_timestamp, by_frame_id

    def __len__(self) -> int:
        return len(self._by_timestamp)

    def record(self, timestamp_ns: int | None = None, frame_id: int | None = None) -> TruthRecord:
        """The record of a frame by its device timestamp (exact, preferred) or its GVSP block
        id (16 bits: ambiguous once the log spans more than 65535 frames; the latest wins).

        Raises KeyError when the log has no such frame (call `reload` first for new frames).
        """
        if timestamp_ns is not None:
            return self._by_timestamp[int(timestamp_ns)]
        if frame_id is not None:
            return self._by_frame_id[int(frame_id)]
        raise KeyError("give timestamp_ns or frame_id")

    def record_of(self, frame: Any) -> TruthRecord:
        """The record of a received `hal.camera.base.Frame`: by its device timestamp
        (``metadata["device_timestamp_ns"]`` when the measurement loop re-based the frame's
        time, else ``timestamp_ns``); reloads the log once when the frame is newer."""
        metadata: Mapping[str, Any] = frame.metadata
        timestamp_ns = int(metadata.get("device_timestamp_ns", frame.timestamp_ns))
        try:
            return self.record(timestamp_ns=timestamp_ns)
        except KeyError:
            self.reload()
            return self.record(timestamp_ns=timestamp_ns)

    def strain_of(self, frame: Any) -> float:
        """True engineering strain of the specimen in a received frame."""
        return self.record_of(frame).strain

    def strain_between(self, reference: Any, frame: Any) -> float:
        """True engineering strain of `frame` relative to `reference`, as an extensometer
        zeroed on the reference would read it: (1 + e) / (1 + e_ref) - 1."""
        return (1.0 + self.strain_of(frame)) / (1.0 + self.strain_of(reference)) - 1.0


def true_strain(truth_path: Path, frame: Any) -> float:
    """True engineering strain of a received frame, read from the truth log at `truth_path`."""
    return SpecimenTruth(truth_path).strain_of(frame)


@dataclasses.dataclass
class SpecimenCamera:
    """A running specimen camera (see `specimen_camera`)."""

    address: str
    serial: str
    width: int
    height: int
    truth_path: Path
    process: subprocess.Popen

    @property
    def url(self) -> str:
        """Its URL for `hal.camera.aravis.AravisCamera` (no options)."""
        return f"aravis://{self.address}"

    def truth(self) -> SpecimenTruth:
        """The truth log as written so far."""
        return SpecimenTruth(self.truth_path)


@contextlib.contextmanager
def specimen_camera(
    truth_path: Path,
    *,
    address: str = "127.0.0.2",
    serial: str = "SPEC01",
    width: int = 512,
    height: int = 512,
    strain_rate_per_s: float = 0.01,
    max_strain: float = 0.1,
    hold_s: float = 0.0,
    seed: int = 7,
    trigger_wire: Path | None = None,
    miss_every: int = 0,
    first_delay_s: float = 0.0,
    niceness: int = 0,
    timeout_s: float = 60.0,
) -> Iterator[SpecimenCamera]:
    """Run the specimen camera program until the block ends (then SIGTERM; it must exit 0).

    Args:
        truth_path: where the camera writes its truth log (JSON lines).
        address: loopback address it serves on (added to `lo` if needed).
        serial: its serial number.
        width, height: sensor and default region size, px.
        strain_rate_per_s: engineering strain per second once stretching.
        max_strain: strain at which the stretch stops growing.
        hold_s: seconds at zero strain after the first frame before stretching starts.
        seed: seed of the speckle pattern.
        trigger_wire: a firmware edge log whose trigger pulses trigger the camera (see
            `tests.system.gv_specimen_camera`); None = no wire.
        miss_every: the wire drops every Nth pulse (0 = none).
        first_delay_s: the wire passes the first pulse this late, s.
        niceness: added to the program's nice value (leaves CPU to an emulated device).
        timeout_s: how long to wait for its READY line.
    """
    ensure_loopback_address(address)
    command = [
        sys.executable,
        "-m",
        "tests.system.gv_specimen_camera",
        "--address",
        address,
        "--serial",
        serial,
        "--width",
        str(width),
        "--height",
        str(height),
        "--strain-rate",
        repr(float(strain_rate_per_s)),
        "--max-strain",
        repr(float(max_strain)),
        "--hold-s",
        repr(float(hold_s)),
        "--seed",
        str(seed),
        "--truth",
        str(truth_path),
        *(["--trigger-wire", str(trigger_wire)] if trigger_wire is not None else []),
        *(["--miss-every", str(miss_every)] if miss_every else []),
        *(["--first-delay-s", repr(float(first_delay_s))] if first_delay_s else []),
    ]
    environment = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    process = subprocess.Popen(
        command,
        stdout=subprocess.PIPE,
        text=True,
        cwd=REPO_ROOT,
        env=environment,
        preexec_fn=(lambda: os.nice(niceness)) if niceness else None,
    )
    try:
        _read_ready(process, timeout_s)
        yield SpecimenCamera(address, serial, width, height, Path(truth_path), process)
    finally:
        status = _end(process)
        if process.stdout is not None:
            process.stdout.close()
    if status != 0:
        raise RuntimeError(f"the specimen camera exited with status {status}")


def _read_ready(process: subprocess.Popen, timeout_s: float) -> str:
    assert process.stdout is not None
    deadline = time.monotonic() + timeout_s
    while True:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise RuntimeError(f"the specimen camera did not say READY within {timeout_s:g} s")
        readable, _, _ = select.select([process.stdout], [], [], remaining)
        if not readable:
            continue
        line = process.stdout.readline()
        if not line:
            raise RuntimeError(f"the specimen camera exited ({process.wait(timeout=10)})")
        if line.startswith("READY"):
            return line.strip()
