"""Clock-sync benchmark of the trigger microcontroller's link: host time of a trigger edge.

`run_clock_sync_benchmark(out, as_json)` builds the real firmware and its simavr harness
(`firmware_bridge.firmware_build`), runs it (`firmware_bridge.simulator.SimulatedMcu`, paced
to the wall clock), connects `firmware_bridge.link.McuLink` with its default clock sync (a
PING every 100 ms, a sliding window of 64 round trips), triggers every 50 ms for
`duration_s`, and reports how well the host times the link gives the TRIGGER events match
the truth. The target: under 100 us.

Ground truth, and how good it is. A simulated MCU has no physical clock. The harness logs
every trigger edge twice: in simulated ns (exact to the CPU cycle) and on the host clock
(CLOCK_MONOTONIC, the link's clock) at the moment it simulated that edge, which is when a
watcher of the wire, a camera's trigger input, would see it. That second time is the truth
here; it is good to the harness's pacing step (it simulates 20 us, then sleeps once simulated
time is more than 20 us ahead, so a cycle runs up to ~40 us early or late by the host's
sleep overshoot). The older truth, the pacing line ``released + s`` (the host's stamp of
the release plus the edge's simulated time), is reported beside it: it also carries the
harness's start delay after "go" (measured here, `edge_vs_pacing_us`, about 0.1 ms) and is
void when the harness fell more than 20 ms behind (a slip).

Figures:

* **error_vs_edge_us** (the headline): host time of each TRIGGER as the link delivered it
  (converted with the fit at its arrival) minus the edge's host time, over the events after
  a 2 s warm-up: p50 and p99 of the absolute value, mean, min, max. Also the same with the
  final fit (**..._final_fit_us**) and about its own mean (**..._about_mean_us**: what is
  left once a constant path asymmetry is calibrated away, as it has to be on hardware).
* **error_vs_pacing_us**, **..._final_fit_us**: the same against the pacing line;
  **edge_vs_pacing_us**: the edge's host time minus the pacing line.
* **path_us**: the round trip split at the pacing line: PING out (``released + tick - sent``)
  and PONG back (``received - released - tick``). Round trips alone cannot see this split;
  a split that is not even is a constant bias of the midpoint fit (`firmware_bridge.
  clocksync`), and that bias is what the mean of error_vs_edge shows.
* **round_trip_us**, **fit_sigma_us** (the fit's own 1 sigma for each event),
  **prediction_vs_midpoint_us** (each round trip's midpoint minus the prediction of the fit
  before it: the fit's jitter as round trips see it), **causal** (round trips whose
  [sent, received] interval the prediction missed, and the final fit's causal bound),
  **rate_error_ppm** (the fit's rate against the 2 MHz tick, which the pacing keeps exact).

The link corrects the known part of the asymmetry: the firmware stamps a PING at its last
byte and a PING is 8 bytes shorter than its PONG; simavr's UART takes 11 bit times a byte at
500 kBd (22 us), so the PING's stamp lies 88 us before the round trip's midpoint
(`wire_byte_ns`). The rest of the asymmetry (the host's pty and thread wake-ups; the
harness hands bytes over in both directions at the end of each 20 us step) is not
corrected: it would have to be measured against this very truth.

What it does not measure: a real UART, a USB-serial adapter's latency timer, or a real
crystal's drift (the simulated tick is exact); the host's camera timestamps.
"""

from __future__ import annotations

import platform
import re
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

TARGET_US = 100.0
TRIGGER_PERIOD_TICKS = 100_000
TRIGGER_WIDTH_TICKS = 200
TICK_NS = 500
WARMUP_S = 2.0
WIRE_BYTE_NS = 22_000.0
"""simavr's UART at 500 kBd: 11 bit times per byte (it always counts a parity bit)."""


def _percentiles_us(values_ns: list[float]) -> dict[str, float]:
    if not values_ns:
        return {}
    data = np.asarray(values_ns, dtype=float) / 1e3
    magnitude = np.abs(data)
    return {
        "p50_abs": round(float(np.percentile(magnitude, 50)), 1),
        "p99_abs": round(float(np.percentile(magnitude, 99)), 1),
        "max_abs": round(float(magnitude.max()), 1),
        "mean": round(float(data.mean()), 1),
        "min": round(float(data.min()), 1),
        "max": round(float(data.max()), 1),
    }


def _spread_us(values_ns: list[float]) -> dict[str, float]:
    if not values_ns:
        return {}
    data = np.asarray(values_ns, dtype=float) / 1e3
    return {
        "min": round(float(data.min()), 1),
        "p50": round(float(np.percentile(data, 50)), 1),
        "p99": round(float(np.percentile(data, 99)), 1),
        "max": round(float(data.max()), 1),
    }


