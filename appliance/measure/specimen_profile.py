"""The width profile along a specimen's axis: its parallel length, the ends, the edge lines.

`appliance.measure.specimen_detection` measures a width on every row of the image resampled
along the axis (NaN where a row has none); here that profile becomes the parallel length:

* `parallel_run`: the longest run of rows no wider than the narrowest by more than
  `PARALLEL_TOLERANCE` (a stretch a little wider and narrow again on both sides is a speckle's
  doing and stays in);
* `parallel_ends`: where the width, walking outward, first exceeds the parallel width by the
  tolerance (the ends), and the centre along the axis from the shoulders' symmetry;
* `robust_line`: a straight line through an edge's points, refitted once without outliers;
* `running_median`, `running_mean`: NaN-aware running statistics.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

PARALLEL_TOLERANCE = (0.8, 0.01)
"""Width above the parallel width that ends the parallel length: the larger of 0.8 px and 1 %."""
BUMP_TOLERANCES = 3.0
"""A stretch wider than the parallel width by less than this many tolerances, narrow again on
both sides, is a speckle's doing, not a shoulder (which widens on to the tab)."""


def parallel_run(widths: np.ndarray, window: int) -> tuple[int, int] | None:
    """[start, stop) rows of the longest run whose width (a running median over `window` rows)
    exceeds the parallel width by no more than the tolerance, bumps of less than
    `BUMP_TOLERANCES` with narrow rows on both sides included; None when shorter than 20 rows.
    A row without a width (NaN in the running median: no specimen on the axis, or edges lost
    to a speckle) ends a run, unless the parallel width resumes after it within `2 * window`
    rows (such a gap is bridged). None also when fewer than half of the run's rows have a
    width."""
    valid = np.isfinite(widths)
    if valid.sum() < 20:
        return None
    smooth = running_median(widths, window)
    finite = smooth[np.isfinite(smooth)]
    if finite.size == 0:
        return None
    reference = float(finite.min())
    for _ in range(2):
        tolerance = max(PARALLEL_TOLERANCE[0], PARALLEL_TOLERANCE[1] * reference)
        reference = float(np.median(finite[finite <= reference + tolerance]))
    tolerance = max(PARALLEL_TOLERANCE[0], PARALLEL_TOLERANCE[1] * reference)
    excess = smooth - reference
    within = excess <= tolerance
    labels, count = ndimage.label(excess > tolerance)
    for number in range(1, count + 1):
        rows = np.nonzero(labels == number)[0]
        first, last = rows[0], rows[-1]
        bounded = first > 0 and last < len(smooth) - 1 and within[first - 1] and within[last + 1]
        if bounded and np.max(excess[rows]) < BUMP_TOLERANCES * tolerance:
            within[rows] = True
    labels, count = ndimage.label(~np.isfinite(smooth))
    for number in range(1, count + 1):
        rows = np.nonzero(labels == number)[0]
        first, last = rows[0], rows[-1]
        bounded = first > 0 and last < len(smooth) - 1 and within[first - 1] and within[last + 1]
        if bounded and rows.size <= 2 * window:
            within[rows] = True
    best: tuple[int, int] | None = None
    start = None
    for i, flag in enumerate(np.append(within, False)):
        if flag and start is None:
            start = i
        elif not flag and start is not None:
            if best is None or i - start > best[1] - best[0]:
                best = (start, i)
            start = None
    if best is None or np.isfinite(widths[best[0] : best[1]]).sum() < max(
        20, (best[1] - best[0]) // 2
    ):
        return None
    return best


