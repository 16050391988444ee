"""Specimen detection: a flat tensile specimen's outline, axis, parallel length and width, from
one image alone.

`detect_specimen(image)` finds the specimen against its background, back-lit (a dark
silhouette on a bright field) or front-lit (a bright or speckled specimen on a dark or bright
backdrop), a little rotated, off-centre, with the grips in view:

1. segmentation, on a copy reduced to about 512 px: the image smoothed, split in two by Otsu's
   threshold (refused when the split does not separate two populations: a uniform image), the
   background being the class that holds most of the image's border; the connected regions
   of the foreground larger than `MIN_AREA_FRACTION` of the image are the candidates (none: no
   specimen; two of comparable size: two objects); the chosen one's holes are filled;
2. a first axis from the region's second moments, then twice: the image resampled along that
   axis (rows along it, one pixel apart, columns across it), averaged along the axis over
   `EDGE_SMOOTHING_PX` rows to wash out a speckle, and on every row the two edges nearest the
   axis located to a fraction of a pixel where the profile crosses halfway between the grey
   levels just outside and just inside the edge; a row whose width stands out from its
   neighbours' (a speckle fooled the edge search) is left out;
3. the parallel length (`appliance.measure.specimen_profile`): the longest run of rows whose
   width exceeds the narrowest by no more than `PARALLEL_TOLERANCE` (a shoulder, a tab or a
   grip is wider); its ends are where the width has departed from the parallel width by that
   tolerance, so they lie a little beyond the tangent points of the transition arcs (about
   1.7 mm for an ISO 37 type 1 dumb-bell). Its
   centre along the axis is the mean of the midpoints between the two shoulders' crossings of
   that level and of 2, 4, ... 32 times it: the shoulders' symmetry fixes it to a fraction of
   a pixel where the flat start of the arcs would not. A parallel length that touches the
   image's side is refused; one that runs out of the image at one end or both (a view that
   cuts it), or whose width does not rise onto a shoulder (a plain bar), is centred on the
   part measured, and says which ends were seen;
4. a straight line fitted to each edge over the middle 80 % of the run (points beyond 3 median
   deviations dropped once): the axis is their mean direction, the width their distance across
   it at the centre, the centre halfway between the edges.

Angles follow `[gauge] axis_deg`: degrees from the image's +x towards +y, in [0, 180) (90 = a
vertical specimen). Pixel centres are at integer coordinates, x = column, y = row.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from appliance.measure.specimen_profile import (
    parallel_ends,
    parallel_run,
    robust_line,
    running_median,
)

WORKING_SIZE_PX = 512
"""Longest side of the reduced copy that is segmented, px."""
MIN_AREA_FRACTION = 0.003
"""Smallest region that counts as an object, as a fraction of the image's area."""
SECOND_OBJECT_FRACTION = 0.25
"""A second region at least this fraction of the largest one's area is a second object."""
MIN_SEPARATION = 0.8
"""Otsu's effectiveness (between-class over total variance) below which the image holds no
two populations (a uniform image with noise scores about 0.64, a specimen over 0.85)."""
EDGE_SMOOTHING_PX = 15
"""Rows averaged along the axis before the edges are located, px."""
FIT_TRIM = 0.1
"""Fraction of the parallel length left out at each end when its edges are fitted (where the
transition arcs begin)."""
OUTLIER_WINDOW_PX = 61
OUTLIER_PX = 1.0
"""A row whose width differs from the median of the `OUTLIER_WINDOW_PX` rows about it by more
than `OUTLIER_PX` and 4 robust standard deviations of that difference (a speckle at the edge
fooled its edge search) is left out."""
MIN_EDGE_ROWS = 10
"""Fewest rows with a located edge, on each side, that a parallel length's edge lines are fitted
through."""


class SpecimenNotFound(ValueError):
    """The image holds no single specimen that can be measured; the message says what was seen
    (one line)."""


class NothingStandsOut(SpecimenNotFound):
    """The image is one population of grey levels: no specimen in view, or a specimen that
    fills the view (a speckle from edge to edge)."""