def measure_clock_sync(duration_s: float, work_dir: Path) -> dict[str, Any]:
    """Run the firmware under simavr for `duration_s` of triggering and return the figures
    (see the module docstring). Raises `FirmwareBuildError` without the toolchain."""
    from firmware_bridge.clocksync import ClockSync, RoundTrip
    from firmware_bridge.firmware_build import build_firmware, build_harness, default_build_dir
    from firmware_bridge.link import McuLink, StoppedEvent, TriggerEvent, wire_asymmetry_ns
    from firmware_bridge.messages import TriggerSource
    from firmware_bridge.simulator import SimulatedMcu

    class RecordingSync(ClockSync):
        """Keeps every round trip offered, with the fit's prediction made before it."""

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self.offered: list[tuple[RoundTrip, int | None]] = []

        def add(self, sample: RoundTrip) -> bool:
            estimate = self.estimate
            predicted = None if estimate is None else estimate.host_time_ns(sample.tick)
            self.offered.append((sample, predicted))
            return super().add(sample)

    build_dir = default_build_dir()
    elf, harness = build_firmware(build_dir), build_harness(build_dir)
    probe = McuLink.__init__.__kwdefaults__ or {}
    sync_interval_s = probe.get("sync_interval_s", 0.1)
    mcu = SimulatedMcu(elf, harness, work_dir, hold=True)
    with mcu:
        clock = RecordingSync(2_000_000.0, asymmetry_ns=wire_asymmetry_ns(WIRE_BYTE_NS))
        link = McuLink(mcu.port, clock_sync=clock)
        try:
            before = time.monotonic_ns()
            mcu.release()
            released_ns = (before + time.monotonic_ns()) // 2
            link.connect(timeout_s=5.0)
            connected_ns = time.monotonic_ns()
            link.configure(TriggerSource.PERIOD, TRIGGER_WIDTH_TICKS, TRIGGER_PERIOD_TICKS)
            link.arm()
            deadline = time.monotonic() + duration_s
            triggers: list[Any] = []
            while time.monotonic() < deadline:
                event = link.next_event(0.2)
                if isinstance(event, TriggerEvent):
                    triggers.append(event)
            link.disarm()
            for event in link.events(0.5):
                if isinstance(event, TriggerEvent):
                    triggers.append(event)
                elif isinstance(event, StoppedEvent):
                    break
            final = link.clock_estimate()
            statistics = link.statistics()
            rises = [(ns, wall) for ns, level, wall in mcu.edge_wall_times() if level == 1]
            edges = [ns for ns, _ in rises]
            walls = dict(rises)
        finally:
            link.close()
    log = mcu.log_text()
    slips = re.search(r"pacing slips (\d+), worst lag ([0-9.]+) ms", log)

    by_seq = {event.trigger_seq: event for event in triggers}
    settled_after = connected_ns + int(WARMUP_S * 1e9)
    delivered: list[float] = []
    refitted: list[float] = []
    versus_wall: list[float] = []
    refitted_wall: list[float] = []
    pacing_lag: list[float] = []
    sigmas: list[float] = []
    for index, edge_ns in enumerate(edges):
        event = by_seq.get(index + 1)
        if event is None or event.host_time_ns is None or event.received_ns < settled_after:
            continue
        truth = released_ns + edge_ns
        delivered.append(event.host_time_ns - truth)
        wall = walls.get(edge_ns)
        if wall is not None:
            versus_wall.append(event.host_time_ns - wall)
            pacing_lag.append(wall - truth)
        if final is not None:
            refitted.append(final.host_time_ns(event.tick) - truth)
            if wall is not None:
                refitted_wall.append(final.host_time_ns(event.tick) - wall)
        if event.uncertainty_ns is not None:
            sigmas.append(event.uncertainty_ns)

    rtts, outs, backs, residuals = [], [], [], []
    misses, judged, worst_miss = 0, 0, 0.0
    for sample, predicted in clock.offered:
        rtts.append(sample.rtt_ns)
        pacing = released_ns + sample.tick * TICK_NS
        outs.append(pacing - sample.sent_ns)
        backs.append(sample.received_ns - pacing)
        if predicted is None or sample.sent_ns < settled_after:
            continue
        judged += 1
        residuals.append(sample.midpoint_ns + clock.asymmetry_ns - predicted)
        miss = max(sample.sent_ns - predicted, predicted - sample.received_ns, 0)
        if miss > 0:
            misses += 1
            worst_miss = max(worst_miss, miss)

    headline = _percentiles_us(versus_wall)
    figures: dict[str, Any] = {
        "benchmark": "clock_sync",
        "target_us": TARGET_US,
        "target_met": bool(headline) and headline["p99_abs"] < TARGET_US,
        "headline": "error_vs_edge_us.p99_abs",
        "duration_s": duration_s,
        "warmup_s": WARMUP_S,
        "sync_interval_s": sync_interval_s,
        "trigger_period_ms": TRIGGER_PERIOD_TICKS * TICK_NS / 1e6,
        "triggers_compared": len(delivered),
        "round_trips": len(clock.offered),
        "asymmetry_correction_us": round(clock.asymmetry_ns / 1e3, 1),
        "error_vs_edge_us": headline,
        "error_vs_edge_final_fit_us": _percentiles_us(refitted_wall),
        "error_vs_edge_about_mean_us": _percentiles_us(
            list(np.asarray(versus_wall) - np.mean(versus_wall)) if versus_wall else []
        ),
        "error_vs_pacing_us": _percentiles_us(delivered),
        "error_vs_pacing_final_fit_us": _percentiles_us(refitted),
        "edge_vs_pacing_us": _spread_us(pacing_lag),
        "path_us": {"ping_out": _spread_us(outs), "pong_back": _spread_us(backs)},
        "round_trip_us": _spread_us(rtts),
        "fit_sigma_us": _spread_us(sigmas),
        "prediction_vs_midpoint_us": _percentiles_us(residuals),
        "causal": {
            "round_trips_judged": judged,
            "prediction_outside_round_trip": misses,
            "worst_miss_us": round(worst_miss / 1e3, 1),
            "final_bound_us": None if final is None else round(final.causal_bound_ns / 1e3, 1),
        },
        "rate_error_ppm": None if final is None else round((final.rate_hz / 2e6 - 1) * 1e6, 2),
        "harness": {
            "pacing_slips": int(slips.group(1)) if slips else None,
            "worst_lag_ms": float(slips.group(2)) if slips else None,
        },
        "link": {
            "timeouts": statistics.timeouts,
            "crc_errors": statistics.crc_errors,
            "lost_packets": statistics.lost_packets,
            "clock_samples_rejected": statistics.clock_samples_rejected,
        },
        "ground_truth": (
            "the host clock when the harness simulated each rising edge (its edge log), to "
            "its 20 us pacing step; also against the pacing line (released + simulated ns), "
            "which is void when pacing slipped"
        ),
        "machine": {"python": platform.python_version(), "processor": platform.machine()},
    }
    return figures


