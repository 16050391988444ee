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

Calibration targets (`appliance.optics.calibration_target.CalibrationTarget`: ChArUco,
chessboard, circle grid) are drawn as textures with a white quiet zone of one square around
them (`target_texture`), rendered in 8 bits with grey levels and Gaussian noise
(`render_target`), and posed for a calibration by `calibration_poses`: views that tilt the
board by 30..45 degrees about a random in-plane axis and move it over the field. Their truth is
geometric: `target_pixels` projects the target's corners through the true camera and pose.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt
from scipy import ndimage

from appliance.optics.calibration_target import CIRCLE_DIAMETER_FRACTION, CalibrationTarget
from appliance.optics.camera_model import CameraModel, PlanePose, PlaneProjection

FloatArray = npt.NDArray[np.float64]

DEFAULT_BLUR_PX = 1.0
MAX_TEXEL_MM = 0.05
"""Coarsest texel of a rendered calibration target, mm."""
TEXELS_PER_PX = 3.0
"""Texels to a pixel of the target's plane at the image centre (the finest a target gets)."""


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


@dataclass(frozen=True)
class TargetLook:
    """How a target image looks: grey levels (8-bit counts) and noise.

    Attributes:
        white, black: grey of the target's white and black, counts.
        background: grey of what lies around the target, counts.
        noise_grey: standard deviation of the Gaussian sensor noise, counts.
        blur_px: anti-aliasing and lens blur, px (see `render_plane`).
    """

    white: float = 200.0
    black: float = 30.0
    background: float = 90.0
    noise_grey: float = 1.0
    blur_px: float = DEFAULT_BLUR_PX


def target_texture(
    target: CalibrationTarget, texel_mm: float = 0.05
) -> tuple[FloatArray, float, tuple[float, float]]:
    """The target drawn as a texture (1 = white, 0 = black) with a white quiet zone of one
    square around it.

    Args:
        target: the target.
        texel_mm: wanted texel size, mm; rounded so that a square is a whole number of texels.

    Returns:
        (texture, texel_mm, origin_mm) as `render_plane` takes them.
    """
    texels_per_square = max(8, round(target.square_mm / texel_mm))
    return _texture(target, texels_per_square)


@functools.lru_cache(maxsize=4)
def _texture(
    target: CalibrationTarget, texels_per_square: int
) -> tuple[FloatArray, float, tuple[float, float]]:
    texel = target.square_mm / texels_per_square
    n = texels_per_square
    columns, rows = target.columns, target.rows
    if target.kind == "charuco":
        drawn = target.charuco_board().generateImage((columns * n, rows * n), marginSize=0)
        pattern = np.asarray(drawn, np.float64) / 255.0
    elif target.kind == "chessboard":
        row, column = np.mgrid[0 : rows * n, 0 : columns * n] // n
        pattern = ((row + column) % 2).astype(np.float64)
    else:
        width, height = (columns + 1) * n, (rows + 1) * n
        y, x = (np.mgrid[0:height, 0:width] + 0.5) * texel
        pitch = target.square_mm
        dx = x - pitch * np.clip(np.rint(x / pitch), 1, columns)
        dy = y - pitch * np.clip(np.rint(y / pitch), 1, rows)
        radius = 0.5 * CIRCLE_DIAMETER_FRACTION * pitch
        pattern = np.clip(0.5 + (np.hypot(dx, dy) - radius) / texel, 0.0, 1.0)
    texture = np.pad(pattern, n, constant_values=1.0)
    texture.setflags(write=False)
    origin = (0.5 * texel - target.square_mm, 0.5 * texel - target.square_mm)
    return texture, texel, origin


def target_pixels(target: CalibrationTarget, pose: PlanePose, camera: CameraModel) -> FloatArray:
    """True pixel positions (n, 2) of every corner of the target (ids in order)."""
    return PlaneProjection(camera, pose).to_pixels(target.object_points_mm)


