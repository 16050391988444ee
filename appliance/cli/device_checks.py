"""Installer's checks of the devices: `extensometer camera-check` and `machine-check`.

The first commands run on a new installation, before any test: does the camera deliver
frames of the expected size and format at the expected rate without loss, does the machine's
controller answer with a sensible state, how fast, and does the trigger microcontroller run
the firmware this host speaks (`check_trigger`: handshake, round trips, clock fit, encoder
position; nothing is triggered)?

`check_camera` opens a camera, configures it (exposure, gain, region, pixel format of the
configuration, or the given overrides), free-runs it at a frame rate, grabs N frames, and
reports size, format, the frame rate achieved (host arrival times) and by the device's
clock, frames lost (gaps in the camera's frame counter), the device timestamps and the
images' grey levels (to judge exposure: the saturated fraction); with `[optics] calibration`
it checks that the calibration was made for the images' size (a file made for another sensor
size or region is refused, exit status 2) and reports its checksum, scale and the largest lens
distortion it corrects in the field. `check_machine` opens a
controller, reads its state N times and reports the last state, the read rate and the read
latency. Neither starts a test or moves the crosshead.

Both take devices through the backend registry like any test: `sim://` gives the simulator
(its world built from the configuration), anything else the hardware backend.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np

from appliance.cli.detection_overlay import (
    gauge_overlay,
    overlay_quality,
    save_detection_overlay,
)
from appliance.config import Config, register_map_of
from appliance.measure.gauges import Calibration
from appliance.measure.image_quality import view_quality
from appliance.plan.optics import configured_optics
from appliance.run.object_plane import check_image_size
from hal.camera.base import Camera, CameraSettings, PixelFormat, TriggerInfo, TriggerMode
from hal.errors import HardwareTimeout
from hal.machine.base import MachineState, TestingMachine
from hal.registry import camera_from_url, machine_from_url


def camera_for_check(config: Config, url: str) -> Camera:
    """The camera named by `url`, constructed as a test would (a simulator with its world)."""
    if url.startswith("sim://"):
        return _sim_world(config).camera
    return camera_from_url(url)


def machine_for_check(config: Config, url: str) -> TestingMachine:
    """The controller named by `url`, with the configuration's register map."""
    if url.startswith("sim://"):
        return _sim_world(config).controller
    return machine_from_url(
        url,
        register_map=register_map_of(config, "[machine.registers]"),
        accepts_commands=False,
    )


def simulated_setup(config: Config) -> Config:
    """A configuration for looking at the simulated bench as a simulated test sees it: the
    preset's optics and gauge length where `[optics]` and `[gauge] length_mm` give none, and
    the simulated camera keeping the clock's pace (`[sim] realtime`), as a camera does."""
    from appliance.sim.world import PRESETS

    optics = configured_optics(config, PRESETS[config.sim.material].optics)
    world = _sim_world(config)
    return dataclasses.replace(
        config,
        optics=dataclasses.replace(
            config.optics,
            focal_length_mm=optics.focal_length_mm,
            object_distance_mm=optics.object_distance_mm,
            pixel_size_um=optics.pixel_size_um,
        ),
        gauge=dataclasses.replace(
            config.gauge, length_mm=config.gauge.length_mm or world.gauge_length_mm
        ),
        sim=dataclasses.replace(config.sim, realtime=True),
    )


def _sim_world(config: Config):
    from appliance.sim.world import PRESETS, SimWorld

    optics = configured_optics(config, PRESETS[config.sim.material].optics)
    return SimWorld.from_config(config, optics)


def _percentiles(values: np.ndarray) -> dict[str, float | None]:
    if values.size == 0:
        return {"p50": None, "p99": None, "max": None}
    p50, p99 = np.percentile(values, [50, 99])
    return {"p50": float(p50), "p99": float(p99), "max": float(values.max())}