def format_table(figures: dict[str, Any]) -> str:
    """The figures as a short human-readable report."""

    def row(label: str, values: dict[str, Any], keys: tuple[str, ...]) -> str:
        if not values:
            return f"  {label:<34} (none)"
        return f"  {label:<34} " + "  ".join(f"{k} {values[k]:>8}" for k in keys)

    abs_keys = ("p50_abs", "p99_abs", "max_abs", "mean")
    spread = ("min", "p50", "p99", "max")
    causal = figures["causal"]
    verdict = "met" if figures["target_met"] else "NOT met"
    lines = [
        f"clock sync over simavr: {figures['triggers_compared']} triggers after "
        f"{figures['warmup_s']} s warm-up, {figures['round_trips']} round trips, "
        f"ping every {figures['sync_interval_s']} s",
        row("error vs edge (us)", figures["error_vs_edge_us"], abs_keys),
        row("  same, final fit (us)", figures["error_vs_edge_final_fit_us"], abs_keys),
        row("  about its mean (us)", figures["error_vs_edge_about_mean_us"], abs_keys),
        row("error vs pacing line (us)", figures["error_vs_pacing_us"], abs_keys),
        row("  same, final fit (us)", figures["error_vs_pacing_final_fit_us"], abs_keys),
        row("edge - pacing line (us)", figures["edge_vs_pacing_us"], spread),
        row("PING out, vs pacing line (us)", figures["path_us"]["ping_out"], spread),
        row("PONG back, vs pacing line (us)", figures["path_us"]["pong_back"], spread),
        row("round trip (us)", figures["round_trip_us"], spread),
        row("fit 1 sigma per event (us)", figures["fit_sigma_us"], spread),
        row("midpoint - prediction (us)", figures["prediction_vs_midpoint_us"], abs_keys),
        f"  predictions outside their round trip: {causal['prediction_outside_round_trip']} of "
        f"{causal['round_trips_judged']} (worst {causal['worst_miss_us']} us); final causal "
        f"bound {causal['final_bound_us']} us",
        f"  rate error {figures['rate_error_ppm']} ppm; asymmetry corrected "
        f"{figures['asymmetry_correction_us']} us; harness slips "
        f"{figures['harness']['pacing_slips']}, worst lag {figures['harness']['worst_lag_ms']} ms",
        f"  target: p99 |error vs edge| < {figures['target_us']} us: {verdict}",
        f"  ground truth: {figures['ground_truth']}",
    ]
    return "\n".join(lines)


def run_clock_sync_benchmark(out: Path | None, as_json: bool, *, duration_s: float = 10.0) -> int:
    """Entry point of the clock-sync benchmark; prints the figures,
    writes its report into the directory `out` (when given).

    Returns the exit status: 0 when measured (whether or not the target was met), 2 when the
    firmware toolchain or libsimavr is missing (the reason goes to stderr).
    """
    from appliance.bench.results import emit_figures
    from firmware_bridge.firmware_build import FirmwareBuildError

    if duration_s <= WARMUP_S:
        raise ValueError(f"duration_s must exceed the {WARMUP_S} s warm-up, got {duration_s}")
    try:
        with tempfile.TemporaryDirectory(prefix="clock-sync-bench-") as work:
            figures = measure_clock_sync(duration_s, Path(work))
    except FirmwareBuildError as error:
        sys.stderr.write(f"clock-sync benchmark: cannot build the firmware: {error}\n")
        return 2
    emit_figures(
        "clock-sync",
        "Host timestamps of trigger events after clock sync",
        figures,
        format_table(figures),
        as_json=as_json,
        out=out,
    )
    return 0
