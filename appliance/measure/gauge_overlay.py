"""What a test would place on a frame, described for drawing over it.

`camera-check --save` draws it into a PNG (`appliance.cli.detection_overlay`) and the set-up
view streams it to the viewer (`appliance.live.viewer.preview`): one description, two
renderings.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class GaugeOverlay:
    """What a test would place on a frame, to draw over it (sensor pixels, (x, y)).

    Attributes:
        lines: the placement in words: the specimen found, where the gauge goes and the
            length it achieves, or why it is refused.
        outline_px: the specimen's outline, (N, 2); None when nothing was detected.
        axis_px: the axis over the parallel length, from end to end, (2, 2).
        end_ticks_px: a tick across the axis at each end of the parallel length, (2, 2, 2).
        ends_in_view: whether each end was seen.
        points_px: the points a test would track, (M, 2); None without a gauge.
        marks_px: the marks' centres, (K, 2).
        refused: no gauge can be placed on the frame (`lines` say why).
        centre_px: the gauge's centre; None when no centre was found.
    """

    lines: tuple[str, ...]
    outline_px: np.ndarray | None = None
    axis_px: np.ndarray | None = None
    end_ticks_px: np.ndarray | None = None
    ends_in_view: tuple[bool, bool] = (True, True)
    points_px: np.ndarray | None = None
    marks_px: np.ndarray | None = None
    refused: bool = False
    centre_px: tuple[float, float] | None = None
