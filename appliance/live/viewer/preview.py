"""The set-up view in a Rerun viewer: the live frame, what a test would place on it, and the
figures an installer aims, focuses and lights the camera by (`extensometer preview`).

Entity tree and timelines
-------------------------
    camera/image                the frame, at full resolution (overlays in sensor pixels)
    camera/specimen/outline     LineStrips2D: the detected specimen's outline (green)
    camera/specimen/axis        LineStrips2D: its axis over the parallel length (blue)
    camera/specimen/ends        LineStrips2D: ticks across the axis at the parallel length's
                                ends (yellow; labelled "end not seen" when not seen)
    camera/gauge/points         Points2D: the points a test would track (red)
    camera/gauge/marks          Points2D: the marks' centres (red rings, labelled)
    camera/gauge/subsets        Boxes2D: the subset around each point (`[tracking] subset_px`)
    quality/focus_gradient      Scalars: the sharpest tiles' weakest-direction gradient,
                                8-bit grey levels per px (the focus: turn the ring to its peak)
    quality/mean_grey           Scalars: mean grey level, 8-bit scale
    quality/saturated_fraction  Scalars: fraction of the pixels at full scale
    quality/dark_fraction       Scalars: fraction of the pixels at 0
    quality/mean_intensity_gradient   Scalars: MIG in the gauge's subsets, grey levels per px
    quality/sssig               Scalars: the smallest subset's SSSIG, grey levels squared
    quality/speckle_size_px     Scalars: speckle size in the subsets, px
    quality/frame_rate_hz       Scalars: frames per second by the device clock
    status/placement            TextDocument: the placement (or why none), the figures
    status/log                  TextLog: start, each new placement or refusal, the end

Timelines: `frame` (sequence: the preview's frame count from 0) and `preview_time` (duration
since the first frame, host clock). The image and the figures are logged with every frame;
the placement when a new one is found (a detection takes longer than a frame), and it stays
on the image until the next. Overlays are cleared when a frame is refused a placement.

The sinks are `[rerun]`'s, as for a test: `serve` opens a gRPC server (`RerunService`) that
the preview's recording is a client of, `connect` pushes to a viewer, `save` writes an .rrd
(`{test}` becomes the recording id). The recording's application id is "extensometer", its
recording id "preview-<UTC time>".
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from appliance.config import RerunConfig
from appliance.errors import InputError
from appliance.live.viewer.layout import APPLICATION_ID, EVENTS, FRAME, IMAGE
from appliance.live.viewer.output import has_sinks
from appliance.live.viewer.server import RerunService, one_line
from appliance.measure.gauge_overlay import GaugeOverlay
from appliance.measure.speckle_quality import FrameQuality

PREVIEW_TIME = "preview_time"

OUTLINE = "camera/specimen/outline"
AXIS = "camera/specimen/axis"
ENDS = "camera/specimen/ends"
SPECIMEN = "camera/specimen"
GAUGE = "camera/gauge"
GAUGE_POINTS = "camera/gauge/points"
GAUGE_MARKS = "camera/gauge/marks"
SUBSETS = "camera/gauge/subsets"
PLACEMENT = "status/placement"

QUALITY_SERIES = {
    "focus_gradient": "focus (grey levels/px)",
    "mean_grey": "mean grey",
    "saturated_fraction": "saturated fraction",
    "dark_fraction": "dark fraction",
    "mean_intensity_gradient": "MIG in subsets (grey levels/px)",
    "sssig": "SSSIG, smallest subset (grey levels^2)",
    "speckle_size_px": "speckle size (px)",
    "frame_rate_hz": "frame rate (Hz)",
}
"""The figures logged with every frame, `quality/<name>`, with their series names."""

OUTLINE_COLOUR = (0, 200, 0)
AXIS_COLOUR = (0, 120, 255)
ENDS_COLOUR = (255, 220, 0)
GAUGE_COLOUR = (255, 0, 0)


class PreviewViewer:
    """Streams the set-up view to the sinks of `[rerun]` (see the module docstring).

        viewer = PreviewViewer(config.rerun, "preview-20260101T120000Z")
        viewer.show_frame(n, elapsed_s, image, figures)   # every frame
        viewer.show_placement(placement, subset_px)       # when a new one is found
        viewer.close("preview ended: ...")

    Args:
        config: `[rerun]`: serve, connect and save (the image rate and scale are a test's;
            the preview sends every frame it shows at full resolution).
        recording_id: the preview's recording id.
        application_id: the Rerun application id.

    Raises:
        InputError: no sink, a malformed `connect` URL, a `save` directory that does not
            exist or a file that cannot be created, a `serve` address that cannot be listened
            on (one line naming the key).
    """

    def __init__(
        self, config: RerunConfig, recording_id: str, *, application_id: str = APPLICATION_ID
    ) -> None:
        if not has_sinks(config):
            raise InputError(
                "no viewer: give --rerun-serve HOST:PORT, --rerun-connect URL or --rerun-save "
                "FILE.rrd ([rerun] serve, connect or save)"
            )
        if config.connect and not (
            config.connect.startswith(("rerun://", "rerun+http://", "rerun+https://"))
            and config.connect.endswith("/proxy")
        ):
            raise InputError(
                f"[rerun] connect: must be rerun+http://HOST:PORT/proxy, got {config.connect!r}"
            )
        save = Path(config.save.replace("{test}", recording_id)) if config.save else None
        if save is not None and not save.parent.is_dir():
            raise InputError(f"[rerun] save: {save}: no such directory {str(save.parent)!r}")
        self.recording_id = recording_id
        self.frames_shown = 0
        self.placements_shown = 0
        self._service = (
            RerunService(
                config.serve,
                application_id=application_id,
                server_memory_limit=f"{config.history_mb:g}MB",
            )
            if config.serve
            else None
        )
        sinks: list = []
        if self._service is not None:
            sinks.append(rr.GrpcSink(self._service.local_url))
        if config.connect:
            sinks.append(rr.GrpcSink(config.connect))
        if save is not None:
            sinks.append(rr.FileSink(save))
        self._stream = rr.RecordingStream(application_id, recording_id=recording_id)
        try:
            self._stream.set_sinks(*sinks, default_blueprint=preview_blueprint())
        except RuntimeError as exc:
            self._stream.disconnect()
            if self._service is not None:
                self._service.close()
            raise InputError(f"[rerun] save: {save}: {one_line(exc)}") from None
        self._stream.send_recording_name(recording_id)
        self._log_styles()
        self._stream.log(
            EVENTS,
            rr.TextLog(f"{recording_id}: set-up view started", level=rr.TextLogLevel.INFO),
        )

    @property
    def url(self) -> str | None:
        """What a remote viewer opens (`[rerun] serve`), or None."""
        return self._service.url if self._service is not None else None

    def show_frame(
        self, frame: int, elapsed_s: float, image: np.ndarray, figures: Mapping[str, float]
    ) -> None:
        """Log a frame and its figures (`QUALITY_SERIES` names; NaN and absent ones are left
        out)."""
        self._set_time(frame, elapsed_s)
        self._stream.log(IMAGE, rr.Image(image))
        for name, value in figures.items():
            if name in QUALITY_SERIES and value is not None and math.isfinite(value):
                self._stream.log(f"quality/{name}", rr.Scalars(float(value)))
        self.frames_shown += 1

    def show_placement(self, placement: GaugeOverlay, subset_px: int) -> None:
        """Log a new placement over the frames from the last one shown (or why there is
        none: the overlays are cleared)."""
        stream = self._stream
        stream.log(
            PLACEMENT,
            rr.TextDocument(
                "\n".join(["## Placement", "", *(f"- {line}" for line in placement.lines)]),
                media_type=rr.MediaType.MARKDOWN,
            ),
        )
        level = rr.TextLogLevel.WARN if placement.refused else rr.TextLogLevel.INFO
        stream.log(EVENTS, rr.TextLog("; ".join(placement.lines), level=level))
        self.placements_shown += 1
        if placement.outline_px is None:
            stream.log(SPECIMEN, rr.Clear(recursive=True))
        else:
            stream.log(
                OUTLINE, rr.LineStrips2D([_closed(placement.outline_px)], colors=[OUTLINE_COLOUR])
            )
            stream.log(AXIS, rr.LineStrips2D([placement.axis_px], colors=[AXIS_COLOUR]))
            stream.log(
                ENDS,
                rr.LineStrips2D(
                    list(placement.end_ticks_px),
                    colors=[ENDS_COLOUR],
                    labels=["" if seen else "end not seen" for seen in placement.ends_in_view],
                ),
            )
        if placement.points_px is None or placement.marks_px is None:
            stream.log(GAUGE, rr.Clear(recursive=True))
            return
        points = np.asarray(placement.points_px, dtype=np.float64)
        stream.log(
            GAUGE_POINTS, rr.Points2D(points, colors=[GAUGE_COLOUR], radii=rr.Radius.ui_points(3))
        )
        stream.log(
            GAUGE_MARKS,
            rr.Points2D(
                placement.marks_px,
                colors=[GAUGE_COLOUR],
                radii=rr.Radius.ui_points(8),
                labels=[f"mark {n}" for n in range(1, len(placement.marks_px) + 1)],
            ),
        )
        stream.log(
            SUBSETS,
            rr.Boxes2D(
                centers=points,
                sizes=np.full_like(points, float(subset_px)),
                colors=[GAUGE_COLOUR],
                radii=rr.Radius.ui_points(0.5),
            ),
        )

    def note(self, text: str, *, warning: bool = False) -> None:
        """Add a line to `status/log`."""
        level = rr.TextLogLevel.WARN if warning else rr.TextLogLevel.INFO
        self._stream.log(EVENTS, rr.TextLog(text, level=level))

    def close(self, summary: str, timeout_s: float = 10.0) -> str | None:
        """Log `summary`, flush and close the recording and the server (the server stays up
        until its viewers hang up). Returns the problem met while flushing, one line, or None."""
        self._stream.log(EVENTS, rr.TextLog(summary, level=rr.TextLogLevel.INFO))
        problem = None
        try:
            self._stream.flush(timeout_sec=timeout_s)
        except RuntimeError as exc:
            problem = one_line(exc)
        self._stream.disconnect()
        if self._service is not None:
            self._service.close(timeout_s)
        return problem

    def _set_time(self, frame: int, elapsed_s: float) -> None:
        self._stream.set_time(FRAME, sequence=frame)
        self._stream.set_time(PREVIEW_TIME, duration=np.timedelta64(round(elapsed_s * 1e9), "ns"))

    def _log_styles(self) -> None:
        for name, label in QUALITY_SERIES.items():
            self._stream.log(f"quality/{name}", rr.SeriesLines(names=label), static=True)


def _closed(outline: np.ndarray) -> np.ndarray:
    outline = np.asarray(outline, dtype=np.float64).reshape(-1, 2)
    return np.vstack([outline, outline[:1]])


def preview_blueprint() -> rrb.Blueprint:
    """The set-up view's layout: the camera with overlays on the left; focus, exposure and
    speckle over time, the placement and the log on the right."""
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial2DView(name="camera", origin="/camera"),
            rrb.Vertical(
                rrb.TimeSeriesView(
                    name="focus and texture",
                    origin="/quality",
                    contents=["/quality/focus_gradient", "/quality/mean_intensity_gradient"],
                ),
                rrb.TimeSeriesView(
                    name="exposure",
                    origin="/quality",
                    contents=[
                        "/quality/saturated_fraction",
                        "/quality/dark_fraction",
                    ],
                ),
                rrb.TimeSeriesView(
                    name="speckle and rate",
                    origin="/quality",
                    contents=["/quality/speckle_size_px", "/quality/frame_rate_hz"],
                ),
                rrb.Tabs(
                    rrb.TextDocumentView(name="placement", origin=f"/{PLACEMENT}"),
                    rrb.TextLogView(name="log", origin=f"/{EVENTS}"),
                ),
                row_shares=[3, 2, 2, 3],
            ),
            column_shares=[3, 2],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline=PREVIEW_TIME),
    )


def figures_of(quality: FrameQuality, frame_rate_hz: float | None) -> dict[str, float]:
    """The `QUALITY_SERIES` figures of a frame's quality and the frame rate measured."""
    figures = {
        "focus_gradient": quality.focus_gradient,
        "mean_grey": quality.mean_grey,
        "saturated_fraction": quality.saturated_fraction,
        "dark_fraction": quality.dark_fraction,
        "frame_rate_hz": math.nan if frame_rate_hz is None else frame_rate_hz,
    }
    subsets = quality.subsets
    if subsets is not None:
        figures.update(
            mean_intensity_gradient=subsets.mean_intensity_gradient,
            sssig=subsets.sssig,
            speckle_size_px=subsets.speckle_size_px,
        )
    return figures
