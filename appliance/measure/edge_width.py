"""The specimen's width from its edges, at several stations along the gauge.

ISO 10113 takes the plastic strain ratio r from the change of width, measured at several
places along the gauge length; Poisson's ratio and the width of a necking specimen come from
the same measurement. `EdgeWidthGauge` measures the width of the specimen in every frame at
`count` *stations* between the two axial gauge marks, placed at the fractions
(k + 1) / (count + 1), k = 0 ... count - 1, of the distance from the first mark to the second
in the current frame: the stations move with the tracked marks, so each stays on about the
same material section while the specimen stretches.

At a station the image is resampled on a strip square to the line between the marks
(`STRIP_ROWS_PX` rows along the axis, averaged to wash out a speckle, one pixel apart across
it), and each of the two edges is located to a fraction of a pixel where the strip's profile
crosses halfway between the grey levels just outside and just inside the edge (2 to 14 px
from it, inside at most to the specimen's middle), searched within `SEARCH_PX` of where it
was in the previous frame and located twice, the second time about the first estimate. The
width is the distance between the two edge points: in px by the nominal scale, or with a
calibration's projection between the two points mapped onto the specimen plane (mm), as the
axial gauge measures its length.

A station is *flagged* (its width NaN, nothing guessed) when its strip leaves the image, when
an edge's contrast (inside against outside level) falls below `MIN_CONTRAST_FRACTION` of its
contrast in the reference frame, or when no halfway crossing lies within the search. The
transverse strain is the mean, over the stations measured in both the reference and this
frame, of each station's w / w0 - 1; NaN when none is.

The image alone is read (the lighting decides which side is brighter: the specimen on the
reference frame's axis against the levels beyond its edges).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from appliance.measure.gauges import Calibration
from appliance.measure.specimen_detection import (
    SpecimenDetection,
    SpecimenNotFound,
    detect_specimen,
)

STRIP_ROWS_PX = 41
"""Rows along the axis averaged into a station's profile, px."""
SEARCH_PX = 8
"""How far from its last position an edge is looked for, px."""
LEVEL_PX = (2, 14)
"""The grey levels either side of an edge are averaged this far from it, px."""
MIN_CONTRAST_FRACTION = 0.5
"""An edge whose contrast falls below this fraction of its reference contrast is not seen."""
MAX_STATIONS = 32
"""The most stations a gauge measures."""


class EdgesNotFound(ValueError):
    """The reference frame shows no edge at any station; the message says where (one line)."""


@dataclass(frozen=True)
class WidthReading:
    """The specimen's width in one frame.

    Attributes:
        widths_mm: each station's width, mm (in px scaled, or on the specimen plane); NaN
            where the station is flagged.
        seen: whether each station's two edges were located.
        mean_width_mm: mean of the widths of the stations seen; NaN when none is. A station
            dropping out steps it; the transverse strain, a mean of each station's own
            w / w0, does not.
        transverse_strain: mean over the stations seen here and in the reference of
            w / w0 - 1; NaN when none is.
    """

    widths_mm: tuple[float, ...]
    seen: tuple[bool, ...]
    mean_width_mm: float
    transverse_strain: float

    @property
    def stations_seen(self) -> int:
        """How many stations were measured."""
        return int(sum(self.seen))


@dataclass
class _Station:
    fraction: float
    left_px: float
    right_px: float
    contrast: tuple[float, float]
    width0_mm: float


