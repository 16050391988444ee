"""What the viewer shows and where: the entity tree, the timelines and the layout.

Entity tree and timelines
-------------------------
    camera                  AnnotationContext: point classes tracked / reacquired / lost (static)
    camera/image            the frame, at `image_rate_hz`, scaled by `image_scale` (the
                            reference frame at frame -1); a static Transform3D scales it back to
                            sensor pixels, so every overlay is in sensor pixels
    camera/points           Points2D: tracked points, class id = `TrackStatus` (colour, label)
    camera/gauges           LineStrips2D: the axial (and transverse) gauge between mark
                            centroids, coloured red while the data is not valid
    strain/axial            Scalars: axial engineering strain
    strain/true             Scalars: axial true strain
    strain/transverse       Scalars: transverse engineering strain (with a transverse gauge)
    strain/width            Scalars: transverse engineering strain from the specimen's width
                            at its edges (with `[transverse] stations`)
    gauge/elongation_mm     Scalars: axial elongation, mm
    machine/force_n         Scalars (drawn as points): force, N
    machine/crosshead_mm    Scalars: crosshead position, mm
    status/points_lost      Scalars: points not measured in the frame
    status/state            TextDocument: run state, strain, data valid, points lost, viewer
                            counts (at most once per second of device time, and on changes)
    status/log              TextLog: start, data valid / not valid, points lost / found, frames
                            dropped, reference updates (debug), the exit status at the end
    status/result           AnyValues: exit status, reason, frame and viewer counts, and the
                            test's results as the Modbus result registers serve them (the
                            same names: `result_r_8_12`, `result_n`, ...; NaN not determined)
                            (static)
    facts/calibration       AnyValues: scale, gauge length, image size, points (static)
    facts/summary           TextDocument: the test's facts (static)

Timelines: `device_time` (timestamp: the device time of the exposure, mapped to UNIX time with
the run's epoch offset), `test_time` (duration since the reference frame, device clock),
`frame` (sequence: the sample index; the reference is -1) and `strain_ue` (sequence: the axial
engineering strain in microstrain, set when the strain is finite).

Force against strain. Rerun 0.41 has no XY plot (the abscissa of a time series view is the
timeline; rerun issue #8286 is open), and a curve in a 2D spatial view is drawn at aspect 1:1
(strains of 1e-3..6 against forces of 10..1e5 N) without axes. A strain timeline gives a real
plot with axes, zoom and hover: the force series on the `strain_ue` timeline *is* force
against strain, exact, one row per sample (no re-logging of a growing curve), and scrubbing
it shows the image and overlays at each strain. The viewer's x-axis follows the time panel's
timeline: the "force vs strain" view reads against strain once `strain_ue` is selected (and
against time otherwise). Force is drawn as points, so an unloading or the break, where strain
falls back, adds no false connecting lines.

The blueprint lays out the camera (image and overlays) on the left; strain against time,
force against strain and the status (state / events / facts as tabs) on the right; the time
panel starts on `test_time`. It is sent as the *default* blueprint, so a viewer whose user has
rearranged the layout keeps it from one test to the next.
"""

from __future__ import annotations

import rerun as rr
import rerun.blueprint as rrb

from appliance.measure.tracking import TrackStatus
from appliance.run.state import ExitStatus

APPLICATION_ID = "extensometer"

DEVICE_TIME = "device_time"
TEST_TIME = "test_time"
FRAME = "frame"
STRAIN_TIMELINE = "strain_ue"

CAMERA = "camera"
IMAGE = "camera/image"
POINTS = "camera/points"
GAUGES = "camera/gauges"
AXIAL_STRAIN = "strain/axial"
TRUE_STRAIN = "strain/true"
TRANSVERSE_STRAIN = "strain/transverse"
WIDTH_STRAIN = "strain/width"
ELONGATION = "gauge/elongation_mm"
FORCE = "machine/force_n"
CROSSHEAD = "machine/crosshead_mm"
POINTS_LOST = "status/points_lost"
STATE = "status/state"
EVENTS = "status/log"
RESULT = "status/result"
CALIBRATION = "facts/calibration"
FACTS = "facts/summary"

REFERENCE_FRAME = -1
"""`frame` of the reference image (sample indices start at 0)."""

STATUS_COLOURS = {
    TrackStatus.TRACKED: (40, 200, 60),
    TrackStatus.REACQUIRED: (250, 180, 0),
    TrackStatus.LOST: (230, 30, 30),
}
AXIAL_COLOUR = (0, 190, 255)
TRANSVERSE_COLOUR = (230, 80, 230)
INVALID_COLOUR = (230, 30, 30)
EXIT_LEVELS = {
    ExitStatus.COMPLETED: rr.TextLogLevel.INFO,
    ExitStatus.BREAK: rr.TextLogLevel.INFO,
    ExitStatus.STOPPED: rr.TextLogLevel.INFO,
    ExitStatus.ABORTED: rr.TextLogLevel.WARN,
    ExitStatus.FAULT: rr.TextLogLevel.ERROR,
}


def viewer_blueprint() -> rrb.Blueprint:
    """The viewer's layout: camera with overlays; strain, force vs strain and status; time panel."""
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial2DView(name="camera", origin=f"/{CAMERA}"),
            rrb.Vertical(
                rrb.TimeSeriesView(name="strain vs time", origin="/strain"),
                rrb.TimeSeriesView(
                    name=f"force vs strain (timeline {STRAIN_TIMELINE})",
                    origin="/machine",
                    contents=[f"/{FORCE}"],
                ),
                rrb.Tabs(
                    rrb.TextDocumentView(name="status", origin=f"/{STATE}"),
                    rrb.TextLogView(name="events", origin=f"/{EVENTS}"),
                    rrb.TextDocumentView(name="facts", origin=f"/{FACTS}"),
                ),
                row_shares=[3, 3, 2],
            ),
            column_shares=[2, 3],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline=TEST_TIME),
    )