def check_camera(
    camera: Camera,
    config: Config,
    *,
    frames: int = 100,
    rate_hz: float = 30.0,
    exposure_us: float | None = None,
    fetch_timeout_s: float = 2.0,
    calibration: Calibration | None = None,
    save_path: Path | None = None,
) -> dict[str, Any]:
    """Grab `frames` free-running frames and report what arrived; with `save_path`, write the
    last frame there with the specimen detection and the gauge drawn over it
    (`appliance.cli.detection_overlay`).

    Args:
        camera: a constructed, not opened, camera (closed again on return).
        config: the [camera] table gives gain, region and pixel format (and the exposure
            when `exposure_us` is None; 1000 us when neither is set).
        frames: frames to grab (>= 2).
        rate_hz: the internal trigger's frame rate.
        exposure_us: exposure override, us.
        fetch_timeout_s: timeout of each fetch.
        calibration: the `[optics] calibration` to check against the images' size.
        save_path: where to write the last frame with its overlays and set-up figures;
            None = nowhere.

    Returns:
        A JSON-ready report: `frames`, `width`, `height`, `pixel_format`, `fps` (host arrival),
        `device_fps` (device timestamps), `lost` (frame-counter gaps), `timeouts`,
        `exposure_us` in force, `first_timestamp_ns`, `last_timestamp_ns`,
        `interval_ms` (p50/p99/max of arrival intervals), grey level `mean_grey`,
        `saturated_fraction`, `sharpest_gradient` (the texture and focus of the last
        frame's sharpest tiles, grey levels per px: `appliance.measure.image_quality`), the
        backend's `statistics` where it has them, and the verdict: `fit` (bool) and
        `problems` (one phrase each: a frame rate below 90 % of the one asked for, lost
        frames, timeouts, timestamps not increasing, too dark, overexposed, no sharp
        texture in view). With a calibration, `calibration`: its `file`, `checksum`,
        `scale_mm_per_px` and `max_distortion_px` (the largest lens distortion over the
        image's border and centre lines). With `save_path`, `saved` (the file) and `subsets`:
        the speckle in the subsets a test would track (`subsets`, `subset_px`,
        `mean_intensity_gradient`, `sssig`, `speckle_size_px`:
        `appliance.measure.speckle_quality.SubsetQuality`).

    Raises:
        HardwareError: the camera cannot be opened or configured, or sends nothing.
        InputError: the calibration was made for another image size (names the file).
    """
    if frames < 2:
        raise ValueError(f"frames must be >= 2, got {frames}")
    c = config.camera
    exposure = exposure_us or c.exposure_us or 1000.0
    settings = CameraSettings(
        exposure_us=exposure,
        gain_db=c.gain_db,
        region=config.camera.region(),
        pixel_format=PixelFormat(c.pixel_format),
    )
    arrivals: list[float] = []
    ids: list[int] = []
    stamps: list[int] = []
    timeouts = 0
    grey_sum = 0.0
    saturated = 0
    pixels = 0
    last_image = None
    camera.open()
    try:
        in_force = camera.configure(settings)
        camera.prepare(TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=rate_hz))
        camera.arm()
        try:
            while len(ids) < frames:
                try:
                    frame = camera.fetch(fetch_timeout_s)
                except HardwareTimeout:
                    timeouts += 1
                    if not ids or timeouts >= 3:
                        raise
                    continue
                arrivals.append(time.perf_counter())
                ids.append(frame.frame_id)
                stamps.append(frame.timestamp_ns)
                image = np.asarray(frame.image)
                grey_sum += float(image.mean())
                saturated += int(np.count_nonzero(image >= in_force.pixel_format.max_value))
                pixels += image.size
                last_image = image
        finally:
            camera.disarm()
        stats = camera.statistics()
    finally:
        camera.close()
    arrival = np.asarray(arrivals)
    stamp = np.asarray(stamps, dtype=np.int64)
    frame_ids = np.asarray(ids, dtype=np.int64)
    gaps = np.diff(frame_ids) - 1
    span_s = arrival[-1] - arrival[0]
    device_span_s = (stamp[-1] - stamp[0]) * 1e-9
    height, width = last_image.shape[:2]
    if calibration is not None:
        check_image_size(calibration, int(width), int(height))
    report: dict[str, Any] = {
        "camera": camera.url,
        "frames": len(ids),
        "width": int(width),
        "height": int(height),
        "pixel_format": in_force.pixel_format.value,
        "exposure_us": in_force.exposure_us,
        "requested_rate_hz": rate_hz,
        "fps": (len(ids) - 1) / span_s if span_s > 0 else None,
        "device_fps": (len(ids) - 1) / device_span_s if device_span_s > 0 else None,
        "lost": int(gaps[gaps > 0].sum()),
        "timeouts": timeouts,
        "first_frame_id": int(frame_ids[0]),
        "last_frame_id": int(frame_ids[-1]),
        "first_timestamp_ns": int(stamp[0]),
        "last_timestamp_ns": int(stamp[-1]),
        "timestamps_increasing": bool(np.all(np.diff(stamp) > 0)),
        "interval_ms": _percentiles(np.diff(arrival) * 1e3),
        "mean_grey": grey_sum / len(ids),
        "saturated_fraction": saturated / pixels,
    }
    if stats:
        report["statistics"] = stats
    if calibration is not None and calibration.camera is not None:
        report["calibration"] = {
            "file": calibration.file,
            "checksum": calibration.checksum,
            "scale_mm_per_px": calibration.scale_mm_per_px,
            "max_distortion_px": _max_distortion_px(calibration, int(width), int(height)),
        }
    view = view_quality(last_image, in_force.pixel_format.max_value)
    report["sharpest_gradient"] = view.sharpest_gradient * in_force.pixel_format.max_value
    problems = list(_delivery_problems(report)) + list(view.problems)
    report["fit"] = not problems
    report["problems"] = problems
    if save_path is not None:
        full_scale = in_force.pixel_format.max_value
        overlay = gauge_overlay(last_image, config)
        quality = overlay_quality(last_image, full_scale, config, overlay)
        save_detection_overlay(save_path, last_image, full_scale, config, overlay, quality)
        report["saved"] = str(save_path)
        if quality.subsets is not None:
            report["subsets"] = dataclasses.asdict(quality.subsets)
    return report


