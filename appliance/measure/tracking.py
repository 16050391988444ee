"""Tracking gauge marks through a whole test, to strains of several hundred percent.

One image correlation against the first image cannot follow a rubber specimen to 600 %: the
speckles stretch sevenfold along the axis and shrink across it, far beyond what a first-order
subset shape function matches. `MarkTracker` therefore follows each mark (a small group of
points) from frame to frame and *updates its reference* whenever the match degrades:

* each mark has its own window: the reference crop around the mark and, in every frame, a
  target crop of the same size placed where the mark is predicted to be (constant velocity
  from the last two frames). Only these windows are filtered and interpolated, so the cost per
  frame does not depend on the sensor size, and the windows follow the marks wherever they
  travel;
* in each window IC-GN starts from the predicted position and the mark's current deformation
  (optionally after an integer ZNCC or LPQ search every frame); a point is *tracked* when
  IC-GN converges with ZNCC >= `min_zncc` within `search_radius_px` of its prediction;
* the reference of a mark is replaced by the current frame when the ZNCC of any of its points
  falls below `update_zncc`, a point had to be re-acquired, or the deformation since the
  reference (largest displacement gradient) exceeds `update_deformation`; never from a frame
  in which one of its points was lost (an occlusion must not become the reference). The new
  reference positions are the positions just measured, so every later position is still an
  absolute position in image coordinates and strain stays referred to the original gauge
  length; what a reference update adds is the measurement error of that frame, carried
  forward (a random walk of one position error per update, measured by the simulated-test
  benchmark);
* after a reference update the subset shrinks with the lateral contraction measured since the
  first image (down to `min_subset_px`), so subsets stay inside a specimen that narrows;
* a point that fails is searched again at once with `reacquire_radius_px` on a wider window
  (re-acquisition); if that fails too it is LOST for this frame and its position is estimated
  from the mark's tracked points and their deformation gradient, so the mark's centroid does
  not jump; a mark with no tracked point keeps its predicted position and is reported lost;
* the search of a stage set to "auto" is the product's choice for each mark's blur and the
  expected one-step stretch (`appliance.measure.automatic_search`), made again when these
  move; every change of the search is reported with the inputs it used (`search_choices`,
  `follow_search_choices`);
* motion blur: the first reference is sharp, later frames may be blurred by the marks' motion
  during the exposure. With the exposure known, each mark's blur is estimated from its
  tracked velocity and the first reference is blurred to match (`appliance.dic.correlation`;
  when a frame's own measurement changes the estimate, it is matched again, and that match
  kept unless it measures fewer points or, for a mark that had to be re-acquired, correlates
  worse); updated references come from frames exposed at the same speed and
  are used as they are;
* a mark found only by re-acquisition has jumped between frames (a slip, a vibration): its
  velocity stays as it was, unless it was found so in the frame before too (its speed
  changed).

Directions: the loading axis is a unit vector in image coordinates (default: along the rows,
the image y axis); "across" is perpendicular to it.
"""

from __future__ import annotations

import enum
import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from appliance.dic.correlation import DEFAULT_PREFILTER_SIGMA, Correlator
from appliance.dic.icgn import PointStatus
from appliance.dic.lpq import window_for_blur
from appliance.measure.automatic_search import (
    AUTO,
    AutomaticSearch,
    SearchChoiceChange,
    SearchInputs,
    axial_strain_rate_per_s,
    prewarps_about,
)


class TrackStatus(enum.IntEnum):
    """State of one point in one frame.

    TRACKED: measured in this frame.
    REACQUIRED: failed the normal search, measured by the wider re-acquisition search.
    LOST: not measured; its position is estimated from the rest of its mark (or predicted).
    """

    TRACKED = 0
    REACQUIRED = 1
    LOST = 2


# Plain ints for the per-frame array work: numpy looks an enum member's type up for array
# protocols on every use, which costs more than the comparison itself.
_TRACKED = int(TrackStatus.TRACKED)
_REACQUIRED = int(TrackStatus.REACQUIRED)
_LOST = int(TrackStatus.LOST)
_CONVERGED = int(PointStatus.CONVERGED)


