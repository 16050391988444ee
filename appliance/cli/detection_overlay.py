"""One frame with what specimen detection finds drawn over it, for an installer to look at.

`save_detection_overlay(path, image, ...)` writes a colour PNG (or any format OpenCV writes by
the file's extension) of the frame, stretched to 8 bits, with the specimen's outline (green),
its axis over the parallel length (blue), the parallel length's ends (yellow ticks across the
axis, labelled when not seen) and, when the configuration gives a gauge length and a scale,
the gauge marks a test would place (red points, their centres circled); the placement and the
figures are written in the top-left corner. The gauge goes where a test puts it
(`appliance.rig.gauge_centre_in`): a configured centre without detection, the image's centre
when nothing stands out (a specimen that fills the view), said as such. A frame without a
single specimen gets the refusal written on it instead: the overlay shows what was seen
either way.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from appliance.cli.detect import PLACEMENT_NOTES, gauge_marks
from appliance.config import Config
from appliance.errors import InputError
from appliance.rig import gauge_centre_in

GREEN = (0, 200, 0)
BLUE = (255, 120, 0)
YELLOW = (0, 220, 255)
RED = (0, 0, 255)
WHITE = (255, 255, 255)
"""Overlay colours, OpenCV's BGR order."""


def detection_overlay(image: np.ndarray, max_value: float, config: Config) -> np.ndarray:
    """The frame as 8-bit BGR with the detection and the gauge drawn over it."""
    grey = np.clip(np.asarray(image, np.float64) * (255.0 / max_value), 0, 255).astype(np.uint8)
    canvas = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    scale = max(1, round(max(canvas.shape[:2]) / 1000))
    try:
        centre = gauge_centre_in(config, "frame")(image)
    except InputError as exc:
        _text(canvas, [f"no gauge placed: {exc}"], scale)
        return canvas
    found = centre.detection
    lines = []
    if found is not None:
        outline = np.round(found.outline_px).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(canvas, [outline], True, GREEN, scale, cv2.LINE_AA)
        first, second = (np.asarray(end) for end in found.parallel_ends_px)
        cv2.line(canvas, _px(first), _px(second), BLUE, scale, cv2.LINE_AA)
        across = np.array([-found.along[1], found.along[0]]) * (0.6 * found.width_px)
        for end, seen in zip((first, second), found.ends_in_view, strict=True):
            cv2.line(canvas, _px(end - across), _px(end + across), YELLOW, scale, cv2.LINE_AA)
            if not seen:
                origin = _px(end + across * 1.1)
                cv2.putText(
                    canvas,
                    "end not seen",
                    origin,
                    cv2.FONT_HERSHEY_SIMPLEX,
                    0.4 * scale,
                    YELLOW,
                    scale,
                )
        lines.append(
            f"specimen: centre ({found.centre_px[0]:.1f}, {found.centre_px[1]:.1f}) px, "
            f"axis {found.axis_deg:.2f} deg, width {found.width_px:.2f} px"
        )
    lines.append(
        f"gauge {centre.placement} at ({centre.centre_px[0]:.1f}, {centre.centre_px[1]:.1f}) "
        f"px, axis {centre.axis_deg:.2f} deg"
        + (f": {PLACEMENT_NOTES[centre.placement]}" if centre.placement in PLACEMENT_NOTES else "")
    )
    try:
        gauge = gauge_marks(config, centre, image.shape)
    except InputError as exc:
        lines.append(f"gauge refused: {exc}")
        gauge = None
    if gauge is not None:
        for x, y in gauge["points_px"]:
            cv2.circle(canvas, _px((x, y)), 2 * scale, RED, -1, cv2.LINE_AA)
        for x, y in gauge["marks_px"]:
            cv2.circle(canvas, _px((x, y)), 6 * scale, RED, scale, cv2.LINE_AA)
        lines.append(
            f"gauge {gauge['placement']}: {gauge['achieved_length_mm']:.3f} mm "
            f"(asked {gauge['length_mm']:g} mm)"
        )
    _text(canvas, lines, scale)
    return canvas


def save_detection_overlay(path: Path, image: np.ndarray, max_value: float, config: Config) -> None:
    """Write `detection_overlay` of `image` to `path`.

    Raises:
        InputError: the file cannot be written (names it).
    """
    canvas = detection_overlay(image, max_value, config)
    try:
        written = cv2.imwrite(str(path), canvas)
    except cv2.error as exc:
        raise InputError(f"{path}: cannot write the image ({exc.err or exc})") from None
    if not written:
        raise InputError(f"{path}: cannot write the image (a .png, .tif or .bmp name?)")


def _px(point) -> tuple[int, int]:
    return int(round(float(point[0]))), int(round(float(point[1])))


def _text(canvas: np.ndarray, lines: list[str], scale: int) -> None:
    for number, line in enumerate(lines):
        origin = (10 * scale, (25 + 22 * number) * scale)
        cv2.putText(
            canvas, line, origin, cv2.FONT_HERSHEY_SIMPLEX, 0.5 * scale, (0, 0, 0), 3 * scale
        )
        cv2.putText(canvas, line, origin, cv2.FONT_HERSHEY_SIMPLEX, 0.5 * scale, WHITE, scale)
