"""Where the gauge goes: on the detected specimen, or where the configuration says.

`GaugeCentre` is the centre and axis the marks are laid out about (by
`appliance.measure.gauges.place_marks`) and how they were found: `detected_gauge_centre` runs
the specimen detection (`appliance.measure.specimen_detection`) on the reference image and
centres the gauge on the parallel length, along its axis; a centre given in the configuration
is used as it is, along the configured axis. `marks_beyond_parallel_length` says why placed
marks do not fit the detected parallel length (the gauge is too long for the specimen), so the
test can be refused before it starts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from appliance.measure.specimen_detection import SpecimenDetection, detect_specimen

DETECTED = "detected"
CONFIGURED = "configured"
IMAGE_CENTRE = "image centre"


@dataclass(frozen=True)
class GaugeCentre:
    """The centre and axis of a gauge in the reference image, and how they were found.

    Attributes:
        centre_px: (x, y), px.
        axis_deg: the loading axis, degrees from +x towards +y (90 = vertical).
        placement: "detected" (on the specimen found in the image), "configured"
            (`[gauge] centre_x_px`, `centre_y_px`, `axis_deg`) or "image centre" (nothing
            stands out from the background: a specimen that fills the view, along
            `[gauge] axis_deg`).
        detection: the specimen found, when detected.
    """

    centre_px: tuple[float, float]
    axis_deg: float
    placement: str
    detection: SpecimenDetection | None = None

    def facts(self) -> dict[str, object]:
        """What a test records and summarises of its gauge's placement."""
        facts: dict[str, object] = {
            "gauge_placement": self.placement,
            "gauge_centre_px": [float(self.centre_px[0]), float(self.centre_px[1])],
            "gauge_axis_deg": float(self.axis_deg),
        }
        if self.detection is not None:
            facts["specimen_width_px"] = self.detection.width_px
            facts["specimen_parallel_length_px"] = self.detection.parallel_length_px
            facts["specimen_parallel_ends_in_view"] = list(self.detection.ends_in_view)
        return facts


def detected_gauge_centre(image: np.ndarray) -> GaugeCentre:
    """The gauge centred on the parallel length of the specimen found in `image`, along its
    axis.

    Raises:
        SpecimenNotFound: no single specimen could be measured (the message says what was
            seen).
    """
    detection = detect_specimen(image)
    return GaugeCentre(detection.centre_px, detection.axis_deg, DETECTED, detection)


def marks_beyond_parallel_length(points_px: np.ndarray, detection: SpecimenDetection) -> str | None:
    """Why marks at `points_px` (n, 2) do not all lie on the detected parallel length (along
    its axis), as one line; None when they do."""
    along = detection.along
    centre = np.asarray(detection.centre_px)
    ends = [float((np.asarray(end) - centre) @ along) for end in detection.parallel_ends_px]
    low, high = min(ends), max(ends)
    s = (np.asarray(points_px, np.float64) - centre) @ along
    if s.min() >= low and s.max() <= high:
        return None
    first, second = detection.parallel_ends_px
    return (
        f"the marks span {s.max() - s.min():.0f} px along the specimen, more than its parallel "
        f"length of {high - low:.0f} px (from ({first[0]:.0f}, {first[1]:.0f}) to "
        f"({second[0]:.0f}, {second[1]:.0f}) px): shorten the gauge"
    )
