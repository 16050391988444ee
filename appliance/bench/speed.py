"""Speed benchmark: IC-GN throughput, integer-search time, and OpenCV references, in one run.

Measured on one synthetic dense-speckle scene (1024 x 1024, subpixel translation):

- IC-GN points per second at subsets 21, 41 and 61, on one thread and on all cores (kernel
  time of `ICGN.compute`, which includes the target's spline prefilter, over ~2000 points);
- integer search time per point at subset 41 and radius 10, 50 and 100, for LPQ
  (`lpq_search`) and for ZNCC (`zncc_search`, i.e. `cv2.matchTemplate` TM_CCOEFF_NORMED);
- `cv2.findTransformECC` (MOTION_AFFINE, gaussFiltSize=1) on the same points at subset 41,
  the nearest widely used subpixel alternative;
- `extensometer track` end to end against ECC on the same points and image files
  (`appliance.bench.track_speed`): the ratio of their points per second in one run, on one
  core and on two.

Each time is the median of several repeats after a warm-up run (numba compilation excluded).
"""

from __future__ import annotations

import os
import platform
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numba
import numpy as np

from appliance import __version__
from appliance.bench.results import emit_figures
from appliance.bench.track_speed import format_track_table, measure_track_speed
from appliance.dic import integer_search
from appliance.dic.icgn import ICGN
from appliance.dic.synthetic import AffineMapping, dense_speckle, render

SIZE = 1024
SHIFT = (0.37, -0.21)
SUBSETS = (21, 41, 61)
RADII = (10, 50, 100)
REPEATS = 5


def _median_seconds(action: Callable[[], object], repeats: int = REPEATS) -> float:
    action()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        action()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def _scene() -> tuple[np.ndarray, np.ndarray]:
    pattern = dense_speckle(SIZE, SIZE, seed=2024)
    reference = render(pattern, SIZE, SIZE)
    target = render(pattern, SIZE, SIZE, AffineMapping.translation(*SHIFT))
    return reference, target


def _grid(margin: int, step: int) -> np.ndarray:
    ys, xs = np.mgrid[margin : SIZE - margin : step, margin : SIZE - margin : step]
    return np.c_[xs.ravel(), ys.ravel()].astype(np.float64)


def _icgn_rates(reference: np.ndarray, target: np.ndarray) -> list[dict]:
    rows = []
    points = _grid(margin=80, step=20)
    guess = np.tile(np.round(SHIFT), (len(points), 1))
    for subset in SUBSETS:
        for threads in sorted({1, numba.config.NUMBA_NUM_THREADS}):
            icgn = ICGN(subset=subset, threads=threads)
            icgn.prepare(reference, points)
            seconds = _median_seconds(lambda icgn=icgn: icgn.compute(target, guess))
            result = icgn.compute(target, guess)
            rows.append(
                {
                    "subset": subset,
                    "threads": threads,
                    "points": len(points),
                    "points_per_s": len(points) / seconds,
                    "mean_iterations": float(result.iterations.mean()),
                    "converged_fraction": float(result.ok().mean()),
                    "max_abs_error_px": float(
                        max(np.abs(result.u - SHIFT[0]).max(), np.abs(result.v - SHIFT[1]).max())
                    ),
                }
            )
    return rows


def _search_times(reference: np.ndarray, target: np.ndarray) -> list[dict]:
    rows = []
    points = _grid(margin=200, step=75)[:40]
    for radius in RADII:
        timings = {}
        for name, method in (
            ("lpq", integer_search.lpq_search),
            ("zncc", integer_search.zncc_search),
        ):
            seconds = _median_seconds(
                lambda method=method, radius=radius: method(
                    reference, target, points, subset=41, radius=radius
                ),
                repeats=3,
            )
            timings[name] = seconds / len(points) * 1e3
        rows.append(
            {
                "subset": 41,
                "radius": radius,
                "points": len(points),
                "lpq_ms_per_point": timings["lpq"],
                "zncc_ms_per_point": timings["zncc"],
                "lpq_over_zncc": timings["lpq"] / timings["zncc"],
            }
        )
    return rows


