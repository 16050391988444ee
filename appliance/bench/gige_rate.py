"""Full-rate benchmark of the whole appliance on a GigE Vision camera: drops and register latency.

`extensometer bench gige [--duration-s S] [--width-px W] [--height-px H] [--frame-rate-hz F]
[--json] [--out DIR]` serves a GigE Vision camera on 127.0.0.1 in a process of its own
(`appliance.sim.gige_camera.DrawnGigECamera`: Aravis' fake camera sending frames this program
draws) and runs one test through the appliance's own path, as `extensometer run --record FILE
--out DIR --modbus-tcp 127.0.0.1:PORT` does (`appliance.runner.run_test` with the hooks of
`appliance.live.link.LiveLink`): the camera opened by address through Aravis
(``aravis://127.0.0.1?packet_size=8192``), free-running at `--frame-rate-hz` (200) at W x H
Mono8 (1024 x 1024), 10 points (2 axial marks of 5, subset 41 px), the MCAP recording on
(every frame's tracker windows, whole frames at 2 Hz), the strain file, and the Modbus TCP
server on 127.0.0.1, which a client in a process of its own polls every 10 ms
(`appliance.bench.modbus`'s client). The test is stopped `--duration-s` (60) after its first
sample.

The frames: a speckle coat (`appliance.sim.stretched_speckle`) stretched slowly back and forth
along the image's vertical axis about its centre row, from 0 to 0.5 % strain and back every
10 s. The camera renders the coat at 33 strains once, before it serves, and sends each frame
the image of the strain of its device time (a triangle wave, stepped: about 30 frames in a row
at 200 frames/s are the same image), so drawing a frame costs a copy and the camera's
process spends its time sending. The true strain of every frame follows from its device
timestamp; the strain measured is scored against it (`max_abs_strain_error`).

Reported:

* **frames**: drawn by the camera; delivered by the camera backend (``frames_delivered``: the
  reference frame, the frames measured, those the appliance dropped, and the few in flight
  when the stop came); lost before delivery (``frames_lost``: gaps in the camera's frame ids
  and incomplete buffers: packets lost on the way, or a frame that found no free buffer in
  Aravis' pool because the appliance did not fetch fast enough, an Aravis underrun); measured;
  dropped by the appliance (the loop's ``frames_dropped`` less the losses before delivery it
  also counts: frames its queue had no room for); not measured after the stop; the rate
  the camera sent at (frame ids over device time between the first and the last sample) and
  the rate measured.
* **delivery -> register update**, p50/p99/max: from the moment the camera's `fetch`
  returned the frame (the measurement loop's own ``delivered`` stamp, which
  `StrainSample.latency_s` counts from) to the moment the Modbus server's ``publish`` returned
  on the tracking thread (a perf_counter stamp taken by an immediate sink after the link's);
  the same as `extensometer bench modbus`'s figure. Its parts: delivery -> sample (the loop's
  latency), and the register write. The sample's latency is read back a few microseconds
  after the sample was made, by an immediate sink ahead of the link's.
* **what the client sees** (`appliance.bench.modbus.client_figures`): its requests' round
  trip, delivery -> first answer carrying the frame, register update -> that answer.
* the tracking thread's busy time per frame (measuring, strain, the immediate sinks: what
  bounds the rate it can keep up with), the recording's figures (samples, whole frames
  recorded and skipped, degradation), the appliance process's CPU time per second of the
  test (all threads), the 1-minute load average before anything started and after the
  test, and the benchmark's niceness (other work on the same cores shows in every figure).

Target: at 1 MP Mono8 and 200 frames/s, no frame dropped by the appliance over 60 s; met when
the camera sent at >= 99.5 % of the requested rate, no frame was lost before delivery and the
appliance dropped none. The camera paces itself to whole multiples of its frame period
(`appliance.sim.gige_camera`): on a busy host it skips periods and sends slower than asked,
which the report says rather than hides. Delivery -> register update is measured and
compared with `bench modbus`'s target (p99 < 2 ms) for information.

What it does not measure: a real sensor or network (loopback, 8192-byte packets, no loss, no
resends), the camera and the appliance on separate computers (here they share the cores),
the machine's controller (none is read), the Rerun viewer. Run it inside a loopback-only
network namespace (``unshare --net sh -c 'ip link set lo up && ...'``), as the tests are.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import platform
import resource
import sys
import tempfile
import threading
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from appliance.bench.camera import gvcp_port_bound
from appliance.bench.modbus import TARGET_P99_MS, client_figures
from appliance.bench.peer_process import free_loopback_port, percentiles_ms, start_peer, stop_peer
from appliance.errors import InputError

CAMERA_ADDRESS = "127.0.0.1"
CAMERA_SERIAL = "GIGE01"
PACKET_SIZE_BYTES = 8192
"""GVSP packet size: what a GigE link with jumbo frames carries."""
WIDTH_PX = HEIGHT_PX = 1024
FRAME_RATE_HZ = 200.0
DURATION_S = 60.0
EXPOSURE_US = 1000.0
POLL_INTERVAL_S = 0.010
SEED = 7
STRAIN_AMPLITUDE = 0.005
STRAIN_CYCLE_S = 10.0
STRAIN_LEVELS = 33
"""The camera's frames: the coat at this many strains from 0 to `STRAIN_AMPLITUDE`."""
GAUGE_FRACTION = 0.4
"""The gauge length as a fraction of the frame's height (410 px, 18.4 mm, at 1024 px)."""
OPTICS = {"focal_length_mm": 25.0, "object_distance_mm": 250.0, "pixel_size_um": 5.0}
"""A 25 mm lens at 250 mm with 5 um pixels: 0.045 mm per pixel on the specimen."""
POINTS_PER_MARK = 5
QUEUE_SIZE = 8
"""The measurement loop's frames queue (`MeasurementLoop`'s default, as `run_test` builds it)."""
RATE_MARGIN = 0.995
FIRST_SAMPLE_TIMEOUT_S = 120.0