@dataclass(frozen=True)
class TrackerSettings:
    """Tuning of `MarkTracker`; every length in px of the image. The configuration's
    `[tracking]` table is this class: a key per field, the same defaults, and each field's
    `metadata` gives the bounds (`minimum`, `maximum`, inclusive), `choices` or `odd` the
    configuration checks; fields with `configurable` False are the tracker's own constants.

    Attributes:
        subset_px: subset side at the first reference (odd).
        min_subset_px: smallest subset after lateral contraction (odd).
        search: integer search in every frame: "none" (IC-GN starts from the predicted
            position and deformation: the fast default, since the prediction is within a
            pixel or two of the truth), "zncc" / "lpq" (searched every frame) or "auto"
            (searched every frame with the product's choice for the blur and the one-step
            stretch, `appliance.measure.automatic_search`).
        search_radius_px: half-width of the every-frame window around the prediction: the
            search radius, and the furthest a match may land from its prediction (at least 1:
            the exposure planner keeps the frame-to-frame motion within it).
        reacquire_search: search used to re-acquire a failed point: "zncc", "lpq" or "auto"
            (the product's choice, as for `search`).
        reacquire_radius_px: its half-width.
        prefilter_sigma_px: Gaussian pre-filter of IC-GN.
        min_zncc: a point whose refined ZNCC is below this is not tracked.
        update_zncc: a mark whose worst point has a ZNCC below this updates its reference.
        update_deformation: a mark whose largest displacement gradient (relative to its
            reference) exceeds this updates its reference.
        margin_px: extra border of every window beyond subset and search.
        blur_tolerance_px: re-prepare the first reference when the estimated blur of a mark
            differs by more than this from the blur applied to it.
        axis: loading axis, unit vector (x, y) in image coordinates.
    """

    subset_px: int = field(default=41, metadata={"minimum": 5, "maximum": 301, "odd": True})
    min_subset_px: int = field(default=11, metadata={"minimum": 5, "maximum": 301, "odd": True})
    search: str = field(default="none", metadata={"choices": ("none", "zncc", "lpq", AUTO)})
    search_radius_px: int = field(default=10, metadata={"minimum": 1, "maximum": 1000})
    reacquire_search: str = field(default="zncc", metadata={"choices": ("zncc", "lpq", AUTO)})
    reacquire_radius_px: int = field(default=40, metadata={"minimum": 0, "maximum": 1000})
    prefilter_sigma_px: float = field(
        default=DEFAULT_PREFILTER_SIGMA, metadata={"minimum": 0.0, "maximum": 5.0}
    )
    min_zncc: float = field(default=0.8, metadata={"minimum": -1.0, "maximum": 1.0})
    update_zncc: float = field(default=0.95, metadata={"minimum": -1.0, "maximum": 1.0})
    update_deformation: float = field(default=0.08, metadata={"minimum": 0.001, "maximum": 1.0})
    margin_px: int = field(default=4, metadata={"configurable": False})
    blur_tolerance_px: float = field(default=0.5, metadata={"configurable": False})
    axis: tuple[float, float] = field(default=(0.0, 1.0), metadata={"configurable": False})

    def __post_init__(self) -> None:
        if self.subset_px < 5 or self.subset_px % 2 == 0:
            raise ValueError(f"subset_px must be an odd size >= 5, got {self.subset_px}")
        if not 5 <= self.min_subset_px <= self.subset_px or self.min_subset_px % 2 == 0:
            raise ValueError(f"min_subset_px must be odd in 5..subset_px, got {self.min_subset_px}")
        if self.search not in ("none", "zncc", "lpq", AUTO):
            raise ValueError(f"search must be none, zncc, lpq or auto, got {self.search!r}")
        if self.reacquire_search not in ("zncc", "lpq", AUTO):
            raise ValueError(
                f"reacquire_search must be zncc, lpq or auto, got {self.reacquire_search!r}"
            )
        if not 0 <= self.search_radius_px <= self.reacquire_radius_px:
            raise ValueError("need 0 <= search_radius_px <= reacquire_radius_px")
        if not -1 <= self.min_zncc <= self.update_zncc <= 1:
            raise ValueError("need -1 <= min_zncc <= update_zncc <= 1")
        if not self.update_deformation > 0:
            raise ValueError("update_deformation must be > 0")
        norm = math.hypot(*self.axis)
        if not norm > 0:
            raise ValueError("axis must be a non-zero vector")
        object.__setattr__(self, "axis", (self.axis[0] / norm, self.axis[1] / norm))


