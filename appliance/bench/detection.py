"""Benchmark of specimen detection: axis, centre and width against the simulated views' truth.

`extensometer bench detection [--quick] [--out DIR]` renders still views of the two simulated
specimens (`appliance.sim.specimen_view`): the ISO 37 type 1 dumb-bell at the rubber preset's
scale and the ISO 6892-1 type 1 flat piece at the metal preset's, each under the three
lightings (a speckled specimen on a dark backdrop and on a white card, a back-lit silhouette),
rotated from -5 to +5 degrees, off-centre by up to 120 px, half of them with the grips' jaws
in view, over two seeds (speckle and noise); and the reference views of the two simulated
tests (`appliance.sim.world`, as `extensometer run --sim` sees them: the rubber's shows one
tab and only the start of the other shoulder). The product's detection
(`appliance.measure.specimen_detection`) runs on each; the views' truth only scores it.

Figures, over the cases, median and worst: the axis's error (target 0.1 degree), the centre's
distance from the specimen's true centre (2 px), the width's error (0.2 px), and the time the
detection takes. `--quick`: one seed and three poses.
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


def cases(quick: bool) -> list[dict[str, Any]]:
    """The rendered views' parameters."""
    shapes = (
        ("ISO 37 type 1", Specimen.iso37_type1, PRESETS["rubber"].optics.scale_mm_per_px),
        ("ISO 6892-1 type 1", Specimen.iso6892_flat, PRESETS["metal"].optics.scale_mm_per_px),
    )
    poses = POSES[:3] if quick else POSES
    seeds = (1,) if quick else (1, 2)
    return [
        {
            "shape": shape,
            "specimen": make,
            "scale_mm_per_px": scale,
            "lighting": lighting,
            "rotation_deg": rotation,
            "offset_px": offset,
            "grips": grips,
            "seed": seed,
        }
        for shape, make, scale in shapes
        for lighting in LIGHTINGS
        for rotation, offset, grips in poses
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
        "detection_s": elapsed_s,
    }


def _rendered(case: dict[str, Any]) -> dict[str, Any]:
    offset = case["offset_px"]
    image, truth = render_specimen_view(
        case["specimen"](),
        scale_mm_per_px=case["scale_mm_per_px"],
        sensor_size=SENSOR,
        centre_px=(0.5 * (SENSOR[0] - 1) + offset[0], 0.5 * (SENSOR[1] - 1) + offset[1]),
        rotation_deg=case["rotation_deg"],
        lighting=case["lighting"],
        grips=case["grips"],
        seed=case["seed"],
    )
    score = _score(image, truth.centre_px, truth.axis_deg, truth.width_px)
    named = {k: v for k, v in case.items() if k not in ("specimen", "scale_mm_per_px")}
    return {**named, "offset_px": list(offset), **score}


def _simulated_test(material: str) -> dict[str, Any]:
    world = SimWorld(PRESETS[material])
    scene = world.scene
    image, _ = scene.render(0.0, 0.0, Region(0, 0, scene.sensor_width, scene.sensor_height))
    width_px = world.specimen.parallel_width_mm / world.optics.scale_mm_per_px
    score = _score(image, world.specimen_centre_px, 90.0, width_px)
    return {
        "shape": f"simulated {material} test's reference",
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
    table = _table(overall, by_lighting, by_shape, results)
    print(table)
    if out is not None:
        figures = {
            "targets": TARGETS,
            "overall": overall,
            "by_lighting": by_lighting,
            "by_shape": by_shape,
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
    overall: dict[str, Any],
    by_lighting: dict[str, dict[str, Any]],
    by_shape: dict[str, dict[str, Any]],
    results: list[dict[str, Any]],
) -> str:
    met = overall["targets_met"]
    lines = [
        "| cases | n | refused | axis error, deg (median / worst) | centre error, px | "
        "width error, px | detection, s |",
        "|---|---|---|---|---|---|---|",
        _row("all", overall),
        *(_row(f"lighting {name}", figures) for name, figures in by_lighting.items()),
        *(_row(name, figures) for name, figures in by_shape.items()),
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
            f"- {r['shape']}, {r['lighting']}, {r['rotation_deg']:+g} deg: {r['refusal']}"
            for r in refusals
        ]
    return "\n".join(lines)