def strain_at(timestamp_ns: int, first_ns: int) -> float:
    """The camera's true engineering strain at a device time: a stepped triangle wave from 0 to
    `STRAIN_AMPLITUDE` and back every `STRAIN_CYCLE_S`, from the first frame it drew."""
    phase = ((timestamp_ns - first_ns) * 1e-9 / STRAIN_CYCLE_S) % 1.0
    level = round((1.0 - abs(2.0 * phase - 1.0)) * (STRAIN_LEVELS - 1))
    return STRAIN_AMPLITUDE * level / (STRAIN_LEVELS - 1)


def _serve_camera(width: int, height: int) -> None:
    """The camera (its own process): serves until `stop` on stdin, then prints its figures."""
    from appliance.sim.gige_camera import MONO8, DrawnGigECamera, FrameRequest
    from appliance.sim.stretched_speckle import StretchedSpecimen

    specimen = StretchedSpecimen(width, height, SEED)
    images = [
        np.clip(np.rint(specimen.render(0, 0, width, height, strain)), 0, 255).astype(np.uint8)
        for strain in np.linspace(0.0, STRAIN_AMPLITUDE, STRAIN_LEVELS)
    ]
    drawn = {"frames": 0, "first_timestamp_ns": None, "last_timestamp_ns": None}

    def draw(request: FrameRequest) -> np.ndarray | None:
        if request.pixel_format != MONO8:
            return None
        if drawn["first_timestamp_ns"] is None:
            drawn["first_timestamp_ns"] = request.timestamp_ns
        drawn["frames"] += 1
        drawn["last_timestamp_ns"] = request.timestamp_ns
        strain = strain_at(request.timestamp_ns, drawn["first_timestamp_ns"])
        image = images[round(strain / STRAIN_AMPLITUDE * (STRAIN_LEVELS - 1))]
        return image[request.y : request.y + request.height, request.x : request.x + request.width]

    with DrawnGigECamera(CAMERA_ADDRESS, CAMERA_SERIAL, width, height, draw):
        print("ready", flush=True)
        sys.stdin.readline()
    print(json.dumps(drawn), flush=True)