@dataclass(frozen=True)
class ReadRegion:
    """A rectangle of an image, in pixels: columns x .. x + width - 1, rows y .. y + height - 1."""

    x: int
    y: int
    width: int
    height: int

    def union(self, other: ReadRegion) -> ReadRegion:
        """The smallest rectangle holding both."""
        x0, y0 = min(self.x, other.x), min(self.y, other.y)
        x1 = max(self.x + self.width, other.x + other.width)
        y1 = max(self.y + self.height, other.y + other.height)
        return ReadRegion(x0, y0, x1 - x0, y1 - y0)

    def contains(self, other: ReadRegion) -> bool:
        """Whether `other` lies wholly inside this rectangle."""
        return (
            self.x <= other.x
            and self.y <= other.y
            and other.x + other.width <= self.x + self.width
            and other.y + other.height <= self.y + self.height
        )


@dataclass(frozen=True)
class TrackedFrame:
    """Result of one frame for all points (n of them).

    Attributes:
        positions: (n, 2) positions (x, y) in this image, px; LOST points estimated.
        status: (n,) `TrackStatus`.
        zncc: (n,) ZNCC of the match against the mark's current reference (NaN if lost).
        gradients: (n, 4) (ux, uy, vx, vy) relative to the mark's current reference.
        reference_updates: marks whose reference was replaced after this frame.
        marks_lost: marks with no measured point in this frame.
        read_regions: for every mark, the bounding rectangle of every pixel of this image the
            tracker read (its windows, and the new reference after an update). These pixels
            alone determine the result: a copy of the image that holds them and anything
            else elsewhere tracks to the same numbers.
        search_choices: the changes of an automatic search made for this frame (stages set
            to "auto"), with the inputs they used; empty when none changed.
    """

    positions: np.ndarray
    status: np.ndarray
    zncc: np.ndarray
    gradients: np.ndarray
    reference_updates: int
    marks_lost: int
    read_regions: tuple[ReadRegion, ...]
    search_choices: tuple[SearchChoiceChange, ...] = ()

    @property
    def measured(self) -> np.ndarray:
        """(n,) mask of points measured in this frame (tracked or re-acquired)."""
        return self.status != TrackStatus.LOST


def _mean_rows(values: np.ndarray) -> np.ndarray:
    """`values.mean(axis=0)`: the same sum and division, without numpy's Python-level wrapper
    (which costs more than the arithmetic for the few rows of a mark)."""
    return np.add.reduce(values, axis=0) / values.shape[0]


def _odd_at_most(value: float, lowest: int, highest: int) -> int:
    size = int(math.floor(value))
    size -= 1 - size % 2
    return max(lowest, min(highest, size))


_STAGES = ("track", "reacquire")


