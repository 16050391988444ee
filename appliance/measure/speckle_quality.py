"""How good a live frame is for setting up the camera: focus, exposure and the speckle where
the gauge goes.

An installer aims, focuses and lights the camera before a test, watching these figures change
as the lens turns (`extensometer preview`). Every grey-level figure is on the 8-bit scale
(grey levels of a Mono8 image; a 12-bit image's values are scaled by 255 / 4095 first), so a
figure means the same for every pixel format.

* `focus_gradient(image, full_scale)`: the weakest-direction intensity gradient of the image's
  sharpest tiles (`appliance.measure.image_quality.view_quality`'s `sharpest_gradient`, the
  same figure, computed on all tiles at once so that it keeps up with a live image), grey
  levels per px. It peaks when the specimen's speckle is in focus and is what
  `camera-check` judges (at least 3.8 on the 8-bit scale).
* `subset_quality(image, centres_px, subset_px, full_scale)`: the speckle in the subsets a
  test would track, one square `subset_px` window at each centre (the gauge's points):
  - the mean intensity gradient (MIG; Pan et al., Opt. Lasers Eng. 48 (2010) 469-477) inside
    the subsets, grey levels per px, their mean;
  - the sum of squared subset intensity gradients (SSSIG; Pan et al., "Study on subset size
    selection in digital image correlation for speckle patterns", Opt. Express 16 (2008)
    7037-7048), the smaller of its x and y sums, grey levels squared, the smallest over the
    subsets: the displacement's standard deviation from image noise sigma is about
    sqrt(2) * sigma / sqrt(SSSIG), so a subset with too small an SSSIG measures noisily;
  - the speckle size: the full width at half maximum of the subsets' mean autocorrelation
    peak divided by sqrt(2), px. For a speckle of Gaussian spots it is
    the spots' own full width at half maximum; the DIC literature asks for 3 to 5 px, and a
    subset should span several speckles (`speckles_per_subset`).
* `frame_quality(...)`: all of them and the mean grey level, saturated and dark fractions of a
  frame, as one `FrameQuality`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from appliance.measure.image_quality import VIEW_TILE_PX

EIGHT_BIT = 255.0
"""Full scale every figure is expressed on."""

SHARPEST_PERCENTILE = 99.0
"""The tiles the focus figure is taken from: this percentile of the tiles' gradients (as
`view_quality`)."""


@dataclass(frozen=True)
class SubsetQuality:
    """The speckle in the subsets a test would track (see the module docstring).

    Attributes:
        subsets: how many subsets were judged (those wholly inside the image).
        subset_px: their side, px.
        mean_intensity_gradient: MIG inside the subsets, 8-bit grey levels per px (mean).
        sssig: the smallest subset's SSSIG (the smaller of its x and y sums), 8-bit grey
            levels squared.
        speckle_size_px: the speckle size over the subsets, px (NaN without texture).
    """

    subsets: int
    subset_px: int
    mean_intensity_gradient: float
    sssig: float
    speckle_size_px: float

    @property
    def speckles_per_subset(self) -> float:
        """How many speckles fit across a subset (NaN without a speckle size)."""
        if not self.speckle_size_px > 0:
            return math.nan
        return self.subset_px / self.speckle_size_px


@dataclass(frozen=True)
class FrameQuality:
    """The set-up figures of one frame.

    Attributes:
        mean_grey: mean grey level, 8-bit scale.
        saturated_fraction: fraction of the pixels at full scale.
        dark_fraction: fraction of the pixels at 0.
        focus_gradient: the sharpest tiles' weakest-direction gradient, 8-bit grey levels per
            px (`focus_gradient`).
        subsets: the speckle in the gauge's subsets; None when no subset fits the image.
    """

    mean_grey: float
    saturated_fraction: float
    dark_fraction: float
    focus_gradient: float
    subsets: SubsetQuality | None


def focus_gradient(image: np.ndarray, full_scale: float) -> float:
    """The weakest-direction intensity gradient of the image's sharpest `VIEW_TILE_PX` tiles
    (their 99th percentile), 8-bit grey levels per px: exactly `view_quality`'s
    `sharpest_gradient` times 255, computed on every tile at once."""
    values = np.asarray(image, dtype=np.float64) * (EIGHT_BIT / full_scale)
    height, width = values.shape
    tile = min(VIEW_TILE_PX, height, width)
    rows, columns = height // tile, width // tile
    tiles = values[: rows * tile, : columns * tile].reshape(rows, tile, columns, tile)
    gx = 0.5 * (tiles[:, 1:-1, :, 2:] - tiles[:, 1:-1, :, :-2])
    gy = 0.5 * (tiles[:, 2:, :, 1:-1] - tiles[:, :-2, :, 1:-1])
    xx = (gx * gx).mean(axis=(1, 3))
    xy = (gx * gy).mean(axis=(1, 3))
    yy = (gy * gy).mean(axis=(1, 3))
    smaller = 0.5 * (xx + yy) - np.sqrt(0.25 * (xx - yy) ** 2 + xy * xy)
    weakest = np.sqrt(np.maximum(smaller, 0.0))
    return float(np.percentile(weakest, SHARPEST_PERCENTILE))


def speckle_size_px(windows: Sequence[np.ndarray] | np.ndarray) -> float:
    """The speckle size in a window, or in windows of one size together (each at least 9 x 9
    px): the full width at half maximum of their mean autocorrelation peak (the mean of x and
    y) divided by sqrt(2), px; NaN without texture. It reads low as the speckle grows against
    the window (whose own mean is taken out): in 41 px windows of Gaussian spots 4 % at 3.3 px,
    9 % at 5 px and 14 % at 6.7 px; averaging windows steadies it."""
    stack = np.asarray(windows, dtype=np.float64)
    if stack.ndim == 2:
        stack = stack[np.newaxis]
    _, height, width = stack.shape
    lags_x = np.arange(width // 2)
    lags_y = np.arange(height // 2)
    along_x = np.zeros(lags_x.size)
    along_y = np.zeros(lags_y.size)
    textured = 0
    for window in stack:
        values = window - window.mean()
        power = np.abs(np.fft.rfft2(values, s=(2 * height, 2 * width))) ** 2
        correlation = np.fft.irfft2(power, s=(2 * height, 2 * width))
        peak = correlation[0, 0] / (height * width)
        if not peak > 0:
            continue
        along_x += correlation[0, lags_x] / (height * (width - lags_x)) / peak
        along_y += correlation[lags_y, 0] / ((height - lags_y) * width) / peak
        textured += 1
    if not textured:
        return math.nan
    widths = [_half_width(profile / textured) for profile in (along_x, along_y)]
    if any(math.isnan(w) for w in widths):
        return math.nan
    return float(np.mean(widths)) * 2.0 / math.sqrt(2.0)


def _half_width(profile: np.ndarray) -> float:
    """Where a decreasing profile starting at 1 first falls to 0.5, px (linear between
    samples); NaN when it never does."""
    below = np.flatnonzero(profile <= 0.5)
    if below.size == 0:
        return math.nan
    k = int(below[0])
    before, after = profile[k - 1], profile[k]
    return (k - 1) + (before - 0.5) / (before - after)


def subset_quality(
    image: np.ndarray,
    centres_px: Sequence[Sequence[float]] | np.ndarray,
    subset_px: int,
    full_scale: float,
) -> SubsetQuality | None:
    """The speckle in the square `subset_px` subsets centred on `centres_px` ((x, y), px,
    rounded to the nearest pixel); subsets not wholly inside the image are left out. None when
    none is inside."""
    values = np.asarray(image)
    height, width = values.shape
    half = subset_px // 2
    to_eight_bit = EIGHT_BIT / full_scale
    migs, sssigs, windows = [], [], []
    for x, y in np.asarray(centres_px, dtype=np.float64).reshape(-1, 2):
        if not (np.isfinite(x) and np.isfinite(y)):
            continue
        cx, cy = int(round(x)), int(round(y))
        if cx - half < 1 or cy - half < 1 or cx + half >= width - 1 or cy + half >= height - 1:
            continue
        around = values[cy - half - 1 : cy + half + 2, cx - half - 1 : cx + half + 2]
        around = np.asarray(around, dtype=np.float64) * to_eight_bit
        sx = 0.5 * (around[1:-1, 2:] - around[1:-1, :-2])
        sy = 0.5 * (around[2:, 1:-1] - around[:-2, 1:-1])
        migs.append(float(np.hypot(sx, sy).mean()))
        sssigs.append(min(float((sx * sx).sum()), float((sy * sy).sum())))
        windows.append(around[1:-1, 1:-1])
    if not migs:
        return None
    return SubsetQuality(
        subsets=len(migs),
        subset_px=subset_px,
        mean_intensity_gradient=float(np.mean(migs)),
        sssig=float(min(sssigs)),
        speckle_size_px=speckle_size_px(windows),
    )


def frame_quality(
    image: np.ndarray,
    full_scale: float,
    subset_centres_px: Sequence[Sequence[float]] | np.ndarray,
    subset_px: int,
) -> FrameQuality:
    """The set-up figures of a frame: exposure, focus, and the speckle in the subsets at
    `subset_centres_px`."""
    values = np.asarray(image)
    return FrameQuality(
        mean_grey=float(values.mean()) * EIGHT_BIT / full_scale,
        saturated_fraction=float(np.count_nonzero(values >= full_scale)) / values.size,
        dark_fraction=float(np.count_nonzero(values <= 0)) / values.size,
        focus_gradient=focus_gradient(values, full_scale),
        subsets=subset_quality(values, subset_centres_px, subset_px, full_scale),
    )