def _config_text(width: int, height: int, frame_rate_hz: float, modbus_port: int) -> str:
    scale_mm_per_px = (
        OPTICS["pixel_size_um"]
        * 1e-3
        * (OPTICS["object_distance_mm"] - OPTICS["focal_length_mm"])
        / OPTICS["focal_length_mm"]
    )
    gauge_length_mm = GAUGE_FRACTION * height * scale_mm_per_px
    optics = "".join(f"{key} = {value!r}\n" for key, value in OPTICS.items())
    return (
        f"[optics]\n{optics}"
        "[camera]\n"
        f'url = "aravis://{CAMERA_ADDRESS}?packet_size={PACKET_SIZE_BYTES}"\n'
        f"exposure_us = {EXPOSURE_US!r}\nframe_rate_hz = {float(frame_rate_hz)!r}\n"
        '[machine]\nurl = ""\naccepts_commands = false\n'
        f"[gauge]\nlength_mm = {gauge_length_mm!r}\npoints_per_mark = {POINTS_PER_MARK}\n"
        "[run]\nspeed_mm_min = 1.0\nuntil_break = false\n"
        f'[modbus]\ntcp = "127.0.0.1:{modbus_port}"\n'
    )


@dataclasses.dataclass
class _Stamps:
    """Per sample, on the tracking thread: (frame id, device ns, time_s, latency_s, strain,
    data valid, perf_counter before the link's sink, perf_counter after it)."""

    rows: list[tuple[int, int, float, float, float, bool, float, float]] = dataclasses.field(
        default_factory=list
    )
    before: float = 0.0
    first: threading.Event = dataclasses.field(default_factory=threading.Event)
    cpu_s: list[tuple[float, float]] = dataclasses.field(default_factory=list)
    """(perf_counter, the process's CPU time) at the first sample and at the stop."""

    def ahead(self, _sample: Any) -> None:
        self.before = time.perf_counter()

    def behind(self, sample: Any) -> None:
        after = time.perf_counter()
        self.rows.append(
            (
                sample.frame_id,
                sample.timestamp_ns,
                sample.time_s,
                sample.latency_s,
                sample.reading.engineering_strain,
                bool(sample.data_valid),
                self.before,
                after,
            )
        )
        if not self.first.is_set():
            self.cpu_s.append((after, _cpu_s()))
            self.first.set()


def _stop_after(loop: Any, stamps: _Stamps, duration_s: float, stop: threading.Event) -> None:
    """Stop the test `duration_s` after its first sample (or when `stop` is set)."""
    if stamps.first.wait(FIRST_SAMPLE_TIMEOUT_S) and not stop.wait(duration_s):
        stamps.cpu_s.append((time.perf_counter(), _cpu_s()))
        loop.request_stop("benchmark over")
    elif not stop.is_set():
        loop.request_stop("no sample")


@contextlib.contextmanager
def _peers(width: int, height: int, modbus_port: int) -> Iterator[dict[str, Any]]:
    """The camera, and the polling client between `start_client` (once the server is up) and
    `stop_client` (before the server closes); their outputs in the dict when the block ends."""
    if gvcp_port_bound(CAMERA_ADDRESS):
        raise InputError(f"bench gige: something already serves GVCP on {CAMERA_ADDRESS}:3956")
    peers: dict[str, Any] = {}
    camera = start_peer(
        "appliance.bench.gige_rate", ["camera", str(width), str(height)], "the GigE camera"
    )

    def start_client() -> None:
        peers["client_process"] = start_peer(
            "appliance.bench.modbus",
            ["poll", str(modbus_port), repr(POLL_INTERVAL_S)],
            "the polling client",
        )

    def stop_client() -> None:
        client = peers.pop("client_process", None)
        if client is not None:
            peers["client"] = json.loads(stop_peer(client, "the polling client"))

    peers["start_client"], peers["stop_client"] = start_client, stop_client
    try:
        yield peers
    finally:
        stop_client()
        peers["camera"] = json.loads(stop_peer(camera, "the GigE camera"))


def _cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _cpu_share(marks: list[tuple[float, float]]) -> float | None:
    """The appliance process's CPU seconds per second between the first sample and the stop
    (all its threads: 2.0 = two cores busy)."""
    if len(marks) < 2 or marks[1][0] <= marks[0][0]:
        return None
    return (marks[1][1] - marks[0][1]) / (marks[1][0] - marks[0][0])


