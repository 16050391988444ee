"""Real-time benchmark: the simulated rubber test at the camera's pace, recording and serving.

`extensometer bench realtime` runs `extensometer run --sim --realtime` (the rubber preset to
its break by default: 41.8 s of test at the planned 20 frames/s) with a recording
(`--record`) and the Modbus TCP server on a free loopback port (`--modbus-tcp`), as a test on
the appliance runs, in a process of its own, and reports per run:

- the frames measured and the frames dropped (the simulated camera's frames that found its
  16 host buffers full, and frames the measurement loop's queue could not take);
- the latency from frame delivery to a complete sample (median and 99th percentile);
- the wall time, and the CPU time the test process used (user and system, all threads, its
  start and its report included: about 5 s on the reference host, a tenth of a second per
  frame of a 50-frame test but 6 ms per frame of the 836 to the break): per measured frame,
  and as a share of the host's cores over the test's wall time;
- the host's load average at the start and at the end: on a host shared with other work the
  test gets less of the cores, and a real-time test drops frames when it gets less than its
  CPU time per frame every frame period. The CPU time per frame depends far less on the load
  than the drops do.

Nothing here is a pass/fail: the report says what was measured.
"""

from __future__ import annotations

import json
import os
import resource
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from appliance import __version__
from appliance.bench.results import emit_figures


class TestFailed(Exception):
    """A simulated test that ended without its summary (one line: its exit status and last
    line of output)."""


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def run_once(until_strain: float | None, material: str) -> dict[str, Any]:
    """One real-time simulated test with a recording and the Modbus server; its figures."""
    with tempfile.TemporaryDirectory(prefix="bench-realtime-") as scratch:
        command = [
            sys.executable,
            "-m",
            "appliance.cli",
            "run",
            "--sim",
            "--realtime",
            "--material",
            material,
            "--record",
            str(Path(scratch) / "test.mcap"),
            "--modbus-tcp",
            f"127.0.0.1:{_free_port()}",
            "--out",
            str(Path(scratch) / "out"),
            "--json",
        ]
        if until_strain is not None:
            command += ["--until-strain", f"{until_strain:g}"]
        load_start = os.getloadavg()[0]
        cpu_before = _children_cpu_s()
        started = time.perf_counter()
        done = subprocess.run(command, capture_output=True, text=True, check=False)
        wall_s = time.perf_counter() - started
        cpu_s = _children_cpu_s() - cpu_before
        load_end = os.getloadavg()[0]
    text = done.stdout
    try:
        summary = json.loads(text[text.index("{") : text.rindex("}") + 1])
    except ValueError:
        tail = (done.stderr or text).strip().splitlines()[-1:] or ["no output"]
        raise TestFailed(f"the simulated test failed (exit {done.returncode}): {tail[0]}") from None
    frames = int(summary["frames_processed"])
    dropped = int(summary["frames_dropped"])
    return {
        "exit_status": summary["exit_status"],
        "frame_rate_hz": summary.get("frame_rate_hz"),
        "test_duration_s": summary.get("test_duration_s"),
        "frames_processed": frames,
        "frames_dropped": dropped,
        "latency_ms_p50": summary.get("latency_ms_p50"),
        "latency_ms_p99": summary.get("latency_ms_p99"),
        "recording_samples": summary.get("recording_samples"),
        "recording_full_frames": summary.get("recording_full_frames"),
        "iso9513_class": summary.get("iso9513_class"),
        "wall_s": wall_s,
        "cpu_s": cpu_s,
        "cpu_ms_per_measured_frame": 1e3 * cpu_s / max(frames, 1),
        "cores_busy": cpu_s / wall_s,
        "load_average_1_min": [load_start, load_end],
    }


def measure_realtime(runs: int, until_strain: float | None, material: str) -> dict[str, Any]:
    """`runs` real-time tests one after the other; their figures and medians."""
    results = [run_once(until_strain, material) for _ in range(runs)]
    return {
        "software_version": __version__,
        "cpus": os.cpu_count(),
        "material": material,
        "until_strain": until_strain,
        "runs": results,
        "median_frames_dropped": statistics.median(r["frames_dropped"] for r in results),
        "median_cpu_ms_per_measured_frame": statistics.median(
            r["cpu_ms_per_measured_frame"] for r in results
        ),
    }


def format_table(figures: dict[str, Any]) -> str:
    """Human-readable summary of `measure_realtime` figures."""
    end = "the break" if figures["until_strain"] is None else f"strain {figures['until_strain']}"
    lines = [
        f"Simulated {figures['material']} test to {end} in real time, recording and Modbus TCP "
        f"served, on {figures['cpus']} CPUs:",
        f"  {'frames':>6} {'dropped':>7} {'rate Hz':>7} {'p50 ms':>7} {'p99 ms':>7} "
        f"{'wall s':>7} {'CPU s':>6} {'CPU ms/frame':>12} {'cores':>5} {'load start, end':>16}",
    ]
    for r in figures["runs"]:
        start, stop = r["load_average_1_min"]
        lines.append(
            f"  {r['frames_processed']:6d} {r['frames_dropped']:7d} {r['frame_rate_hz']:7.1f} "
            f"{r['latency_ms_p50']:7.2f} {r['latency_ms_p99']:7.2f} {r['wall_s']:7.1f} "
            f"{r['cpu_s']:6.1f} {r['cpu_ms_per_measured_frame']:12.1f} {r['cores_busy']:5.2f} "
            f"{start:7.2f}, {stop:6.2f}"
        )
    lines.append(
        f"Median: {figures['median_frames_dropped']:g} frames dropped, "
        f"{figures['median_cpu_ms_per_measured_frame']:.1f} ms of CPU per measured frame"
    )
    return "\n".join(lines)


def run_realtime_benchmark(
    out: Path | None,
    as_json: bool,
    *,
    runs: int = 1,
    until_strain: float | None = None,
    material: str = "rubber",
) -> int:
    """Entry point of `extensometer bench realtime`; returns the exit status (1, with one
    line on stderr, when a test ends without its summary)."""
    try:
        figures = measure_realtime(runs, until_strain, material)
    except TestFailed as exc:
        print(f"extensometer: bench realtime: {exc}", file=sys.stderr)
        return 1
    emit_figures(
        "realtime",
        "Real time: the simulated test at the camera's pace, recording and Modbus served",
        figures,
        format_table(figures),
        as_json=as_json,
        out=out,
    )
    return 0
