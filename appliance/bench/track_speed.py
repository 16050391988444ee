"""`extensometer track` end to end against OpenCV's ECC, on the same points and image files.

The scene: a 1024 x 1024 dense speckle (8-bit PNG files, Gaussian sensor noise of 2 grey
levels), a reference and `IMAGES` targets translated by `STEP_PX` more each, 900 points of
interest on a 30 x 30 grid, subset 41.

- ECC: `cv2.findTransformECC` (MOTION_AFFINE, 20 iterations or a step below 1e-4,
  gaussFiltSize 1) per point, one OpenCV thread on one core: the images read from their files
  (the same decoder as `track`), the reference subset matched in a window of the target around
  the point's previous position (`ECC_MARGIN_PX` beyond the subset), started from the previous
  image's result, as `track` seeds each image from the last.
- track: `extensometer track REF IMG... --points FILE --search-radius R --threads T --json`
  in its own process, on one core (`--threads 1`) and on two (`--threads 2`), at search radii
  `RADII`; the points per second it reports (from reading the reference to the last image
  measured, image reading included; the process's start, the loading of its compiled
  kernels and the writing of its output left out).

Each figure is the median of `REPEATS` runs, ECC's and track's interleaved, so that the ratios
compare runs made at the same time on the same host. On a host shared with other work the
second core may be busy: beside the two-core figures stands the host's own two-core scaling,
measured in each repeat on a compiled loop with nothing to share (`host_two_core_scaling`: 2
on an idle host).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numba
import numpy as np

from appliance.dic.synthetic import (
    AffineMapping,
    add_gaussian_noise,
    dense_speckle,
    quantize,
    render,
)

SIZE = 1024
GRID = 30
SUBSET = 41
IMAGES = 10
STEP_PX = (1.3, -2.1)
RADII = (10, 50)
REPEATS = 3
ECC_MARGIN_PX = 8
NOISE_GREY = 2.0


def _write_scene(directory: Path) -> tuple[Path, list[Path], Path, np.ndarray]:
    pattern = dense_speckle(SIZE, SIZE, seed=2024)
    images = []
    for k in range(IMAGES + 1):
        mapping = AffineMapping.translation(STEP_PX[0] * k, STEP_PX[1] * k)
        grey = render(pattern, SIZE, SIZE, mapping)
        path = directory / f"image{k}.png"
        cv2.imwrite(str(path), quantize(add_gaussian_noise(grey, NOISE_GREY, seed=100 + k)))
        images.append(path)
    spacing = (SIZE - 2 * 80) / (GRID - 1)
    ys, xs = np.mgrid[0:GRID, 0:GRID]
    xy = np.c_[80 + xs.ravel() * spacing, 80 + ys.ravel() * spacing].round()
    points = directory / "points.csv"
    points.write_text("x,y\n" + "".join(f"{x:g},{y:g}\n" for x, y in xy), encoding="utf-8")
    return images[0], images[1:], points, xy


def _read_grey(path: Path) -> np.ndarray:
    return cv2.imdecode(np.fromfile(path, dtype=np.uint8), cv2.IMREAD_UNCHANGED)


def _ecc_run(reference: Path, targets: list[Path], xy: np.ndarray) -> tuple[float, np.ndarray]:
    """Seconds of one ECC pass over the sequence, and (images, n, 2) displacements (NaN where
    ECC failed)."""
    half = SUBSET // 2
    m = ECC_MARGIN_PX
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-4)
    found = np.full((len(targets), len(xy), 2), np.nan)
    started = time.perf_counter()
    ref32 = _read_grey(reference).astype(np.float32)
    previous = np.zeros((len(xy), 2))
    for k, path in enumerate(targets):
        tgt32 = _read_grey(path).astype(np.float32)
        for p, ((x, y), (pu, pv)) in enumerate(zip(xy.astype(int), previous, strict=True)):
            iu, iv = int(round(pu)), int(round(pv))
            cx, cy = x + iu, y + iv
            template = ref32[y - half : y + half + 1, x - half : x + half + 1]
            window = tgt32[cy - half - m : cy + half + m + 1, cx - half - m : cx + half + m + 1]
            warp = np.array([[1, 0, m + pu - iu], [0, 1, m + pv - iv]], dtype=np.float32)
            try:
                _, warp = cv2.findTransformECC(
                    template, window, warp, cv2.MOTION_AFFINE, criteria, None, 1
                )
            except cv2.error:
                continue
            centre = warp @ np.array([half, half, 1.0])
            found[k, p] = (centre[0] - half - m + iu, centre[1] - half - m + iv)
        ok = np.isfinite(found[k, :, 0])
        previous[ok] = found[k, ok]
    return time.perf_counter() - started, found


def _track_run(
    reference: Path, targets: list[Path], points: Path, radius: int, cores: set[int]
) -> tuple[float, np.ndarray]:
    """track's reported points per second on `cores`, and its (images, n, 2) displacements."""
    threads = len(cores)
    command = [sys.executable, "-m", "appliance.cli", "track", str(reference)]
    command += [str(p) for p in targets]
    command += ["--points", str(points), "--search-radius", str(radius)]
    command += ["--threads", str(threads), "--json"]
    done = subprocess.run(
        command,
        capture_output=True,
        text=True,
        timeout=600,
        check=True,
        preexec_fn=lambda: os.sched_setaffinity(0, cores),
    )
    document = json.loads(done.stdout)
    found = np.array(
        [
            [(np.nan, np.nan) if p["u"] is None else (p["u"], p["v"]) for p in image["points"]]
            for image in document["images"]
        ],
        dtype=np.float64,
    )
    return document["throughput"]["points_per_s"], found


