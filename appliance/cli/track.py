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

The work runs on `--threads` workers (default: every core this process may use, up to numba's
thread count): the ZNCC search of all points in batches (`appliance.dic.batched_search`) or the
LPQ search's single compiled pass, IC-GN on the parallel kernel, and the next image read and
prepared (its spline coefficients) while the current one is measured. The numbers do not
depend on the thread count. The JSON says the throughput (`throughput`: points and images per
second from reading the reference to the last image measured, the compiled kernels' loading
left out, and the threads).

The search (`--search auto`, the default) is the one `appliance.dic.search_choice` picks for
the known blur (`--blur-px`) and the expected one-step stretch (`--stretch LOW:HIGH`), and the
JSON says which (`search`; a run that ends well also says it on stderr). Points the search
misses (IC-GN not converged, or a ZNCC below 0.9) are recovered: seeds searched over a scale set of
pre-warps when too few points were found, then every missed point from its nearest found
neighbour's first-order prediction (`appliance.dic.seeded_recovery`); each image says how many
(`search`: `recovered`, `scale_searched`, `waves`). Under a known blur, IC-GN's reference is
blurred as the reference sees the blur through the measured stretch
(`appliance.dic.stretch.blur_in_reference`; each image's `search.icgn_reference_blur_px`).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numba
import numpy as np

from appliance.cli import arguments
from appliance.cli.image_files import read_grey
from appliance.cli.points_file import read_points
from appliance.dic.correlation import (
    DEFAULT_PREFILTER_SIGMA,
    SEARCH_METHODS,
    PointStatus,
    subsets_outside,
)
from appliance.dic.icgn import ICGN, ICGNResult, PreparedTarget
from appliance.dic.point_measurement import PointMeasurement
from appliance.dic.search_choice import SearchChoice, choose_search, explicit_search
from appliance.dic.stretch import STRETCH_AXES
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
        "--search",
        choices=("auto", *SEARCH_METHODS),
        default="auto",
        help="integer search method (auto: the product's choice for the blur and stretch)",
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
        "--lpq-window",
        type=arguments.window_size,
        default=None,
        help="LPQ window M, px (default: 3 x the blur, at least 7, at most the subset)",
    )
    track.add_argument(
        "--stretch",
        type=_stretch_range,
        default=None,
        metavar="LOW:HIGH",
        help="expected one-step strain range, e.g. 0:0.5 (a negative LOW as "
        "--stretch=-0.2:0.3): every point is searched over pre-warped subsets of that range "
        "(default: none; missed points are recovered)",
    )
    track.add_argument(
        "--stretch-axis", choices=STRETCH_AXES, default="x", help="direction of that stretch (x)"
    )
    track.add_argument(
        "--calibration",
        metavar="FILE",
        help="camera calibration (extensometer calibrate): add object-plane positions and "
        "displacements in mm (X_mm, Y_mm, dX_mm, dY_mm) to the JSON",
    )
    track.add_argument(
        "--threads",
        type=arguments.within(int, 1, numba.config.NUMBA_NUM_THREADS),
        default=default_threads(),
        help=f"worker threads ({default_threads()} here: the cores this process may use)",
    )
    output = track.add_mutually_exclusive_group()
    output.add_argument("--json", action="store_true", help="print JSON on stdout")
    output.add_argument("--out", metavar="FILE", help="write JSON to FILE")
    track.set_defaults(handler=track_images)