class EdgeWidthGauge:
    """The width at `count` stations between the axial marks, frame after frame.

    Args:
        reference: the reference frame (2-D grey levels).
        first_px, second_px: (x, y) of the two axial marks in the reference frame, px.
        calibration: px -> mm, as the axial gauge's.
        count: stations, 1 to `MAX_STATIONS`.
        half_width_px: about half the specimen's width in the reference frame, px (the
            specimen detection's, or a guess within `SEARCH_PX`: the edges are then found by
            a wider search in the reference frame).

    Raises:
        EdgesNotFound: no station's two edges are found in the reference frame.
        ValueError: `count` out of range, or marks that coincide.
    """

    def __init__(
        self,
        reference: np.ndarray,
        first_px: tuple[float, float],
        second_px: tuple[float, float],
        calibration: Calibration,
        count: int,
        half_width_px: float,
    ) -> None:
        if not 1 <= count <= MAX_STATIONS:
            raise ValueError(f"stations must be 1 to {MAX_STATIONS}, got {count}")
        if not (half_width_px > LEVEL_PX[0] + 2 and math.isfinite(half_width_px)):
            raise ValueError(f"half_width_px must exceed {LEVEL_PX[0] + 2}, got {half_width_px}")
        self.calibration = calibration
        image = np.asarray(reference)
        first, second = np.asarray(first_px, float), np.asarray(second_px, float)
        if not np.hypot(*(second - first)) > 0:
            raise ValueError("the axial marks coincide")
        self.bright_inside = _specimen_brighter(image, first, second, half_width_px)
        self.stations: list[_Station] = []
        for k in range(count):
            fraction = (k + 1) / (count + 1)
            station = _Station(fraction, -half_width_px, half_width_px, (0.0, 0.0), math.nan)
            found = self._locate(image, first, second, station, reference_search=True)
            if found is not None:
                station.left_px, station.right_px, station.contrast = found
                station.width0_mm = self._width_mm(first, second, station)
            self.stations.append(station)
        if not any(math.isfinite(s.width0_mm) for s in self.stations):
            centre = first + 0.5 * (second - first)
            raise EdgesNotFound(
                f"no specimen edge found across the gauge near ({centre[0]:.0f}, "
                f"{centre[1]:.0f}) px"
            )

    @property
    def count(self) -> int:
        """Number of stations."""
        return len(self.stations)

    @property
    def reference_widths_mm(self) -> tuple[float, ...]:
        """Each station's width in the reference frame, mm (NaN where not seen)."""
        return tuple(s.width0_mm for s in self.stations)

    def station_points_px(
        self, first_px: tuple[float, float], second_px: tuple[float, float]
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each station's two edge points (left, right), px, as last located, for display."""
        first, second = np.asarray(first_px, float), np.asarray(second_px, float)
        points = []
        for station in self.stations:
            centre, across = _frame_of(first, second, station.fraction)
            points.append((centre + station.left_px * across, centre + station.right_px * across))
        return points

    def read(
        self, image: np.ndarray, first_px: tuple[float, float], second_px: tuple[float, float]
    ) -> WidthReading:
        """The widths in `image`, with the axial marks at `first_px` and `second_px` (px)."""
        grey = np.asarray(image)
        first, second = np.asarray(first_px, float), np.asarray(second_px, float)
        widths: list[float] = []
        strains: list[float] = []
        seen: list[bool] = []
        usable = np.all(np.isfinite(first)) and np.all(np.isfinite(second))
        for station in self.stations:
            found = None
            if usable and math.isfinite(station.width0_mm):
                found = self._locate(grey, first, second, station, reference_search=False)
            if found is None:
                widths.append(math.nan)
                seen.append(False)
                continue
            station.left_px, station.right_px = float(found[0]), float(found[1])
            width = self._width_mm(first, second, station)
            widths.append(width)
            seen.append(math.isfinite(width))
            if math.isfinite(width):
                strains.append(width / station.width0_mm - 1.0)
        measured = [w for w in widths if math.isfinite(w)]
        return WidthReading(
            widths_mm=tuple(widths),
            seen=tuple(seen),
            mean_width_mm=float(np.mean(measured)) if measured else math.nan,
            transverse_strain=float(np.mean(strains)) if strains else math.nan,
        )

    def rezero(self, reading: WidthReading) -> WidthReading:
        """Take `reading` (this gauge's reading of the frame a zero command applies to) as the
        new reference widths, as the axial gauge takes its new gauge length: each station seen
        in it starts again from its width there; a station not seen then has no reference any
        more and stays flagged for the rest of the test (it is never given a guessed one).

        Returns:
            `reading` with its transverse strain re-expressed against the new references: 0
            when a station was seen, NaN when none was.
        """
        for station, width in zip(self.stations, reading.widths_mm, strict=True):
            station.width0_mm = width if math.isfinite(width) else math.nan
        seen_any = any(math.isfinite(w) for w in reading.widths_mm)
        return WidthReading(
            widths_mm=reading.widths_mm,
            seen=reading.seen,
            mean_width_mm=reading.mean_width_mm,
            transverse_strain=0.0 if seen_any else math.nan,
        )

    def _width_mm(self, first: np.ndarray, second: np.ndarray, station: _Station) -> float:
        centre, across = _frame_of(first, second, station.fraction)
        if self.calibration.projection is None:
            return float(station.right_px - station.left_px) * self.calibration.scale_mm_per_px
        points = np.array([centre + station.left_px * across, centre + station.right_px * across])
        try:
            plane = self.calibration.projection.to_plane_mm(points)
        except ValueError:
            return math.nan
        return float(np.hypot(*(plane[1] - plane[0])))

    def _locate(
        self,
        image: np.ndarray,
        first: np.ndarray,
        second: np.ndarray,
        station: _Station,
        reference_search: bool,
    ) -> tuple[float, float, tuple[float, float]] | None:
        """(left, right, contrasts) of the station's edges across the axis, px from the
        station's centre; None when the station is flagged."""
        reach = 2 * SEARCH_PX if reference_search else SEARCH_PX
        low = math.floor(station.left_px) - reach - LEVEL_PX[1] - 2
        high = math.ceil(station.right_px) + reach + LEVEL_PX[1] + 2
        columns = np.arange(low, high + 1, dtype=float)
        profile = _profile(image, first, second, station.fraction, columns)
        if profile is None:
            return None
        sign = 1.0 if self.bright_inside else -1.0
        inside_px = min(LEVEL_PX[1], int(0.5 * (station.right_px - station.left_px)) - 1)
        if inside_px <= LEVEL_PX[0]:
            return None
        edges = []
        for edge_px, outward, index in ((station.left_px, -1, 0), (station.right_px, 1, 1)):
            located = _crossing(profile, edge_px - low, outward, sign, reach, inside_px)
            if located is None:
                return None
            position, contrast = located
            if not reference_search and contrast < MIN_CONTRAST_FRACTION * station.contrast[index]:
                return None
            edges.append((position + low, contrast))
        (left, left_contrast), (right, right_contrast) = edges
        if not right - left > 2 * LEVEL_PX[0] + 2:
            return None
        return left, right, (left_contrast, right_contrast)


def _frame_of(first: np.ndarray, second: np.ndarray, fraction: float) -> tuple[np.ndarray, ...]:
    """The station's centre and the unit vector across the axis (to the right of the first
    mark-to-second mark direction)."""
    along = second - first
    along = along / np.hypot(*along)
    return first + fraction * (second - first), np.array([-along[1], along[0]])


def _profile(
    image: np.ndarray, first: np.ndarray, second: np.ndarray, fraction: float, columns: np.ndarray
) -> np.ndarray | None:
    """The profile across the axis at the station, averaged over `STRIP_ROWS_PX` rows along
    it; None when the strip leaves the image."""
    centre, across = _frame_of(first, second, fraction)
    along = np.array([across[1], -across[0]])
    rows = np.arange(STRIP_ROWS_PX, dtype=float) - (STRIP_ROWS_PX - 1) / 2
    map_x = centre[0] + rows[:, None] * along[0] + columns[None, :] * across[0]
    map_y = centre[1] + rows[:, None] * along[1] + columns[None, :] * across[1]
    height, width = image.shape[:2]
    if map_x.min() < 0 or map_y.min() < 0 or map_x.max() > width - 1 or map_y.max() > height - 1:
        return None
    x0, y0 = int(map_x.min()), int(map_y.min())
    x1, y1 = min(int(map_x.max()) + 2, width), min(int(map_y.max()) + 2, height)
    crop = np.asarray(image[y0:y1, x0:x1], np.float32)
    strip = cv2.remap(
        crop, (map_x - x0).astype(np.float32), (map_y - y0).astype(np.float32), cv2.INTER_LINEAR
    ).astype(np.float64)
    return strip.mean(axis=0)


def _crossing(
    profile: np.ndarray, edge: float, outward: int, sign: float, reach: int, inside_px: int
) -> tuple[float, float] | None:
    """(position, contrast) of the edge near index `edge` of `profile` (the background lies
    in direction `outward`; `sign` +1 when the specimen is brighter): where the profile
    crosses halfway between its levels `LEVEL_PX` outside and inside the edge (inside up to
    `inside_px`, the specimen's middle when it is narrow), searched within `reach` of `edge`,
    then again within `SEARCH_PX` of that. None when it crosses nowhere."""
    near, far = LEVEL_PX
    contrast = 0.0
    for search in (reach, SEARCH_PX):
        k = int(round(edge))
        if k - search - far - 1 < 0 or k + search + far + 1 >= len(profile):
            return None
        outside = profile[k + outward * near : k + outward * (far + 1) : outward].mean()
        inside = profile[k - outward * near : k - outward * (inside_px + 1) : -outward].mean()
        contrast = (inside - outside) * sign
        if not contrast > 0:
            return None
        middle = 0.5 * (inside + outside)
        start = k - search
        a = profile[start : k + search] - middle
        b = profile[start + 1 : k + search + 1] - middle
        crossing = (a * b <= 0) & ((b - a) * sign * -outward > 0)
        if not crossing.any():
            return None
        at = np.flatnonzero(crossing)
        positions = start + at + a[at] / (a[at] - b[at])
        edge = float(positions[np.argmin(np.abs(positions - edge))])
    return edge, contrast


def _specimen_brighter(
    image: np.ndarray, first: np.ndarray, second: np.ndarray, half_width_px: float
) -> bool:
    """Whether the specimen is brighter than the background beyond its edges: the middle of
    the strip across the gauge's centre against the levels beyond both edges."""
    reach = half_width_px + 2 * SEARCH_PX
    columns = np.arange(math.floor(-reach), math.ceil(reach) + 1, dtype=float)
    profile = _profile(image, first, second, 0.5, columns)
    if profile is None:
        raise EdgesNotFound("the strip across the gauge's centre leaves the image")
    t = columns
    inside = profile[np.abs(t) <= 0.5 * half_width_px].mean()
    outside = profile[np.abs(t) >= half_width_px + SEARCH_PX].mean()
    return bool(inside > outside)


def edge_width_gauge(
    reference: np.ndarray,
    first_px: tuple[float, float],
    second_px: tuple[float, float],
    calibration: Calibration,
    count: int,
    detection: SpecimenDetection | None = None,
) -> EdgeWidthGauge:
    """The width gauge of a test on its reference frame, between its axial marks: the
    specimen's half-width from `detection`, or from the specimen detected in `reference`
    when none is given.

    Raises:
        EdgesNotFound: no specimen is found, or no station's edges.
    """
    if detection is None:
        try:
            detection = detect_specimen(reference)
        except SpecimenNotFound as exc:
            raise EdgesNotFound(f"no specimen edges to measure the width at: {exc}") from None
    return EdgeWidthGauge(
        reference, first_px, second_px, calibration, count, 0.5 * detection.width_px
    )
