"""Frames dropped during a test are said out loud, not only counted.

A camera frame the loop has no room for (the tracking fell behind), or one missing from the
camera's frame counter, is a gap in the strain series the machine's controller reads. Each
sample carries the count so far (`StrainSample.frames_dropped`), and the strain file, the
recording, the Modbus registers (`frames_dropped`, status bit 8) and the viewer show it;
`DropWarning` adds a warning, at most once per `interval_s` of test time, with how many frames
were dropped since the last warning and the rate measured against the rate planned.
"""

from __future__ import annotations

from collections.abc import Callable

from appliance.measure.frame_measurer import StrainSample


class DropWarning:
    """A sink that warns when frames were dropped.

    Args:
        planned_rate_hz: the frame rate the test was planned for.
        warn: called with one line (on the loop's publishing thread).
        interval_s: the shortest test time between two warnings, s.
    """

    def __init__(
        self, planned_rate_hz: float, warn: Callable[[str], None], *, interval_s: float = 1.0
    ) -> None:
        self.planned_rate_hz = planned_rate_hz
        self.warn = warn
        self.interval_s = interval_s
        self.warnings = 0
        self._window: tuple[float, int, int] | None = None

    def __call__(self, sample: StrainSample) -> None:
        """Look at the next sample; warn when its window of `interval_s` dropped frames."""
        if self._window is None:
            self._window = (sample.time_s, sample.index, sample.frames_dropped)
            return
        start_s, start_index, start_dropped = self._window
        span_s = sample.time_s - start_s
        if span_s < self.interval_s:
            return
        dropped = sample.frames_dropped - start_dropped
        if dropped > 0:
            measured_hz = (sample.index - start_index) / span_s
            self.warn(
                f"{dropped} camera frames dropped in {span_s:.1f} s of the test: measuring "
                f"{measured_hz:.1f} of {self.planned_rate_hz:.1f} frames/s planned "
                f"({sample.frames_dropped} dropped in all)"
            )
            self.warnings += 1
        self._window = (sample.time_s, sample.index, sample.frames_dropped)
