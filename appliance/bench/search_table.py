"""Search comparison benchmark: which integer search finds the points, and at what cost.

`extensometer bench search --out DIR` writes `DIR/search.md`, `DIR/search.json` and the plot
`DIR/search.png`. Every case renders a reference and a target analytically
(`appliance.dic.synthetic`: the benchmark's Gaussian speckle at the paper's density, R = 4 px,
640 x 360 px): a one-step uniaxial stretch along x about the image centre (incompressible
lateral contraction) with a translation of (25, 4) px, a centred motion blur along x on the
target, an illumination change of the target (gain and offset), Gaussian noise on both and
8-bit quantisation. 45 points on a 30 px grid (9 x 5, +-120 px along the stretch, so the
far ones move up to 79 px at 45 %: beyond a 50 px search window) are measured through the
product's own pipeline (`appliance.dic.point_measurement.PointMeasurement`, the one
`extensometer track` runs) on one thread, each method with:

- `zncc`: ZNCC search against the sharp reference, IC-GN, nothing else (`--search zncc`);
- `zncc-matched`: the same with the reference blurred to match the known blur
  (`--search zncc --blur-px L`);
- `lpq`: LPQ search at the window rule's size for the blur
  (`appliance.dic.lpq.window_for_blur`), reference blurred to match (`--search lpq --blur-px L`);
- `auto`: the automatic choice for the known blur, stretch untold (`--blur-px L`);
- `auto-told`: the automatic choice told the stretch lies in 0 ... 50 %
  (`--blur-px L --stretch 0:0.5`).

A point succeeds when IC-GN converged within 0.5 px of the truth. Time per point is the wall
time of the measurement (search, IC-GN, recovery) over the points, the reference prepared
beforehand, after a warm-up that loads the compiled kernels.

The default grid (34 cases) takes about a minute on two cores; `--full` runs every
combination of blur 0, 5, 10, 12, 15 px, stretch 0, 15, 30, 45, 50 %, noise sigma 0, 2, 5
grey levels, illumination (gain, offset) (1, 0), (0.7, +20), (1.3, -20) and subsets 21, 41,
61 px (675 cases).
"""

from __future__ import annotations

import itertools
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np

from appliance import __version__
from appliance.bench.results import write_report
from appliance.dic.blur import motion_blur
from appliance.dic.correlation import DEFAULT_PREFILTER_SIGMA
from appliance.dic.icgn import PointStatus
from appliance.dic.point_measurement import PointMeasurement
from appliance.dic.search_choice import SearchChoice, choose_search, explicit_search
from appliance.dic.synthetic import (
    AffineMapping,
    add_gaussian_noise,
    gaussian_speckle,
    quantize,
    render,
)

WIDTH, HEIGHT = 640, 360
TRANSLATION_PX = (25.0, 4.0)
RADIUS_PX = 50
SUCCESS_PX = 0.5
METHODS = ("zncc", "zncc-matched", "lpq", "auto", "auto-told")
TOLD_STRETCH = (0.0, 0.5)
ILLUMINATIONS = ((1.0, 0.0), (0.7, 20.0), (1.3, -20.0))


@dataclass(frozen=True)
class Case:
    """One cell of the grid."""

    blur_px: float
    stretch: float
    noise: float
    gain: float
    offset: float
    subset: int

    def label(self) -> dict:
        return {
            "blur_px": self.blur_px,
            "stretch": self.stretch,
            "noise": self.noise,
            "gain": self.gain,
            "offset": self.offset,
            "subset": self.subset,
        }


def coarse_grid() -> list[Case]:
    """The default grid: blur x stretch x two illuminations at sigma 2 and 41 px, and the
    noise and subset extremes at 10 px blur and 45 %."""
    cases = [
        Case(blur, stretch, 2.0, gain, offset, 41)
        for blur in (0.0, 5.0, 10.0, 12.0, 15.0)
        for stretch in (0.0, 0.25, 0.45)
        for gain, offset in ILLUMINATIONS[:2]
    ]
    cases += [Case(10.0, 0.45, noise, 1.0, 0.0, 41) for noise in (0.0, 5.0)]
    cases += [Case(10.0, 0.45, 2.0, 1.0, 0.0, subset) for subset in (21, 61)]
    return cases


def full_grid() -> list[Case]:
    """Every combination (see the module docstring)."""
    return [
        Case(blur, stretch, noise, gain, offset, subset)
        for blur, stretch, noise, (gain, offset), subset in itertools.product(
            (0.0, 5.0, 10.0, 12.0, 15.0),
            (0.0, 0.15, 0.3, 0.45, 0.5),
            (0.0, 2.0, 5.0),
            ILLUMINATIONS,
            (21, 41, 61),
        )
    ]


