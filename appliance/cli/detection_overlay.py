"""One frame with what specimen detection finds drawn over it, for an installer to look at.

`save_detection_overlay(path, image, ...)` writes a colour PNG (or any format OpenCV writes by
the file's extension) of the frame, stretched to 8 bits, with the specimen's outline (green),
its axis over the parallel length (blue), the parallel length's ends (yellow ticks across the
axis, labelled when not seen) and, when the configuration gives a gauge length and a scale,
the gauge marks a test would place (red points with their `[tracking] subset_px` subsets as
squares, the marks' centres circled); the placement and the figures are written in the
top-left corner, with the frame's set-up figures when given (`quality_lines`: focus, mean
grey, saturated and dark fractions, and in the subsets MIG, SSSIG and speckle size; see
`appliance.measure.speckle_quality`). `gauge_overlay` is the placement as data, which
`extensometer preview` draws in a Rerun viewer with the same figures. The gauge goes where a
test puts it (`appliance.rig.gauge_centre_in`): a configured centre without detection, the
image's centre when nothing stands out (a specimen that fills the view), said as such. A
frame without a single specimen gets the refusal written on it instead: the overlay shows
what was seen either way.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from appliance.cli.detect import PLACEMENT_NOTES, gauge_marks
from appliance.config import Config
from appliance.errors import InputError
from appliance.measure.gauge_overlay import GaugeOverlay
from appliance.measure.speckle_quality import FrameQuality, frame_quality
from appliance.rig import gauge_centre_in

GREEN = (0, 200, 0)
BLUE = (255, 120, 0)
YELLOW = (0, 220, 255)
RED = (0, 0, 255)
WHITE = (255, 255, 255)
"""Overlay colours, OpenCV's BGR order."""


def gauge_overlay(image: np.ndarray, config: Config) -> GaugeOverlay:
    """The placement a test would make on `image` (`appliance.rig.gauge_centre_in`, then the
    marks of `appliance.cli.detect.gauge_marks`), ready to draw."""
    try:
        centre = gauge_centre_in(config, "frame")(image)
    except InputError as exc:
        return GaugeOverlay(lines=(f"no gauge placed: {exc}",), refused=True)
    found = centre.detection
    lines = []
    outline = axis = ticks = None
    ends_in_view = (True, True)
    if found is not None:
        outline = np.asarray(found.outline_px, dtype=np.float64).reshape(-1, 2)
        first, second = (np.asarray(end, dtype=np.float64) for end in found.parallel_ends_px)
        axis = np.array([first, second])
        across = np.array([-found.along[1], found.along[0]]) * (0.6 * found.width_px)
        ticks = np.array([[end - across, end + across] for end in (first, second)])
        ends_in_view = (bool(found.ends_in_view[0]), bool(found.ends_in_view[1]))
        lines.append(
            f"specimen: centre ({found.centre_px[0]:.1f}, {found.centre_px[1]:.1f}) px, "
            f"axis {found.axis_deg:.2f} deg, width {found.width_px:.2f} px"
        )
    lines.append(
        f"gauge {centre.placement} at ({centre.centre_px[0]:.1f}, {centre.centre_px[1]:.1f}) "
        f"px, axis {centre.axis_deg:.2f} deg"
        + (f": {PLACEMENT_NOTES[centre.placement]}" if centre.placement in PLACEMENT_NOTES else "")
    )
    points = marks = None
    refused = False
    try:
        gauge = gauge_marks(config, centre, image.shape)
    except InputError as exc:
        lines.append(f"gauge refused: {exc}")
        gauge = None
        refused = True
    if gauge is not None:
        points = np.asarray(gauge["points_px"], dtype=np.float64).reshape(-1, 2)
        marks = np.asarray(gauge["marks_px"], dtype=np.float64).reshape(-1, 2)
        lines.append(
            f"gauge {gauge['placement']}: {gauge['achieved_length_mm']:.3f} mm "
            f"(asked {gauge['length_mm']:g} mm)"
        )
    elif not refused:
        lines.append("no gauge marks: [gauge] length_mm and [optics] (or a calibration) needed")
    return GaugeOverlay(
        lines=tuple(lines),
        outline_px=outline,
        axis_px=axis,
        end_ticks_px=ticks,
        ends_in_view=ends_in_view,
        points_px=points,
        marks_px=marks,
        refused=refused,
        centre_px=(float(centre.centre_px[0]), float(centre.centre_px[1])),
    )