@dataclass(frozen=True)
class SpecimenDetection:
    """A specimen found in an image.

    Attributes:
        centre_px: (x, y) of the parallel length's centre on the axis, px.
        axis_deg: the loading axis, degrees from +x towards +y, in [0, 180).
        width_px: width of the parallel length across the axis, px.
        parallel_ends_px: ((x, y), (x, y)) the parallel length's ends on the axis, px, the
            first at the smaller y (the smaller x for a horizontal specimen).
        parallel_length_px: distance between the ends, px.
        edge_rms_px: root mean square of the edge points about their fitted lines, px.
        ends_in_view: whether each end of the parallel length (in the order of
            `parallel_ends_px`) was seen: the width rises onto a shoulder in the image. An
            end not seen (the image ends first, or the width does not rise within a quarter
            of the parallel length beyond it: a plain bar's end) is where the measured part
            ends, and the centre along the axis is then the middle of that part.
        dark_on_bright: the specimen is darker than its background (back-lit).
        outline_px: (n, 2) the outline of the region found (the specimen, with any grip that
            touches it), px, for display.
    """

    centre_px: tuple[float, float]
    axis_deg: float
    width_px: float
    parallel_ends_px: tuple[tuple[float, float], tuple[float, float]]
    parallel_length_px: float
    edge_rms_px: float
    ends_in_view: tuple[bool, bool]
    dark_on_bright: bool
    outline_px: np.ndarray

    @property
    def along(self) -> np.ndarray:
        """Unit vector (x, y) along the axis."""
        theta = math.radians(self.axis_deg)
        return np.array([math.cos(theta), math.sin(theta)])

    def as_dict(self) -> dict[str, object]:
        """The figures, JSON-ready (the outline left out)."""
        return {
            "centre_x_px": self.centre_px[0],
            "centre_y_px": self.centre_px[1],
            "axis_deg": self.axis_deg,
            "width_px": self.width_px,
            "parallel_length_px": self.parallel_length_px,
            "parallel_ends_px": [list(end) for end in self.parallel_ends_px],
            "edge_rms_px": self.edge_rms_px,
            "ends_in_view": list(self.ends_in_view),
            "lighting": "dark on bright" if self.dark_on_bright else "bright on dark",
        }


@dataclass(frozen=True)
class _Region:
    mask: np.ndarray
    factor: float
    sign: float
    outline_px: np.ndarray


def detect_specimen(image: np.ndarray) -> SpecimenDetection:
    """Find the specimen in `image` (2-D grey levels, or colour averaged to grey).

    Raises:
        SpecimenNotFound: no specimen, more than one object, a parallel length that touches
            the image's edge or runs out of it, or one too short to measure.
    """
    grey = np.asarray(image, np.float32)
    if grey.ndim == 3:
        grey = grey.mean(axis=2)
    if grey.ndim != 2 or min(grey.shape) < 32:
        raise SpecimenNotFound(f"an image of shape {grey.shape} holds no specimen to find")
    region = _segment(grey)
    ys, xs = np.nonzero(region.mask)
    scale = region.factor
    points = np.column_stack([(xs + 0.5) * scale - 0.5, (ys + 0.5) * scale - 0.5])
    centre = points.mean(axis=0)
    mu = np.cov(points.T)
    theta = 0.5 * math.atan2(2 * mu[0, 1], mu[0, 0] - mu[1, 1])
    for _ in range(2):
        centre, theta, figures = _measure_along(grey, region, points, centre, theta)
    width, ends, rms, ends_in_view = figures
    axis_deg = math.degrees(theta) % 180.0
    first, second = ends
    if (first[1], first[0]) > (second[1], second[0]):
        first, second = second, first
        ends_in_view = (ends_in_view[1], ends_in_view[0])
    return SpecimenDetection(
        centre_px=(float(centre[0]), float(centre[1])),
        axis_deg=axis_deg,
        width_px=width,
        parallel_ends_px=((float(first[0]), float(first[1])), (float(second[0]), float(second[1]))),
        parallel_length_px=float(np.hypot(*(second - first))),
        edge_rms_px=rms,
        ends_in_view=ends_in_view,
        dark_on_bright=region.sign < 0,
        outline_px=region.outline_px,
    )