def points_grid() -> np.ndarray:
    """The 45 measured points, (x, y) px."""
    ys, xs = np.mgrid[120:241:30, 200:441:30]
    return np.c_[xs.ravel(), ys.ravel()].astype(np.float64)


def scene(case: Case, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reference, target and the true (u, v) of `points_grid()` for a case."""
    pattern = gaussian_speckle(
        WIDTH, HEIGHT, count=round(1200 * WIDTH * HEIGHT / 700**2), radius=4.0, seed=seed
    )
    mapping = AffineMapping(
        u=TRANSLATION_PX[0],
        v=TRANSLATION_PX[1],
        ux=case.stretch,
        vy=(1.0 + case.stretch) ** -0.5 - 1.0,
        xc=WIDTH / 2,
        yc=HEIGHT / 2,
    )
    reference = render(pattern, HEIGHT, WIDTH)
    target = render(pattern, HEIGHT, WIDTH, mapping)
    if case.blur_px > 0:
        target = motion_blur(target, case.blur_px, 0.0)
    target = case.gain * target + case.offset
    if case.noise > 0:
        reference = add_gaussian_noise(reference, case.noise, seed=seed * 2 + 1)
        target = add_gaussian_noise(target, case.noise, seed=seed * 2 + 2)
    points = points_grid()
    x, y = mapping.forward(points[:, 0], points[:, 1])
    truth = np.c_[x - points[:, 0], y - points[:, 1]]
    return (
        quantize(reference, 8).astype(np.float64),
        quantize(target, 8).astype(np.float64),
        truth,
    )


def choice_for(method: str, case: Case) -> tuple[SearchChoice, float]:
    """The search of a method and the blur its reference is matched to."""
    if method == "zncc":
        return explicit_search("zncc", blur_px=0.0, subset=case.subset), 0.0
    if method == "zncc-matched":
        return explicit_search("zncc", blur_px=case.blur_px, subset=case.subset), case.blur_px
    if method == "lpq":
        return explicit_search("lpq", blur_px=case.blur_px, subset=case.subset), case.blur_px
    if method == "auto":
        return choose_search(blur_px=case.blur_px, subset=case.subset), case.blur_px
    told = choose_search(blur_px=case.blur_px, stretch=TOLD_STRETCH, subset=case.subset)
    return told, case.blur_px


def measure(method: str, case: Case, reference, target, truth) -> dict:
    """Success rate and time per point of one method on one scene."""
    choice, blur = choice_for(method, case)
    pipeline = PointMeasurement(
        reference,
        points_grid(),
        choice,
        subset=case.subset,
        radius=RADIUS_PX,
        prefilter_sigma=DEFAULT_PREFILTER_SIGMA,
        threads=1,
        blur=(blur, 0.0),
    )
    prepared = pipeline.icgn.prepare_target(target)
    started = time.perf_counter()
    result = pipeline.measure(target, np.zeros((len(truth), 2)), prepared)
    seconds = time.perf_counter() - started
    converged = np.asarray(result.status) == PointStatus.CONVERGED
    error = np.hypot(result.u - truth[:, 0], result.v - truth[:, 1])
    found = converged & (np.nan_to_num(error, nan=np.inf) <= SUCCESS_PX)
    return {
        "method": method,
        "success": float(found.mean()),
        "ms_per_point": 1e3 * seconds / len(truth),
        "lpq_window": choice.lpq_window,
    }


def _warm_up() -> None:
    """Load the compiled kernels every method runs, on a small case, untimed."""
    case = Case(5.0, 0.25, 2.0, 1.0, 0.0, 41)
    reference, target, truth = scene(case, seed=1)
    for method in METHODS:
        measure(method, case, reference, target, truth)


def run_cases(cases: list[Case]) -> list[dict]:
    """Every method on every case; one row per case and method."""
    numba.set_num_threads(1)
    _warm_up()
    rows = []
    for k, case in enumerate(cases):
        reference, target, truth = scene(case, seed=100 + k)
        for method in METHODS:
            rows.append({**case.label(), **measure(method, case, reference, target, truth)})
        print(f"  case {k + 1}/{len(cases)}: {case.label()}", file=sys.stderr)
    return rows


def summary(rows: list[dict]) -> dict:
    """Per method: mean success, median time per point, and the cells each wins outright."""
    out: dict = {}
    cells: dict[tuple, dict[str, dict]] = {}
    for row in rows:
        key = tuple(row[k] for k in ("blur_px", "stretch", "noise", "gain", "offset", "subset"))
        cells.setdefault(key, {})[row["method"]] = row
    for method in METHODS:
        mine = [r for r in rows if r["method"] == method]
        out[method] = {
            "mean_success": float(np.mean([r["success"] for r in mine])),
            "median_ms_per_point": float(np.median([r["ms_per_point"] for r in mine])),
        }
    lpq_wins, lpq_loses = [], []
    for key, by in cells.items():
        others = max(by[m]["success"] for m in METHODS if m != "lpq")
        if by["lpq"]["success"] > others:
            lpq_wins.append(list(key))
        elif by["lpq"]["success"] < others:
            lpq_loses.append(list(key))
    out["lpq_wins"] = lpq_wins
    out["lpq_loses"] = len(lpq_loses)
    against = [
        (key, by["lpq"]["success"] - by["zncc-matched"]["success"]) for key, by in cells.items()
    ]
    out["lpq_beats_matched_zncc"] = [list(key) for key, gain in against if gain > 0]
    out["lpq_behind_matched_zncc"] = [list(key) for key, gain in against if gain < 0]
    out["cells"] = len(cells)
    ratios = [by["auto"]["ms_per_point"] / by["zncc"]["ms_per_point"] for by in cells.values()]
    out["auto_time_ratio_median"] = float(np.median(ratios))
    out["auto_time_ratio_max"] = float(np.max(ratios))
    return out


def targets(rows: list[dict]) -> list[dict]:
    """The targets: 45 % with 10-12 px blur, 25 px translation, 41 px subsets, sigma 2 noise:
    >= 95 % untold and >= 99 % told; no blur: 100 %; auto within 3x plain ZNCC's time."""

    def worst(method: str, **match) -> float | None:
        values = [
            r["success"]
            for r in rows
            if r["method"] == method and all(r[k] == v for k, v in match.items())
        ]
        return min(values) if values else None

    out = []
    for blur in (10.0, 12.0):
        for method, limit in (("auto", 0.95), ("auto-told", 0.99)):
            measured = worst(
                method, blur_px=blur, stretch=0.45, subset=41, noise=2.0, gain=1.0, offset=0.0
            )
            if measured is not None:
                out.append(
                    {
                        "target": f"{method}, 45 % stretch, {blur:g} px blur, 41 px, sigma 2",
                        "measured": measured,
                        "limit": limit,
                        "met": measured >= limit,
                    }
                )
    for method in ("auto", "auto-told"):
        measured = worst(method, blur_px=0.0, subset=41, noise=2.0, gain=1.0, offset=0.0)
        if measured is not None:
            out.append(
                {
                    "target": f"{method}, no blur, any stretch, 41 px, sigma 2",
                    "measured": measured,
                    "limit": 1.0,
                    "met": measured >= 1.0,
                }
            )
    return out


def write_plot(rows: list[dict], out: Path) -> str:
    """Success against blur at 0 % and 45 % stretch (sigma 2, no illumination change, 41 px),
    and the time per point of each method; returns the file name."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for ax, stretch in zip(axes[:2], (0.0, 0.45), strict=True):
        for method in METHODS:
            mine = sorted(
                (
                    r
                    for r in rows
                    if r["method"] == method
                    and r["stretch"] == stretch
                    and r["noise"] == 2.0
                    and r["gain"] == 1.0
                    and r["subset"] == 41
                ),
                key=lambda r: r["blur_px"],
            )
            ax.plot(
                [r["blur_px"] for r in mine],
                [100 * r["success"] for r in mine],
                marker="o",
                label=method,
            )
        ax.set_title(f"one-step stretch {stretch:.0%}, 41 px subset, sigma 2", fontsize=9)
        ax.set_xlabel("blur, px")
        ax.set_ylabel("points within 0.5 px, %")
        ax.set_ylim(-3, 103)
        ax.legend(fontsize=7)
    times = [np.median([r["ms_per_point"] for r in rows if r["method"] == m]) for m in METHODS]
    axes[2].bar(METHODS, times)
    axes[2].set_ylabel("median time per point, ms (one thread)")
    axes[2].tick_params(axis="x", labelsize=7)
    fig.tight_layout()
    name = "search.png"
    fig.savefig(out / name, dpi=110)
    plt.close(fig)
    return name


def _cell(key: list) -> str:
    blur, stretch, noise, gain, offset, subset = key
    return (
        f"blur {blur:g} px, stretch {stretch:.0%}, sigma {noise:g}, gain {gain:g}, "
        f"offset {offset:+g}, subset {subset}"
    )


def report_markdown(results: dict, plot: str) -> str:
    """The report's body."""
    s = results["summary"]
    lines = [
        "Which integer search finds the points of a one-step stretch under blur, noise and an "
        "illumination change, and at what cost; see `appliance/bench/search_table.py` for the "
        "scenes and the methods.",
        "",
        f"- grid: {'full' if results['full'] else 'coarse (the default)'}, "
        f"{s['cells']} cases, {len(points_grid())} points each, {results['seconds']:.0f} s",
        "",
        "## Targets",
        "",
        "| target | measured | limit | met |",
        "|---|---|---|---|",
    ]
    for t in results["targets"]:
        lines.append(
            f"| {t['target']} | {100 * t['measured']:.1f} % | {100 * t['limit']:.0f} % | "
            f"{'yes' if t['met'] else 'no'} |"
        )
    lines += [
        f"| auto's time per point over plain ZNCC's, median (largest) | "
        f"{s['auto_time_ratio_median']:.2f} ({s['auto_time_ratio_max']:.2f}) | 3 | "
        f"{'yes' if s['auto_time_ratio_median'] <= 3 else 'no'} |",
        "",
        "## Summary",
        "",
        "| method | mean success | median time per point |",
        "|---|---|---|",
    ]
    for method in METHODS:
        lines.append(
            f"| {method} | {100 * s[method]['mean_success']:.1f} % | "
            f"{s[method]['median_ms_per_point']:.2f} ms |"
        )
    wins = s["lpq_wins"]
    lines += [
        "",
        f"LPQ at the rule's window found more points than every other method in {len(wins)} "
        f"of {s['cells']} cases"
        + (
            ": "
            + "; ".join(
                f"blur {w[0]:g}, stretch {w[1]:.0%}, sigma {w[2]:g}, "
                f"gain {w[3]:g}, offset {w[4]:+g}, subset {w[5]}"
                for w in wins
            )
            if wins
            else ""
        )
        + f", and fewer than the best in {s['lpq_loses']}.",
        "",
        "Against blur-matched ZNCC alone (the same pipeline without recovery), LPQ found more "
        f"points in {len(s['lpq_beats_matched_zncc'])} cases ("
        + "; ".join(_cell(c) for c in s["lpq_beats_matched_zncc"])
        + f") and fewer in {len(s['lpq_behind_matched_zncc'])} ("
        + "; ".join(_cell(c) for c in s["lpq_behind_matched_zncc"])
        + ").",
        "",
        "## Every case",
        "",
        "Success within 0.5 px, % (time per point, ms).",
        "",
        "| blur px | stretch | sigma | gain | offset | subset | "
        + " | ".join(METHODS)
        + " | LPQ window |",
        "|" + "---|" * (7 + len(METHODS)),
    ]
    by_case: dict[tuple, dict[str, dict]] = {}
    for row in results["rows"]:
        key = tuple(row[k] for k in ("blur_px", "stretch", "noise", "gain", "offset", "subset"))
        by_case.setdefault(key, {})[row["method"]] = row
    for key, by in by_case.items():
        blur, stretch, noise, gain, offset, subset = key
        cells = [f"{100 * by[m]['success']:.0f} ({by[m]['ms_per_point']:.2f})" for m in METHODS]
        lines.append(
            f"| {blur:g} | {stretch:.0%} | {noise:g} | {gain:g} | {offset:+g} | {subset} | "
            + " | ".join(cells)
            + f" | {by['lpq']['lpq_window']} |"
        )
    lines += ["", f"![{plot}]({plot})"]
    return "\n".join(lines) + "\n"


def run_search_benchmark(out: Path, *, full: bool = False) -> int:
    """Entry point of `extensometer bench search`: writes its report, figures and plot into
    `out`; returns the exit status."""
    started = time.perf_counter()
    cases = full_grid() if full else coarse_grid()
    rows = run_cases(cases)
    results = {
        "software_version": __version__,
        "full": full,
        "rows": rows,
        "seconds": time.perf_counter() - started,
    }
    results["summary"] = summary(rows)
    results["targets"] = targets(rows)
    out.mkdir(parents=True, exist_ok=True)
    plot = write_plot(rows, out)
    report = write_report(
        out,
        "search",
        "Integer search under blur and one-step stretch: ZNCC, LPQ and the automatic choice",
        results,
        report_markdown(results, plot),
    )
    s = results["summary"]
    for method in METHODS:
        print(
            f"{method:13s} mean success {100 * s[method]['mean_success']:5.1f} %  "
            f"median {s[method]['median_ms_per_point']:.2f} ms/point"
        )
    for t in results["targets"]:
        print(f"  {'ok ' if t['met'] else 'MISS'} {t['target']}: {100 * t['measured']:.1f} %")
    print(
        f"auto / zncc time per point: median {s['auto_time_ratio_median']:.2f}, "
        f"largest {s['auto_time_ratio_max']:.2f}"
    )
    print(f"report: {report}")
    return 0