def _max_distortion_px(calibration: Calibration, width: int, height: int) -> float:
    """The largest lens distortion of the calibration over the image's border and its centre
    lines, px."""
    assert calibration.camera is not None
    xs = np.linspace(0.0, width - 1.0, 33)
    ys = np.linspace(0.0, height - 1.0, 33)
    edges = [
        np.column_stack([xs, np.full_like(xs, y)]) for y in (0.0, (height - 1) / 2, height - 1.0)
    ] + [np.column_stack([np.full_like(ys, x), ys]) for x in (0.0, (width - 1) / 2, width - 1.0)]
    try:
        return float(calibration.camera.camera.distortion_px(np.vstack(edges)).max())
    except ValueError:
        return float("nan")


def _delivery_problems(report: dict[str, Any]) -> list[str]:
    """What the frames' delivery says against measuring with this camera."""
    problems = []
    rate = report["device_fps"] or report["fps"]
    asked = report["requested_rate_hz"]
    if rate is None or rate < 0.9 * asked:
        shown = "unknown" if rate is None else f"{rate:.1f}"
        problems.append(f"frame rate {shown} fps, below 90 % of the {asked:g} fps asked for")
    if report["lost"]:
        problems.append(f"{report['lost']} frames lost")
    if report["timeouts"]:
        problems.append(f"{report['timeouts']} fetches timed out")
    if not report["timestamps_increasing"]:
        problems.append("device timestamps not increasing")
    return problems


def check_machine(
    machine: TestingMachine, *, reads: int = 50, timeout_s: float = 1.0
) -> dict[str, Any]:
    """Read the controller's state `reads` times, as fast as it answers.

    Args:
        machine: a constructed, not opened, controller (closed again on return).
        reads: number of reads (>= 1).
        timeout_s: timeout of each read.

    Returns:
        A JSON-ready report: `machine` (URL), `reads`, `state` (the last reading: crosshead_mm,
        speed_mm_min, force_n, running, encoder_counts), `rate_hz`, `latency_ms`
        (p50/p99/max) and the backend's `statistics` where it has them.

    Raises:
        HardwareError: the controller cannot be reached, or answers with an exception.
    """
    if reads < 1:
        raise ValueError(f"reads must be >= 1, got {reads}")
    latencies: list[float] = []
    state: MachineState | None = None
    machine.open(timeout_s)
    try:
        started = time.perf_counter()
        for _ in range(reads):
            before = time.perf_counter()
            state = machine.read_state(timeout_s)
            latencies.append((time.perf_counter() - before) * 1e3)
        elapsed = time.perf_counter() - started
        stats = machine.statistics()
    finally:
        machine.close()
    assert state is not None
    report: dict[str, Any] = {
        "machine": machine.url,
        "reads": reads,
        "state": {k: v for k, v in dataclasses.asdict(state).items() if k != "timestamp_ns"},
        "rate_hz": reads / elapsed if elapsed > 0 else None,
        "latency_ms": _percentiles(np.asarray(latencies)),
    }
    if stats:
        report["statistics"] = stats
    return report