class _Mark:
    """One group of points followed with its own reference window."""

    def __init__(self, indices: np.ndarray, settings: TrackerSettings) -> None:
        self.indices = indices
        self.settings_of = {"track": settings.search, "reacquire": settings.reacquire_search}
        self.auto_stages = tuple(name for name in _STAGES if self.settings_of[name] == AUTO)
        self.auto = (
            AutomaticSearch(settings.axis, settings.blur_tolerance_px) if self.auto_stages else None
        )
        first = int(indices[0])
        contiguous = np.array_equal(indices, np.arange(first, first + indices.size))
        self.rows = slice(first, first + indices.size) if contiguous else indices
        self.settings = settings
        self.subset = settings.subset_px
        self.deformation_total = np.eye(2)
        self.blur_applied = 0.0
        self.first_reference = True
        self.stages: dict[str, _Stage] = {}
        self.decision: SearchChoiceChange | None = None
        self.velocity = np.zeros(2)
        self.velocity_measured = False
        self.jumped = False
        self.gradient = np.zeros(4)
        self.last_time: float | None = None

    def method(self, name: str) -> str:
        """The search of stage `name`: its setting, or the automatic choice's."""
        setting = self.settings_of[name]
        return self.auto.choice.method if setting == AUTO else setting

    def lpq_window(self, name: str, blur_px: float) -> int | None:
        """The LPQ window of stage `name` (None unless it searches with LPQ): the blur rule's
        for the blur applied to the reference or, for an automatic choice, for the blur it
        was made for (a later reference carries the targets' blur without any applied)."""
        if self.method(name) != "lpq":
            return None
        if self.settings_of[name] == AUTO:
            blur_px = self.auto.inputs.blur_px
        return window_for_blur(blur_px, _axis_angle(self.settings.axis), subset=self.subset)

    def prewarps(self, name: str) -> list[tuple[float, ...]]:
        """Pre-warps of stage `name`'s search: the current deformation, and for an automatic
        choice the one-step stretch's about it."""
        if self.settings_of[name] == AUTO:
            return prewarps_about(self.gradient, self.auto.choice)
        return [tuple(self.gradient)]

    def search_outdated(self) -> bool:
        """Whether an automatic stage's correlator was built for another search than the
        choice now names (method or LPQ window)."""
        return any(
            (stage.method, stage.lpq_window)
            != (self.method(name), self.lpq_window(name, self.blur_applied))
            for name, stage in self.stages.items()
            if name in self.auto_stages
        )

    def set_reference(self, image: np.ndarray, positions: np.ndarray) -> None:
        """Make `image` the (sharp) reference with the mark's points at `positions` (m, 2)."""
        s = self.settings
        self.reference_positions = positions.copy()
        lo, hi = positions.min(axis=0), positions.max(axis=0)
        self.stages = {}
        for name, radius in (
            ("track", s.search_radius_px),
            ("reacquire", s.reacquire_radius_px),
        ):
            border = self.subset // 2 + radius + s.margin_px
            origin = np.floor(lo).astype(np.int64) - border
            width, height = (np.ceil(hi).astype(np.int64) + border + 1 - origin).tolist()
            crop = np.array(_crop(image, origin, width, height))
            self.stages[name] = _Stage(origin, crop)
        self.prepare(0.0)

    def reference_region(self, shape: tuple[int, ...]) -> ReadRegion:
        """The pixels of an image of `shape` that `set_reference` read."""
        regions = [
            _crop_region(shape, stage.origin, stage.crop.shape[1], stage.crop.shape[0])
            for stage in self.stages.values()
        ]
        return functools.reduce(ReadRegion.union, regions)

    def prepare(self, blur_px: float) -> None:
        """(Re)build the correlators on the reference crops, blurred by `blur_px` along the axis;
        an LPQ search takes the window of the blur rule (`appliance.dic.lpq.window_for_blur`).

        The every-frame correlator is prepared at once, the re-acquisition one when first used
        (`correlator`): a reference update does not pay for a re-acquisition that may never
        be needed.
        """
        s = self.settings
        self.blur_applied = blur_px
        for name, radius in (("track", s.search_radius_px), ("reacquire", s.reacquire_radius_px)):
            stage = self.stages[name]
            stage.method = self.method(name)
            stage.lpq_window = self.lpq_window(name, blur_px)
            stage.correlator = Correlator(
                subset=self.subset,
                search=stage.method,
                search_radius=radius,
                reference_blur=(blur_px, _axis_angle(s.axis)) if blur_px > 0 else None,
                lpq_window=stage.lpq_window,
                prefilter_sigma=s.prefilter_sigma_px,
                threads=1,
            )
            stage.ready = False
        self.correlator("track")

    def correlator(self, name: str) -> Correlator:
        """The correlator of stage `name` ("track" or "reacquire"), prepared."""
        stage = self.stages[name]
        if not stage.ready:
            stage.correlator.prepare(stage.crop, self.reference_positions - stage.origin)
            stage.ready = True
        return stage.correlator


@dataclass
class _Stage:
    """A mark's reference window for one kind of match (every frame, or re-acquisition)."""

    origin: np.ndarray
    crop: np.ndarray
    correlator: Correlator | None = None
    ready: bool = False
    method: str = ""
    lpq_window: int | None = None


def _matches_better(candidate: tuple, incumbent: tuple) -> bool:
    """Whether a mark's second match `candidate` (against a reference blurred for the speed the
    first measured, `MarkTracker._match`) replaces the first, `incumbent`: unless it measures
    fewer points or, where the first had to re-acquire a point, as many with a lower mean ZNCC."""
    measured = candidate[1] != _LOST
    before = incumbent[1] != _LOST
    if measured.sum() != before.sum():
        return bool(measured.sum() > before.sum())
    if not np.any(incumbent[1] == _REACQUIRED):
        return True
    return bool(candidate[2][measured].mean() >= incumbent[2][before].mean())


def _axis_angle(axis: tuple[float, float]) -> float:
    return math.degrees(math.atan2(axis[1], axis[0]))


