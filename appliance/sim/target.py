"""Planar textures seen through a camera model: calibration targets and any other flat object.

`render_plane` is the one renderer: a texture (a float image with a known texel size in mm
and the plane point of its first texel) lying in a plane with a `PlanePose`, seen through a
`CameraModel` (pinhole or telecentric, with its lens distortion). Every pixel centre's ray is
found exactly (`CameraModel.normalised`, the lens's distortion removed by Newton's method),
intersected with the plane, and the texture is sampled there.

Anti-aliasing. Before sampling, the texture is low-pass filtered with a Gaussian whose
standard deviation is `blur_px` pixels' worth of plane (the scale at the image centre); the
filter stands for the lens's point spread and the pixel's area, and removes the frequencies a
pixel grid cannot carry. A symmetric filter does not move a straight edge, a chessboard's
saddle point or a circle's centre, so corner truth stays where the geometry puts it.
`supersample` n > 1 averages n x n sample positions inside each pixel (a box filter on top).

Truth for targets is geometric: `PlaneProjection(camera, pose).to_pixels(points_mm)` of the
target's corners (`CalibrationTarget.object_points_mm`).
"""

from __future__ import annotations

import functools
import math

import numpy as np
import numpy.typing as npt
from scipy import ndimage

from appliance.optics.camera_model import CameraModel, PlanePose, PlaneProjection

FloatArray = npt.NDArray[np.float64]

DEFAULT_BLUR_PX = 0.5


def render_plane(
    texture: npt.ArrayLike,
    texel_mm: float,
    origin_mm: tuple[float, float],
    pose: PlanePose,
    camera: CameraModel,
    background: float = 0.0,
    *,
    blur_px: float = DEFAULT_BLUR_PX,
    supersample: int = 1,
) -> FloatArray:
    """What `camera` sees of a flat `texture` lying in the plane `pose`.

    Args:
        texture: 2-D float image; texel (row i, column j) has its centre at the plane point
            ``(origin_mm[0] + j * texel_mm, origin_mm[1] + i * texel_mm)`` (X along columns,
            Y along rows).
        texel_mm: texel size on the plane, mm.
        origin_mm: plane point (X, Y), mm, of the centre of texel (0, 0).
        pose: the plane's pose in the camera frame.
        camera: intrinsics and lens distortion (pinhole or telecentric).
        background: value of pixels whose ray misses the texture or the plane.
        blur_px: Gaussian anti-aliasing filter (lens and pixel), standard deviation in pixels
            at the image centre; 0 = none.
        supersample: n x n sample positions per pixel, averaged.

    Returns:
        (height_px, width_px) float64 image in the texture's units.

    Raises:
        ValueError: a texel size that is not > 0, a texture that is not 2-D, or
            `supersample` < 1.
    """
    image = np.asarray(texture, np.float64)
    if image.ndim != 2 or image.size == 0:
        raise ValueError(f"texture must be a non-empty 2-D image, got shape {image.shape}")
    if not (math.isfinite(texel_mm) and texel_mm > 0):
        raise ValueError(f"texel_mm must be > 0, got {texel_mm}")
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    sigma_texels = blur_px * _centre_scale_mm_per_px(camera, pose) / texel_mm
    pad = int(math.ceil(4.0 * sigma_texels)) + 2
    padded = np.pad(image, pad, constant_values=background)
    if sigma_texels > 0:
        padded = ndimage.gaussian_filter(padded, sigma_texels, mode="constant", cval=background)
    rotation, translation = pose.rotation, pose.translation
    normal = rotation[:, 2]
    total = np.zeros(camera.height_px * camera.width_px)
    for rays in _sample_rays(camera, supersample):
        plane_mm, hits = _intersect(rays, rotation, translation, normal, camera.telecentric)
        columns = (plane_mm[:, 0] - origin_mm[0]) / texel_mm + pad
        rows = (plane_mm[:, 1] - origin_mm[1]) / texel_mm + pad
        columns[~hits] = -1e9
        rows[~hits] = -1e9
        total += ndimage.map_coordinates(
            padded, [rows, columns], order=1, mode="constant", cval=background, prefilter=False
        )
    return (total / supersample**2).reshape(camera.height_px, camera.width_px)


def _centre_scale_mm_per_px(camera: CameraModel, pose: PlanePose) -> float:
    try:
        return PlaneProjection(camera, pose).scale_mm_per_px((camera.cx_px, camera.cy_px))
    except ValueError:
        return 0.0


@functools.lru_cache(maxsize=2)
def _sample_rays(camera: CameraModel, supersample: int) -> tuple[FloatArray, ...]:
    """Undistorted normalised coordinates (H*W, 2) of every pixel's sample positions, one
    array per sub-pixel offset (the lens inversion is the costly part; views share it)."""
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    rows, columns = np.mgrid[0 : camera.height_px, 0 : camera.width_px]
    centres = np.column_stack([columns.ravel(), rows.ravel()]).astype(np.float64)
    rays = []
    for dy in offsets:
        for dx in offsets:
            normalised = camera.normalised(centres + (dx, dy))
            normalised.setflags(write=False)
            rays.append(normalised)
    return tuple(rays)


def _intersect(
    rays: FloatArray,
    rotation: FloatArray,
    translation: FloatArray,
    normal: FloatArray,
    telecentric: bool,
) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
    """Plane points (n, 2) mm where the rays meet the plane, and which rays meet it in front
    of the camera."""
    a, b = rays[:, 0], rays[:, 1]
    offset = float(normal @ translation)
    with np.errstate(divide="ignore", invalid="ignore"):
        if telecentric:
            z = (offset - normal[0] * a - normal[1] * b) / normal[2]
            points = np.column_stack([a, b, z])
            hits = np.isfinite(z)
        else:
            along = normal[0] * a + normal[1] * b + normal[2]
            distance = offset / along
            points = np.column_stack([a, b, np.ones_like(a)]) * distance[:, None]
            hits = np.isfinite(distance) & (distance > 0)
    points[~hits] = 0.0
    plane = (points - translation) @ rotation[:, :2]
    return plane, hits
