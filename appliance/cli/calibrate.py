"""`extensometer calibrate`: calibrate the camera from images of a target; field-check it.

    extensometer calibrate IMG [IMG ...] --target charuco --squares COLSxROWS --square-mm S
                           [--marker-mm M] [--dictionary DICT_5X5_100] [--plane IMG]
                           [--telecentric [--object-distance-mm Z]] --out FILE.json
    extensometer calibrate --check FILE.json IMG ...

The calibration (`appliance.optics.target_calibration`) fits a pinhole camera with five
Brown-Conrady coefficients to the target's corners in every image, takes the target's surface
in the `--plane` image (default the first) as the specimen plane, and writes the calibration
file. `--telecentric` fits a telecentric (orthographic) camera instead (fx, fy in px per mm,
the same distortion model, fitted with scipy: `appliance.optics.telecentric_calibration`); the
planes' distance is not observable through such a lens and is recorded as
`--object-distance-mm` (0 unless given). `--check` solves the target's pose in each image
under the stored intrinsics (a telecentric camera's too) and says whether the calibration
still fits: exit 0 fit, 1 not fit. Bad input, or a calibration that falls short of its
limits, ends with one line and exit status 2.
"""

from __future__ import annotations

import argparse
import datetime
import re
from pathlib import Path

import numpy as np

import appliance
from appliance.cli import arguments
from appliance.cli.image_files import read_grey
from appliance.cli.printing import print_json
from appliance.errors import InputError
from appliance.optics.calibration_file import load_calibration, save_calibration
from appliance.optics.calibration_target import DEFAULT_DICTIONARY, KINDS, CalibrationTarget
from appliance.optics.target_calibration import (
    MIN_VIEWS,
    CalibrationLimits,
    CheckLimits,
    View,
    calibrate,
    check_calibration,
    find_target,
    target_from_document,
)

EXIT_NOT_FIT = 1


def add_parser(commands: argparse._SubParsersAction) -> None:
    """The `calibrate` command."""
    parser = commands.add_parser(
        "calibrate",
        help="calibrate the camera from images of a target, or check a calibration",
        description=(
            "Fit the camera's intrinsics and lens distortion (OpenCV, pinhole, k1 k2 p1 p2 "
            "k3) to views of a planar target, take the target's surface in the --plane image "
            "as the specimen plane, and write the calibration file. At least "
            f"{MIN_VIEWS} views; ten or more, tilted 30..45 degrees and spread over the "
            "field's edges and corners, are recommended. With --check FILE: the target's "
            "pose in each image under the stored intrinsics, the reprojection error and the "
            "scale now against the stored scale; exit 0 when the calibration still fits, 1 "
            "when it does not."
        ),
    )
    parser.add_argument("images", metavar="IMG", nargs="+", help="images of the target")
    parser.add_argument("--target", choices=KINDS, help="target kind")
    parser.add_argument(
        "--squares",
        type=_squares,
        metavar="COLSxROWS",
        help="squares across and down (circles: circles across and down)",
    )
    parser.add_argument(
        "--square-mm",
        type=arguments.within(float, 0.0, 1000.0, above=True),
        metavar="S",
        help="square side (circles: centre spacing), mm",
    )
    parser.add_argument(
        "--marker-mm",
        type=arguments.within(float, 0.0, 1000.0, above=True),
        metavar="M",
        help="ChArUco marker side, mm (0.7 of the square)",
    )
    parser.add_argument(
        "--dictionary",
        default=DEFAULT_DICTIONARY,
        help=f"ChArUco marker dictionary ({DEFAULT_DICTIONARY})",
    )
    parser.add_argument(
        "--plane",
        metavar="IMG",
        help="image of the target lying where the specimen's surface will be (the first IMG)",
    )
    parser.add_argument("--out", metavar="FILE", help="calibration file to write (JSON)")
    parser.add_argument(
        "--max-rms-px",
        type=arguments.within(float, 0.0, 100.0, above=True),
        default=CalibrationLimits.max_rms_px,
        help=f"largest RMS reprojection error, px ({CalibrationLimits.max_rms_px:g})",
    )
    parser.add_argument(
        "--min-coverage",
        type=arguments.within(float, 0.0, 1.0),
        default=CalibrationLimits.min_coverage,
        help="least fraction of the field the target's corners must cover "
        f"({CalibrationLimits.min_coverage:g})",
    )
    parser.add_argument(
        "--telecentric",
        action="store_true",
        help="a telecentric lens: fit an orthographic camera (fx, fy in px per mm) with the "
        "same distortion model",
    )
    parser.add_argument(
        "--object-distance-mm",
        type=arguments.within(float, 0.0, 1e5),
        default=0.0,
        metavar="Z",
        help="--telecentric: the nominal distance recorded for the specimen plane, mm (0); "
        "a telecentric lens cannot observe it",
    )
    parser.add_argument(
        "--check", metavar="FILE", help="check the calibration FILE against the images"
    )
    parser.add_argument(
        "--max-scale-change-percent",
        type=arguments.within(float, 0.0, 100.0, above=True),
        default=100.0 * CheckLimits.max_scale_change,
        help="--check: largest change of the scale at the image centre, %% "
        f"({100.0 * CheckLimits.max_scale_change:g})",
    )
    parser.add_argument("--json", action="store_true", help="print JSON on stdout")
    parser.set_defaults(handler=run_calibrate)


