"""A still view of a specimen as an installer may have set it up: the cases specimen detection is
scored on.

`render_specimen_view` draws an undeformed `Specimen` (`appliance.sim.specimen`) at a given
scale, rotated about the optical axis, anywhere in the image, under one of three lightings, with
or without the grips' jaws clamping its tabs, and returns the image with its truth (the
specimen's centre, axis and parallel width in pixels), which only scores a detection.

Lightings (`LIGHTINGS`):

* "front-dark": a speckled specimen lit from the front on a dark backdrop (the simulated
  camera's usual view);
* "front-bright": a speckled specimen on a white card;
* "back-lit": the specimen's dark silhouette against a bright diffuser.

Geometry. A pixel centre (c, r) sees the material point (X, Y) = R(-angle) ((c, r) - centre)
* scale, mm: material Y along the loading axis, X across it, as in `appliance.sim.deformation`.
Each pixel is the specimen's grey level blended with what lies behind by the fraction of the
pixel the specimen covers across its edge (the signed distance to the outline in pixels, plus
one half, clipped to [0, 1]: exact for an edge along a pixel column and symmetric for every
edge, so the width and the centre are not biased). The speckle is a Gaussian-filtered random
field with spots of `speckle_radius_px`, fixed to the image (a still view has no motion to
follow). Camera noise: Gaussian, `noise_grey` rms.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from appliance.sim.specimen import Specimen

LIGHTINGS = ("front-dark", "front-bright", "back-lit")
"""The lightings `render_specimen_view` draws."""

_BACKDROP = {"front-dark": 20.0, "front-bright": 235.0, "back-lit": 225.0}
_SPECIMEN_MEAN = {"front-dark": 128.0, "front-bright": 110.0, "back-lit": 18.0}
_SPECIMEN_SPREAD = {"front-dark": 70.0, "front-bright": 60.0, "back-lit": 3.0}
_GRIP = {"front-dark": 95.0, "front-bright": 70.0, "back-lit": 12.0}


@dataclass(frozen=True)
class SpecimenViewTruth:
    """Where the specimen lies in a rendered view (for scoring only).

    Attributes:
        centre_px: (x, y) of the specimen's centre, px.
        axis_deg: the loading axis, degrees from +x towards +y, in [0, 180).
        width_px: the parallel length's width, px.
        parallel_length_px: the parallel length, px.
    """

    centre_px: tuple[float, float]
    axis_deg: float
    width_px: float
    parallel_length_px: float


def render_specimen_view(
    specimen: Specimen,
    *,
    scale_mm_per_px: float,
    sensor_size: tuple[int, int],
    centre_px: tuple[float, float] | None = None,
    rotation_deg: float = 0.0,
    lighting: str = "front-dark",
    grips: bool = False,
    grip_width_mm: float | None = None,
    speckle_radius_px: float = 2.0,
    noise_grey: float = 1.0,
    seed: int = 0,
) -> tuple[np.ndarray, SpecimenViewTruth]:
    """Render a still view of `specimen`; see the module docstring.

    Args:
        specimen: the test piece.
        scale_mm_per_px: object-plane size of a pixel, mm.
        sensor_size: (width, height), px.
        centre_px: where the specimen's centre lies, (x, y) px; None = the image centre.
        rotation_deg: the axis's rotation from the image's vertical, degrees (positive turns
            the axis from +y towards -x, as `axis_deg` grows).
        lighting: one of `LIGHTINGS`.
        grips: draw the grips' jaws over the tabs beyond the clamp edges, out to the image's
            border.
        grip_width_mm: the jaws' width across the axis, mm; None = twice the tab width.
        speckle_radius_px: speckle spot radius, px.
        noise_grey: camera noise, grey levels rms.
        seed: seed of the speckle and the noise.

    Returns:
        (image, truth): uint8 (height, width) image and the specimen's true placement.
    """
    if lighting not in LIGHTINGS:
        raise ValueError(f"lighting must be one of {', '.join(LIGHTINGS)}, got {lighting!r}")
    if not scale_mm_per_px > 0:
        raise ValueError(f"scale_mm_per_px must be > 0, got {scale_mm_per_px}")
    width, height = sensor_size
    if centre_px is None:
        centre_px = (0.5 * (width - 1), 0.5 * (height - 1))
    rng = np.random.default_rng(seed)
    angle = math.radians(rotation_deg)
    cols, rows = np.meshgrid(
        np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64)
    )
    dx, dy = cols - centre_px[0], rows - centre_px[1]
    # The axis (material +Y) points along (-sin a, cos a) in the image: axis_deg = 90 + a.
    along_x, along_y = -math.sin(angle), math.cos(angle)
    Y = (dx * along_x + dy * along_y) * scale_mm_per_px
    X = (dx * along_y - dy * along_x) * scale_mm_per_px
    distance_px = (specimen.half_width_mm(Y) - np.abs(X)) / scale_mm_per_px
    cover = np.clip(distance_px + 0.5, 0.0, 1.0)
    cover[np.abs(Y) > 0.5 * specimen.overall_length_mm] = 0.0
    speckle = ndimage.gaussian_filter(rng.standard_normal((height, width)), speckle_radius_px)
    speckle /= speckle.std()
    coat = _SPECIMEN_MEAN[lighting] + _SPECIMEN_SPREAD[lighting] * np.tanh(speckle)
    backdrop = np.full((height, width), _BACKDROP[lighting])
    image = backdrop + cover * (coat - backdrop)
    if grips:
        jaw_half_px = 0.5 * (grip_width_mm or 2.0 * specimen.end_width_mm) / scale_mm_per_px
        clamp_px = 0.5 * specimen.grip_distance_mm / scale_mm_per_px
        along_px = Y / scale_mm_per_px
        across_px = X / scale_mm_per_px
        jaw = np.clip(np.abs(along_px) - clamp_px + 0.5, 0.0, 1.0) * np.clip(
            jaw_half_px - np.abs(across_px) + 0.5, 0.0, 1.0
        )
        texture = _GRIP[lighting] + 4.0 * ndimage.gaussian_filter(
            rng.standard_normal((height, width)), 3.0
        )
        image = image + jaw * (texture - image)
    image = image + noise_grey * rng.standard_normal((height, width))
    truth = SpecimenViewTruth(
        centre_px=(float(centre_px[0]), float(centre_px[1])),
        axis_deg=(90.0 + rotation_deg) % 180.0,
        width_px=specimen.parallel_width_mm / scale_mm_per_px,
        parallel_length_px=specimen.parallel_length_mm / scale_mm_per_px,
    )
    return np.clip(np.rint(image), 0, 255).astype(np.uint8), truth
