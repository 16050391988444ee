"""`extensometer track`: correlate points of interest between a reference and target images.

Each target is measured against the reference (integer search, then IC-GN), the result of one
image seeding the next. Results go to stdout as a table or JSON, or to a file; the images
measured before a bad one are still written.

With `--calibration FILE` (written by `extensometer calibrate`, for the reference's image
size) each point of the JSON also gets its position on the specimen plane, `X_mm`, `Y_mm`
(where it is in the image, mapped through the calibration: lens distortion removed, its ray
intersected with the calibrated plane), and its displacement there since the reference,
`dX_mm`, `dY_mm`; all four null where the point was not found. The document then names the
calibration (`calibration`: file, checksum, scale).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from appliance.cli import arguments
from appliance.cli.image_files import read_grey
from appliance.cli.points_file import read_points
from appliance.dic.correlation import (
    DEFAULT_PREFILTER_SIGMA,
    SEARCH_METHODS,
    Correlator,
    PointStatus,
    subsets_outside,
)
from appliance.dic.icgn import ICGNResult
from appliance.errors import InputError
from appliance.measure.tracking import TrackerSettings
from appliance.optics.calibration_file import CameraCalibration, load_calibration
from appliance.optics.camera_model import PlaneProjection


def add_parser(commands: argparse._SubParsersAction) -> None:
    """The `track` command."""
    track = commands.add_parser(
        "track",
        help="correlate points between a reference and target images",
        description=(
            "Measure the displacement of each point of interest from REF to every IMG: "
            "integer search, then IC-GN subpixel refinement with a first-order shape "
            "function. Each image is measured against REF; the result of the previous "
            "image seeds the next one (the points file's u0,v0 seed the first)."
        ),
    )
    track.add_argument("reference", metavar="REF", help="reference image (TIFF, PNG, BMP)")
    track.add_argument("images", metavar="IMG", nargs="+", help="target images")
    track.add_argument(
        "--points", required=True, metavar="FILE", help="CSV with header x,y[,u0,v0]"
    )
    track.add_argument(
        "--subset", type=arguments.subset_size, default=41, help="subset size, px (41)"
    )
    track.add_argument(
        "--search", choices=SEARCH_METHODS, default="zncc", help="integer search method (zncc)"
    )
    track.add_argument(
        "--search-radius",
        type=arguments.within(int, 0, 1000),
        default=50,
        help="search half-width, px (50)",
    )
    track.add_argument(
        "--prefilter-sigma",
        type=arguments.like_key(TrackerSettings, "prefilter_sigma_px"),
        default=DEFAULT_PREFILTER_SIGMA,
        help=f"Gaussian pre-filter of both images before IC-GN, px ({DEFAULT_PREFILTER_SIGMA}; "
        "0 = off)",
    )
    track.add_argument(
        "--blur-px",
        type=arguments.within(float, 0.0, 301.0),
        default=0.0,
        help="known motion blur of the targets, px: the reference is blurred to match (0)",
    )
    track.add_argument(
        "--blur-angle-deg",
        type=arguments.within(float, -360.0, 360.0),
        default=0.0,
        help="direction of that motion, degrees from +x towards +y (0)",
    )
    track.add_argument(
        "--lpq-window", type=arguments.window_size, default=None, help="LPQ window M, px (7)"
    )
    track.add_argument(
        "--calibration",
        metavar="FILE",
        help="camera calibration (extensometer calibrate): add object-plane positions and "
        "displacements in mm (X_mm, Y_mm, dX_mm, dY_mm) to the JSON",
    )
    output = track.add_mutually_exclusive_group()
    output.add_argument("--json", action="store_true", help="print JSON on stdout")
    output.add_argument("--out", metavar="FILE", help="write JSON to FILE")
    track.set_defaults(handler=track_images)


def track_images(args: argparse.Namespace) -> int:
    """Run `track`; returns the exit status."""
    points = read_points(args.points)
    reference = read_grey(args.reference)
    height, width = reference.shape
    calibration = _calibration(args.calibration, (width, height))
    outside = subsets_outside(points.xy, reference.shape, args.subset)
    if outside.any():
        k = int(np.argmax(outside))
        x, y = points.xy[k]
        raise InputError(
            f"{args.points}:{points.lines[k]}: subset {args.subset}x{args.subset} at "
            f"({x:g}, {y:g}) reaches outside the {width}x{height} reference image "
            f"{args.reference}"
        )
    try:
        correlator = Correlator(
            subset=args.subset,
            search=args.search,
            search_radius=args.search_radius,
            prefilter_sigma=args.prefilter_sigma,
            reference_blur=(args.blur_px, args.blur_angle_deg) if args.blur_px > 0 else None,
            lpq_window=args.lpq_window,
        )
    except ValueError as exc:
        raise InputError(f"track: --lpq-window: {exc}") from None
    correlator.prepare(reference.astype(np.float64), points.xy)
    plane = _Plane(calibration.projection(), points.xy) if calibration is not None else None
    guess = np.zeros((len(points.xy), 2)) if points.guess is None else points.guess.copy()
    measured: list[dict] = []
    try:
        for path in args.images:
            image = read_grey(path)
            if image.shape != reference.shape:
                raise InputError(
                    f"{path}: size {image.shape[1]}x{image.shape[0]} differs from the "
                    f"reference {args.reference} ({width}x{height})"
                )
            result = correlator.measure(image.astype(np.float64), guess).refinement
            converged = result.status == PointStatus.CONVERGED
            guess[converged, 0] = result.u[converged]
            guess[converged, 1] = result.v[converged]
            measured.append(_image_record(path, points.xy, result, plane))
    except InputError as error:
        _emit(args, measured, calibration)
        raise error
    _emit(args, measured, calibration)
    return 0


def _calibration(path: str | None, size: tuple[int, int]) -> CameraCalibration | None:
    """The `--calibration` file, checked for the reference's size; None without one."""
    if path is None:
        return None
    try:
        return load_calibration(Path(path), sensor_size=size)
    except InputError as exc:
        raise InputError(f"track: --calibration: {exc}") from None


