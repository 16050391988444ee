"""Measuring a calibrator's frames with the extensometer's own tracking: the readings of an ISO
9513 verification.

The calibrator (`Calibrator`: a real one driven by a lab, or the simulated one) carries two
targets in the specimen plane, their centres the nominal gauge length apart along the loading
axis, each with a dark line across its centre. For each series (`measure_series`):

1. the calibrator is set to zero and a reference frame taken; the gauge marks are placed on it
   as a test places them (`appliance.measure.gauges.place_marks`: centred, the gauge length
   apart, each mark a short line of points along the axis) and the tracker and gauges are
   built on it (`tracker_and_gauges`): the reading is zero there;
2. the gauge length is measured on the reference frame: the distance between the two dark
   lines (`line_distance_px`), in mm through the calibration;
3. for the first series, `rest_frames` frames are read with the calibrator still: the
   readings at rest, whose spread gives the resolution;
4. the calibrator is set to each step of the series in turn and a frame read at each: the
   elongation the gauges give, in um. Between steps further apart than `max_travel_px` the
   calibrator travels through intermediate positions whose frames are tracked and not
   recorded, as a real calibrator moves under the extensometer's eye.

Frames are tracked without a motion prediction (the calibrator is still at each frame).
Nothing here knows the calibrator's true displacement: the readings come from the frames.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from scipy import ndimage

from appliance.config import GaugeConfig
from appliance.errors import InputError
from appliance.measure.frame_measurer import tracker_and_gauges
from appliance.measure.gauges import Calibration, marks_outside, place_marks
from appliance.measure.tracking import TrackerSettings
from appliance.run.verification import CalibrationPoint, series_elongations

LINE_SEARCH_MM = 1.0
"""How far from its nominal place along the axis a target's line is looked for, mm."""
LINE_BAND_PX = 40
"""Half-width across the axis of the band averaged into a line's profile, px."""


class Calibrator(Protocol):
    """A calibrator under the extensometer's camera."""

    def move_to(self, reading_um: float) -> None:
        """Set the calibrator so that it reads `reading_um` (its elongation, um)."""

    def grab(self) -> np.ndarray:
        """A frame from the extensometer's camera (2-D grey image)."""


@dataclass(frozen=True)
class Setup:
    """How the extensometer measures the calibrator.

    Attributes:
        gauge_length_mm: the nominal gauge length, mm.
        centre_px: the targets' midpoint (x, y) in the image, px.
        calibration: px -> mm.
        gauge: the marks' layout ([gauge]: points per mark, spacing, axis).
        tracking: the tracker's settings ([tracking]).
        max_travel_px: the largest move between two frames while the calibrator travels, px.
    """

    gauge_length_mm: float
    centre_px: tuple[float, float]
    calibration: Calibration
    gauge: GaugeConfig
    tracking: TrackerSettings
    max_travel_px: float = 4.0


class SeriesReader:
    """The extensometer on one series: marks placed on the reference frame, every later frame
    read as an elongation (um)."""

    def __init__(self, reference: np.ndarray, setup: Setup) -> None:
        g = setup.gauge
        points, layout = place_marks(
            setup.centre_px,
            setup.gauge_length_mm,
            setup.calibration,
            axis_deg=g.axis_deg,
            mark_width_px=g.mark_spacing_px * (g.points_per_mark - 1),
            points_per_mark=g.points_per_mark,
            along_axis=True,
        )
        outside = marks_outside(points, reference.shape, setup.tracking.min_subset_px)
        if outside is not None:
            raise InputError(f"[gauge] length_mm: {outside}: the calibrator's targets do not fit")
        self.tracker, self.gauges = tracker_and_gauges(
            setup.tracking, reference, points, layout, setup.calibration
        )
        self.setup = setup
        theta = math.radians(g.axis_deg)
        self.axis = np.array([math.cos(theta), math.sin(theta)])
        marks = [points[list(mark)].mean(axis=0) for mark in layout.marks[:2]]
        self.gauge_length_mm = self._measure_gauge_length(reference, marks)

    def read_um(self, image: np.ndarray) -> float:
        """The elongation the gauges read on `image`, um (NaN: a mark lost)."""
        frame = self.tracker.track(np.asarray(image, dtype=np.float64), 0.0)
        return self.gauges.read(frame.positions, frame.measured).elongation_mm * 1e3

    def _measure_gauge_length(self, reference: np.ndarray, marks: list[np.ndarray]) -> float | None:
        """The distance between the targets' lines on the reference frame, mm; None when a
        line is not found. With a calibration's projection the lines are looked for on the
        specimen plane (where they are straight, whatever the lens), else in the image."""
        calibration = self.setup.calibration
        projection = calibration.projection
        step_mm = calibration.scale_mm_per_px
        search = math.ceil(LINE_SEARCH_MM / step_mm)
        along = np.arange(-search, search + 1, dtype=np.float64)
        across = np.arange(-LINE_BAND_PX, LINE_BAND_PX + 1, dtype=np.float64)
        u, v = np.meshgrid(along, across, indexing="ij")
        if projection is None:
            centres = marks
            axis = self.axis
        else:
            centres = list(projection.to_plane_mm(np.array(marks)))
            axis = (centres[1] - centres[0]) / np.hypot(*(centres[1] - centres[0]))
        ends = []
        for centre in centres:
            grid = np.stack(
                [centre[0] + u * axis[0] - v * axis[1], centre[1] + u * axis[1] + v * axis[0]],
                axis=-1,
            )
            if projection is None:
                pixels = grid
            else:
                grid = centre + (grid - centre) * step_mm
                pixels = projection.to_pixels(grid.reshape(-1, 2)).reshape(grid.shape)
            found = _profile_offset(reference, pixels, along)
            if found is None:
                return None
            ends.append(centre + found * (step_mm if projection is not None else 1.0) * axis)
        length = float(np.hypot(*(ends[1] - ends[0])))
        return length if projection is not None else length * step_mm


