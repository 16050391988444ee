"""`extensometer detect`: find the specimen in an image and show where the gauge would go.

The same placement a test makes on its reference frame (`appliance.rig.gauge_centre_in`):

* without `[gauge] centre_x_px`, `centre_y_px`: the specimen detected
  (`appliance.measure.specimen_detection`): its centre on its parallel length (`centre_x_px`,
  `centre_y_px`), its axis (`axis_deg`, the convention of `[gauge] axis_deg`: degrees from the
  image's +x towards +y, 90 = vertical), its width, the parallel length's ends and whether
  each was seen (`ends_in_view`), the gauge centred on it (`gauge_placement` "detected");
  an image in which nothing stands out from the background (a specimen that fills the view)
  puts the gauge on the image's centre along `[gauge] axis_deg` (`gauge_placement`
  "image centre"), and says so;
* with both keys set: the gauge there, along `[gauge] axis_deg` ("configured"); nothing is
  detected, as in a test;
* with `[gauge] marks = "dots"` or `"lines"`: the two painted marks a test would track, found
  as a test finds them (`appliance.rig.painted_marks`), and the gauge between them ("painted
  dots", "painted lines"); no mark, one, or more than two is refused in one line, naming what
  was seen.

When the configuration gives the gauge length and a scale (`[optics]` or `[optics]
calibration`), the gauge marks a test would place (each mark's centre) and the gauge length
they achieve follow. A specimen that cannot be measured, or a gauge that does not fit the
image or the detected parallel length, is refused in one line (exit status 2).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from appliance.cli import arguments
from appliance.cli.image_files import read_grey
from appliance.cli.printing import print_json
from appliance.config import Config
from appliance.measure.gauges import Calibration, StrainGaugesLayout
from appliance.measure.specimen_gauge import (
    CONFIGURED,
    IMAGE_CENTRE,
    GaugeCentre,
)
from appliance.plan.optics import configured_optics
from appliance.rig import gauge_centre_in, painted_marks, speckle_marks
from appliance.run.object_plane import calibration_file, resolved_calibration_path

PLACEMENT_NOTES = {
    CONFIGURED: "[gauge] centre_x_px, centre_y_px along [gauge] axis_deg; nothing detected",
    IMAGE_CENTRE: (
        "nothing stands out from the background (a specimen that fills the view): the gauge "
        "is centred on the image along [gauge] axis_deg"
    ),
}
"""What the text output says of a placement other than on the detected specimen."""


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
    if config.gauge.marks in ("dots", "lines"):
        image = read_grey(args.image)
        points, layout, centre = painted_marks(image, config, str(args.image))
        document_marks = painted_gauge(config, points, layout, centre, image.shape)
    else:
        place = gauge_centre_in(config, str(args.image))
        image = read_grey(args.image)
        centre = place(image)
        document_marks = gauge_marks(config, centre, image.shape)
    detection = centre.detection
    document: dict[str, Any] = {
        "image": str(args.image),
        **(detection.as_dict() if detection is not None else {}),
        "gauge_placement": centre.placement,
        "gauge_centre_px": [float(centre.centre_px[0]), float(centre.centre_px[1])],
        "gauge_axis_deg": float(centre.axis_deg),
        "gauge": document_marks,
    }
    if args.json:
        print_json(document, sys.stdout)
    else:
        _print_text(document)
    return 0


def gauge_marks(
    config: Config, centre: GaugeCentre, shape: tuple[int, ...]
) -> dict[str, Any] | None:
    """The marks a test would place about `centre` (checked against its detected parallel
    length, when it has one); None without a gauge length or a scale.

    Raises:
        InputError: marks beyond the image or the parallel length, naming the key.
    """
    g = config.gauge
    calibration = _calibration(config, (shape[1], shape[0]))
    if g.length_mm is None or calibration is None:
        return None
    points, layout = speckle_marks(config, centre, g.length_mm, calibration, shape)
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


def painted_gauge(
    config: Config,
    points: np.ndarray,
    layout: StrainGaugesLayout,
    centre: GaugeCentre,
    shape: tuple[int, ...],
) -> dict[str, Any]:
    """The gauge between the two painted marks at `points` (px): their centres and, with a
    scale, the gauge length they span (`length_mm` is then the configured length or None)."""
    calibration = _calibration(config, (shape[1], shape[0]))
    achieved: float | None = None
    if calibration is not None:
        if calibration.projection is not None:
            achieved = layout.axial.length_mm(points, calibration.projection)
        else:
            achieved = layout.axial.length_px(points) * calibration.scale_mm_per_px
    return {
        "placement": centre.placement,
        "centre_px": [float(centre.centre_px[0]), float(centre.centre_px[1])],
        "axis_deg": float(centre.axis_deg),
        "length_mm": config.gauge.length_mm,
        "achieved_length_mm": achieved,
        "marks_px": points.tolist(),
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
    placement = document["gauge_placement"]
    rows: list[tuple[str, str]] = []
    if "parallel_ends_px" in document:
        (x1, y1), (x2, y2) = document["parallel_ends_px"]
        first, second = ("seen" if seen else "not seen" for seen in document["ends_in_view"])
        rows += [
            ("centre_x_px", f"{document['centre_x_px']:.2f}"),
            ("centre_y_px", f"{document['centre_y_px']:.2f}"),
            ("axis_deg", f"{document['axis_deg']:.3f}"),
            ("width_px", f"{document['width_px']:.2f}"),
            ("parallel_length_px", f"{document['parallel_length_px']:.1f}"),
            ("parallel_ends_px", f"({x1:.1f}, {y1:.1f}) ({x2:.1f}, {y2:.1f})"),
            ("ends_in_view", f"{first}, {second}"),
            ("edge_rms_px", f"{document['edge_rms_px']:.3f}"),
            ("lighting", document["lighting"]),
        ]
    gx, gy = document["gauge_centre_px"]
    rows += [
        ("gauge_placement", placement),
        ("gauge_centre_px", f"({gx:.2f}, {gy:.2f})"),
        ("gauge_axis_deg", f"{document['gauge_axis_deg']:.3f}"),
    ]
    if placement in PLACEMENT_NOTES:
        rows.append(("gauge_placement_note", PLACEMENT_NOTES[placement]))
    gauge = document["gauge"]
    if gauge is None:
        rows.append(("gauge", "- (needs [gauge] length_mm and [optics] or a calibration)"))
    else:
        length, achieved = gauge["length_mm"], gauge["achieved_length_mm"]
        rows += [
            ("gauge_length_mm", "-" if length is None else f"{length:g}"),
            (
                "gauge_length_achieved_mm",
                "- (needs [optics] or a calibration)" if achieved is None else f"{achieved:.4f}",
            ),
        ]
        rows += [
            (f"mark_{n}_px", f"({x:.2f}, {y:.2f})")
            for n, (x, y) in enumerate(gauge["marks_px"], start=1)
        ]
    for key, value in rows:
        out.write(f"{key:26s} {value}\n")