def quality_lines(quality: FrameQuality) -> list[str]:
    """A frame's set-up figures in words (`appliance.measure.speckle_quality`)."""
    lines = [
        f"focus {quality.focus_gradient:.2f} grey levels/px, mean grey {quality.mean_grey:.1f}, "
        f"saturated {quality.saturated_fraction * 100:.2f} %, dark "
        f"{quality.dark_fraction * 100:.2f} %"
    ]
    subsets = quality.subsets
    if subsets is not None:
        lines.append(
            f"{subsets.subsets} subsets of {subsets.subset_px} px: MIG "
            f"{subsets.mean_intensity_gradient:.2f} grey levels/px, SSSIG "
            f"{subsets.sssig:.3g}, speckle {subsets.speckle_size_px:.2f} px "
            f"({subsets.speckles_per_subset:.1f} per subset)"
        )
    return lines


def overlay_quality(
    image: np.ndarray, max_value: float, config: Config, overlay: GaugeOverlay
) -> FrameQuality:
    """The set-up figures of `image` in the subsets a test would track: at the gauge's points;
    without marks, one subset at the gauge's centre; none without a placement."""
    if overlay.points_px is not None:
        centres = overlay.points_px
    elif overlay.centre_px is not None:
        centres = np.array([overlay.centre_px])
    else:
        centres = np.empty((0, 2))
    return frame_quality(image, max_value, centres, config.tracking.subset_px)


def detection_overlay(
    image: np.ndarray,
    max_value: float,
    config: Config,
    overlay: GaugeOverlay | None = None,
    quality: FrameQuality | None = None,
) -> np.ndarray:
    """The frame as 8-bit BGR with the detection, the gauge and its subsets drawn over it, and
    the placement and the set-up figures (`quality`, when given) written in the corner."""
    grey = np.clip(np.asarray(image, np.float64) * (255.0 / max_value), 0, 255).astype(np.uint8)
    canvas = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    scale = max(1, round(max(canvas.shape[:2]) / 1000))
    if overlay is None:
        overlay = gauge_overlay(image, config)
    if overlay.outline_px is not None:
        outline = np.round(overlay.outline_px).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(canvas, [outline], True, GREEN, scale, cv2.LINE_AA)
        first, second = overlay.axis_px
        cv2.line(canvas, _px(first), _px(second), BLUE, scale, cv2.LINE_AA)
        for (start, stop), seen in zip(overlay.end_ticks_px, overlay.ends_in_view, strict=True):
            cv2.line(canvas, _px(start), _px(stop), YELLOW, scale, cv2.LINE_AA)
            if not seen:
                origin = _px(stop + (stop - start) * 0.05)
                cv2.putText(
                    canvas,
                    "end not seen",
                    origin,
                    cv2.FONT_HERSHEY_SIMPLEX,
                    0.4 * scale,
                    YELLOW,
                    scale,
                )
    if overlay.points_px is not None and overlay.marks_px is not None:
        half = config.tracking.subset_px // 2
        for x, y in overlay.points_px:
            cv2.circle(canvas, _px((x, y)), 2 * scale, RED, -1, cv2.LINE_AA)
            cv2.rectangle(canvas, _px((x - half, y - half)), _px((x + half, y + half)), RED, 1)
        for x, y in overlay.marks_px:
            cv2.circle(canvas, _px((x, y)), 6 * scale, RED, scale, cv2.LINE_AA)
    lines = list(overlay.lines)
    if quality is not None:
        lines += quality_lines(quality)
    _text(canvas, lines, scale)
    return canvas


def save_detection_overlay(
    path: Path,
    image: np.ndarray,
    max_value: float,
    config: Config,
    overlay: GaugeOverlay | None = None,
    quality: FrameQuality | None = None,
) -> None:
    """Write `detection_overlay` of `image` to `path`.

    Raises:
        InputError: the file cannot be written (names it).
    """
    canvas = detection_overlay(image, max_value, config, overlay, quality)
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
