"""What a viewer draws over a recording's images: the tracked points and where the windows lie.

The recording (`appliance.recording.format`) keeps every mark's window each frame and whole
frames at a lower rate. For Foxglove (and any reader of its schemas) the writer adds, in
protobuf Foxglove schemas, with the same log time and sequence as the images they belong to:

* `/annotations/full` (`foxglove.ImageAnnotations`), with every `/camera/full` image: every
  point as a circle coloured by its status (green tracked, amber reacquired, red lost, its
  position then estimated), labelled with its number, and each window's outline.
* `/annotations/window/<k>` (`foxglove.ImageAnnotations`), with every `/camera/window/<k>`
  image: the points of mark k in that window's pixels.
* `/camera/transforms` (`foxglove.FrameTransforms`), with every sample: where each window
  sits in the frame. The full frames have `frame_id` `camera`, the windows of mark k
  `camera/window/<k>`; the transform from `camera` to `camera/window/<k>` is a translation by
  the window's first pixel (x, y, 0), in pixels of the frame (the image plane's axes: x to the
  right, y down), without rotation. The same place is in `/tracking/points` (`windows`).

Annotation coordinates follow Foxglove's convention: the top-left corner of the top-left
pixel is (0, 0), so a point at pixel centre (x, y) of the recording's convention (pixel
centres at integers) is drawn at (x + 0.5, y + 0.5).

These channels are for viewing only: replay measures from the images and `/tracking/points`,
never from them, and a recording without them (an older one) replays the same.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from foxglove_schemas_protobuf.CircleAnnotation_pb2 import CircleAnnotation
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.KeyValuePair_pb2 import KeyValuePair
from foxglove_schemas_protobuf.Point2_pb2 import Point2
from foxglove_schemas_protobuf.PointsAnnotation_pb2 import PointsAnnotation
from foxglove_schemas_protobuf.TextAnnotation_pb2 import TextAnnotation

from appliance.measure.frame_windows import ImageWindow
from appliance.measure.tracking import TrackStatus

TOPIC_FULL_ANNOTATIONS = "/annotations/full"
TOPIC_WINDOW_ANNOTATIONS = "/annotations/window/{mark}"
TOPIC_TRANSFORMS = "/camera/transforms"

FULL_FRAME_ID = "camera"
WINDOW_FRAME_ID = "camera/window/{mark}"

POINT_DIAMETER_PX = 12.0
LINE_THICKNESS_PX = 2.0
LABEL_SIZE_PX = 14.0

STATUS_COLOURS = {
    TrackStatus.TRACKED: (0.1, 0.85, 0.2),
    TrackStatus.REACQUIRED: (1.0, 0.7, 0.0),
    TrackStatus.LOST: (1.0, 0.15, 0.15),
}
"""Point status -> (red, green, blue) of its circle, 0 to 1."""

_WINDOW_COLOUR = Color(r=0.2, g=0.6, b=1.0, a=1.0)
_LABEL_COLOUR = Color(r=1.0, g=1.0, b=1.0, a=1.0)
_LABEL_BACKGROUND = Color(r=0.0, g=0.0, b=0.0, a=0.6)


def window_frame_id(mark: int) -> str:
    """The `frame_id` of mark `mark`'s window images."""
    return WINDOW_FRAME_ID.format(mark=mark)


def _colour(status: int) -> Color:
    red, green, blue = STATUS_COLOURS[TrackStatus(int(status))]
    return Color(r=red, g=green, b=blue, a=1.0)


def _add_points(
    annotations: ImageAnnotations,
    positions: np.ndarray,
    status: np.ndarray,
    numbers: Sequence[int],
    origin: tuple[int, int],
) -> None:
    x0, y0 = origin
    for number in numbers:
        x, y = (float(c) for c in positions[number])
        if not (np.isfinite(x) and np.isfinite(y)):
            continue
        centre = Point2(x=x - x0 + 0.5, y=y - y0 + 0.5)
        annotations.circles.append(
            CircleAnnotation(
                position=centre,
                diameter=POINT_DIAMETER_PX,
                thickness=LINE_THICKNESS_PX,
                outline_color=_colour(status[number]),
            )
        )
        annotations.texts.append(
            TextAnnotation(
                position=Point2(x=centre.x + POINT_DIAMETER_PX / 2, y=centre.y),
                text=str(number),
                font_size=LABEL_SIZE_PX,
                text_color=_LABEL_COLOUR,
                background_color=_LABEL_BACKGROUND,
            )
        )


def _annotations(time_ns: int, index: int | None) -> ImageAnnotations:
    sample = "reference" if index is None else str(index)
    annotations = ImageAnnotations(metadata=[KeyValuePair(key="sample", value=sample)])
    annotations.timestamp.FromNanoseconds(int(time_ns))
    return annotations


def full_frame_annotations(
    time_ns: int,
    index: int | None,
    positions: np.ndarray,
    status: np.ndarray,
    windows: Sequence[ImageWindow] = (),
) -> bytes:
    """A serialised `foxglove.ImageAnnotations` for a full frame: every point and the
    outline of every window.

    Args:
        time_ns: the frame's acquisition time, UNIX ns (its image's timestamp).
        index: the sample index (None for the reference frame).
        positions: (n, 2) point positions (x, y) in the frame, px (pixel centres at integers).
        status: (n,) `TrackStatus` of each point.
        windows: the windows cut from this frame, one per mark.
    """
    annotations = _annotations(time_ns, index)
    _add_points(annotations, positions, status, range(len(positions)), (0, 0))
    for window in windows:
        height, width = window.pixels.shape
        x, y = float(window.x), float(window.y)
        corners = [(x, y), (x + width, y), (x + width, y + height), (x, y + height)]
        annotations.points.append(
            PointsAnnotation(
                type=PointsAnnotation.Type.LINE_LOOP,
                points=[Point2(x=cx, y=cy) for cx, cy in corners],
                outline_color=_WINDOW_COLOUR,
                thickness=LINE_THICKNESS_PX,
            )
        )
    return annotations.SerializeToString()


def window_annotations(
    time_ns: int,
    index: int,
    window: ImageWindow,
    positions: np.ndarray,
    status: np.ndarray,
    mark_points: Sequence[int],
) -> bytes:
    """A serialised `foxglove.ImageAnnotations` for one mark's window: the mark's points in
    the window's own pixels.

    Args:
        time_ns: the frame's acquisition time, UNIX ns (the window image's timestamp).
        index: the sample index.
        window: the window; its (x, y) is subtracted from the positions.
        positions: (n, 2) positions of every point in the frame, px.
        status: (n,) `TrackStatus` of every point.
        mark_points: the numbers of the mark's points.
    """
    annotations = _annotations(time_ns, index)
    _add_points(annotations, positions, status, mark_points, (window.x, window.y))
    return annotations.SerializeToString()


def window_transforms(time_ns: int, windows: Sequence[ImageWindow]) -> bytes:
    """A serialised `foxglove.FrameTransforms`: from the full frame (`camera`) to each
    window's frame (`camera/window/<k>`), a translation by its first pixel, in pixels."""
    message = FrameTransforms()
    for mark, window in enumerate(windows):
        transform = FrameTransform(
            parent_frame_id=FULL_FRAME_ID, child_frame_id=window_frame_id(mark)
        )
        transform.timestamp.FromNanoseconds(int(time_ns))
        transform.translation.x = float(window.x)
        transform.translation.y = float(window.y)
        transform.translation.z = 0.0
        transform.rotation.w = 1.0
        message.transforms.append(transform)
    return message.SerializeToString()