def parallel_ends(
    s_grid: np.ndarray, widths: np.ndarray, start: int, stop: int, in_view: np.ndarray
) -> tuple[float | None, float, float | None]:
    """The parallel length's ends and its centre along the axis (positions on `s_grid`).

    The ends are where the width, going outward from the run [start, stop), first exceeds the
    parallel width by the tolerance (interpolated between rows). The centre is the mean of the
    midpoints between the two sides' crossings of that level and of 2, 4, ... 32 times it,
    as far as both sides reach them within a quarter of the run beyond its ends (the steep
    part of the shoulders, before any grip): the shoulders' symmetry fixes it better than the
    flat start of the transition arcs does. An end is None where it is not seen: the width
    does not depart from the parallel width before the image ends (`in_view` False), nor
    within a quarter of the run (the specimen ends there, or its width is lost).
    """
    smooth = running_mean(widths, 5)
    reference = float(np.nanmedian(smooth[start:stop]))
    tolerance = max(PARALLEL_TOLERANCE[0], PARALLEL_TOLERANCE[1] * reference)
    reach = max(1, (stop - start) // 4)
    midpoints = []
    ends: tuple[float | None, float | None] = (None, None)
    for k in range(6):
        level = reference + tolerance * 2**k
        low = _outward_crossing(s_grid, smooth, start, -1, level, reach, in_view)
        high = _outward_crossing(s_grid, smooth, stop - 1, 1, level, reach, in_view)
        if k == 0:
            ends = (
                None if low is None or math.isnan(low) else low,
                None if high is None or math.isnan(high) else high,
            )
        if low is None or high is None or math.isnan(low) or math.isnan(high):
            break
        midpoints.append(0.5 * (low + high))
    low, high = ends
    if midpoints:
        centre = float(np.mean(midpoints))
    elif low is not None and high is not None:
        centre = 0.5 * (low + high)
    else:
        centre = math.nan
    return low, centre, high


def _outward_crossing(
    s_grid: np.ndarray,
    widths: np.ndarray,
    row: int,
    step: int,
    level: float,
    reach: int,
    in_view: np.ndarray,
) -> float | None:
    """Position where `widths`, walked from `row` in direction `step` over the rows that have
    one, first rises above `level`; None when the image ends first, NaN when it does not
    within `reach` rows."""
    if not widths[row] <= level:
        return float(s_grid[row])
    for nxt in range(row + step, row + step * (reach + 1), step):
        if not 0 <= nxt < len(widths) or not in_view[nxt]:
            return None
        if not np.isfinite(widths[nxt]):
            continue
        if widths[nxt] > level:
            fraction = (level - widths[row]) / (widths[nxt] - widths[row])
            return float(s_grid[row] + (s_grid[nxt] - s_grid[row]) * fraction)
        row = nxt
    return math.nan


def running_median(values: np.ndarray, window: int) -> np.ndarray:
    """Median of the finite values in a centred window of `window` rows (NaN where fewer than
    half of them are finite)."""
    half = window // 2
    padded = np.pad(values, half, constant_values=np.nan)
    windows = np.lib.stride_tricks.sliding_window_view(padded, window)
    enough = np.isfinite(windows).sum(axis=1) >= (window + 1) // 2
    out = np.full(len(values), np.nan)
    if enough.any():
        out[enough] = np.nanmedian(windows[enough], axis=1)
    return out


def running_mean(values: np.ndarray, window: int) -> np.ndarray:
    """Mean of the finite values in a centred window of `window` rows (NaN where there is
    none)."""
    finite = np.isfinite(values)
    total = ndimage.uniform_filter1d(np.where(finite, values, 0.0), window, mode="nearest")
    count = ndimage.uniform_filter1d(finite.astype(float), window, mode="nearest")
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0.5 / window, total / np.maximum(count, 1e-12), np.nan)


def robust_line(s: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares line t(s) (polyval coefficients), refitted once without the points beyond
    3 median absolute deviations; and the rms of the points kept about it."""
    keep = np.isfinite(t)
    line = np.polyfit(s[keep], t[keep], 1)
    residual = t - np.polyval(line, s)
    mad = np.nanmedian(np.abs(residual[keep]))
    keep &= np.abs(residual) <= max(3 * 1.4826 * mad, 1e-6)
    line = np.polyfit(s[keep], t[keep], 1)
    rms = float(np.sqrt(np.mean((t[keep] - np.polyval(line, s[keep])) ** 2)))
    return line, rms
