"""`extensometer detect`: find the specimen in an image and show where the gauge would go.

The same detection and placement a test runs on its reference frame (`appliance.rig`,
`appliance.measure.specimen_gauge`): the specimen's centre on its parallel length
(`centre_x_px`, `centre_y_px`), its axis (`axis_deg`, the convention of `[gauge] axis_deg`:
degrees from the image's +x towards +y, 90 = vertical), its width, the parallel length's ends;
and, when the configuration gives the gauge length and a scale (`[optics]` or
`[optics] calibration`), the gauge marks a test would place (each mark's centre) and the
gauge length they achieve. A `[gauge] centre_x_px`, `centre_y_px` in the configuration places
the marks there, as in a test. A specimen that cannot be found, or a gauge that does not fit
its parallel length, is refused in one line (exit status 2).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from appliance.cli import arguments
from appliance.cli.image_files import read_grey
from appliance.cli.printing import print_json
from appliance.config import Config
from appliance.errors import InputError
from appliance.measure.gauges import Calibration, marks_outside, place_marks
from appliance.measure.specimen_detection import SpecimenDetection, SpecimenNotFound
from appliance.measure.specimen_gauge import (
    CONFIGURED,
    GaugeCentre,
    detected_gauge_centre,
    marks_beyond_parallel_length,
)
from appliance.plan.optics import configured_optics
from appliance.run.object_plane import calibration_file, resolved_calibration_path


def add_parser(commands: argparse._SubParsersAction) -> None:
    """The `detect` command."""
    detect = commands.add_parser(
        "detect",
        help="find the specimen in an image and the gauge marks a test would place",
        description=(
            "Find the specimen in IMG (its centre, axis, width and parallel length) and, with "
            "a gauge length and a scale in the configuration, the gauge marks a test would "
            "place on it."
        ),
    )
    detect.add_argument("image", metavar="IMG", type=Path, help="image (TIFF, PNG, BMP)")
    detect.add_argument("--config", type=Path, metavar="FILE", help="configuration (TOML)")
    detect.add_argument("--json", action="store_true", help="print a JSON document")
    detect.set_defaults(handler=detect_command)


def detect_command(args: argparse.Namespace) -> int:
    """Run `detect`; exit status 0."""
    config = resolved_calibration_path(arguments.configuration(args.config, args), args.config)
    image = read_grey(args.image)
    g = config.gauge
    try:
        detected = detected_gauge_centre(image)
    except SpecimenNotFound as exc:
        raise InputError(f"{args.image}: {exc}") from None
    detection = detected.detection
    assert detection is not None
    centre = detected
    if g.centre_x_px is not None and g.centre_y_px is not None:
        centre = GaugeCentre((g.centre_x_px, g.centre_y_px), g.axis_deg, CONFIGURED)
    gauge = gauge_marks(config, centre, detection, image.shape)
    document: dict[str, Any] = {"image": str(args.image), **detection.as_dict(), "gauge": gauge}
    if args.json:
        print_json(document, sys.stdout)
    else:
        _print_text(document)
    return 0


def gauge_marks(
    config: Config, centre: GaugeCentre, detection: SpecimenDetection, shape: tuple[int, ...]
) -> dict[str, Any] | None:
    """The marks a test would place about `centre`; None without a gauge length or a scale.

    Raises:
        InputError: marks beyond the image or the parallel length, naming the key.
    """
    g = config.gauge
    calibration = _calibration(config, (shape[1], shape[0]))
    if g.length_mm is None or calibration is None:
        return None
    try:
        points, layout = place_marks(
            centre.centre_px,
            g.length_mm,
            calibration,
            axis_deg=centre.axis_deg,
            mark_width_px=g.mark_spacing_px * (g.points_per_mark - 1),
            points_per_mark=g.points_per_mark,
            transverse_width_mm=g.transverse_width_mm or None,
            along_axis=True,
        )
    except ValueError as exc:
        raise InputError(f"[gauge] length_mm: {exc}") from None
    outside = marks_outside(points, shape, config.tracking.min_subset_px)
    if outside is not None:
        raise InputError(f"[gauge] length_mm: {outside}: shorten the gauge or move its centre")
    if centre.detection is not None:
        beyond = marks_beyond_parallel_length(points, detection)
        if beyond is not None:
            raise InputError(f"[gauge] length_mm: {beyond}")
    axial = layout.axial
    if calibration.projection is not None:
        achieved = axial.length_mm(points, calibration.projection)
    else:
        achieved = axial.length_px(points) * calibration.scale_mm_per_px
    marks = [points[list(mark)].mean(axis=0).tolist() for mark in layout.marks]
    return {
        "placement": centre.placement,
        "centre_px": [float(centre.centre_px[0]), float(centre.centre_px[1])],
        "axis_deg": float(centre.axis_deg),
        "length_mm": g.length_mm,
        "achieved_length_mm": float(achieved),
        "marks_px": marks,
        "points_px": points.tolist(),
    }


def _calibration(config: Config, size: tuple[int, int]) -> Calibration | None:
    """The calibration a test would measure with; None when the configuration gives none."""
    from_file = calibration_file(config, size)
    if from_file is not None:
        return from_file
    o = config.optics
    if o.focal_length_mm is None and o.object_distance_mm is None and o.pixel_size_um is None:
        return None
    optics = configured_optics(config, None)
    return Calibration.from_optics(optics.pixel_size_um, optics.magnification)


def _print_text(document: dict[str, Any]) -> None:
    out = sys.stdout
    (x1, y1), (x2, y2) = document["parallel_ends_px"]
    rows: list[tuple[str, str]] = [
        ("centre_x_px", f"{document['centre_x_px']:.2f}"),
        ("centre_y_px", f"{document['centre_y_px']:.2f}"),
        ("axis_deg", f"{document['axis_deg']:.3f}"),
        ("width_px", f"{document['width_px']:.2f}"),
        ("parallel_length_px", f"{document['parallel_length_px']:.1f}"),
        ("parallel_ends_px", f"({x1:.1f}, {y1:.1f}) ({x2:.1f}, {y2:.1f})"),
        ("edge_rms_px", f"{document['edge_rms_px']:.3f}"),
        ("lighting", document["lighting"]),
    ]
    gauge = document["gauge"]
    if gauge is None:
        rows.append(("gauge", "- (needs [gauge] length_mm and [optics] or a calibration)"))
    else:
        rows += [
            ("gauge_placement", gauge["placement"]),
            ("gauge_length_mm", f"{gauge['length_mm']:g}"),
            ("gauge_length_achieved_mm", f"{gauge['achieved_length_mm']:.4f}"),
        ]
        rows += [
            (f"mark_{n}_px", f"({x:.2f}, {y:.2f})")
            for n, (x, y) in enumerate(gauge["marks_px"], start=1)
        ]
    for key, value in rows:
        out.write(f"{key:26s} {value}\n")
