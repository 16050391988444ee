"""Acquisition benchmark of the Aravis (GigE Vision) camera backend: frames/s and losses.

`extensometer bench camera [--out FILE] [--json]` acquires, through
`hal.camera.aravis.AravisCamera`, 512x512 Mono8 frames free-running at the camera's highest
frame rate, once per exposure (100, 1000 and 3000 us), and reports per run:

* **fps**: frames delivered by `fetch` per second of wall time over the measured frames (the
  target: >= 150 frames/s without loss);
* **device_fps**: the same from the frames' device timestamps (the rate the camera sent at;
  ``fps`` above it means frames queued in the buffer pool were drained);
* **lost_frames** (gaps in `Frame.frame_id` plus incomplete buffers, from the backend's
  statistics), **failures**, **underruns**, **missing_packets**, **resend_requests** and
  **resent_packets** (Aravis' stream counters) over the measured frames;
* **interval_ms**: p50/p99/max of the host time between consecutive `fetch` returns, and
  **device_interval_ms**: the same from the frames' device timestamps;
* **transport_ms**: Aravis' host reception time minus the device timestamp, p50/p99. Only
  meaningful when the camera's clock is the host's real-time clock, as it is for Aravis' fake
  camera; for a real camera the two clocks differ by an arbitrary offset.

With no URL it starts ``arv-fake-gv-camera-0.8 -i 127.0.0.1`` itself (and stops it) and
opens ``aravis://127.0.0.1``; run it inside a loopback-only network namespace
(``unshare --net sh -c 'ip link set lo up && ...'``), as the tests do. A warm-up of 10
frames per run is not counted. The fake camera's frame rate does not depend on exposure
(it only scales the pattern), so differences between the runs are the host's.

What it does not measure: a real camera's sensor readout or a real network (loopback has
no packet loss and a 64 KiB MTU; the fake sends 1400-byte packets by default), the
measurement loop downstream of `fetch`.
"""

from __future__ import annotations

import contextlib
import errno
import os
import platform
import shutil
import socket
import subprocess
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from appliance.bench.peer_process import percentiles_ms

EXPOSURES_US = (100.0, 1000.0, 3000.0)
WIDTH = HEIGHT = 512
TARGET_FPS = 150.0
WARMUP_FRAMES = 10
FETCH_TIMEOUT_S = 2.0
FAKE_ADDRESS = "127.0.0.1"
_GVCP_PORT = 3956


def gvcp_port_bound(address: str) -> bool:
    """True when something holds UDP ADDRESS:3956 (a camera serving GVCP); sends nothing."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.bind((address, _GVCP_PORT))
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                return True
            raise
    return False


@contextlib.contextmanager
def _fake_camera(timeout_s: float = 10.0) -> Iterator[str]:
    """Aravis' fake GigE Vision camera on 127.0.0.1 for the block; its URL."""
    program = shutil.which("arv-fake-gv-camera-0.8")
    if program is None:
        raise RuntimeError("arv-fake-gv-camera-0.8 is not installed (apt-get install aravis-tools)")
    if gvcp_port_bound(FAKE_ADDRESS):
        raise RuntimeError(f"something already serves GVCP on {FAKE_ADDRESS}:{_GVCP_PORT}")
    process = subprocess.Popen(
        [program, "-i", FAKE_ADDRESS, "-s", "GV01"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + timeout_s
        while not gvcp_port_bound(FAKE_ADDRESS):
            if process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("arv-fake-gv-camera-0.8 did not start")
            time.sleep(0.02)
        yield f"aravis://{FAKE_ADDRESS}"
    finally:
        process.terminate()
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=10)


def _difference(after: Mapping[str, Any], before: Mapping[str, Any], key: str) -> int:
    return int(after[key]) - int(before[key])


def _measure_run(camera: Any, exposure_us: float, frames: int) -> dict[str, Any]:
    from hal.camera.base import CameraSettings, PixelFormat, Region, TriggerInfo, TriggerMode

    applied = camera.configure(
        CameraSettings(
            exposure_us=exposure_us,
            region=Region(0, 0, WIDTH, HEIGHT),
            pixel_format=PixelFormat.MONO8,
        )
    )
    _, highest = camera.frame_rate_bounds()
    camera.prepare(TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=highest))
    camera.arm()
    try:
        for _ in range(WARMUP_FRAMES):
            camera.fetch(FETCH_TIMEOUT_S)
        before = camera.statistics()
        returned_s, ids, device_ns, system_ns = [], [], [], []
        for _ in range(frames):
            frame = camera.fetch(FETCH_TIMEOUT_S)
            returned_s.append(time.perf_counter())
            ids.append(frame.frame_id)
            device_ns.append(frame.timestamp_ns)
            system_ns.append(frame.metadata["system_timestamp_ns"])
        after = camera.statistics()
    finally:
        camera.disarm()
    elapsed_s = returned_s[-1] - returned_s[0]
    device = np.asarray(device_ns, dtype=np.int64)
    device_span_s = float(device[-1] - device[0]) * 1e-9
    return {
        "exposure_us": applied.exposure_us,
        "requested_rate_hz": highest,
        "frames": frames,
        "fps": (frames - 1) / elapsed_s if elapsed_s > 0 else None,
        "device_fps": (frames - 1) / device_span_s if device_span_s > 0 else None,
        "lost_frames": _difference(after, before, "frames_lost"),
        "frame_id_gaps": int(np.sum(np.diff(ids) - 1)),
        "incomplete_buffers": _difference(after, before, "incomplete_buffers"),
        "failures": _difference(after, before, "failures"),
        "underruns": _difference(after, before, "underruns"),
        "missing_packets": _difference(after, before, "missing_packets"),
        "resend_requests": _difference(after, before, "resend_requests"),
        "resent_packets": _difference(after, before, "resent_packets"),
        "interval_ms": percentiles_ms(np.diff(returned_s)),
        "device_interval_ms": percentiles_ms(np.diff(device) * 1e-9),
        "transport_ms": percentiles_ms((np.asarray(system_ns, np.int64) - device) * 1e-9),
    }


