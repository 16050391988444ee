"""Camera calibrations made from simulated target views, and how far they are from the true lens.

The optics benchmark (`appliance.bench.optics`) calibrates the simulated bench's lens the way a
lab calibrates a real one: images of a ChArUco board through the lens, the first lying in the
specimen's plane at rest (the plane the calibration measures in), the others tilted over the
field (`appliance.sim.target.calibration_poses`), given to the product's own calibration
(`appliance.optics.target_calibration.calibrate`, what `extensometer calibrate` runs). The
calibration sees only the images; the world's true camera and plane are read afterwards, to
score it:

* `rms_reprojection_px`: the calibration's own RMS reprojection error over every corner;
* `scale_error_percent`: the calibrated scale at the image centre against the true lens's on
  the true specimen plane, % (signed);
* `corner_distortion_error_px`: at the four field corners, the largest difference between the
  distortion the calibrated camera puts there and the true lens's (`CameraModel.distortion_px`),
  px;
* `corner_length_error_px`: the largest error, over the four corners, of the distance on the
  specimen plane from the image centre to the corner (calibrated against true), in pixels of
  the true scale: intrinsics, distortion and plane together, over the whole field.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from appliance.config import Config
from appliance.optics.calibration_file import CameraCalibration, save_calibration
from appliance.optics.calibration_target import CalibrationTarget
from appliance.optics.camera_model import CameraModel, PlanePose, PlaneProjection
from appliance.optics.target_calibration import calibrate, find_target
from appliance.plan.optics import configured_optics
from appliance.sim.target import TargetLook, calibration_poses, render_target
from appliance.sim.world import PRESETS, SimWorld

SQUARES = (9, 14)
"""The board imaged: 9 x 14 ChArUco squares, sized to the field (`target_for`)."""

VIEWS = 25
"""Views per calibration: the specimen plane's and 24 tilted over the field, three at each of
its four corners and four edges (with 14, one or two at each, the distortion at the field's
corners came within 0.019 / 0.010 / 0.027 px of the lens's over seeds 1, 2, 3)."""

TARGETS = {"rms_reprojection_px": 0.05, "scale_error_percent": 0.02, "corner_distortion_px": 0.02}
"""The calibration's targets: RMS reprojection (px), |scale error| at the specimen plane (%),
distortion recovered at the field corners (px)."""


def bench_world(config: Config) -> SimWorld:
    """The simulated world `config` describes (its lens and specimen plane are the truth)."""
    optics = configured_optics(config, PRESETS[config.sim.material].optics)
    return SimWorld.from_config(config, optics)


def target_for(camera: CameraModel, plane: PlanePose) -> CalibrationTarget:
    """A `SQUARES` ChArUco board whose short side spans about 70 % of the field's (squares a
    whole half millimetre, markers 70 % of a square)."""
    scale = PlaneProjection(camera, plane).scale_mm_per_px((camera.cx_px, camera.cy_px))
    field_mm = scale * min(camera.width_px, camera.height_px)
    square_mm = max(1.0, round(2.0 * 0.7 * field_mm / SQUARES[0]) / 2.0)
    return CalibrationTarget("charuco", SQUARES[0], SQUARES[1], square_mm, 0.7 * square_mm)


def target_views(
    camera: CameraModel,
    plane: PlanePose,
    target: CalibrationTarget,
    folder: Path,
    *,
    seed: int,
    count: int = VIEWS,
) -> list[Path]:
    """Images of `target` through `camera` written as PNG into `folder`: the first lying in
    `plane` centred on the image centre, the others tilted over the field (`seed` picks their
    poses and noise)."""
    folder.mkdir(parents=True, exist_ok=True)
    distance_mm = float(plane.translation_mm[2])
    poses = calibration_poses(camera, target, count, distance_mm=distance_mm, seed=seed)
    centre = PlaneProjection(camera, plane).to_plane_mm([[camera.cx_px, camera.cy_px]])[0]
    middle = np.array([0.5 * target.size_mm[0], 0.5 * target.size_mm[1], 0.0])
    origin = plane.translation + plane.rotation @ (np.array([*centre, 0.0]) - middle)
    poses[0] = PlanePose.from_arrays(plane.rotation_vector, origin)
    paths = []
    for k, pose in enumerate(poses):
        path = folder / f"view{k:02d}.png"
        image = render_target(target, pose, camera, look=TargetLook(), seed=seed * 1000 + k)
        cv2.imwrite(str(path), image)
        paths.append(path)
    return paths


def calibrate_views(
    paths: list[Path], target: CalibrationTarget, *, telecentric: bool = False
) -> CameraCalibration:
    """The product's calibration from the images of `target` (the first is the specimen
    plane); `telecentric`: fit a telecentric camera (`extensometer calibrate --telecentric`)."""
    views = []
    for path in paths:
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        views.append(find_target(target, image, path.name))
    return calibrate(views, target, plane_index=0, telecentric=telecentric)


def calibration_for(config: Config, folder: Path, *, seed: int) -> tuple[Path, dict[str, Any]]:
    """Calibrate the lens of the world `config` describes from target views written under
    `folder`; save it as `folder/lens.cal.json`; returns its path and its figures
    (`score`)."""
    world = bench_world(config)
    started = time.perf_counter()
    target = target_for(world.lens_camera, world.specimen_plane)
    paths = target_views(world.lens_camera, world.specimen_plane, target, folder, seed=seed)
    calibration = calibrate_views(paths, target, telecentric=world.lens_camera.telecentric)
    figures = score(calibration, world.lens_camera, world.specimen_plane)
    figures["seed"] = seed
    figures["target"] = target.describe()
    figures["wall_s"] = time.perf_counter() - started
    path = folder / "lens.cal.json"
    save_calibration(calibration, path)
    return path, figures


def score(calibration: CameraCalibration, camera: CameraModel, plane: PlanePose) -> dict[str, Any]:
    """How far `calibration` is from the true `camera` and specimen `plane` (see the module)."""
    fitted = calibration.camera
    centre = (0.5 * (camera.width_px - 1), 0.5 * (camera.height_px - 1))
    true_scale = PlaneProjection(camera, plane).scale_mm_per_px(centre)
    corners = np.array(
        [
            [0.0, 0.0],
            [camera.width_px - 1.0, 0.0],
            [0.0, camera.height_px - 1.0],
            [camera.width_px - 1.0, camera.height_px - 1.0],
        ]
    )
    true_distortion = camera.distortion_px(corners)
    fitted_distortion = fitted.distortion_px(corners)
    centre_and_corners = np.vstack([[centre], corners])
    true_mm = PlaneProjection(camera, plane).to_plane_mm(centre_and_corners)
    fitted_mm = calibration.projection().to_plane_mm(centre_and_corners)
    true_length = np.hypot(*(true_mm[1:] - true_mm[0]).T)
    fitted_length = np.hypot(*(fitted_mm[1:] - fitted_mm[0]).T)
    return {
        "rms_reprojection_px": calibration.rms_reprojection_px,
        "scale_error_percent": 100.0 * (calibration.scale_mm_per_px / true_scale - 1.0),
        "scale_uncertainty_percent": 100.0
        * calibration.scale_uncertainty_mm_per_px
        / calibration.scale_mm_per_px,
        "true_corner_distortion_px": float(true_distortion.max()),
        "corner_distortion_error_px": float(np.abs(fitted_distortion - true_distortion).max()),
        "corner_length_error_px": float(np.abs(fitted_length - true_length).max() / true_scale),
        "coverage_fraction": calibration.coverage_fraction,
    }


def calibration_config(
    bench: str = "typical", material: str = "rubber", sim: dict[str, Any] | None = None
) -> Config:
    """The configuration whose world is calibrated: `material`'s camera on `bench`, with the
    `[sim]` keys `sim` set (`lens = "telecentric"`: the bench's telecentric lens, calibrated
    as such)."""
    config = Config()
    return dataclasses.replace(
        config,
        sim=dataclasses.replace(config.sim, material=material, bench=bench, **(sim or {})),
    )


class Calibrations:
    """One calibration per (material, bench), made when first asked for, as a lab calibrates a
    bench once for every test on it (the lens does not depend on the test).

    Args:
        folder: where each calibration's views and file go (`<material>-<bench>/`).
        sim: `[sim]` keys set in every world calibrated (`calibration_config`).
    """

    def __init__(self, folder: Path, sim: dict[str, Any] | None = None) -> None:
        self._folder = folder
        self._sim = sim
        self._made: dict[tuple[str, str], tuple[Path, dict[str, Any]]] = {}

    def add(self, material: str, bench: str, path: Path, figures: dict[str, Any]) -> None:
        """Keep a calibration made elsewhere for (`material`, `bench`, its own lens)."""
        self._made[(material, bench, None)] = (path, figures)

    def get(
        self, material: str, bench: str, lens: str | None = None
    ) -> tuple[Path, dict[str, Any]]:
        """The calibration file of `material`'s camera on `bench` and its figures (seed 1);
        `lens` replaces the bench's lens (`[sim] lens`)."""
        key = (material, bench, lens)
        if key not in self._made:
            folder = self._folder / "-".join([material, bench, *([lens] if lens else [])])
            sim = {**(self._sim or {}), **({"lens": lens} if lens else {})}
            config = calibration_config(bench, material, sim)
            self._made[key] = calibration_for(config, folder, seed=1)
        return self._made[key]


def calibration_trials(
    folder: Path,
    seeds: list[int],
    calibrations: Calibrations | None = None,
    sim: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Calibrate the typical bench's lens (the rubber preset's camera, with the `[sim]` keys
    `sim`) once per seed; the figures of every trial, their median and worst (largest
    magnitude), each against its target. Seed 1's calibration is kept in `calibrations`."""
    config = calibration_config(sim=sim)
    trials = []
    for seed in seeds:
        path, figures = calibration_for(config, folder / f"seed{seed}", seed=seed)
        if seed == 1 and calibrations is not None:
            calibrations.add("rubber", "typical", path, figures)
        trials.append(figures)
        print(
            f"calibration, seed {seed}: RMS {figures['rms_reprojection_px']:.4f} px, scale "
            f"{figures['scale_error_percent']:+.4f} %, corners "
            f"{figures['corner_distortion_error_px']:.4f} px ({figures['wall_s']:.0f} s)",
            flush=True,
        )
    keys = {
        "rms_reprojection_px": "rms_reprojection_px",
        "scale_error_percent": "scale_error_percent",
        "corner_distortion_px": "corner_distortion_error_px",
    }
    rows = {}
    for target_key, key in keys.items():
        values = np.array([t[key] for t in trials])
        worst = float(values[np.argmax(np.abs(values))])
        rows[key] = {
            "median": float(np.median(values)),
            "worst": worst,
            "target": TARGETS[target_key],
            "verdict": "met" if abs(worst) <= TARGETS[target_key] else "missed",
        }
    corner = np.array([t["corner_length_error_px"] for t in trials])
    rows["corner_length_error_px"] = {
        "median": float(np.median(corner)),
        "worst": float(corner.max()),
        "target": None,
        "verdict": "-",
    }
    return {
        "bench": "typical",
        "camera": "rubber preset",
        "target": trials[0]["target"],
        "views": VIEWS,
        "true_corner_distortion_px": trials[0]["true_corner_distortion_px"],
        "trials": trials,
        "figures": rows,
    }
