"""Benchmark of specimen detection: axis, centre and width against the simulated views' truth.

`extensometer bench detection [--quick] [--out DIR]` renders still views of the two simulated
specimens (`appliance.sim.specimen_view`): the ISO 37 type 1 dumb-bell at the rubber preset's
scale and the ISO 6892-1 type 1 flat piece at the metal preset's, each under the three
lightings (a speckled specimen on a dark backdrop and on a white card, a back-lit silhouette),
rotated from -5 to +5 degrees, off-centre by up to 120 px, half of them with the grips' jaws
in view, over two seeds (speckle and noise), on a 1024 x 2048 px sensor; the same specimens in
small views (640 x 480 and 800 x 600 px, the whole specimen filling 90 % of the height, without
grips, three poses: rotated up to 3 degrees, off-centre by up to 20 px), which are segmented
at full size; and the reference views of the two simulated tests (`appliance.sim.world`, as
`extensometer run --sim` sees them: the rubber's shows one tab and only the start of the other
shoulder). The product's detection
(`appliance.measure.specimen_detection`) runs on each; the views' truth only scores it.

Figures, over the cases, median and worst: the axis's error (target 0.1 degree), the centre's
distance from the specimen's true centre (2 px), the width's error (0.2 px), and the time the
detection takes; by lighting, specimen, view, and for each small view, specimen and lighting.
`--quick`: one seed, three poses (one in the small views).
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from appliance.bench.results import write_report
from appliance.measure.specimen_detection import SpecimenNotFound, detect_specimen
from appliance.sim.specimen import Specimen
from appliance.sim.specimen_view import LIGHTINGS, render_specimen_view
from appliance.sim.world import PRESETS, SimWorld
from hal.camera.base import Region

TARGETS = {"axis_error_deg": 0.1, "centre_error_px": 2.0, "width_error_px": 0.2}
SENSOR = (1024, 2048)
POSES = (
    (0.0, (0.0, 0.0), False),
    (-5.0, (-90.0, 40.0), True),
    (5.0, (60.0, -80.0), False),
    (2.5, (30.0, 120.0), True),
    (-2.5, (-45.0, -110.0), False),
)
"""(rotation, degrees; offset of the centre from the image's, px; grips in view)."""
SMALL_VIEWS = ((640, 480), (800, 600))
"""(width, height) of the small views, px: the specimen's whole length fills
`SMALL_VIEW_FILL` of the height (`SPECIMEN_LENGTH_MM`), without grips."""
SMALL_VIEW_FILL = 0.9
SPECIMEN_LENGTH_MM = {"ISO 37 type 1": 115.0, "ISO 6892-1 type 1": 200.0}
SMALL_POSES = (
    (0.0, (0.0, 0.0), False),
    (-3.0, (-20.0, 6.0), False),
    (3.0, (15.0, -6.0), False),
)
"""The small views' poses (offsets within what keeps the tabs in view)."""


def cases(quick: bool) -> list[dict[str, Any]]:
    """The rendered views' parameters."""
    shapes = (
        ("ISO 37 type 1", Specimen.iso37_type1, PRESETS["rubber"].optics.scale_mm_per_px),
        ("ISO 6892-1 type 1", Specimen.iso6892_flat, PRESETS["metal"].optics.scale_mm_per_px),
    )
    poses = POSES[:3] if quick else POSES
    small_poses = SMALL_POSES[:1] if quick else SMALL_POSES
    seeds = (1,) if quick else (1, 2)
    views = [(SENSOR, shape, make, scale, poses) for shape, make, scale in shapes]
    views += [
        (size, shape, make, SPECIMEN_LENGTH_MM[shape] / (SMALL_VIEW_FILL * size[1]), small_poses)
        for size in SMALL_VIEWS
        for shape, make, _ in shapes
    ]
    return [
        {
            "view": f"{size[0]}x{size[1]}",
            "sensor_size": size,
            "shape": shape,
            "specimen": make,
            "scale_mm_per_px": scale,
            "lighting": lighting,
            "rotation_deg": rotation,
            "offset_px": offset,
            "grips": grips,
            "seed": seed,
        }
        for size, shape, make, scale, view_poses in views
        for lighting in LIGHTINGS
        for rotation, offset, grips in view_poses
        for seed in seeds
    ]


def _score(image: np.ndarray, centre_px, axis_deg: float, width_px: float) -> dict[str, Any]:
    started = time.perf_counter()
    try:
        found = detect_specimen(image)
    except SpecimenNotFound as exc:
        return {"found": False, "refusal": str(exc)}
    elapsed_s = time.perf_counter() - started
    return {
        "found": True,
        "axis_error_deg": abs((found.axis_deg - axis_deg + 90.0) % 180.0 - 90.0),
        "centre_error_px": float(np.hypot(*np.subtract(found.centre_px, centre_px))),
        "width_error_px": found.width_px - width_px,
        "ends_in_view": list(found.ends_in_view),
        "detection_s": elapsed_s,
    }


def _rendered(case: dict[str, Any]) -> dict[str, Any]:
    offset = case["offset_px"]
    width, height = case["sensor_size"]
    image, truth = render_specimen_view(
        case["specimen"](),
        scale_mm_per_px=case["scale_mm_per_px"],
        sensor_size=(width, height),
        centre_px=(0.5 * (width - 1) + offset[0], 0.5 * (height - 1) + offset[1]),
        rotation_deg=case["rotation_deg"],
        lighting=case["lighting"],
        grips=case["grips"],
        seed=case["seed"],
    )
    score = _score(image, truth.centre_px, truth.axis_deg, truth.width_px)
    named = {k: v for k, v in case.items() if k not in ("specimen", "sensor_size")}
    return {**named, "offset_px": list(offset), **score}


def _simulated_test(material: str) -> dict[str, Any]:
    world = SimWorld(PRESETS[material])
    scene = world.scene
    image, _ = scene.render(0.0, 0.0, Region(0, 0, scene.sensor_width, scene.sensor_height))
    width_px = world.specimen.parallel_width_mm / world.optics.scale_mm_per_px
    score = _score(image, world.specimen_centre_px, 90.0, width_px)
    return {
        "view": f"{scene.sensor_width}x{scene.sensor_height}",
        "shape": f"simulated {material} test's reference",
        "scale_mm_per_px": world.optics.scale_mm_per_px,
        "lighting": "front-dark",
        "rotation_deg": 0.0,
        "offset_px": None,
        "grips": False,
        "seed": 1,
        **score,
    }


def _statistics(results: list[dict[str, Any]]) -> dict[str, Any]:
    found = [r for r in results if r["found"]]
    figures: dict[str, Any] = {"cases": len(results), "refused": len(results) - len(found)}
    for key in (*TARGETS, "detection_s"):
        values = np.abs([r[key] for r in found]) if found else np.array([math.nan])
        figures[key] = {"median": float(np.median(values)), "worst": float(np.max(values))}
    figures["targets_met"] = {
        key: bool(figures["refused"] == 0 and figures[key]["worst"] <= target)
        for key, target in TARGETS.items()
    }
    return figures


def run_detection_benchmark(out: Path | None, *, quick: bool = False) -> int:
    """Run the benchmark, print its table and with `out` write `detection.md` and
    `detection.json` there; exit status 0 (measured, met or not)."""
    results = [_rendered(case) for case in cases(quick)]
    results += [_simulated_test(material) for material in ("rubber", "metal")]
    overall = _statistics(results)
    by_lighting = {
        lighting: _statistics([r for r in results if r["lighting"] == lighting])
        for lighting in LIGHTINGS
    }
    by_shape = {
        shape: _statistics([r for r in results if r["shape"] == shape])
        for shape in dict.fromkeys(r["shape"] for r in results)
    }
    by_view = {
        f"view {view}": _statistics([r for r in results if r["view"] == view])
        for view in dict.fromkeys(r["view"] for r in results)
    }
    small = {
        f"{view} {shape}, {lighting}": _statistics(
            [
                r
                for r in results
                if (r["view"], r["shape"], r["lighting"]) == (view, shape, lighting)
            ]
        )
        for view in (f"{w}x{h}" for w, h in SMALL_VIEWS)
        for shape in SPECIMEN_LENGTH_MM
        for lighting in LIGHTINGS
    }
    groups = {
        **{f"lighting {name}": figures for name, figures in by_lighting.items()},
        **by_shape,
        **by_view,
        **small,
    }
    table = _table(overall, groups, results)
    print(table)
    if out is not None:
        figures = {
            "targets": TARGETS,
            "overall": overall,
            "by_lighting": by_lighting,
            "by_shape": by_shape,
            "by_view": by_view,
            "small_views": small,
            "cases": results,
        }
        report = write_report(
            out,
            "detection",
            "Specimen detection against the simulated views' truth",
            figures,
            f"{__doc__.split(chr(10) * 2, 1)[1]}\n{table}",
        )
        print(f"report: {report}")
    return 0


def _row(name: str, figures: dict[str, Any]) -> str:
    cells = [
        f"{figures[key]['median']:.3f} / {figures[key]['worst']:.3f}"
        for key in (*TARGETS, "detection_s")
    ]
    return f"| {name} | {figures['cases']} | {figures['refused']} | " + " | ".join(cells) + " |"


def _table(
    overall: dict[str, Any], groups: dict[str, dict[str, Any]], results: list[dict[str, Any]]
) -> str:
    met = overall["targets_met"]
    lines = [
        "| cases | n | refused | axis error, deg (median / worst) | centre error, px | "
        "width error, px | detection, s |",
        "|---|---|---|---|---|---|---|",
        _row("all", overall),
        *(_row(name, figures) for name, figures in groups.items()),
        "",
        "Targets over all cases (worst): "
        + ", ".join(
            f"{key} <= {target:g}: {'met' if met[key] else 'NOT met'}"
            for key, target in TARGETS.items()
        ),
    ]
    refusals = [r for r in results if not r["found"]]
    if refusals:
        lines += ["", "Refused:"]
        lines += [
            f"- {r['view']} {r['shape']}, {r['lighting']}, {r['rotation_deg']:+g} deg: "
            f"{r['refusal']}"
            for r in refusals
        ]
    return "\n".join(lines)