def _crop_region(shape: tuple[int, ...], origin: np.ndarray, width: int, height: int) -> ReadRegion:
    """The pixels of an image of `shape` that `_crop` reads for a window at `origin`."""
    h, w = shape
    x0 = min(max(int(origin[0]), 0), w - 1)
    y0 = min(max(int(origin[1]), 0), h - 1)
    x1 = min(max(int(origin[0]) + width - 1, 0), w - 1)
    y1 = min(max(int(origin[1]) + height - 1, 0), h - 1)
    return ReadRegion(x0, y0, x1 - x0 + 1, y1 - y0 + 1)


def _crop(image: np.ndarray, origin: np.ndarray, width: int, height: int) -> np.ndarray:
    """Window of `image` at `origin` (x0, y0) as float64; parts outside the image repeat the
    edge. A float64 image's window wholly inside may be a view (valid while the image is)."""
    x0, y0 = int(origin[0]), int(origin[1])
    h, w = image.shape
    if 0 <= x0 and x0 + width <= w and 0 <= y0 and y0 + height <= h:
        return np.ascontiguousarray(image[y0 : y0 + height, x0 : x0 + width], dtype=np.float64)
    rows = np.clip(np.arange(y0, y0 + height), 0, h - 1)
    cols = np.clip(np.arange(x0, x0 + width), 0, w - 1)
    return np.asarray(image[np.ix_(rows, cols)], dtype=np.float64)