def _ecc_rate(reference: np.ndarray, target: np.ndarray) -> dict:
    subset = 41
    half = subset // 2
    margin = 4
    points = _grid(margin=80, step=20)[::4]
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-4)
    ref32 = reference.astype(np.float32)
    tgt32 = target.astype(np.float32)
    errors = []

    def run_all() -> None:
        errors.clear()
        for x, y in points.astype(int):
            template = ref32[y - half : y + half + 1, x - half : x + half + 1]
            window = tgt32[
                y - half - margin : y + half + margin + 1, x - half - margin : x + half + margin + 1
            ]
            warp = np.array([[1, 0, margin], [0, 1, margin]], dtype=np.float32)
            try:
                _, warp = cv2.findTransformECC(
                    template, window, warp, cv2.MOTION_AFFINE, criteria, None, 1
                )
            except cv2.error:
                errors.append(np.inf)
                continue
            errors.append(abs(float(warp[0, 2] - margin) - SHIFT[0]))

    previous = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        seconds = _median_seconds(run_all, repeats=3)
    finally:
        cv2.setNumThreads(previous)
    return {
        "subset": subset,
        "threads": 1,
        "points": len(points),
        "points_per_s": len(points) / seconds,
        "median_abs_error_u_px": float(np.median(errors)),
    }


def measure_speed() -> dict:
    """Run every measurement and return the figures as a JSON-ready dict.

    The host's load average is kept beside them (at the start and at the end): on a host shared
    with other work the absolute rates drop, the ratios measured in one run much less.
    """
    load_at_start = os.getloadavg()[0]
    reference, target = _scene()
    icgn = _icgn_rates(reference, target)
    search = _search_times(reference, target)
    ecc = _ecc_rate(reference, target)
    track = measure_track_speed()
    single_41 = next(r for r in icgn if r["subset"] == 41 and r["threads"] == 1)
    return {
        "software_version": __version__,
        "machine": {
            "cpus": os.cpu_count(),
            "numba_threads": numba.config.NUMBA_NUM_THREADS,
            "processor": platform.processor() or platform.machine(),
            "python": platform.python_version(),
            "numpy": np.__version__,
            "opencv": cv2.__version__,
            "numba": numba.__version__,
            "load_average_1_min": [load_at_start, os.getloadavg()[0]],
        },
        "scene": {"size": SIZE, "pattern": "dense_speckle seed 2024", "shift_px": SHIFT},
        "icgn": icgn,
        "search": search,
        "ecc": ecc,
        "track": track,
        "ratios": {
            "icgn_41_one_thread_over_ecc": single_41["points_per_s"] / ecc["points_per_s"],
            "lpq_over_zncc_radius_50": next(r for r in search if r["radius"] == 50)[
                "lpq_over_zncc"
            ],
        },
    }


def format_table(figures: dict) -> str:
    """Human-readable summary of `measure_speed` figures."""
    start, end = figures["machine"]["load_average_1_min"]
    lines = [f"Host load average (1 min) at the start and the end: {start:.2f}, {end:.2f}"]
    lines.append("IC-GN (first-order, ZNSSD, bicubic B-spline), points/s:")
    lines.append(f"  {'subset':>6} {'threads':>7} {'points/s':>10} {'iter':>5} {'max err px':>10}")
    for r in figures["icgn"]:
        lines.append(
            f"  {r['subset']:6d} {r['threads']:7d} {r['points_per_s']:10.0f} "
            f"{r['mean_iterations']:5.2f} {r['max_abs_error_px']:10.2e}"
        )
    ecc = figures["ecc"]
    lines.append(
        f"cv2.findTransformECC (affine, subset 41, 1 thread): {ecc['points_per_s']:.0f} points/s"
    )
    lines.append("Integer search at subset 41, ms per point:")
    lines.append(f"  {'radius':>6} {'LPQ':>8} {'ZNCC':>8} {'LPQ/ZNCC':>9}")
    for r in figures["search"]:
        lines.append(
            f"  {r['radius']:6d} {r['lpq_ms_per_point']:8.3f} {r['zncc_ms_per_point']:8.3f} "
            f"{r['lpq_over_zncc']:9.2f}"
        )
    ratios = figures["ratios"]
    lines.append(
        f"IC-GN 41 one thread / ECC: {ratios['icgn_41_one_thread_over_ecc']:.1f}x; "
        f"LPQ / matchTemplate at radius 50: {ratios['lpq_over_zncc_radius_50']:.2f}"
    )
    lines.append(format_track_table(figures["track"]))
    return "\n".join(lines)


def run_speed_benchmark(out: Path | None = None, as_json: bool = False) -> int:
    """Entry point of `extensometer bench speed`; returns the exit status."""
    figures = measure_speed()
    emit_figures(
        "speed",
        "Speed of the measurement core: IC-GN, integer search and track end to end",
        figures,
        format_table(figures),
        as_json=as_json,
        out=out,
    )
    return 0