def line_offset_px(
    image: np.ndarray,
    centre_px: tuple[float, float],
    axis: np.ndarray,
    search_px: float,
    band_px: int = LINE_BAND_PX,
) -> float | None:
    """Where a dark line across the axis lies near `centre_px`, px along the axis from it
    (`_profile_offset` on a grid of +-`search_px` along the axis and +-`band_px` across it);
    None when there is no dark line."""
    along = np.arange(-math.ceil(search_px), math.ceil(search_px) + 1, dtype=np.float64)
    across = np.arange(-band_px, band_px + 1, dtype=np.float64)
    u, v = np.meshgrid(along, across, indexing="ij")
    pixels = np.stack(
        [centre_px[0] + u * axis[0] - v * axis[1], centre_px[1] + u * axis[1] + v * axis[0]],
        axis=-1,
    )
    return _profile_offset(image, pixels, along)


def _profile_offset(image: np.ndarray, pixels: np.ndarray, along: np.ndarray) -> float | None:
    """The position, in the units of `along`, of a dark line in the image sampled at `pixels`
    ((n_along, n_across, 2) x, y px; bilinear), whose rows lie at `along` across the line.

    The samples are averaged across into a profile. The line is the run of samples around the
    profile's minimum darker than halfway between the minimum and the profile's median; its
    position is the midpoint of its two edges, each where the profile crosses that level
    (linear interpolation). None when the profile has no dip or the run reaches the end of
    the window.
    """
    samples = ndimage.map_coordinates(
        np.asarray(image, dtype=np.float64),
        [pixels[..., 1], pixels[..., 0]],
        order=1,
        mode="nearest",
    )
    profile = samples.mean(axis=1)
    median = float(np.median(profile))
    lowest = int(np.argmin(profile))
    depth = median - float(profile[lowest])
    if not depth > 0:
        return None
    level = median - 0.5 * depth
    start = stop = lowest
    while start > 0 and profile[start - 1] < level:
        start -= 1
    while stop < profile.size - 1 and profile[stop + 1] < level:
        stop += 1
    if start == 0 or stop == profile.size - 1:
        return None
    edges = []
    for inside, outside in ((start, start - 1), (stop, stop + 1)):
        fraction = (level - profile[inside]) / (profile[outside] - profile[inside])
        edges.append(along[inside] + fraction * (along[outside] - along[inside]))
    return 0.5 * (edges[0] + edges[1])


@dataclass(frozen=True)
class SeriesReadings:
    """What one series measured: its points and, for the first series, the readings at rest."""

    points: tuple[CalibrationPoint, ...]
    rest_um: tuple[float, ...]
    gauge_length_mm: float | None


def measure_series(
    calibrator: Calibrator,
    setup: Setup,
    name: str,
    direction: str,
    steps_um: Sequence[float],
    *,
    rest_frames: int = 0,
    scale_um_per_px: float | None = None,
) -> SeriesReadings:
    """Run one series on `calibrator` (module docstring).

    Args:
        calibrator: the calibrator.
        setup: how the extensometer measures it.
        name: the series' name.
        direction: "increasing" or "decreasing".
        steps_um: the calibrator's elongations, um (any order).
        rest_frames: frames read at rest after the reference.
        scale_um_per_px: for the calibrator's travel between steps; None = the calibration's.

    Raises:
        InputError: the targets do not fit in the image.
    """
    calibrator.move_to(0.0)
    reader = SeriesReader(calibrator.grab(), setup)
    rest = tuple(reader.read_um(calibrator.grab()) for _ in range(rest_frames))
    per_px = scale_um_per_px or setup.calibration.scale_mm_per_px * 1e3
    longest = setup.max_travel_px * per_px
    position = 0.0
    points = []
    for target in series_elongations(steps_um, direction):
        moves = max(1, math.ceil(abs(target - position) / longest))
        for k in range(1, moves):
            calibrator.move_to(position + (target - position) * k / moves)
            reader.read_um(calibrator.grab())
        calibrator.move_to(target)
        reading = reader.read_um(calibrator.grab())
        points.append(CalibrationPoint(name, float(target), reading, reader.gauge_length_mm))
        position = target
    calibrator.move_to(0.0)
    return SeriesReadings(tuple(points), rest, reader.gauge_length_mm)