@numba.njit(parallel=True, cache=True)
def _busy_loop(rounds):
    out = np.zeros(8)
    for k in numba.prange(8):
        total = 0.0
        for i in range(rounds):
            total += np.sin(i * 1e-3 + k)
        out[k] = total
    return out


def _host_two_core_scaling(two: set[int]) -> float:
    """Time of a compiled loop split over 8 equal parts on one thread over its time on two,
    on the cores `two`: 2 when both cores are free."""
    saved_affinity, saved_threads = os.sched_getaffinity(0), numba.get_num_threads()
    os.sched_setaffinity(0, two)
    _busy_loop(10)
    seconds = []
    try:
        for threads in (1, 2):
            numba.set_num_threads(threads)
            started = time.perf_counter()
            _busy_loop(2_000_000)
            seconds.append(time.perf_counter() - started)
    finally:
        numba.set_num_threads(saved_threads)
        os.sched_setaffinity(0, saved_affinity)
    return seconds[0] / seconds[1]


def _errors(found: np.ndarray) -> dict:
    truth = np.array(STEP_PX) * np.arange(1, IMAGES + 1)[:, None, None]
    error = np.hypot(*(found - truth).transpose(2, 0, 1))
    ok = np.isfinite(error)
    return {
        "found_fraction": float(ok.mean()),
        "median_error_px": float(np.median(error[ok])) if ok.any() else None,
    }


def measure_track_speed() -> dict:
    """Run the comparison; returns its figures as a JSON-ready dict (see the module docstring).

    The two-core figures are None on a host that lets this process use a single core.
    """
    cores = sorted(os.sched_getaffinity(0))
    one, two = {cores[0]}, set(cores[:2]) if len(cores) >= 2 else None
    ecc_rates: list[float] = []
    host_scaling: list[float] = []
    track_rates: dict[tuple[int, int], list[float]] = {}
    accuracy: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="track-speed-") as directory:
        reference, targets, points, xy = _write_scene(Path(directory))
        n = len(xy) * len(targets)
        saved_affinity, saved_threads = os.sched_getaffinity(0), cv2.getNumThreads()
        for _ in range(REPEATS):
            os.sched_setaffinity(0, one)
            cv2.setNumThreads(1)
            try:
                seconds, found = _ecc_run(reference, targets, xy)
            finally:
                os.sched_setaffinity(0, saved_affinity)
                cv2.setNumThreads(saved_threads)
            ecc_rates.append(n / seconds)
            accuracy["ecc"] = _errors(found)
            if two is not None:
                host_scaling.append(_host_two_core_scaling(two))
            for radius in RADII:
                for group in (one, two):
                    if group is None:
                        continue
                    rate, found = _track_run(reference, targets, points, radius, group)
                    track_rates.setdefault((radius, len(group)), []).append(rate)
                    accuracy[f"track_radius_{radius}"] = _errors(found)
    ecc = statistics.median(ecc_rates)
    rows = []
    for radius in RADII:
        single = statistics.median(track_rates[(radius, 1)])
        double = statistics.median(track_rates[(radius, 2)]) if two is not None else None
        rows.append(
            {
                "search_radius_px": radius,
                "points_per_s_one_core": single,
                "points_per_s_two_cores": double,
                "one_core_over_ecc": single / ecc,
                "two_cores_over_one": None if double is None else double / single,
            }
        )
    return {
        "scene": {
            "size_px": SIZE,
            "points": GRID * GRID,
            "subset_px": SUBSET,
            "images": IMAGES,
            "step_px": STEP_PX,
            "noise_grey": NOISE_GREY,
            "ecc_margin_px": ECC_MARGIN_PX,
        },
        "repeats": REPEATS,
        "ecc_points_per_s_one_core": ecc,
        "host_two_core_scaling": statistics.median(host_scaling) if host_scaling else None,
        "track": rows,
        "accuracy": accuracy,
    }


def format_track_table(figures: dict) -> str:
    """The comparison's lines of `bench speed`'s table."""
    scene = figures["scene"]
    lines = [
        f"track end to end vs cv2.findTransformECC ({scene['points']} points, subset "
        f"{scene['subset_px']}, {scene['images']} images of {scene['size_px']} px, PNG read "
        f"included), points/s:",
        f"  ECC, one core: {figures['ecc_points_per_s_one_core']:.0f}",
        f"  {'radius':>6} {'1 core':>8} {'2 cores':>8} {'1 core/ECC':>10} {'2 cores/1':>9}",
    ]
    for r in figures["track"]:
        double = r["points_per_s_two_cores"]
        lines.append(
            f"  {r['search_radius_px']:6d} {r['points_per_s_one_core']:8.0f} "
            + ("       -" if double is None else f"{double:8.0f}")
            + f" {r['one_core_over_ecc']:10.2f} "
            + ("        -" if double is None else f"{r['two_cores_over_one']:9.2f}")
        )
    scaling = figures["host_two_core_scaling"]
    if scaling is not None:
        lines.append(f"  the host's own two-core scaling meanwhile (2 = idle): {scaling:.2f}")
    for name, row in figures["accuracy"].items():
        error = row["median_error_px"]
        lines.append(
            f"  {name}: found {row['found_fraction']:.3f}, median error "
            + ("-" if error is None else f"{error:.4f} px")
        )
    return "\n".join(lines)