def measure_camera(
    url: str, frames: int = 600, exposures_us: Sequence[float] = EXPOSURES_US
) -> dict[str, Any]:
    """Open `url` and measure one free-running run per exposure; the figures as a dict."""
    from hal.camera.aravis import AravisCamera

    load = os.getloadavg()[0]
    camera = AravisCamera(url)
    camera.open(timeout_s=10.0)
    try:
        runs = [_measure_run(camera, exposure, frames) for exposure in exposures_us]
        options = camera.options
        model = " ".join(
            camera.feature_value(name) for name in ("DeviceVendorName", "DeviceModelName")
        )
        packet_size = camera.feature_value("GevSCPSPacketSize")
    finally:
        camera.close()
    met = all(run["fps"] is not None and run["fps"] >= TARGET_FPS for run in runs) and all(
        run["lost_frames"] == 0 for run in runs
    )
    return {
        "benchmark": "camera",
        "target": f">= {TARGET_FPS:g} frames/s at {WIDTH}x{HEIGHT} Mono8 without loss",
        "verdict": "met" if met else "missed",
        "setup": {
            "url": url,
            "camera": model,
            "region": f"{WIDTH}x{HEIGHT}",
            "pixel_format": "Mono8",
            "buffers": options.buffers,
            "packet_size_bytes": int(packet_size),
            "frames_per_run": frames,
            "warmup_frames": WARMUP_FRAMES,
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
            "load_average_1min": load,
        },
        "runs": runs,
    }


def _cell(value: float | None, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def format_table(figures: Mapping[str, Any]) -> str:
    """The figures as a Markdown table."""
    setup = figures["setup"]
    lines = [
        f"Camera acquisition, {setup['camera']} at {setup['url']}, {setup['region']} "
        f"{setup['pixel_format']}, {setup['buffers']} buffers, packets of "
        f"{setup['packet_size_bytes']} B, {setup['frames_per_run']} frames per run, "
        f"{setup['cpus']} CPUs, load average {setup['load_average_1min']:.2f}; target: "
        f"{figures['target']} -> {figures['verdict']}",
        "",
        "| exposure us | fps | device fps | lost | failures | underruns | resent "
        "| interval p50/p99/max ms | device interval p50 ms | transport p50/p99 ms |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for run in figures["runs"]:
        interval, device, transport = (
            run["interval_ms"],
            run["device_interval_ms"],
            run["transport_ms"],
        )
        lines.append(
            f"| {run['exposure_us']:g} | {_cell(run['fps'], 1)} | {_cell(run['device_fps'], 1)} "
            f"| {run['lost_frames']} "
            f"| {run['failures']} | {run['underruns']} | {run['resent_packets']} "
            f"| {_cell(interval['p50'])}/{_cell(interval['p99'])}/{_cell(interval['max'])} "
            f"| {_cell(device['p50'])} | {_cell(transport['p50'])}/{_cell(transport['p99'])} |"
        )
    return "\n".join(lines)


def run_camera_benchmark(
    out: Path | None,
    as_json: bool,
    url: str | None = None,
    frames: int = 600,
    *,
    exposures_us: Sequence[float] = EXPOSURES_US,
) -> int:
    """Entry point of `extensometer bench camera`; prints the figures,
    writes its report into the directory `out` (when given).

    With `url` None, runs Aravis' fake camera on 127.0.0.1 for the measurement. Returns the
    exit status (0: measured, whether or not the target was met).
    """
    from appliance.bench.results import emit_figures

    if frames < 2:
        raise ValueError(f"frames must be >= 2, got {frames}")
    if url is None:
        with _fake_camera() as fake_url:
            figures = measure_camera(fake_url, frames, exposures_us)
    else:
        figures = measure_camera(url, frames, exposures_us)
    emit_figures(
        "camera",
        "GigE Vision acquisition: rate and loss",
        figures,
        format_table(figures),
        as_json=as_json,
        out=out,
    )
    return 0