def measure_gige(
    duration_s: float = DURATION_S,
    width: int = WIDTH_PX,
    height: int = HEIGHT_PX,
    frame_rate_hz: float = FRAME_RATE_HZ,
) -> dict[str, Any]:
    """Serve the camera, run the test, and return the figures (see the module docstring).

    Raises:
        InputError: Aravis is not installed, or something already serves GVCP on 127.0.0.1.
    """
    from appliance.config import parse_config
    from appliance.live.link import LiveLink
    from appliance.runner import OutputFiles, run_test

    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis  # noqa: F401
    except (ImportError, ValueError):
        raise InputError(
            "bench gige: Aravis 0.8 through PyGObject is not installed (gir1.2-aravis-0.8, "
            "pygobject)"
        ) from None
    load = os.getloadavg()[0]
    port = free_loopback_port()
    config = parse_config(_config_text(width, height, frame_rate_hz, port), "bench gige")
    stamps = _Stamps()
    warnings: list[str] = []
    stop = threading.Event()
    with (
        tempfile.TemporaryDirectory(prefix="bench-gige-") as scratch,
        _peers(width, height, port) as peers,
    ):
        link = LiveLink(config)
        link_hooks = link.hooks()

        def on_loop(loop: Any) -> None:
            assert link_hooks.on_loop is not None
            link_hooks.on_loop(loop)
            threading.Thread(
                target=_stop_after, args=(loop, stamps, duration_s, stop), daemon=True
            ).start()

        hooks = dataclasses.replace(
            link_hooks,
            immediate_sinks=[stamps.ahead, *link_hooks.immediate_sinks, stamps.behind],
            on_loop=on_loop,
            on_warning=warnings.append,
        )
        files = OutputFiles(
            Path(scratch) / "strain.csv", Path(scratch) / "summary.json", Path(scratch) / "t.mcap"
        )
        try:
            link.start()
            peers["start_client"]()
            outcome = run_test(config, simulate=False, files=files, hooks=hooks, test_id="gige")
        finally:
            stop.set()
            peers["stop_client"]()
            link.close()
        recording = files.recording
        recording_mb = recording.stat().st_size / 1e6 if recording and recording.exists() else None
    summary = outcome.as_dict()
    return _figures(
        summary,
        stamps,
        peers,
        warnings,
        setup={
            "camera": f"aravis://{CAMERA_ADDRESS}",
            "region": f"{width}x{height}",
            "pixel_format": "Mono8",
            "packet_size_bytes": PACKET_SIZE_BYTES,
            "requested_rate_hz": frame_rate_hz,
            "exposure_us": EXPOSURE_US,
            "duration_s": duration_s,
            "points": summary.get("points"),
            "subset_px": config.tracking.subset_px,
            "gauge_length_mm": config.gauge.length_mm,
            "full_frame_rate_hz": config.record.full_frame_rate_hz,
            "poll_interval_ms": POLL_INTERVAL_S * 1e3,
            "scene": f"speckle stretched 0 ... {STRAIN_AMPLITUDE:g} and back every "
            f"{STRAIN_CYCLE_S:g} s ({STRAIN_LEVELS} images)",
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
            "load_average_1min": load,
            "load_average_1min_after": os.getloadavg()[0],
            "niceness": os.nice(0),
            "recording_mb": recording_mb,
            "appliance_cpu_share": _cpu_share(stamps.cpu_s),
        },
    )


