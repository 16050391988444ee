"""Painted marks: two contrasting dots (or lines) on the specimen, found, validated, followed.

Classic video extensometry measures between two marks painted on the specimen; unlike speckle
correlation they survive strains at which the speckle decorrelates (rubber to several hundred
percent). Here a *dot* is a connected blob of the frame, smoothed by a Gaussian of
`DotSettings.smoothing_sigma_px`, above a threshold; its position is the intensity-weighted
centroid of the raw pixels of the blob grown by one pixel (weights from 0 at the threshold to
1 at the dot's paint level), sub-pixel. Its shape is the ellipse of the same second moments:
a round dot becomes an ellipse as the material stretches, and its centroid stays on the
material point at its centre while the deformation across the dot is uniform.

Finding (`find_dots`, on the reference frame): the threshold is half-way between the paint
(the brightest blobs: the 99.999th percentile of the smoothed frame) and the specimen around
it (the 99th percentile: the marks cover less than 1 % of the frame); a candidate is a blob
of at least `min_area_px` whose area fills its moment ellipse (`fill_range`), whose mean is
nearer the paint than the threshold, and whose core is uniform (`max_spread`: a bright cluster
of speckle is neither). Exactly two
candidates must be found: fewer ("missing") or more ("doubled") is refused by
`PaintedMarksNotFound`, naming what was seen.

Lines (`DotSettings.kind = "lines"`, painted across a specimen whose axis runs along the
image's rows) are found and followed as the same blobs (a band fills its moment ellipse to
0.95); a line's position along the axis is the midpoint of its two edges, each where the
profile along the rows (the mean of the blob's middle half of columns) crosses half-way
between the paint and the surround, interpolated to sub-pixel.

Following: `appliance.measure.painted_marks_tracker`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage


@dataclass(frozen=True)
class DotSettings:
    """How painted marks are found and validated; lengths in px of the image.

    Attributes:
        kind: "dots", or "lines" painted across a specimen whose axis runs along the image's
            rows (each line's position along the axis from its sub-pixel edge profile).
        smoothing_sigma_px: Gaussian smoothing before the threshold (keeps single bright
            speckles out of the blobs).
        min_area_px: smallest blob taken for a dot, px^2.
        fill_range: (lowest, highest) ratio of a blob's area to the area of its moment
            ellipse: 1 for a filled ellipse; a dot merged with a reflection or a speckle
            blob falls outside.
        area_change: largest relative change of a dot's area from one frame to the next.
        min_contrast: smallest contrast against the ring around the dot, as a fraction of
            the reference's.
        window_margin_px: room around the dot's extent and the search radius in a window.
        ring_px: width of the ring around a dot whose mean is the dot's surround.
        max_spread: in the reference frame, the largest spread of a mark's core, as a
            fraction of its contrast (paint is uniform, a bright cluster of speckle is not).
    """

    kind: str = "dots"
    smoothing_sigma_px: float = 2.0
    min_area_px: float = 60.0
    fill_range: tuple[float, float] = (0.8, 1.2)
    area_change: float = 0.35
    min_contrast: float = 0.5
    window_margin_px: int = 6
    ring_px: int = 3
    max_spread: float = 0.2

    def __post_init__(self) -> None:
        if self.kind not in ("dots", "lines"):
            raise ValueError(f"kind must be 'dots' or 'lines', got {self.kind!r}")


class PaintedMarksNotFound(ValueError):
    """The reference frame does not hold exactly two painted dots; the message says what
    was seen."""


@dataclass(frozen=True)
class Dot:
    """One blob measured in a frame.

    Attributes:
        centre_px: intensity-weighted centroid (x, y), px.
        area_px: pixels of the blob.
        axes_px: (major, minor) full axes of its moment ellipse, px.
        fill: area / the moment ellipse's area.
        level: mean grey of the blob's raw pixels.
        surround: mean grey of the ring around it.
        spread: standard deviation of the grey levels of its core (the blob less 2 px all
            round; infinite when nothing is left): small for paint, large for speckle.
        cut: the blob reaches the side of the searched window (or the image).
    """

    centre_px: tuple[float, float]
    area_px: float
    axes_px: tuple[float, float]
    fill: float
    level: float
    surround: float
    spread: float
    cut: bool

    @property
    def contrast(self) -> float:
        """Paint against surround, grey levels."""
        return self.level - self.surround

    def describe(self) -> str:
        """ "(x, y) px, area N px" for messages."""
        x, y = self.centre_px
        return f"({x:.0f}, {y:.0f}) px, {self.area_px:.0f} px^2"


def paint_levels(image: np.ndarray, settings: DotSettings | None = None) -> tuple[float, float]:
    """(paint, threshold): the grey level of the brightest blobs of `image` (the 99.999th
    percentile of the smoothed frame), and the level half-way between it and the specimen (its
    99th percentile: the marks must cover less than 1 % of the frame)."""
    s = settings or DotSettings()
    smoothed = ndimage.gaussian_filter(np.asarray(image, np.float64), s.smoothing_sigma_px)
    paint, specimen = np.percentile(smoothed, [99.999, 99.0])
    return float(paint), float(0.5 * (paint + specimen))


def measure_blobs(
    window: np.ndarray, threshold: float, settings: DotSettings | None = None
) -> list[Dot]:
    """Every blob of `window` above `threshold` (after smoothing) of at least `min_area_px`,
    in the window's pixel coordinates."""
    s = settings or DotSettings()
    raw = np.asarray(window, np.float64)
    smoothed = ndimage.gaussian_filter(raw, s.smoothing_sigma_px)
    labels, count = ndimage.label(smoothed > threshold)
    if count == 0:
        return []
    areas = ndimage.sum_labels(np.ones_like(raw), labels, np.arange(1, count + 1))
    objects = ndimage.find_objects(labels)
    return [
        _measure_blob(raw, labels, int(label), objects[label - 1], threshold, s)
        for label in np.flatnonzero(areas >= s.min_area_px) + 1
    ]


def _measure_blob(
    raw: np.ndarray,
    labels: np.ndarray,
    label: int,
    box: tuple[slice, slice],
    threshold: float,
    s: DotSettings,
) -> Dot:
    rows, cols = box
    pad = 1 + s.ring_px
    r0, r1 = max(rows.start - pad, 0), min(rows.stop + pad, raw.shape[0])
    c0, c1 = max(cols.start - pad, 0), min(cols.stop + pad, raw.shape[1])
    blob = labels[r0:r1, c0:c1] == label
    pixels = raw[r0:r1, c0:c1]
    grown = ndimage.binary_dilation(blob)
    ring = ndimage.binary_dilation(grown, iterations=s.ring_px) & ~grown
    level = float(pixels[blob].mean())
    surround = float(pixels[ring].mean()) if ring.any() else math.nan
    weights = np.clip((pixels - threshold) / max(level - threshold, 1e-9), 0.0, 1.0) * grown
    total = weights.sum()
    yy, xx = np.mgrid[r0:r1, c0:c1]
    cx = float((weights * xx).sum() / total)
    cy = float((weights * yy).sum() / total)
    if s.kind == "lines":
        cy = _line_row(raw, blob, (r0, c0), level, surround, cy)
    core = ndimage.binary_erosion(blob, iterations=2)
    spread = float(pixels[core].std()) if core.any() else math.inf
    by, bx = np.nonzero(blob)
    area = float(by.size)
    dx, dy = bx + c0 - bx.mean() - c0, by + r0 - by.mean() - r0
    cov = np.array([[np.mean(dx * dx), np.mean(dx * dy)], [np.mean(dx * dy), np.mean(dy * dy)]])
    cov += np.eye(2) / 12.0
    low, high = np.linalg.eigvalsh(cov)
    axes = (4.0 * math.sqrt(max(high, 0.0)), 4.0 * math.sqrt(max(low, 0.0)))
    ellipse = math.pi * axes[0] * axes[1] / 4.0
    cut = (
        rows.start == 0 or cols.start == 0 or rows.stop == raw.shape[0] or cols.stop == raw.shape[1]
    )
    fill = area / ellipse if ellipse > 0 else math.inf
    return Dot((cx, cy), area, axes, fill, level, surround, spread, cut)


def _line_row(
    raw: np.ndarray,
    blob: np.ndarray,
    origin: tuple[int, int],
    level: float,
    surround: float,
    fallback: float,
) -> float:
    """The row of a line across the specimen: the midpoint of the two sub-pixel crossings of
    the half level (between paint and surround) by the line's profile along the rows, the mean
    of the blob's middle half of columns. `fallback` when the profile has no two crossings."""
    r0, c0 = origin
    columns = np.flatnonzero(blob.any(axis=0))
    quarter = (columns[-1] - columns[0]) // 4
    middle = slice(c0 + columns[0] + quarter, c0 + columns[-1] - quarter + 1)
    profile = raw[:, middle].mean(axis=1)
    rows = np.flatnonzero(blob[:, columns[0] + quarter : columns[-1] - quarter + 1].any(axis=1))
    half = 0.5 * (level + surround)
    top, bottom = r0 + rows[0], r0 + rows[-1]
    if not (0 < top and bottom < raw.shape[0] - 1):
        return fallback
    upper = _crossing(profile, half, top, -1)
    lower = _crossing(profile, half, bottom, 1)
    if upper is None or lower is None:
        return fallback
    return 0.5 * (upper + lower)


def _crossing(profile: np.ndarray, half: float, start: int, step: int) -> float | None:
    """Where `profile` falls through `half` near row `start`, going outwards by `step`,
    interpolated linearly between the last row at or above it and the next; None when that
    is not within the profile."""
    n = profile.size
    row = start
    if profile[row] < half:
        while 0 <= row < n and profile[row] < half:
            row -= step
    else:
        while 0 <= row + step < n and profile[row + step] >= half:
            row += step
    outside = row + step
    if not (0 <= row < n and 0 <= outside < n):
        return None
    a, b = profile[row], profile[outside]
    return row + step * (a - half) / (a - b)


def find_dots(image: np.ndarray, settings: DotSettings | None = None) -> tuple[Dot, Dot]:
    """The two painted dots (or lines, by `settings.kind`) of a reference frame, in order of
    their row (then column).

    Raises:
        PaintedMarksNotFound: fewer or more than two candidates (the message names them).
    """
    s = settings or DotSettings()
    paint, threshold = paint_levels(image, s)
    blobs = measure_blobs(image, threshold, s)
    low, high = s.fill_range
    painted = 0.5 * (threshold + paint)
    dots = [
        b
        for b in blobs
        if low <= b.fill <= high
        and not b.cut
        and b.level >= painted
        and b.spread <= s.max_spread * b.contrast
    ]
    dots.sort(key=lambda d: (d.centre_px[1], d.centre_px[0]))
    if len(dots) == 2:
        return dots[0], dots[1]
    one = s.kind[:-1]
    seen = "; ".join(d.describe() for d in dots[:5]) + (" ..." if len(dots) > 5 else "")
    others = len(blobs) - len(dots)
    rejected = (
        f" ({others} other bright blob(s) not {one}-shaped, not as bright or not uniform)"
        if others
        else ""
    )
    if not dots:
        raise PaintedMarksNotFound(
            f"no painted {one} found above grey {threshold:.0f}{rejected}: two are needed"
        )
    kind = "missing" if len(dots) < 2 else "doubled"
    raise PaintedMarksNotFound(
        f"painted {s.kind} {kind}: {len(dots)} found above grey {threshold:.0f} at {seen}"
        f"{rejected}; exactly two are needed"
    )
