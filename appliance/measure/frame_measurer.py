"""One frame to one strain sample: tracking, strain, validity and the end of a test.

`FrameMeasurer` is the whole measurement of a frame, the same code for the live loop
(`appliance.run.loop`) and for the replay of a recording (`appliance.recording.replay`), so a
replay on the recorded pixels reproduces the recorded strain exactly:

1. the marks are tracked at the frame's device time: speckle by
   `appliance.measure.tracking.MarkTracker`, painted dots by
   `appliance.measure.painted_marks_tracker.PaintedDotTracker` (the same interface);
2. their positions become strains (`appliance.measure.gauges.StrainGauges`); a zero request makes
   this frame's gauge lengths the new L0 first;
   with `widths`, the specimen's width at stations between the axial marks
   (`appliance.measure.edge_width.EdgeWidthGauge`) is measured in the same frame;
3. the sample is *valid* when every axial gauge mark had a measured point and the force has
   not fallen as after a break (a frame of a broken specimen is not a strain);
4. `ending` says whether the test is over: a break (a force drop; where the machine gives no
   force reading, inferred from a gauge mark lost for several frames), the strain limit, a
   time or frame limit. A lost mark is not a break where the force is read: those samples
   are not valid, and the test goes on.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from appliance.measure.edge_width import EdgeWidthGauge, WidthReading
from appliance.measure.frame_windows import ImageWindow, cut_windows
from appliance.measure.gauges import Calibration, StrainGauges, StrainGaugesLayout, StrainReading
from appliance.measure.painted_marks import DotSettings
from appliance.measure.painted_marks_tracker import PaintedDotTracker
from appliance.measure.tracking import MarkTracker, TrackerSettings, TrackStatus
from hal.camera.base import Frame
from hal.machine.base import MachineState


@dataclass(frozen=True)
class StrainSample:
    """Everything measured on one frame.

    Attributes:
        index: sample number in this run (0 = first frame after the reference).
        frame_id: the camera's frame counter.
        timestamp_ns: device time of the start of exposure, ns.
        time_s: seconds since the reference frame (device clock).
        exposure_us: exposure of the frame, us.
        reading: strains and elongation.
        positions: (n, 2) tracked positions, px.
        status: (n,) `appliance.measure.tracking.TrackStatus`.
        zncc: (n,) ZNCC of each point.
        gradients: (n, 4) displacement gradients (ux, uy, vx, vy) of each point relative to
            its mark's current reference (the first-order shape function).
        data_valid: every axial gauge mark had at least one measured point, and the force
            has not fallen as after a break (a frame of a broken specimen is not a strain).
        reference_updates: references replaced after this frame.
        machine: the controller's state read with the frame (None if unavailable).
        latency_s: wall time from frame delivery to this sample.
        windows: copies of the pixels of the frame the tracker read, one window per mark:
            enough to measure the frame again to the same numbers.
        zeroed: the strain was zeroed just before this frame (its gauge lengths became L0).
        frames_dropped: camera frames dropped since the test started, up to this sample (gaps
            in the camera's frame counter and frames the loop had no room for): a rise from
            one sample to the next is a gap in the strain series.
        image: the whole frame (shared, not a copy: read it, never write it).
        metadata: the frame's metadata (a simulator's ground truth, for instance).
        width: the specimen's width at the stations between the axial marks
            (`appliance.measure.edge_width`); None when the test measures no width.
    """

    index: int
    frame_id: int
    timestamp_ns: int
    time_s: float
    exposure_us: float
    reading: StrainReading
    positions: np.ndarray
    status: np.ndarray
    zncc: np.ndarray
    gradients: np.ndarray
    data_valid: bool
    reference_updates: int
    machine: MachineState | None
    latency_s: float
    windows: tuple[ImageWindow, ...] = ()
    zeroed: bool = False
    frames_dropped: int = 0
    image: np.ndarray | None = None
    metadata: Mapping[str, Any] = field(default_factory=dict)
    width: WidthReading | None = None

    @property
    def points_lost(self) -> int:
        """Points not measured in this frame."""
        return int(np.count_nonzero(self.status == TrackStatus.LOST))


@dataclass(frozen=True)
class StopCriteria:
    """When a run ends by itself.

    Attributes:
        until_strain: stop when the engineering strain reaches this; None = no limit.
        until_break: stop when a break is detected.
        max_time_s: stop after this much device time; None = no limit.
        max_frames: stop after this many samples; None = no limit.
    """

    until_strain: float | None = None
    until_break: bool = True
    max_time_s: float | None = None
    max_frames: int | None = None


@dataclass(frozen=True)
class Ending:
    """Why a test ends by itself.

    Attributes:
        broke: the specimen broke (a force drop, or, without force readings, inferred from a
            gauge mark lost for several frames); False: a limit of `StopCriteria` was reached.
        reason: one line.
    """

    broke: bool
    reason: str


@dataclass(frozen=True)
class BreakDetection:
    """How a break is recognised.

    A break is declared when the force has fallen below `force_drop_fraction` of its maximum
    (once the maximum exceeded `min_peak_force_n`). Only where no force is read (no machine,
    or a machine that reports none) is a break inferred instead from a gauge mark that had
    no measured point for `lost_mark_frames` consecutive frames after a valid sample and
    after the strain passed `min_strain` (the marks separating as the specimen snaps).
    """

    force_drop_fraction: float = 0.2
    min_peak_force_n: float = 1.0
    lost_mark_frames: int = 3
    min_strain: float = 0.001


class FrameMeasurer:
    """Measures the frames of one test in order, from the reference on.

    Args:
        tracker: the marks' tracker, prepared on the reference frame (a `MarkTracker` or a
            `PaintedDotTracker`).
        gauges: the strain gauges on the tracked points.
        reference_time_ns: device time of the reference frame, ns.
        break_detection: how a break is recognised.
        wall: wall clock, s, for the latency (injected for tests).
        widths: the specimen's width at stations between the axial marks, measured in every
            frame after the marks are tracked; None = no width.
    """

    def __init__(
        self,
        tracker: MarkTracker | PaintedDotTracker,
        gauges: StrainGauges,
        reference_time_ns: int,
        *,
        break_detection: BreakDetection | None = None,
        wall: Callable[[], float] = time.perf_counter,
        widths: EdgeWidthGauge | None = None,
    ) -> None:
        self.tracker = tracker
        self.gauges = gauges
        self.widths = widths
        self.reference_time_ns = reference_time_ns
        self.detection = break_detection or BreakDetection()
        self._wall = wall
        self._axial_marks = (list(gauges.axial.first), list(gauges.axial.second))
        self.samples = 0
        self.valid_samples = 0
        self.peak_force_n = 0.0
        self._force_read = False
        self._lost_run = 0
        self._force_broken = False
        self._zero_pending = False
        self._last: StrainSample | None = None

    def zero(self) -> None:
        """Zero the strain at the next frame in which every mark is measured: the gauge
        lengths measured in it become L0."""
        self._zero_pending = True

    def measure(
        self,
        frame: Frame,
        machine: MachineState | None,
        delivered_s: float | None = None,
        frames_dropped: int = 0,
    ) -> StrainSample:
        """Measure the next frame; `machine` is the controller's state read with it.

        Args:
            frame: the frame (its image is read where the marks are).
            machine: the controller's state, or None.
            delivered_s: wall time the frame was delivered (for the latency); None = now.
            frames_dropped: frames dropped in the test so far (the sample carries it).
        """
        delivered = self._wall() if delivered_s is None else delivered_s
        time_s = (frame.timestamp_ns - self.reference_time_ns) * 1e-9
        tracked = self.tracker.track(frame.image, time_s, frame.exposure_us * 1e-6)
        zeroed = self._zero_pending and tracked.marks_lost == 0
        if zeroed:
            self.gauges.rezero(tracked.positions)
            self._zero_pending = False
        reading = self.gauges.read(tracked.positions)
        width = None
        if self.widths is not None:
            first, second = (tracked.positions[mark].mean(axis=0) for mark in self._axial_marks)
            width = self.widths.read(frame.image, first, second)
            if zeroed:
                width = self.widths.rezero(width)
        measured = tracked.measured
        marks_seen = all(measured[mark].any() for mark in self._axial_marks)
        detection = self.detection
        if machine is not None and math.isfinite(machine.force_n):
            self._force_read = True
            self.peak_force_n = max(self.peak_force_n, machine.force_n)
        self._force_broken = (
            machine is not None
            and self.peak_force_n >= detection.min_peak_force_n
            and machine.force_n < detection.force_drop_fraction * self.peak_force_n
        )
        self._lost_run = 0 if marks_seen else self._lost_run + 1
        sample = StrainSample(
            index=self.samples,
            frame_id=frame.frame_id,
            timestamp_ns=frame.timestamp_ns,
            time_s=time_s,
            exposure_us=frame.exposure_us,
            reading=reading,
            positions=tracked.positions,
            status=tracked.status,
            zncc=tracked.zncc,
            gradients=tracked.gradients,
            data_valid=marks_seen and not self._force_broken,
            reference_updates=tracked.reference_updates,
            machine=machine,
            latency_s=self._wall() - delivered,
            windows=cut_windows(np.asarray(frame.image), tracked.read_regions),
            zeroed=zeroed,
            frames_dropped=frames_dropped,
            image=frame.image,
            metadata=frame.metadata,
            width=width,
        )
        self.samples += 1
        self.valid_samples += sample.data_valid
        self._last = sample
        return sample

    def ending(self, criteria: StopCriteria) -> Ending | None:
        """Why the last measured sample ends the test, or None when it does not."""
        sample = self._last
        if sample is None:
            return None
        detection = self.detection
        strain = sample.reading.engineering_strain
        if criteria.until_break and self._force_broken:
            force = sample.machine.force_n if sample.machine is not None else math.nan
            return Ending(
                True, f"break: force fell to {force:.1f} N from a peak of {self.peak_force_n:.1f} N"
            )
        if (
            criteria.until_break
            and not self._force_read
            and self.valid_samples > 0
            and self._lost_run >= detection.lost_mark_frames
            and (math.isnan(strain) or strain >= detection.min_strain)
        ):
            return Ending(
                True,
                f"break inferred from a lost mark (no force reading): a gauge mark lost for "
                f"{self._lost_run} frames",
            )
        if criteria.until_strain is not None and strain >= criteria.until_strain:
            return Ending(False, f"strain {strain:.6g} reached {criteria.until_strain:g}")
        if criteria.max_time_s is not None and sample.time_s >= criteria.max_time_s:
            return Ending(False, f"time limit {criteria.max_time_s:g} s reached")
        if criteria.max_frames is not None and self.samples >= criteria.max_frames:
            return Ending(False, f"frame limit {criteria.max_frames} reached")
        return None


def tracker_and_gauges(
    settings: TrackerSettings,
    reference: np.ndarray,
    points: np.ndarray,
    layout: StrainGaugesLayout,
    calibration: Calibration,
    marks: str = "speckle",
) -> tuple[MarkTracker | PaintedDotTracker, StrainGauges]:
    """The tracker and the gauges of a test, on its reference image and placed points: what a
    `FrameMeasurer` measures with, live and in a replay. `marks` is `[gauge] marks`:
    "speckle" (correlation), "dots" or "lines" (painted marks, one point each)."""
    image = np.asarray(reference, dtype=np.float64)
    tracker: MarkTracker | PaintedDotTracker
    if marks in ("dots", "lines"):
        tracker = PaintedDotTracker(image, points, layout.marks, settings, DotSettings(kind=marks))
    else:
        tracker = MarkTracker(image, points, layout.marks, settings)
    gauges = StrainGauges(layout.axial, points, calibration, layout.transverse)
    return tracker, gauges
