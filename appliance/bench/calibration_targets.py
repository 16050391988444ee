"""Benchmark of `extensometer calibrate` with each target kind: what a calibration recovers.

A 2048 x 1024 px sensor of 5.5 um pixels behind a 14 mm lens at 400 mm (fx = 2545 px) with
k1 = -0.05 (about 12 px, 1 %, of distortion at the image corners) sees a target in `views`
poses (`appliance.sim.target.calibration_poses`: one facing, the others tilted 30..45 degrees,
circles 30..40, over the field), rendered in 8 bits with Gaussian noise. For each seed the
calibration's errors against the true camera are measured:

- fx, fy, cx, cy errors, px;
- the lens's displacement at the four image corners (each model's own: a pixel minus where
  its distortion-free twin images the same ray) against the truth's, worst corner, px;
- the scale at the image centre on the plane view's target against the truth, and the
  calibration's stated standard uncertainty, %;
- the RMS reprojection error and the field coverage.

    python -m appliance.bench.calibration_targets [--target charuco] [--views 12]
        [--seeds 1 2 3] [--noise-grey 0.5]

(`appliance.bench.optics_calibration` scores calibrations of the simulated bench's own lens.)
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from appliance.optics.calibration_target import CalibrationTarget
from appliance.optics.camera_model import CameraModel, LensDistortion, PlaneProjection
from appliance.optics.target_calibration import calibrate, find_target
from appliance.sim.target import TargetLook, calibration_poses, render_target

CAMERA = CameraModel.ideal(2048, 1024, 2545.0, distortion=LensDistortion(k1=-0.05))
DISTANCE_MM = 400.0
TARGETS = {
    "charuco": CalibrationTarget("charuco", 10, 6, 15.0),
    "chessboard": CalibrationTarget("chessboard", 9, 6, 12.0),
    "circles": CalibrationTarget("circles", 9, 5, 14.0),
}


@dataclass(frozen=True)
class CalibrationFigures:
    """One simulated calibration's errors against the truth (see the module's docstring)."""

    seed: int
    fx_error_px: float
    fy_error_px: float
    cx_error_px: float
    cy_error_px: float
    corner_distortion_px: float
    corner_distortion_error_px: float
    scale_error_percent: float
    scale_uncertainty_percent: float
    rms_px: float
    coverage_fraction: float


def corner_displacement_px(camera: CameraModel) -> np.ndarray:
    """The lens's displacement (4, 2) px at the four image corners."""
    right, bottom = camera.width_px - 1.0, camera.height_px - 1.0
    corners = np.array([[0.0, 0.0], [right, 0.0], [0.0, bottom], [right, bottom]])
    normalised = camera.normalised(corners)
    ideal = normalised * [camera.fx_px, camera.fy_px] + [camera.cx_px, camera.cy_px]
    return corners - ideal


def calibration_figures(
    target: CalibrationTarget, *, views: int, seed: int, noise_grey: float
) -> CalibrationFigures:
    """Calibrate from simulated views of `target` and compare with the true camera."""
    tilt = (30.0, 40.0) if target.kind == "circles" else (30.0, 45.0)
    poses = calibration_poses(
        CAMERA, target, views, distance_mm=DISTANCE_MM, seed=seed, tilt_deg=tilt
    )
    look = TargetLook(noise_grey=noise_grey)
    found = []
    for k, pose in enumerate(poses):
        image = render_target(target, pose, CAMERA, look=look, seed=1000 * seed + k)
        found.append(find_target(target, image, f"view {k}"))
    calibration = calibrate(found, target)
    camera = calibration.camera
    centre = (0.5 * (CAMERA.width_px - 1), 0.5 * (CAMERA.height_px - 1))
    true_scale = PlaneProjection(CAMERA, poses[0]).scale_mm_per_px(centre)
    truth = corner_displacement_px(CAMERA)
    error = corner_displacement_px(camera) - truth
    return CalibrationFigures(
        seed=seed,
        fx_error_px=camera.fx_px - CAMERA.fx_px,
        fy_error_px=camera.fy_px - CAMERA.fy_px,
        cx_error_px=camera.cx_px - CAMERA.cx_px,
        cy_error_px=camera.cy_px - CAMERA.cy_px,
        corner_distortion_px=float(np.hypot(*truth.T).max()),
        corner_distortion_error_px=float(np.hypot(*error.T).max()),
        scale_error_percent=100.0 * (calibration.scale_mm_per_px / true_scale - 1.0),
        scale_uncertainty_percent=100.0 * calibration.scale_uncertainty_mm_per_px / true_scale,
        rms_px=calibration.rms_reprojection_px,
        coverage_fraction=calibration.coverage_fraction,
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Print the figures of a few seeded calibrations."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--target", choices=sorted(TARGETS), default="charuco")
    parser.add_argument("--views", type=int, default=12)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--noise-grey", type=float, default=0.5)
    args = parser.parse_args(argv)
    target = TARGETS[args.target]
    print(f"{target.describe()}, {args.views} views, noise {args.noise_grey:g} grey")
    print(
        "seed  dfx_px  dfy_px  dcx_px  dcy_px  corner_dist_px  dist_err_px  scale_err_%  "
        "scale_u_%  rms_px  coverage"
    )
    for seed in args.seeds:
        f = calibration_figures(target, views=args.views, seed=seed, noise_grey=args.noise_grey)
        print(
            f"{f.seed:4d}  {f.fx_error_px:+6.2f}  {f.fy_error_px:+6.2f}  {f.cx_error_px:+6.2f}  "
            f"{f.cy_error_px:+6.2f}  {f.corner_distortion_px:14.2f}  "
            f"{f.corner_distortion_error_px:11.3f}  {f.scale_error_percent:+11.4f}  "
            f"{f.scale_uncertainty_percent:9.4f}  {f.rms_px:6.3f}  {f.coverage_fraction:8.2f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