def _stretch_range(text: str) -> tuple[float, float]:
    """`LOW:HIGH` strains, -0.5 < LOW <= HIGH <= 3."""
    try:
        low, high = (float(part) for part in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not LOW:HIGH (e.g. 0:0.5)") from None
    if not (-0.5 < low <= high <= 3.0):
        raise argparse.ArgumentTypeError(f"{text!r}: need -0.5 < LOW <= HIGH <= 3")
    return low, high


def search_choice(args: argparse.Namespace) -> SearchChoice:
    """The search `track` runs for its options."""
    common = dict(
        blur_px=args.blur_px,
        blur_angle_deg=args.blur_angle_deg,
        stretch=args.stretch,
        stretch_axis=args.stretch_axis,
        subset=args.subset,
    )
    if args.search == "auto":
        return choose_search(**common)
    return explicit_search(args.search, lpq_window=args.lpq_window, **common)


def default_threads() -> int:
    """Worker threads of `track` by default: the cores this process may use, at most numba's
    thread count."""
    return max(1, min(len(os.sched_getaffinity(0)), numba.config.NUMBA_NUM_THREADS))


def track_images(args: argparse.Namespace) -> int:
    """Run `track`; returns the exit status."""
    started = time.perf_counter()
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
    if args.lpq_window is not None and args.lpq_window > args.subset:
        raise InputError(
            f"track: --lpq-window: lpq_window {args.lpq_window} exceeds subset {args.subset}"
        )
    numba.set_num_threads(args.threads)
    choice = search_choice(args)
    warm_up_s = _Pipeline.warm_up(args, reference)
    targets = ICGN(subset=args.subset, prefilter_sigma=args.prefilter_sigma)
    images = _Images(args.images, targets.prepare_target, ahead=args.threads > 1)
    plane = _Plane(calibration.projection(), points.xy) if calibration is not None else None
    guess = np.zeros((len(points.xy), 2)) if points.guess is None else points.guess.copy()
    measured: list[dict] = []
    try:
        pipeline = _Pipeline(args, reference, points.xy, choice)
        for path, image, prepared in images:
            if image.shape != reference.shape:
                raise InputError(
                    f"{path}: size {image.shape[1]}x{image.shape[0]} differs from the "
                    f"reference {args.reference} ({width}x{height})"
                )
            result = pipeline.measure(image, guess, prepared)
            converged = result.status == PointStatus.CONVERGED
            guess[converged, 0] = result.u[converged]
            guess[converged, 1] = result.v[converged]
            measured.append(_image_record(path, points.xy, result, plane))
            if pipeline.report is not None:
                measured[-1]["search"] = pipeline.report
    except InputError as error:
        _emit(args, measured, calibration, None, choice)
        raise error
    finally:
        images.close()
    seconds = time.perf_counter() - started - warm_up_s
    throughput = _throughput(len(points.xy), len(measured), seconds, args)
    _emit(args, measured, calibration, throughput, choice)
    print(f"extensometer track: search: {choice.method} ({choice.reason})", file=sys.stderr)
    return 0


class _Pipeline(PointMeasurement):
    """`appliance.dic.point_measurement.PointMeasurement` for `track`'s options: the search of
    all points (ZNCC in batches) and IC-GN on `--threads` workers."""

    def __init__(
        self,
        args: argparse.Namespace,
        reference: np.ndarray,
        xy: np.ndarray,
        choice: SearchChoice | None = None,
    ) -> None:
        super().__init__(
            reference,
            xy,
            search_choice(args) if choice is None else choice,
            subset=args.subset,
            radius=args.search_radius,
            prefilter_sigma=args.prefilter_sigma,
            threads=args.threads,
            blur=(args.blur_px, args.blur_angle_deg),
            search=args.search != "none",
        )

    @classmethod
    def warm_up(cls, args: argparse.Namespace, reference: np.ndarray) -> float:
        """Load (or compile) the kernels the pipeline runs, by measuring a few points of a
        corner of the reference against itself; returns the seconds it took. The throughput
        leaves them out: they are the process's start, paid once whatever the images."""
        started = time.perf_counter()
        side = min(*reference.shape, 2 * args.subset + 2 * args.search_radius, 256)
        corner = np.ascontiguousarray(reference[:side, :side])
        centre = (side - 1) / 2.0
        step = max(1.0, min(4.0, (side - args.subset) / 4.0))
        xy = centre + step * np.array([(i, j) for i in (-1, 0, 1) for j in (-1, 0, 1)], float)
        pipeline = cls(args, corner, xy, search_choice(args))
        prepared = pipeline.icgn.prepare_target(corner)
        pipeline.measure(corner, np.zeros((len(xy), 2)), prepared)
        return time.perf_counter() - started


class _Images:
    """(path, image, prepared image) of every path in order, from iterating. With `ahead`, the
    next image is read and prepared (`prepare`: its spline coefficients) on another thread
    while the caller works on the current one (both release the GIL), the first from the start
    while the reference is being prepared. A bad file raises its `InputError` when its turn
    comes. `close()` when done."""

    def __init__(
        self, paths: list[str], prepare: Callable[[np.ndarray], PreparedTarget], *, ahead: bool
    ) -> None:
        self._paths = paths
        self._prepare = prepare
        self._reader = ThreadPoolExecutor(max_workers=1) if ahead else None
        self._pending: Future | None = None
        if self._reader is not None:
            self._pending = self._reader.submit(self._load, paths[0])

    def _load(self, path: str) -> tuple[np.ndarray, PreparedTarget]:
        image = read_grey(path)
        return image, self._prepare(image)

    def __iter__(self) -> Iterator[tuple[str, np.ndarray, PreparedTarget]]:
        for k, path in enumerate(self._paths):
            if self._reader is None or self._pending is None:
                yield path, *self._load(path)
                continue
            image, prepared = self._pending.result()
            if k + 1 < len(self._paths):
                self._pending = self._reader.submit(self._load, self._paths[k + 1])
            yield path, image, prepared

    def close(self) -> None:
        """Stop reading ahead (a read under way finishes first)."""
        if self._reader is not None:
            self._reader.shutdown(wait=True, cancel_futures=True)


def _throughput(points: int, images: int, seconds: float, args: argparse.Namespace) -> dict:
    return {
        "points_per_s": points * images / seconds,
        "images_per_s": images / seconds,
        "seconds": seconds,
        "threads": args.threads,
    }


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
    names = ("u", "v", "ux", "uy", "vx", "vy")
    columns = [getattr(result, name).tolist() for name in names]
    zncc = result.zncc.tolist()
    iterations = result.iterations.tolist()
    labels = {int(status): status.name.lower() for status in PointStatus}
    records = []
    for k, ((x, y), status) in enumerate(zip(xy.tolist(), result.status.tolist(), strict=True)):
        ok = status == PointStatus.CONVERGED
        shape = {
            name: _finite_or_none(column[k]) if ok else None
            for name, column in zip(names, columns, strict=True)
        }
        records.append(
            {
                "x": float(x),
                "y": float(y),
                **shape,
                "zncc": _finite_or_none(zncc[k]),
                "iterations": int(iterations[k]),
                "status": labels[int(status)],
                **in_plane[k],
            }
        )
    return {"path": str(path), "points": records}


def _emit(
    args: argparse.Namespace,
    measured: list[dict],
    calibration: CameraCalibration | None,
    throughput: dict | None,
    choice: SearchChoice | None = None,
) -> None:
    document: dict = {"images": measured}
    if choice is not None:
        document["search"] = {"requested": args.search, **choice.describe()}
    if calibration is not None:
        document["calibration"] = {
            "file": str(args.calibration),
            "checksum": calibration.checksum,
            "scale_mm_per_px": calibration.scale_mm_per_px,
        }
    if throughput is not None:
        document["throughput"] = throughput
    if args.out:
        try:
            Path(args.out).write_text(_json_text(document), encoding="utf-8")
        except OSError as exc:
            raise InputError(f"{args.out}: cannot write output ({exc.strerror})") from None
    elif args.json:
        sys.stdout.write(_json_text(document))
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


def _json_text(document: dict) -> str:
    """The document as JSON: a line per image (json's compiled encoder writes a line; its
    indenting one is pure Python, the slowest part of a large `track`), a line per other key."""
    parts = []
    for key, value in document.items():
        if key == "images":
            images = ",\n  ".join(json.dumps(image) for image in value)
            parts.append(f'"images": [\n  {images}\n ]' if value else '"images": []')
        else:
            parts.append(f"{json.dumps(key)}: {json.dumps(value)}")
    return "{\n " + ",\n ".join(parts) + "\n}\n"