def camera_report_lines(report: dict[str, Any]) -> list[str]:
    """The camera report as aligned lines for a terminal."""
    lines = [
        f"camera             {report['camera']}",
        f"frames             {report['frames']} ({report['lost']} lost, "
        f"{report['timeouts']} timeouts)",
        f"image              {report['width']} x {report['height']} {report['pixel_format']}",
        f"exposure           {report['exposure_us']:g} us",
        f"frame rate         {_num(report['fps'])} fps (host), {_num(report['device_fps'])} fps "
        f"(device clock); {report['requested_rate_hz']:g} requested",
        f"arrival interval   p50 {_num(report['interval_ms']['p50'])} ms, "
        f"p99 {_num(report['interval_ms']['p99'])} ms",
        f"timestamps         {report['first_timestamp_ns']} .. {report['last_timestamp_ns']} ns"
        f" ({'increasing' if report['timestamps_increasing'] else 'NOT increasing'})",
        f"grey level         mean {report['mean_grey']:.1f}, "
        f"saturated {report['saturated_fraction'] * 100:.2f} %",
        f"texture, focus     gradient {report['sharpest_gradient']:.2f} grey levels/px "
        "(sharpest tiles, least textured direction)",
        f"verdict            {'fit to measure' if report['fit'] else 'NOT fit to measure'}",
        *(f"  problem          {problem}" for problem in report["problems"]),
    ]
    calibration = report.get("calibration")
    if calibration is not None:
        lines.insert(
            -1 - len(report["problems"]),
            f"calibration        {calibration['file']} ({calibration['checksum'][:19]}...), "
            f"{calibration['scale_mm_per_px'] * 1e3:.4f} um/px, lens distortion up to "
            f"{calibration['max_distortion_px']:.2f} px",
        )
    for key, value in (report.get("statistics") or {}).items():
        lines.append(f"  {key:24s} {value}")
    return lines


def machine_report_lines(report: dict[str, Any]) -> list[str]:
    """The controller report as aligned lines for a terminal."""
    s = report["state"]
    lines = [
        f"machine            {report['machine']}",
        f"crosshead          {s['crosshead_mm']:.4f} mm",
        f"speed              {s['speed_mm_min']:.4f} mm/min",
        f"force              {s['force_n']:.3f} N",
        f"running            {s['running']}",
        f"encoder            {s['encoder_counts']}",
        f"reads              {report['reads']} at {_num(report['rate_hz'])} Hz; latency p50 "
        f"{_num(report['latency_ms']['p50'])} ms, p99 {_num(report['latency_ms']['p99'])} ms",
    ]
    for key, value in (report.get("statistics") or {}).items():
        lines.append(f"  {key:24s} {value}")
    return lines


def _num(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.2f}"


def check_trigger(url: str, *, pings: int = 50, timeout_s: float = 2.0) -> dict[str, Any]:
    """Handshake with the trigger microcontroller, time `pings` round trips, fit its clock.

    Args:
        url: the serial port (a device path or pyserial URL).
        pings: round trips to time (>= 1), besides those of the handshake.
        timeout_s: timeout of the handshake and of each request.

    Returns:
        A JSON-ready report: `port`, `protocol_version`, `table_hash` (hex) and whether it
        matches this host's, `tick_hz`, `round_trip_ms` (p50/p99/max), `clock_rate_ppm`
        (the fitted tick rate's deviation from nominal), `clock_residual_us`, `encoder_position`.

    Raises:
        firmware_bridge.link.FirmwareError: the port cannot be opened, the firmware does not
            answer, or it speaks another protocol or table (named in the message).
    """
    from firmware_bridge.link import McuLink

    if pings < 1:
        raise ValueError(f"pings must be >= 1, got {pings}")
    with McuLink(url, sync_interval_s=None) as link:
        info = link.connect(timeout_s)
        trips = [link.ping(timeout_s=timeout_s) for _ in range(pings)]
        position = link.position(timeout_s=timeout_s)
        estimate = link.clock_estimate()
    rtt = np.asarray([t.received_ns - t.sent_ns for t in trips], dtype=np.float64) * 1e-6
    report: dict[str, Any] = {
        "port": url,
        "protocol_version": f"{info.version[0]}.{info.version[1]}",
        "table_hash": f"{info.table_hash:#010x}",
        "tick_hz": info.tick_hz,
        "pings": pings,
        "round_trip_ms": _percentiles(rtt),
        "clock_rate_ppm": (
            (estimate.rate_hz / info.tick_hz - 1.0) * 1e6 if estimate is not None else None
        ),
        "clock_residual_us": estimate.residual_rms_ns * 1e-3 if estimate is not None else None,
        "encoder_position": position.position,
    }
    return report


def trigger_report_lines(report: dict[str, Any]) -> list[str]:
    """The trigger microcontroller report as aligned lines for a terminal."""
    rtt = report["round_trip_ms"]
    return [
        f"port               {report['port']}",
        f"firmware           protocol {report['protocol_version']}, table "
        f"{report['table_hash']} (matches this host)",
        f"tick               {report['tick_hz']} Hz; fitted rate "
        f"{_num(report['clock_rate_ppm'])} ppm off, residual "
        f"{_num(report['clock_residual_us'])} us",
        f"round trip         p50 {_num(rtt['p50'])} ms, p99 {_num(rtt['p99'])} ms over "
        f"{report['pings']} pings",
        f"encoder            {report['encoder_position']} counts",
    ]