class _Plane:
    """Object-plane positions of the points of interest, and their displacements there."""

    def __init__(self, projection: PlaneProjection, xy: np.ndarray) -> None:
        self.projection = projection
        self.reference_mm = self._plane_mm(xy)

    def _plane_mm(self, xy: np.ndarray) -> np.ndarray:
        """(n, 2) plane positions, mm; NaN where a position cannot be mapped."""
        plane = np.full(xy.shape, math.nan)
        for k, point in enumerate(xy):
            if np.all(np.isfinite(point)):
                try:
                    plane[k] = self.projection.to_plane_mm(point[None, :])[0]
                except ValueError:
                    continue
        return plane

    def fields(self, xy: np.ndarray, found: np.ndarray) -> list[dict[str, float | None]]:
        """`X_mm`, `Y_mm`, `dX_mm`, `dY_mm` of each point at `xy` (null where not found)."""
        plane = self._plane_mm(np.where(found[:, None], xy, math.nan))
        moved = plane - self.reference_mm
        return [
            {
                "X_mm": _finite_or_none(plane[k, 0]),
                "Y_mm": _finite_or_none(plane[k, 1]),
                "dX_mm": _finite_or_none(moved[k, 0]),
                "dY_mm": _finite_or_none(moved[k, 1]),
            }
            for k in range(len(xy))
        ]


def _finite_or_none(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def _image_record(
    path: str, xy: np.ndarray, result: ICGNResult, plane: _Plane | None = None
) -> dict:
    """One image's points: a point that was not found (any status but converged) has no
    displacement or gradient (null), only its status saying why, its ZNCC and iterations;
    with a calibration, the object-plane fields (`_Plane.fields`)."""
    found = np.asarray(result.status) == PointStatus.CONVERGED
    moved = xy + np.column_stack([result.u, result.v])
    in_plane = plane.fields(moved, found) if plane is not None else [{}] * len(xy)
    records = []
    for k in range(len(xy)):
        status = PointStatus(int(result.status[k]))
        found = status is PointStatus.CONVERGED
        shape = {
            name: _finite_or_none(getattr(result, name)[k]) if found else None
            for name in ("u", "v", "ux", "uy", "vx", "vy")
        }
        records.append(
            {
                "x": float(xy[k, 0]),
                "y": float(xy[k, 1]),
                **shape,
                "zncc": _finite_or_none(result.zncc[k]),
                "iterations": int(result.iterations[k]),
                "status": status.name.lower(),
                **in_plane[k],
            }
        )
    return {"path": str(path), "points": records}


def _emit(
    args: argparse.Namespace, measured: list[dict], calibration: CameraCalibration | None
) -> None:
    document: dict = {"images": measured}
    if calibration is not None:
        document["calibration"] = {
            "file": str(args.calibration),
            "checksum": calibration.checksum,
            "scale_mm_per_px": calibration.scale_mm_per_px,
        }
    if args.out:
        try:
            Path(args.out).write_text(json.dumps(document, indent=1) + "\n", encoding="utf-8")
        except OSError as exc:
            raise InputError(f"{args.out}: cannot write output ({exc.strerror})") from None
    elif args.json:
        json.dump(document, sys.stdout, indent=1)
        sys.stdout.write("\n")
    else:
        for image in measured:
            print(image["path"])
            print(f"{'x':>9} {'y':>9} {'u':>10} {'v':>10} {'zncc':>8} {'it':>3}  status")
            for p in image["points"]:
                u = "-" if p["u"] is None else f"{p['u']:10.4f}"
                v = "-" if p["v"] is None else f"{p['v']:10.4f}"
                zncc = "-" if p["zncc"] is None else f"{p['zncc']:8.5f}"
                print(
                    f"{p['x']:9.2f} {p['y']:9.2f} {u:>10} {v:>10} {zncc:>8} "
                    f"{p['iterations']:3d}  {p['status']}"
                )