def _figures(
    summary: Mapping[str, Any],
    stamps: _Stamps,
    peers: Mapping[str, Any],
    warnings: list[str],
    setup: dict[str, Any],
) -> dict[str, Any]:
    rows = stamps.rows
    statistics = summary.get("camera_statistics", {})
    delivered = int(statistics.get("frames_delivered", 0))
    lost = int(statistics.get("frames_lost", 0))
    measured = int(summary["frames_processed"])
    dropped = int(summary["frames_dropped"]) - lost
    frames = {
        "drawn_by_camera": int(peers["camera"]["frames"]),
        "delivered": delivered,
        "lost_before_delivery": lost,
        "reference": 1,
        "measured": measured,
        "dropped_by_appliance": dropped,
        "not_measured_after_stop": delivered - 1 - measured - dropped,
        "samples_seen_by_sinks": len(rows),
        "valid_samples": sum(1 for row in rows if row[5]),
    }
    ids = np.array([row[0] for row in rows], dtype=np.int64)
    device_ns = np.array([row[1] for row in rows], dtype=np.int64)
    span_s = float(device_ns[-1] - device_ns[0]) * 1e-9 if len(rows) > 1 else 0.0
    rates = {
        "camera_rate_hz": float(ids[-1] - ids[0]) / span_s if span_s > 0 else None,
        "measured_rate_hz": (len(rows) - 1) / span_s if span_s > 0 else None,
        "test_s": span_s,
    }
    latency = np.array([row[3] for row in rows])
    register_write = np.array([row[7] - row[6] for row in rows])
    delivered_at = {row[0]: row[6] - row[3] for row in rows}
    updated_at = {row[0]: row[7] for row in rows}
    figures: dict[str, Any] = {
        "benchmark": "gige",
        "target": (
            f"{setup['region']} Mono8 at {setup['requested_rate_hz']:g} frames/s through the "
            f"whole appliance: no frame dropped over {setup['duration_s']:g} s"
        ),
        "setup": setup,
        "frames": frames,
        "rates": rates,
        "delivery_to_register_ms": percentiles_ms(latency + register_write),
        "stages_ms": {
            "delivery_to_sample": percentiles_ms(latency),
            "register_write": percentiles_ms(register_write),
        },
        "client": client_figures(peers["client"], delivered_at, updated_at, POLL_INTERVAL_S)
        if "client" in peers
        else None,
        "tracking_thread_ms_per_frame": (
            1e3 / summary["tracking_fps"] if summary.get("tracking_fps") else None
        ),
        "max_abs_strain_error": _max_strain_error(rows, peers["camera"]),
        "exit_status": summary["exit_status"],
        "reason": summary["reason"],
        "camera_statistics": {
            key: statistics.get(key)
            for key in ("failures", "underruns", "missing_packets", "resent_packets")
        },
        "recording": {
            key.removeprefix("recording_"): summary.get(key)
            for key in (
                "recording_samples",
                "recording_full_frames",
                "recording_full_frames_skipped",
                "recording_max_degradation_level",
                "recording_blocked_s",
            )
        },
        "warnings": len(warnings),
        "first_warning": warnings[0] if warnings else None,
    }
    reasons = []
    camera_rate = rates["camera_rate_hz"]
    if camera_rate is None or camera_rate < RATE_MARGIN * setup["requested_rate_hz"]:
        reasons.append(
            f"the camera sent {camera_rate or 0:.1f} frames/s, not {setup['requested_rate_hz']:g}"
        )
    if lost:
        reasons.append(f"{lost} frames were lost before delivery")
    if dropped:
        reasons.append(f"the appliance dropped {dropped} frames")
    figures["verdict"] = "met" if not reasons else "missed"
    figures["verdict_reasons"] = reasons
    p99 = figures["delivery_to_register_ms"]["p99"]
    figures["latency_target"] = f"bench modbus's p99 < {TARGET_P99_MS:g} ms -> " + (
        "met" if p99 is not None and p99 < TARGET_P99_MS else "missed"
    )
    return figures


def _max_strain_error(rows: list[tuple], camera: Mapping[str, Any]) -> float | None:
    """Largest |measured - true| engineering strain over valid samples, the truth relative to
    the reference frame as an extensometer zeroed on it reads it."""
    first_ns = camera.get("first_timestamp_ns")
    if first_ns is None or not rows:
        return None
    errors = []
    for _, device_ns, time_s, _, strain, valid, _, _ in rows:
        if not valid:
            continue
        reference = strain_at(device_ns - round(time_s * 1e9), first_ns)
        truth = (1.0 + strain_at(device_ns, first_ns)) / (1.0 + reference) - 1.0
        errors.append(abs(strain - truth))
    return float(max(errors)) if errors else None


def _cell(value: float | None, digits: int = 3) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _row(name: str, stats: Mapping[str, Any]) -> str:
    return (
        f"| {name} | {_cell(stats['p50'])} | {_cell(stats['p99'])} | {_cell(stats['max'])} "
        f"| {stats['n']} |"
    )


