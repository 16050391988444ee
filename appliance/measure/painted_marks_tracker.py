"""Following two painted marks (`appliance.measure.painted_marks`) from frame to frame.

Following (`PaintedDotTracker`, the interface of `appliance.measure.tracking.MarkTracker`):
each dot is searched in a window around its predicted position (constant velocity), at the
reference's threshold, and validated again every frame: the blob nearest the prediction must
lie within the window (a blob cut by the window or by the image's side has left the view or
merged with something larger), within `search_radius_px` of the prediction, fill its ellipse,
keep its area within `area_change` of the last frame's, and keep at least `min_contrast` of
its reference contrast against the ring around it. A dot that fails any of these is LOST in
that frame (its predicted position is reported and the sample is not valid): never guessed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from appliance.measure.painted_marks import (
    Dot,
    DotSettings,
    PaintedMarksNotFound,
    measure_blobs,
    paint_levels,
)
from appliance.measure.tracking import ReadRegion, TrackedFrame, TrackerSettings, TrackStatus

_TRACKED = int(TrackStatus.TRACKED)
_LOST = int(TrackStatus.LOST)


class _FollowedDot:
    def __init__(self, dot: Dot) -> None:
        self.position = np.array(dot.centre_px)
        self.reference_contrast = dot.contrast
        self.last = dot
        self.velocity = np.zeros(2)
        self.last_time: float | None = None


class PaintedDotTracker:
    """Follows two painted dots from frame to frame (see the module docstring).

    Args:
        reference: the reference frame (2-D grey array).
        points: (2, 2) positions (x, y) of the dots in it, px (from `find_dots`).
        marks: the gauge's marks, one point each: ((0,), (1,)).
        settings: the tracking settings (`search_radius_px` is the search radius).
        dots: how dots are found and validated.

    Raises:
        PaintedMarksNotFound: no dot in the reference at a given point.

    Use: `track(image, time_s, exposure_s)` for every frame in order; the result is an
    `appliance.measure.tracking.TrackedFrame` (ZNCC NaN, gradients zero: no correlation).
    """

    def __init__(
        self,
        reference: np.ndarray,
        points: np.ndarray,
        marks: Sequence[Sequence[int]],
        settings: TrackerSettings | None = None,
        dots: DotSettings | None = None,
    ) -> None:
        self.settings = settings or TrackerSettings()
        self.dot_settings = dots or DotSettings()
        points = np.asarray(points, np.float64)
        if points.shape != (2, 2) or sorted(tuple(m) for m in marks) != [(0,), (1,)]:
            raise ValueError("painted dots: two points, one mark each")
        self.n = 2
        self.reference_updates = 0
        self.threshold = paint_levels(reference, self.dot_settings)[1]
        self._dots = []
        for point in points:
            dot = self._find_near(np.asarray(reference), point, None)
            if dot is None:
                raise PaintedMarksNotFound(
                    f"no painted {self.dot_settings.kind[:-1]} at ({point[0]:.0f}, "
                    f"{point[1]:.0f}) px of the reference"
                )
            self._dots.append(_FollowedDot(dot))
        self.positions = np.array([d.position for d in self._dots])

    @property
    def subsets(self) -> list[int]:
        """Current window of every dot, px (the larger side), for display."""
        return [int(max(d.last.axes_px)) for d in self._dots]

    def track(self, image: np.ndarray, time_s: float, exposure_s: float = 0.0) -> TrackedFrame:
        """Measure both dots in the next frame (`exposure_s` is not used)."""
        image = np.asarray(image)
        positions = np.empty((2, 2))
        status = np.full(2, _LOST, dtype=np.int8)
        regions = []
        for k, followed in enumerate(self._dots):
            dt = None if followed.last_time is None else time_s - followed.last_time
            predicted = followed.position + (followed.velocity * dt if dt else 0.0)
            region = self._window(image.shape, predicted, followed.last)
            regions.append(region)
            dot = self._find_near(image, predicted, followed, region)
            if dot is None:
                positions[k] = predicted
                continue
            found = np.array(dot.centre_px)
            if dt:
                followed.velocity = (found - followed.position) / dt
            followed.position = found
            followed.last = dot
            followed.last_time = time_s
            positions[k] = found
            status[k] = _TRACKED
        self.positions = positions
        return TrackedFrame(
            positions,
            status,
            np.full(2, np.nan),
            np.zeros((2, 4)),
            0,
            int(np.count_nonzero(status == _LOST)),
            tuple(regions),
        )

    def _window(self, shape: tuple[int, ...], centre: np.ndarray, last: Dot) -> ReadRegion:
        s = self.dot_settings
        reach = 0.5 * last.axes_px[0] + self.settings.search_radius_px + s.window_margin_px
        reach += s.ring_px + 3.0 * s.smoothing_sigma_px
        x0 = max(int(math.floor(centre[0] - reach)), 0)
        y0 = max(int(math.floor(centre[1] - reach)), 0)
        x1 = min(int(math.ceil(centre[0] + reach)), shape[1] - 1)
        y1 = min(int(math.ceil(centre[1] + reach)), shape[0] - 1)
        return ReadRegion(x0, y0, max(x1 - x0 + 1, 1), max(y1 - y0 + 1, 1))

    def _find_near(
        self,
        image: np.ndarray,
        predicted: np.ndarray,
        followed: _FollowedDot | None,
        region: ReadRegion | None = None,
    ) -> Dot | None:
        """The valid dot nearest `predicted`, or None. Without `followed` (the reference),
        only the shape is checked, in a window sized for the reference's dots."""
        s = self.dot_settings
        if region is None:
            reach = 4 * self.settings.search_radius_px + 8 * s.window_margin_px
            probe = Dot(tuple(predicted), 0.0, (2.0 * reach, 0.0), 1.0, 0.0, 0.0, 0.0, False)
            region = self._window(image.shape, predicted, probe)
        window = image[region.y : region.y + region.height, region.x : region.x + region.width]
        offset = np.array([region.x, region.y], np.float64)
        blobs = measure_blobs(window, self.threshold, s)
        if not blobs:
            return None
        distances = [np.hypot(*(np.array(b.centre_px) + offset - predicted)) for b in blobs]
        nearest = blobs[int(np.argmin(distances))]
        low, high = s.fill_range
        if nearest.cut or not low <= nearest.fill <= high:
            return None
        if followed is not None:
            if min(distances) > self.settings.search_radius_px + 1.0:
                return None
            ratio = nearest.area_px / followed.last.area_px
            if not 1.0 / (1.0 + s.area_change) <= ratio <= 1.0 + s.area_change:
                return None
            if not nearest.contrast >= s.min_contrast * followed.reference_contrast:
                return None
        x, y = np.array(nearest.centre_px) + offset
        return Dot(
            (float(x), float(y)),
            nearest.area_px,
            nearest.axes_px,
            nearest.fill,
            nearest.level,
            nearest.surround,
            nearest.spread,
            nearest.cut,
        )
