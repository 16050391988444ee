"""Live and remote monitoring of a test in a Rerun viewer (rerun-sdk 0.41).

`RerunViewer` (`output`) is the run output that streams test after test, each a recording
of its own, to the sinks `[rerun]` chooses; `RerunService` (`server`) is the gRPC server
remote viewers connect to, which outlives the tests; `stream` logs one test on a thread of its
own behind a bounded queue, so the viewer never slows the measurement; `layout` names the
entities and timelines and lays out the viewer; `preview` is the installer's set-up view
(`extensometer preview`: the live frame, its focus, exposure and speckle figures, and the
gauge a test would place). Warnings (a viewer that went away) go to the
`appliance.live.viewer` logger.
"""

from appliance.live.viewer.layout import (
    APPLICATION_ID,
    AXIAL_STRAIN,
    EVENTS,
    FORCE,
    IMAGE,
    POINTS,
    RESULT,
    STRAIN_TIMELINE,
    viewer_blueprint,
)
from appliance.live.viewer.output import RerunViewer, has_sinks
from appliance.live.viewer.server import RerunService, proxy_url

__all__ = [
    "APPLICATION_ID",
    "AXIAL_STRAIN",
    "EVENTS",
    "FORCE",
    "IMAGE",
    "POINTS",
    "RESULT",
    "STRAIN_TIMELINE",
    "RerunService",
    "RerunViewer",
    "has_sinks",
    "proxy_url",
    "viewer_blueprint",
]