def format_table(figures: Mapping[str, Any]) -> str:
    """The figures as Markdown."""
    setup, frames, rates = figures["setup"], figures["frames"], figures["rates"]
    recording = figures["recording"]
    lines = [
        f"GigE Vision camera at {setup['camera']} ({setup['region']} {setup['pixel_format']}, "
        f"packets of {setup['packet_size_bytes']} B, {setup['requested_rate_hz']:g} frames/s "
        f"asked; {setup['scene']}) through the whole appliance: {setup['points']} points, "
        f"subset {setup['subset_px']} px, recording (windows every frame, whole frames at "
        f"{setup['full_frame_rate_hz']:g} Hz), Modbus TCP polled every "
        f"{setup['poll_interval_ms']:g} ms; {setup['cpus']} CPUs, load average "
        f"{setup['load_average_1min']:.2f} before and {setup['load_average_1min_after']:.2f} "
        f"after, niceness {setup['niceness']}",
        f"target: {figures['target']} -> {figures['verdict']}"
        + (f" ({'; '.join(figures['verdict_reasons'])})" if figures["verdict_reasons"] else ""),
        "",
        f"test: {rates['test_s']:.1f} s of device time, ended {figures['exit_status']} "
        f"({figures['reason']}); the camera sent {_cell(rates['camera_rate_hz'], 1)} frames/s, "
        f"{_cell(rates['measured_rate_hz'], 1)} measured per second",
        "",
        "| frames | count |",
        "|---|---|",
        *(f"| {name.replace('_', ' ')} | {value} |" for name, value in frames.items()),
        "",
        "| ms | p50 | p99 | max | n |",
        "|---|---|---|---|---|",
        _row("delivery -> register update", figures["delivery_to_register_ms"]),
        _row("  delivery -> sample", figures["stages_ms"]["delivery_to_sample"]),
        _row("  register write", figures["stages_ms"]["register_write"]),
    ]
    client = figures["client"]
    if client:
        lines += [
            _row("client: request round trip", client["round_trip_ms"]),
            _row("client: delivery -> seen", client["delivery_to_seen_ms"]),
            _row("client: register update -> seen", client["register_to_seen_ms"]),
        ]
    stats = figures["camera_statistics"]
    cpu = setup["appliance_cpu_share"]
    lines += [
        "",
        f"latency: {figures['latency_target']}; max |strain error| "
        f"{_cell(figures['max_abs_strain_error'], 7)}; tracking thread busy "
        f"{_cell(figures['tracking_thread_ms_per_frame'], 2)} ms per frame; appliance CPU "
        f"{_cell(cpu, 2)} s per second of test; recording {recording['samples']} samples, "
        f"{recording['full_frames']} whole frames ({recording['full_frames_skipped']} skipped), "
        f"degradation level {recording['max_degradation_level']}, "
        f"{_cell(setup['recording_mb'], 1)} MB; Aravis: {stats['failures']} failures, "
        f"{stats['underruns']} underruns, {stats['missing_packets']} missing packets, "
        f"{stats['resent_packets']} resent; "
        f"{figures['warnings']} warnings"
        + (f" (first: {figures['first_warning']})" if figures["first_warning"] else ""),
    ]
    return "\n".join(lines)


def run_gige_benchmark(
    out: Path | None,
    as_json: bool,
    *,
    duration_s: float = DURATION_S,
    width: int = WIDTH_PX,
    height: int = HEIGHT_PX,
    frame_rate_hz: float = FRAME_RATE_HZ,
) -> int:
    """Entry point of `extensometer bench gige`; prints the figures, writes its report into
    the directory `out` (when given). Returns 0: measured, whether or not the target was met.
    """
    from appliance.bench.results import emit_figures

    figures = measure_gige(duration_s, width, height, frame_rate_hz)
    emit_figures(
        "gige",
        "A GigE Vision camera at full rate through the whole appliance",
        figures,
        format_table(figures),
        as_json=as_json,
        out=out,
    )
    return 0


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "camera":
        _serve_camera(int(sys.argv[2]), int(sys.argv[3]))
    else:
        sys.exit("usage: python -m appliance.bench.gige_rate camera WIDTH HEIGHT (the camera)")