def _segment(grey: np.ndarray) -> _Region:
    height, width = grey.shape
    factor = max(1, int(round(max(height, width) / WORKING_SIZE_PX)))
    small = cv2.resize(
        grey, (width // factor, height // factor), interpolation=cv2.INTER_AREA
    ).astype(np.float32)
    small = cv2.GaussianBlur(small, (0, 0), 1.5)
    low, high = np.percentile(small, [0.5, 99.5])
    if not high - low > 1e-6 * max(abs(high), 1.0):
        raise NothingStandsOut(f"no specimen: the image is uniform (grey level {low:.4g})")
    scaled = np.clip((small - low) / (high - low) * 255.0, 0, 255).astype(np.uint8)
    threshold, binary = cv2.threshold(scaled, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    fg = binary > 0
    total_var = float(scaled.var())
    between = (
        float(fg.mean() * (1 - fg.mean()))
        * (float(scaled[fg].mean()) - float(scaled[~fg].mean())) ** 2
        if 0 < fg.mean() < 1
        else 0.0
    )
    if total_var == 0 or between / total_var < MIN_SEPARATION:
        raise NothingStandsOut(
            f"no specimen: nothing stands out from the background (grey levels {low:.4g} to "
            f"{high:.4g} in one population)"
        )
    border = np.concatenate([fg[0], fg[-1], fg[:, 0], fg[:, -1]])
    sign = 1.0
    if border.mean() > 0.5:
        fg, sign = ~fg, -1.0
    mask = fg.astype(np.uint8)
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    count, labels, stats, centroids = cv2.connectedComponentsWithStats(mask, connectivity=8)
    areas = stats[1:, cv2.CC_STAT_AREA]
    order = np.argsort(areas)[::-1]
    large = [i for i in order if areas[i] >= MIN_AREA_FRACTION * mask.size]
    if not large:
        raise SpecimenNotFound(
            "no specimen: nothing larger than "
            f"{MIN_AREA_FRACTION:.1%} of the image stands out from the background"
        )

    def at(i: int) -> str:
        x, y = centroids[i + 1]
        return f"({(x + 0.5) * factor - 0.5:.0f}, {(y + 0.5) * factor - 0.5:.0f})"

    if len(large) > 1 and areas[large[1]] >= SECOND_OBJECT_FRACTION * areas[large[0]]:
        seen = " and ".join(at(i) for i in large[:3])
        raise SpecimenNotFound(
            f"{len(large)} objects stand out from the background, at {seen} px: "
            "one specimen at a time"
        )
    chosen = ndimage.binary_fill_holes(labels == large[0] + 1).astype(np.uint8)
    contours, _ = cv2.findContours(chosen, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    outline = max(contours, key=cv2.contourArea).reshape(-1, 2).astype(np.float64)
    return _Region(chosen > 0, float(factor), sign, (outline + 0.5) * factor - 0.5)


def _measure_along(
    grey: np.ndarray,
    region: _Region,
    points: np.ndarray,
    centre: np.ndarray,
    theta: float,
) -> tuple[
    np.ndarray, float, tuple[float, tuple[np.ndarray, np.ndarray], float, tuple[bool, bool]]
]:
    """One pass: resample along `theta` through `centre`, locate the edges, find the parallel
    length and fit its edges. Returns the new centre, axis and (width, ends, rms, ends in
    view)."""
    along = np.array([math.cos(theta), math.sin(theta)])
    across = np.array([-along[1], along[0]])
    s = (points - centre) @ along
    t = (points - centre) @ across
    margin = 4 * region.factor + _REACH_PX + 2
    s_grid = np.arange(math.floor(s.min() - margin), math.ceil(s.max() + margin) + 1.0)
    t_grid = np.arange(math.floor(t.min() - margin), math.ceil(t.max() + margin) + 1.0)
    map_x = (centre[0] + s_grid[:, None] * along[0] + t_grid[None, :] * across[0]).astype(
        np.float32
    )
    map_y = (centre[1] + s_grid[:, None] * along[1] + t_grid[None, :] * across[1]).astype(
        np.float32
    )
    strip = cv2.remap(grey, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    height, width = grey.shape
    inside = (map_x >= 0) & (map_x <= width - 1) & (map_y >= 0) & (map_y <= height - 1)
    strip = ndimage.uniform_filter1d(strip, EDGE_SMOOTHING_PX, axis=0, mode="nearest")
    half = EDGE_SMOOTHING_PX // 2
    in_view = ndimage.minimum_filter1d(inside.astype(np.uint8), 2 * half + 1, axis=0) > 0
    mask = cv2.remap(
        region.mask.astype(np.uint8),
        (map_x + 0.5) / np.float32(region.factor) - 0.5,
        (map_y + 0.5) / np.float32(region.factor) - 0.5,
        cv2.INTER_NEAREST,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )
    centre_col = int(np.argmin(np.abs(t_grid)))
    left, right, touching = _edges(strip, mask > 0, in_view, region.sign, centre_col)
    widths = right - left
    deviation = np.abs(widths - running_median(widths, OUTLIER_WINDOW_PX))
    spread = 4 * 1.4826 * np.nanmedian(deviation) if np.isfinite(deviation).any() else 0.0
    outliers = ~(deviation <= max(OUTLIER_PX, spread))
    left[outliers] = right[outliers] = widths[outliers] = np.nan
    run = parallel_run(widths, EDGE_SMOOTHING_PX)
    if run is None and not touching.any():
        raise SpecimenNotFound("the specimen has no parallel length long enough to measure")
    start, stop = run if run is not None else (0, len(widths))
    if np.any(touching[start:stop]):
        rows = np.nonzero(touching[start:stop])[0] + start
        x, y = centre + s_grid[rows[len(rows) // 2]] * along
        raise SpecimenNotFound(
            f"the specimen's parallel length touches the image's edge near ({x:.0f}, {y:.0f}) px"
        )
    first_end, s_centre, last_end = parallel_ends(
        s_grid, widths, start, stop, in_view[:, centre_col]
    )
    ends_in_view = (first_end is not None, last_end is not None)
    if first_end is None or last_end is None:
        first_end = float(s_grid[start]) if first_end is None else first_end
        last_end = float(s_grid[stop - 1]) if last_end is None else last_end
        s_centre = 0.5 * (first_end + last_end)
    trim = max(1, int(FIT_TRIM * (stop - start)))
    rows = np.arange(start + trim, stop - trim)
    if min(np.isfinite(left[rows]).sum(), np.isfinite(right[rows]).sum()) < MIN_EDGE_ROWS:
        raise SpecimenNotFound(
            "the specimen's edges could not be located along its parallel length"
        )
    left_line, left_rms = robust_line(s_grid[rows], t_grid[0] + left[rows])
    right_line, right_rms = robust_line(s_grid[rows], t_grid[0] + right[rows])
    s_mid = s_centre
    slope = 0.5 * (left_line[0] + right_line[0])
    tilt = math.atan(slope)

    def on_axis(s_at: float) -> np.ndarray:
        t_at = 0.5 * (np.polyval(left_line, s_at) + np.polyval(right_line, s_at))
        return centre + s_at * along + t_at * across

    width_px = float(
        (np.polyval(right_line, s_mid) - np.polyval(left_line, s_mid)) * math.cos(tilt)
    )
    ends = (on_axis(first_end), on_axis(last_end))
    rms = float(math.sqrt(0.5 * (left_rms**2 + right_rms**2)))
    return on_axis(s_mid), theta + tilt, (width_px, ends, rms, ends_in_view)


def _edges(
    strip: np.ndarray, mask: np.ndarray, in_view: np.ndarray, sign: float, centre_col: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sub-pixel column of the left and right edge on every row of `strip` (NaN where the row
    has no specimen on the axis), from the segmentation's edges in `mask`; and whether an
    edge's neighbourhood leaves the image."""
    rows, cols = strip.shape
    left = np.full(rows, np.nan)
    right = np.full(rows, np.nan)
    touching = np.zeros(rows, bool)
    index = np.arange(cols)
    reach = _REACH_PX
    for r in np.nonzero(mask[:, centre_col])[0]:
        background = ~mask[r]
        before = index[: centre_col + 1][background[: centre_col + 1]]
        after = index[centre_col:][background[centre_col:]]
        if before.size == 0 or after.size == 0:
            touching[r] = True
            continue
        profile = strip[r]
        for j, step, out in ((before[-1], 1, left), (after[0], -1, right)):
            lo, hi = sorted((j - reach * step, j + reach * step))
            if lo < 0 or hi >= cols or not np.all(in_view[r, lo : hi + 1]):
                touching[r] = True
                break
            out[r] = _crossing(profile, j, step, sign)
    return left, right, touching


_SEARCH_PX = 8
"""How far either side of the segmentation's edge the sub-pixel edge is looked for, px."""
_LEVEL_PX = (2, 5)
"""The grey levels either side of an edge are averaged this far from it, px."""
_REACH_PX = 2 * _SEARCH_PX
"""How far from the segmentation's edge `_crossing` may read, px: its second pass searches
`_SEARCH_PX` about a first edge up to `_SEARCH_PX` away (`_LEVEL_PX[1]` is less)."""


def _crossing(profile: np.ndarray, j: int, step: int, sign: float) -> float:
    """Column where `profile` crosses halfway between its levels just outside and just inside
    the edge near column `j` (the specimen lies in direction `step`): found once about `j`,
    then again about the first estimate. NaN where it crosses nowhere, or where the search
    would leave `profile`."""
    edge = float(j)
    for _ in range(2):
        k = int(round(edge))
        near, far = _LEVEL_PX
        if k - max(_SEARCH_PX, far) < 0 or k + max(_SEARCH_PX, far) >= len(profile):
            return math.nan
        outside = profile[k - far * step : k - near * step + step : step].mean()
        inside = profile[k + near * step : k + far * step + step : step].mean()
        mid = 0.5 * (outside + inside)
        found = None
        for i in range(k - _SEARCH_PX * step, k + (_SEARCH_PX - 2) * step, step):
            a, b = profile[i], profile[i + step]
            if (a - mid) * sign <= 0 < (b - mid) * sign:
                found = float(i + step * (mid - a) / (b - a))
                break
        if found is None:
            return math.nan
        edge = found
    return edge