class MarkTracker:
    """Follows groups of points (marks) from frame to frame with reference updating.

    Args:
        reference: the first image (2-D grey array).
        points: (n, 2) positions (x, y) of all points in it, px.
        marks: groups of point indices tracked together (each point in exactly one group);
            a gauge mark is a natural group.
        settings: tuning.

    Use: `track(image, time_s, exposure_s)` for every frame in order.

    Attributes:
        search_choices: every change of an automatic search so far, in order (stages set to
            "auto"; the first of each mark on the reference, with no motion known).
    """

    def __init__(
        self,
        reference: np.ndarray,
        points: np.ndarray,
        marks: Sequence[Sequence[int]],
        settings: TrackerSettings | None = None,
    ) -> None:
        self.settings = settings or TrackerSettings()
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 2 or not np.all(np.isfinite(points)):
            raise ValueError("points must be a finite (n, 2) array")
        flat = sorted(i for mark in marks for i in mark)
        if flat != list(range(points.shape[0])):
            raise ValueError("every point must belong to exactly one mark")
        self.n = points.shape[0]
        self.positions = points.copy()
        self.reference_updates = 0
        self.search_choices: list[SearchChoiceChange] = []
        self._search_listeners: list[Callable[[SearchChoiceChange], None]] = []
        self._marks = [_Mark(np.asarray(mark, dtype=np.int64), self.settings) for mark in marks]
        still = SearchInputs(0.0, 0.0, 0.0, strain_rate_per_s=None, frame_interval_s=None)
        for number, mark in enumerate(self._marks):
            if mark.auto is not None:
                self._choose(mark, number, still, None, [])
            mark.set_reference(reference, points[mark.indices])

    @property
    def subsets(self) -> list[int]:
        """Current subset size of every mark, px."""
        return [mark.subset for mark in self._marks]

    def search_decisions(self) -> list[SearchChoiceChange | None]:
        """The automatic search decision in force for every mark (None: no stage is "auto"):
        the latest, also where it left the search as it was (a blur moved with the method,
        window and pre-warps unchanged), and so was not reported."""
        return [mark.decision for mark in self._marks]

    def follow_search_choices(self, listener: Callable[[SearchChoiceChange], None]) -> None:
        """Call `listener` with every automatic search choice made so far, then with every
        later one as it is made (on the thread that calls `track`)."""
        for change in self.search_choices:
            listener(change)
        self._search_listeners.append(listener)

    def track(self, image: np.ndarray, time_s: float, exposure_s: float = 0.0) -> TrackedFrame:
        """Measure all points in the next frame.

        Args:
            image: 2-D grey image (the whole frame; only the marks' windows are read).
            time_s: time of the frame (any clock, seconds), for the velocity prediction.
            exposure_s: its exposure, s, for the blur estimate (0 = assume no blur).
        """
        image = np.asarray(image)
        positions = np.empty((self.n, 2))
        status = np.full(self.n, _LOST, dtype=np.int8)
        zncc = np.full(self.n, np.nan)
        gradients = np.zeros((self.n, 4))
        updates = 0
        lost_marks = 0
        regions = []
        choices: list[SearchChoiceChange] = []
        rate = self._strain_rate_per_s() if self._marks[0].auto is not None else None
        for number, mark in enumerate(self._marks):
            reads: list[ReadRegion] = []
            if mark.auto is not None:
                dt = None if mark.last_time is None else time_s - mark.last_time
                speed = float(np.hypot(*mark.velocity))
                inputs = SearchInputs(speed * exposure_s, speed, exposure_s, rate, dt)
                self._choose(mark, number, inputs, time_s, choices)
            result = self._track_mark(mark, image, time_s, exposure_s, reads)
            idx = mark.rows
            positions[idx], status[idx], zncc[idx], gradients[idx] = result[:4]
            if result[4]:
                lost_marks += 1
            elif self._needs_update(status[idx], zncc[idx], gradients[idx]):
                self._update_reference(mark, image, positions[idx])
                reads.append(mark.reference_region(image.shape))
                updates += 1
            regions.append(functools.reduce(ReadRegion.union, reads))
        self.reference_updates += updates
        self.positions = positions
        return TrackedFrame(
            positions, status, zncc, gradients, updates, lost_marks, tuple(regions), tuple(choices)
        )

    def _strain_rate_per_s(self) -> float | None:
        """The axial strain rate the marks' last positions and velocities give, 1/s."""
        centres = np.array([_mean_rows(self.positions[mark.rows]) for mark in self._marks])
        velocities = [mark.velocity if mark.velocity_measured else None for mark in self._marks]
        return axial_strain_rate_per_s(centres, velocities, self.settings.axis)

    def _choose(
        self,
        mark: _Mark,
        number: int,
        inputs: SearchInputs,
        time_s: float | None,
        changes: list[SearchChoiceChange],
    ) -> None:
        """Decide a mark's automatic search again if its inputs moved: the correlators it
        changes are rebuilt, and a change of the search is reported."""
        if not mark.auto.update(inputs, mark.subset):
            return
        change = SearchChoiceChange(time_s, number, mark.auto_stages, inputs, mark.auto.choice)
        mark.decision = change
        if mark.search_outdated():
            mark.prepare(mark.blur_applied)
        if not mark.auto.search_changed:
            return
        changes.append(change)
        self.search_choices.append(change)
        for listener in self._search_listeners:
            listener(change)

    def _track_mark(
        self,
        mark: _Mark,
        image: np.ndarray,
        time_s: float,
        exposure_s: float,
        reads: list[ReadRegion],
    ):
        s = self.settings
        last = self.positions[mark.rows]
        dt = None if mark.last_time is None else time_s - mark.last_time
        predicted = last + (mark.velocity * dt if dt else 0.0)
        velocity = mark.velocity
        jumped = False
        result = None
        for _ in range(2):
            blur = float(np.hypot(*velocity)) * exposure_s
            if mark.first_reference and abs(blur - mark.blur_applied) > s.blur_tolerance_px:
                mark.prepare(blur)
            attempt = self._match(mark, image, predicted, reads)
            if result is not None and not _matches_better(attempt, result):
                break
            result = attempt
            positions, status, _, gradients, mark_lost = result
            if mark_lost or not dt:
                break
            jumped = mark.velocity_measured and not mark.jumped and not np.any(status == _TRACKED)
            if jumped:
                break
            velocity = (_mean_rows(positions) - _mean_rows(last)) / dt
            blur_now = float(np.hypot(*velocity)) * exposure_s
            if not mark.first_reference or abs(blur_now - mark.blur_applied) <= (
                s.blur_tolerance_px
            ):
                break
        positions, status, _, gradients, mark_lost = result
        if not mark_lost:
            mark.gradient = _mean_rows(gradients[status != _LOST])
            mark.jumped = jumped
            if dt:
                mark.velocity = velocity
                mark.velocity_measured = True
        mark.last_time = time_s
        return result

    def _match(
        self, mark: _Mark, image: np.ndarray, predicted: np.ndarray, reads: list[ReadRegion]
    ):
        """Match a mark's points near their predicted positions: every-frame stage, then
        re-acquisition for the points that failed. The regions of `image` read are appended
        to `reads`."""
        s = self.settings
        gradient_guess = mark.gradient
        reference = mark.reference_positions
        m = mark.indices.size
        offset = predicted - reference
        shift = _mean_rows(offset).round().astype(np.int64)
        guess = np.empty((m, 6))
        guess[:, :2] = offset - shift
        guess[:, 2:] = gradient_guess
        prewarps = [tuple(gradient_guess)]
        positions = predicted
        status = np.full(m, _LOST, dtype=np.int8)
        zncc = np.full(m, np.nan)
        gradients = gradient_guess[np.newaxis].repeat(m, axis=0)
        pending = np.ones(m, dtype=bool)
        for name, flag, radius in (
            ("track", _TRACKED, s.search_radius_px),
            ("reacquire", _REACQUIRED, s.reacquire_radius_px),
        ):
            stage = mark.stages[name]
            h, w = stage.crop.shape
            origin = stage.origin + shift
            reads.append(_crop_region(image.shape, origin, w, h))
            correlator = mark.correlator(name)
            correlator.prewarps = mark.prewarps(name) if name in mark.auto_stages else prewarps
            result = correlator.measure(_crop(image, origin, w, h), guess).refinement
            moved = np.hypot(result.u - guess[:, 0], result.v - guess[:, 1])
            good = (
                (result.status == _CONVERGED)
                & (result.zncc >= s.min_zncc)
                & (moved <= radius + 1.0)
            )
            take = pending & good
            rows = take[:, np.newaxis]
            found = np.array((result.u, result.v)).T
            positions = np.where(rows, reference + found + shift, positions)
            status = np.where(take, np.int8(flag), status)
            zncc = np.where(take, result.zncc, zncc)
            shape = np.array((result.ux, result.uy, result.vx, result.vy)).T
            gradients = np.where(rows, shape, gradients)
            pending &= ~good
            if not pending.any():
                break
        measured = ~pending
        mark_lost = not measured.any()
        if mark_lost:
            positions = predicted
        elif pending.any():
            positions[pending] = self._estimate(mark, positions, measured, gradients)
        return positions, status, zncc, gradients, mark_lost

    def _estimate(
        self, mark: _Mark, positions: np.ndarray, measured: np.ndarray, gradients: np.ndarray
    ) -> np.ndarray:
        """Positions of a mark's unmeasured points from the measured ones and their gradient."""
        g = gradients[measured].mean(axis=0)
        f = np.array([[1 + g[0], g[1]], [g[2], 1 + g[3]]])
        ref = mark.reference_positions
        anchor_ref = ref[measured].mean(axis=0)
        anchor_now = positions[measured].mean(axis=0)
        return anchor_now + (ref[~measured] - anchor_ref) @ f.T

    def _needs_update(self, status: np.ndarray, zncc: np.ndarray, gradients: np.ndarray) -> bool:
        s = self.settings
        if (status == _LOST).any():
            return False
        if (status == _REACQUIRED).any():
            return True
        if zncc.min() < s.update_zncc:
            return True
        return float(np.abs(gradients).max()) > s.update_deformation

    def _update_reference(self, mark: _Mark, image: np.ndarray, positions: np.ndarray) -> None:
        s = self.settings
        g = mark.gradient
        step = np.array([[1 + g[0], g[1]], [g[2], 1 + g[3]]])
        mark.deformation_total = step @ mark.deformation_total
        across = np.array([-s.axis[1], s.axis[0]])
        lateral = float(np.linalg.norm(mark.deformation_total @ across))
        mark.subset = _odd_at_most(s.subset_px * min(1.0, lateral), s.min_subset_px, s.subset_px)
        mark.first_reference = False
        mark.gradient = np.zeros(4)
        mark.set_reference(image, positions)


def warm_up_kernels() -> None:
    """Compile (or load from numba's cache) the kernels a tracker runs, on a small synthetic
    image: a few hundred ms the first time in a process, nothing after. Done before a camera
    is armed, it keeps that time out of a test, whose camera would otherwise stream into its
    buffers while the first frames wait for the kernels."""
    from appliance.dic import synthetic

    pattern = synthetic.dense_speckle(96, 96, seed=1, radius=2.0)
    reference = synthetic.render(pattern, 96, 96)
    points = np.array([[48.0, 40.0], [48.0, 56.0]])
    tracker = MarkTracker(reference, points, [(0,), (1,)], TrackerSettings(subset_px=21))
    moved = synthetic.render(pattern, 96, 96, synthetic.AffineMapping.translation(0.0, 0.5))
    tracker.track(moved, 0.1)