def run_calibrate(args: argparse.Namespace) -> int:
    """Calibrate, or check a calibration (`--check`)."""
    if args.check:
        return _check(args)
    for option, value in (
        ("--target", args.target),
        ("--squares", args.squares),
        ("--square-mm", args.square_mm),
        ("--out", args.out),
    ):
        if value is None:
            raise InputError(f"calibrate: {option} is required (or --check FILE)")
    try:
        target = CalibrationTarget(
            args.target,
            args.squares[0],
            args.squares[1],
            args.square_mm,
            args.marker_mm or 0.0,
            args.dictionary,
        )
    except ValueError as exc:
        raise InputError(f"calibrate: {exc}") from None
    names = list(args.images)
    plane_index = 0
    if args.plane is not None:
        matches = [i for i, name in enumerate(names) if _same_file(name, args.plane)]
        if matches:
            plane_index = matches[0]
        else:
            names.append(args.plane)
            plane_index = len(names) - 1
    if len(names) < MIN_VIEWS:
        raise InputError(
            f"calibrate: {len(names)} image(s), at least {MIN_VIEWS} needed (each view of a "
            "plane gives two constraints on the camera matrix; ten or more tilted views over "
            "the field are recommended)"
        )
    views = _views(target, names)
    calibration = calibrate(
        views,
        target,
        plane_index=plane_index,
        limits=CalibrationLimits(args.max_rms_px, args.min_coverage),
        software_version=appliance.__version__,
        created_utc=datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        telecentric=args.telecentric,
        object_distance_mm=args.object_distance_mm,
    )
    save_calibration(calibration, Path(args.out))
    if args.json:
        document = calibration.to_document()
        document["checksum"] = calibration.checksum
        print_json(document)
        return 0
    camera = calibration.camera
    k1, k2, p1, p2, k3 = camera.distortion.coefficients
    corners = np.array(
        [[0.0, 0.0], [camera.width_px - 1.0, 0.0], [0.0, camera.height_px - 1.0]]
        + [[camera.width_px - 1.0, camera.height_px - 1.0]]
    )
    worst = int(np.argmax(calibration.view_errors_px))
    print(f"target        {target.describe()}, {len(views)} views")
    unit, kind = ("px/mm", "telecentric, ") if camera.telecentric else ("px", "")
    print(
        f"camera        {kind}fx {camera.fx_px:.4f} {unit}  fy {camera.fy_px:.4f} {unit}  "
        f"cx {camera.cx_px:.2f} px  cy {camera.cy_px:.2f} px"
    )
    print(f"distortion    k1 {k1:.5g}  k2 {k2:.5g}  p1 {p1:.5g}  p2 {p2:.5g}  k3 {k3:.5g}")
    print(f"              {camera.distortion_px(corners).max():.2f} px at the image corners")
    print(
        f"reprojection  RMS {calibration.rms_reprojection_px:.3f} px, worst view "
        f"{views[worst].name} {calibration.view_errors_px[worst]:.3f} px"
    )
    print(f"coverage      {calibration.coverage_fraction:.0%} of the field")
    distance = f"{calibration.plane.translation_mm[2]:.1f} mm away"
    if camera.telecentric:
        distance += " (nominal)"
    print(
        f"plane         {views[plane_index].name}: {distance}, tilted "
        f"{calibration.plane.normal_tilt_deg:.2f} deg"
    )
    print(
        f"scale         {calibration.scale_mm_per_px:.6f} mm/px at the image centre, "
        f"u = {calibration.scale_uncertainty_mm_per_px:.2g} mm/px "
        f"({100 * calibration.scale_uncertainty_mm_per_px / calibration.scale_mm_per_px:.3f} %)"
    )
    print(f"written       {args.out} ({calibration.checksum[:19]})")
    return 0


