"""How much of an entocentric lens's out-of-plane false strain a rigid reference's scale recovers.

A surface that moves dz away from a pinhole camera at the stand-off Z images at Z / (Z + dz) of
its size: the gauge reads a false strain of about -dz / Z. A rigid part that moves out of plane
with the specimen (the clamped end of a tab, or the face of a grip that the slack's take-up
carries along) shows the same scale change and no strain of its own, so its apparent scale,
fitted over a grid of points, is an estimate of the false strain the gauge carries.

This measurement renders typical-bench frames of a simulated test (`[sim] bench = "typical"`),
refines a grid of points on the clamped end of the moving grip's tab with the product's IC-GN
(subset started at the integer-rounded true displacement, as a search would), takes the points
to the specimen plane through the lens (the bench's true lens stands in for a calibration,
whose scale error is 2e-6), fits the grid's scale change by least squares (isotropic, and
across the specimen only) and compares it with the false strain the gauge's centre section
carries (its dz, the warm-up drift). The truth only scores.

Run: ``python -m appliance.bench.out_of_plane metal|rubber [SEED]`` (one line per instant;
the seed draws the camera noise, 7 unless given).
"""

from __future__ import annotations

import dataclasses
import sys

import numpy as np

from appliance.config import Config
from appliance.dic.icgn import ICGN
from appliance.sim.world import PRESETS, SimWorld
from hal.camera.base import Region

EXPOSURE_S = 0.001
"""Exposure of every rendered frame, s (the blur stays below 0.1 px on either preset)."""

CASES = {
    "metal": {
        "speed_mm_min": 10.0,
        "grid_x_mm": np.linspace(-8.0, 8.0, 7),
        "grid_y_mm": np.linspace(-65.0, -61.5, 3),
        "subset_px": 41,
        "times_s": (0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 14.0),
    },
    "rubber": {
        "speed_mm_min": 500.0,
        "grid_x_mm": np.linspace(-9.0, 9.0, 10),
        "grid_y_mm": np.linspace(-54.0, -48.5, 4),
        "subset_px": 41,
        "times_s": (0.0, 0.02, 0.04, 0.06, 0.08, 0.1, 0.12, 0.15, 0.2, 0.4, 1.0),
    },
}
"""Per preset: test speed, the reference grid in material coordinates (the moving grip's
clamped end: the preset's views show that end, not the fixed one), IC-GN subset, instants.
Every subset lies within the clamped end: one that reaches over the clamp's edge sees the free
tab's strain, one that reaches over the specimen's end the still backdrop."""


def _scale_change(before_mm: np.ndarray, after_mm: np.ndarray, axes: slice) -> float:
    """Least-squares scale change of a point set (translation removed) along `axes`."""
    a = before_mm[:, axes] - before_mm[:, axes].mean(0)
    b = after_mm[:, axes] - after_mm[:, axes].mean(0)
    return float((a * b).sum() / (a * a).sum()) - 1.0


def measure(material: str, seed: int = 7) -> list[dict[str, float]]:
    """One row per instant: true strain of the centre 50 mm, the slack's dz, the gauge's false
    strain, the grid's true and estimated scale change (isotropic, across) and the residual."""
    case = CASES[material]
    config = Config()
    config = dataclasses.replace(
        config,
        sim=dataclasses.replace(config.sim, bench="typical", material=material),
        run=dataclasses.replace(config.run, speed_mm_min=case["speed_mm_min"]),
    )
    world = SimWorld.from_config(config, PRESETS[material].optics)
    geometry = world.scene.geometry
    world.machine.start(world.speed_mm_min, 0.0)
    width, height = geometry.sensor_size
    region = Region(0, 0, width, height)
    rng = np.random.default_rng(seed)
    grid_x, grid_y = np.meshgrid(case["grid_x_mm"], case["grid_y_mm"])
    material_mm = np.column_stack([grid_x.ravel(), grid_y.ravel()])
    at_rest = world.machine.deformation_at(0.0)
    reference_px = world.scene.sensor_positions(material_mm, at_rest, 0.0)

    def frame(t_s: float) -> np.ndarray:
        image, _ = world.scene.render(t_s, t_s + EXPOSURE_S, region)
        sigma = np.sqrt(
            config.sim.read_noise_grey**2
            + np.clip(image, 0.0, None) / config.sim.electrons_per_grey
        )
        return image + rng.normal(0.0, 1.0, image.shape) * sigma

    def gauge_scale(t_s: float) -> float:
        deformation = world.machine.deformation_at(t_s + 0.5 * EXPOSURE_S)
        g = float(geometry.magnification_change(deformation, np.array([0.0]))[0])
        return g / geometry.drift(t_s + 0.5 * EXPOSURE_S)

    icgn = ICGN(subset=case["subset_px"], max_iterations=40)
    icgn.prepare(frame(0.0), reference_px)
    plane = geometry.projection.to_plane_mm
    reference_mm = plane(reference_px)
    rows = []
    for t_s in case["times_s"]:
        deformation = world.machine.deformation_at(t_s + 0.5 * EXPOSURE_S)
        true_px = world.scene.image_positions(material_mm, t_s, t_s + EXPOSURE_S)
        result = icgn.compute(frame(t_s), np.round(true_px - reference_px))
        ok = result.ok()
        measured_mm = plane(reference_px[ok] + np.c_[result.u, result.v][ok])
        ends = np.interp([-25.0, 25.0], deformation.material_y_mm, deformation.spatial_y_mm)
        gauge_false = gauge_scale(0.0) / gauge_scale(t_s) - 1.0
        iso = _scale_change(reference_mm[ok], measured_mm, slice(0, 2))
        across = _scale_change(reference_mm[ok], measured_mm, slice(0, 1))
        rows.append(
            {
                "t_s": t_s,
                "strain": float(ends[1] - ends[0]) / 50.0 - 1.0,
                "slack_mm": geometry.slack_mm(deformation),
                "gauge_false_strain": gauge_false,
                "grid_true": _scale_change(reference_mm, plane(true_px), slice(0, 2)),
                "grid_isotropic": iso,
                "grid_across": across,
                "residual_isotropic": gauge_false - iso,
                "residual_across": gauge_false - across,
                "points": int(ok.sum()),
            }
        )
    return rows


def main(argv: list[str]) -> int:
    if not 1 <= len(argv) <= 2 or argv[0] not in CASES or not argv[-1].isdigit() and len(argv) == 2:
        print(
            f"usage: python -m appliance.bench.out_of_plane {'|'.join(CASES)} [SEED]",
            file=sys.stderr,
        )
        return 2
    rows = measure(argv[0], int(argv[1]) if len(argv) == 2 else 7)
    print(" ".join(rows[0]))
    for row in rows:
        print(
            " ".join(
                f"{value:.4g}" if isinstance(value, float) else str(value) for value in row.values()
            )
        )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