def render_target(
    target: CalibrationTarget,
    pose: PlanePose,
    camera: CameraModel,
    *,
    look: TargetLook | None = None,
    seed: int = 0,
    texel_mm: float | None = None,
) -> npt.NDArray[np.uint8]:
    """An 8-bit image of `target` lying in the plane `pose`, seen through `camera`.

    `texel_mm` (default: `TEXELS_PER_PX` texels to a pixel of the plane at the image centre,
    at most `MAX_TEXEL_MM`) is the texture's resolution; a texel near a pixel's size leaves the
    bilinear sampling of the blurred edges visible (a facing board's corners 0.016 px off at
    0.87 px a texel, 0.002 px at 0.35 px)."""
    look = look or TargetLook()
    if texel_mm is None:
        scale = _centre_scale_mm_per_px(camera, pose) or MAX_TEXEL_MM
        texel_mm = min(MAX_TEXEL_MM, scale / TEXELS_PER_PX)
    texture, texel, origin = target_texture(target, texel_mm)
    grey = look.black + (look.white - look.black) * texture
    image = render_plane(grey, texel, origin, pose, camera, look.background, blur_px=look.blur_px)
    image += np.random.default_rng(seed).normal(0.0, look.noise_grey, image.shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def calibration_poses(
    camera: CameraModel,
    target: CalibrationTarget,
    count: int,
    *,
    distance_mm: float,
    seed: int = 0,
    tilt_deg: tuple[float, float] = (30.0, 45.0),
) -> list[PlanePose]:
    """Poses of `target` for a calibration: the first faces the camera at the image centre
    (the specimen plane), the others tilt it by `tilt_deg` about a random in-plane axis and
    centre it in turn near the field's four corners and four edges (jittered), at
    `distance_mm` along the ray, moving it towards the centre until it is in view. A ChArUco
    board may overhang the image (at least half of its corners stay in, a square's width
    inside the edges), reaching the field's corners; other targets stay whole.

    Raises:
        ValueError: no pose could be found that keeps enough of the target in view (the target
            is too large for the field at that distance).
    """
    rng = np.random.default_rng(seed)
    scale = camera_scale_mm_per_px(camera, distance_mm)
    reach = 0.4 if target.kind == "charuco" else 0.9
    half_x = min(0.5, reach * 0.5 * target.size_mm[0] / scale / camera.width_px)
    half_y = min(0.5, reach * 0.5 * target.size_mm[1] / scale / camera.height_px)
    spots = [(x, y) for y in (half_y, 0.5, 1.0 - half_y) for x in (half_x, 0.5, 1.0 - half_x)]
    spots = spots[:4] + spots[5:]
    poses = [_pose_at(camera, target, distance_mm, (0.5, 0.5), 0.0, 0.0, 0.0)]
    tries = 0
    while len(poses) < count:
        tries += 1
        if tries > 400:
            raise ValueError(
                f"{target.describe()}: no tilted pose keeps it in view at {distance_mm:g} mm"
            )
        spot = spots[(len(poses) - 1) % len(spots)]
        shrink = max(0.0, 1.0 - 0.01 * tries)
        jitter = rng.uniform(-0.03, 0.03, 2)
        where = (
            0.5 + shrink * (spot[0] - 0.5) + jitter[0],
            0.5 + shrink * (spot[1] - 0.5) + jitter[1],
        )
        tilt = math.radians(rng.uniform(*tilt_deg))
        axis = rng.uniform(0.0, 2.0 * math.pi)
        spin = math.radians(rng.uniform(-10.0, 10.0))
        pose = _pose_at(camera, target, distance_mm, where, tilt, axis, spin)
        if _in_view(camera, target, pose):
            poses.append(pose)
            tries = 0
    return poses


def camera_scale_mm_per_px(camera: CameraModel, distance_mm: float) -> float:
    """Scale at the image centre of a plane facing the camera at `distance_mm`, mm/px."""
    pose = PlanePose.facing(distance_mm)
    return PlaneProjection(camera, pose).scale_mm_per_px((camera.cx_px, camera.cy_px))


def _pose_at(
    camera: CameraModel,
    target: CalibrationTarget,
    distance_mm: float,
    where: tuple[float, float],
    tilt_rad: float,
    axis_rad: float,
    spin_rad: float,
) -> PlanePose:
    tilt = tilt_rad * np.array([math.cos(axis_rad), math.sin(axis_rad), 0.0])
    rotation = cv2.Rodrigues(tilt)[0] @ cv2.Rodrigues(np.array([0.0, 0.0, spin_rad]))[0]
    pixel = [[where[0] * (camera.width_px - 1), where[1] * (camera.height_px - 1)]]
    a, b = camera.normalised(pixel)[0]
    aim = np.array([a, b, distance_mm]) if camera.telecentric else distance_mm * np.array([a, b, 1])
    centre = np.array([0.5 * target.size_mm[0], 0.5 * target.size_mm[1], 0.0])
    translation = aim - rotation @ centre
    return PlanePose.from_arrays(cv2.Rodrigues(rotation)[0], translation)


def _in_view(camera: CameraModel, target: CalibrationTarget, pose: PlanePose) -> bool:
    try:
        pixels = target_pixels(target, pose, camera)
        margin = target.square_mm / PlaneProjection(camera, pose).scale_mm_per_px(
            (camera.cx_px, camera.cy_px)
        )
    except ValueError:
        return False
    inside = (
        (pixels[:, 0] >= margin)
        & (pixels[:, 0] <= camera.width_px - 1 - margin)
        & (pixels[:, 1] >= margin)
        & (pixels[:, 1] <= camera.height_px - 1 - margin)
    )
    if target.kind == "charuco":
        return bool(inside.mean() >= 0.5)
    return bool(inside.all())