def _check(args: argparse.Namespace) -> int:
    source = args.check
    calibration = load_calibration(Path(source))
    target = target_from_document(calibration.target, source)
    views = _views(target, list(args.images))
    limits = CheckLimits(args.max_rms_px, args.max_scale_change_percent / 100.0)
    results = check_calibration(calibration, target, views, limits)
    fit = all(result.fit for result in results)
    if args.json:
        print_json(
            {
                "calibration": source,
                "checksum": calibration.checksum,
                "stored_scale_mm_per_px": calibration.scale_mm_per_px,
                "max_rms_px": limits.max_rms_px,
                "max_scale_change": limits.max_scale_change,
                "views": [
                    {
                        "image": r.name,
                        "rms_px": r.rms_px,
                        "scale_mm_per_px": r.scale_mm_per_px,
                        "scale_change": r.scale_change,
                        "fit": r.fit,
                    }
                    for r in results
                ],
                "fit": fit,
            }
        )
    else:
        print(
            f"calibration {source}: scale {calibration.scale_mm_per_px:.6f} mm/px; limits "
            f"RMS {limits.max_rms_px:g} px, scale change {100 * limits.max_scale_change:g} %"
        )
        for r in results:
            print(
                f"{r.name}: RMS {r.rms_px:.3f} px, scale {r.scale_mm_per_px:.6f} mm/px "
                f"({100 * r.scale_change:+.3f} %) {'fit' if r.fit else 'NOT FIT'}"
            )
        print("verdict: fit" if fit else "verdict: not fit (calibrate the camera again)")
    return 0 if fit else EXIT_NOT_FIT


def _views(target: CalibrationTarget, names: list[str]) -> list[View]:
    views = []
    first: tuple[str, tuple[int, int]] | None = None
    for name in names:
        image = _as_8bit(read_grey(name))
        size = (int(image.shape[1]), int(image.shape[0]))
        if first is None:
            first = (name, size)
        elif size != first[1]:
            raise InputError(
                f"{name}: image is {size[0]}x{size[1]} px, {first[0]} is "
                f"{first[1][0]}x{first[1][1]} px (one camera, one size)"
            )
        views.append(find_target(target, image, name))
    return views


def _as_8bit(image: np.ndarray) -> np.ndarray:
    if image.dtype == np.uint8:
        return image
    values = np.nan_to_num(image.astype(np.float64))
    peak = max(float(values.max()), 1e-12)
    return np.clip(np.rint(values * (255.0 / peak)), 0, 255).astype(np.uint8)


def _same_file(a: str, b: str) -> bool:
    try:
        return Path(a).resolve() == Path(b).resolve()
    except OSError:
        return a == b


def _squares(text: str) -> tuple[int, int]:
    match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not match:
        raise argparse.ArgumentTypeError(f"{text!r} is not COLSxROWS (e.g. 10x7)")
    columns, rows = int(match.group(1)), int(match.group(2))
    if not (2 <= columns <= 200 and 2 <= rows <= 200):
        raise argparse.ArgumentTypeError(f"{text!r}: columns and rows must be in 2 .. 200")
    return columns, rows
