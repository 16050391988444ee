"""Whether an image can be measured: exposure, saturation, contrast and speckle sharpness.

Digital image correlation needs texture that is sharp, contrasted and neither burnt out nor
drowned in the dark. The figures here are those of the DIC literature, as fractions of the
pixel format's full scale so they hold for 8- and 16-bit images alike:

* mean grey level, the fractions of saturated (at full scale) and dark (at 0) pixels;
* contrast: the standard deviation of the grey levels;
* mean intensity gradient (MIG; Pan et al., "Mean intensity gradient: an effective global
  parameter for quality assessment of the speckle patterns used in digital image
  correlation", Opt. Lasers Eng. 48 (2010) 469-477): the mean magnitude of the central
  difference gradient, grey levels per px. It grows with contrast and with sharpness (focus)
  and falls with speckles larger than the subset;
* the weakest-direction gradient: the RMS intensity gradient along the window's least
  textured direction (the square root of the smaller eigenvalue of the mean gradient
  structure tensor; its diagonal is the SSSIG of Pan et al. 2008 per pixel, in x and y). A
  speckle has texture in every direction; a ramp, an edge or stripes have none across them,
  and correlation cannot find a displacement along a direction without texture (the
  aperture problem). It is the figure the limits judge.

`speckle_problem` judges the window a mark is tracked in (the reference is refused before a
test when one fails); `view_quality` judges a whole camera view for `camera-check`, where the
specimen may fill only part of the image, by its sharpest tiles.

The limits below sit between what was measured on fit and unfit 41 px windows (fractions of
full scale): a dense speckle has a weakest-direction gradient of 0.047 and a contrast of
0.15; a flat surface with 2 grey levels of noise 0.006, a speckle of 24 px grains 0.012, a
ramp (the Aravis fake camera's image) 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MIN_WEAK_GRADIENT = 0.015
"""Smallest weakest-direction gradient of a window a mark can be tracked in, of full scale per
px (3.8 grey levels per px in 8 bits: about three times what noise alone gives on a flat
surface)."""

MIN_CONTRAST = 0.03
"""Smallest standard deviation of a mark's window, of full scale (about 8 grey levels)."""

MAX_SATURATED = 0.05
"""Largest fraction of saturated pixels in a mark's window (burnt-out speckle has no
gradient, and saturation biases the correlation)."""

VIEW_TILE_PX = 64
"""Side of the tiles a view is judged by: a specimen rarely fills the image."""


@dataclass(frozen=True)
class WindowQuality:
    """Figures of one image or window, each as a fraction of full scale.

    Attributes:
        mean_grey: mean grey level.
        contrast: standard deviation of the grey levels.
        mean_gradient: mean intensity gradient (central differences), per px.
        weak_gradient: RMS intensity gradient along the least textured direction, per px.
        saturated: fraction of pixels at full scale.
        dark: fraction of pixels at 0.
    """

    mean_grey: float
    contrast: float
    mean_gradient: float
    weak_gradient: float
    saturated: float
    dark: float


def window_quality(image: np.ndarray, full_scale: float) -> WindowQuality:
    """The figures of a grey image (at least 3 x 3 px); `full_scale` is its format's largest
    value (255 for Mono8, 4095 for Mono12)."""
    values = np.asarray(image, dtype=np.float64)
    gx = 0.5 * (values[1:-1, 2:] - values[1:-1, :-2])
    gy = 0.5 * (values[2:, 1:-1] - values[:-2, 1:-1])
    xx, xy, yy = float((gx * gx).mean()), float((gx * gy).mean()), float((gy * gy).mean())
    smaller = 0.5 * (xx + yy) - np.sqrt(0.25 * (xx - yy) ** 2 + xy * xy)
    return WindowQuality(
        mean_grey=float(values.mean() / full_scale),
        contrast=float(values.std() / full_scale),
        mean_gradient=float(np.hypot(gx, gy).mean() / full_scale),
        weak_gradient=float(np.sqrt(max(smaller, 0.0)) / full_scale),
        saturated=float(np.count_nonzero(values >= full_scale) / values.size),
        dark=float(np.count_nonzero(values <= 0) / values.size),
    )


def speckle_problem(window: np.ndarray, full_scale: float) -> str | None:
    """Why a mark cannot be tracked in `window` (its subset in the reference), one phrase; None
    when its speckle is fit (see the module's limits)."""
    q = window_quality(window, full_scale)
    if q.saturated > MAX_SATURATED:
        return f"{q.saturated:.0%} of its pixels are saturated (at most {MAX_SATURATED:.0%})"
    if q.contrast < MIN_CONTRAST:
        return (
            f"no contrast: grey level std {q.contrast * full_scale:.1f} "
            f"(at least {MIN_CONTRAST * full_scale:.1f})"
        )
    if q.weak_gradient < MIN_WEAK_GRADIENT:
        return (
            f"no sharp speckle: intensity gradient {q.weak_gradient * full_scale:.2f} grey "
            f"levels/px in its least textured direction (at least "
            f"{MIN_WEAK_GRADIENT * full_scale:.2f}: out of focus, too coarse, stripes or none)"
        )
    return None


@dataclass(frozen=True)
class ViewQuality:
    """How fit a whole camera view is to measure in.

    Attributes:
        whole: the figures of the whole image.
        sharpest_gradient: the weakest-direction gradient of its sharpest tiles
            (`VIEW_TILE_PX` square; the 99th percentile), of full scale per px: the texture
            and focus where the specimen is, wherever it is, if it covers at least about 1 %
            of the view (a 6 mm rubber dumbbell in the simulated rubber test covers 4 %).
        problems: what makes the view unfit, one phrase each; empty when fit.
    """

    whole: WindowQuality
    sharpest_gradient: float
    problems: tuple[str, ...]


def view_quality(image: np.ndarray, full_scale: float) -> ViewQuality:
    """Judge a camera view: exposure (not black, not burnt out) and sharp texture somewhere."""
    values = np.asarray(image, dtype=np.float64)
    whole = window_quality(values, full_scale)
    height, width = values.shape
    tile = min(VIEW_TILE_PX, height, width)
    gradients = [
        window_quality(values[y : y + tile, x : x + tile], full_scale).weak_gradient
        for y in range(0, height - tile + 1, tile)
        for x in range(0, width - tile + 1, tile)
    ]
    sharpest = float(np.percentile(gradients, 99))
    problems = []
    if whole.mean_grey < 0.02:
        problems.append(f"too dark: mean grey {whole.mean_grey * full_scale:.1f}")
    if whole.saturated > MAX_SATURATED:
        problems.append(f"overexposed: {whole.saturated:.0%} of the pixels saturated")
    if sharpest < MIN_WEAK_GRADIENT:
        problems.append(
            f"no sharp texture in view: intensity gradient of the sharpest tiles "
            f"{sharpest * full_scale:.2f} grey levels/px in their least textured direction "
            f"(at least {MIN_WEAK_GRADIENT * full_scale:.2f}: focus, light or the specimen's "
            "pattern)"
        )
    return ViewQuality(whole, sharpest, tuple(problems))
