"""Correlation of points of interest between a reference and target images: search, then refine.

`Correlator` joins an integer-pixel search (LPQ histograms, ZNCC, or none) to IC-GN subpixel
refinement for one reference image and one set of points, the two phases of Zhang et al.
(2016): the integer search brings every point within a pixel of its match; IC-GN then finds
the subpixel displacement and the displacement gradients.

Motion blur. A sharp reference correlated with a blurred target biases both stages: the
ZNSSD minimum wanders off the true displacement by a random amount that grows with the blur
(measured on dense speckle with a 41 px subset: 0.01 px standard deviation at 4 px of blur,
0.3 px at 10 px) and IC-GN converges slowly. When the blur of the targets is known (the
appliance knows crosshead speed, optics and exposure), `reference_blur` blurs the reference
with the same centred line PSF, which restores unbiased matching (0.0035 px at 10 px of blur
in the same test). LPQ's blur insensitivity is the alternative when the blur is unknown; it
needs an LPQ window of about three times the blur length (`lpq_window`), see
`appliance.dic.lpq`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from appliance.dic import integer_search
from appliance.dic.blur import motion_blur
from appliance.dic.icgn import ICGN, ICGNResult, PointStatus
from appliance.dic.integer_search import IntegerMatch
from appliance.dic.lpq import LPQParams

SearchMethod = Literal["lpq", "zncc", "none"]
SEARCH_METHODS: tuple[str, ...] = ("lpq", "zncc", "none")
DEFAULT_PREFILTER_SIGMA = 0.8
"""Gaussian pre-filter of the correlation pipeline, px: the middle of the 0.6..1.0 px range
that removes the noise-induced bias of cubic B-spline IC-GN (Pan, Exp. Mech. 2013)."""


@dataclass(frozen=True)
class Measurement:
    """Result of correlating the prepared points with one target image.

    Attributes:
        refinement: IC-GN result, the measurement proper.
        search: the integer search that seeded it, or None when searching was off.
    """

    refinement: ICGNResult
    search: IntegerMatch | None


def subsets_outside(points: np.ndarray, shape: tuple[int, ...], subset: int) -> np.ndarray:
    """(n,) bool: whether the `subset` x `subset` square centred on each point of `points`
    ((n, 2) x, y px) reaches outside an image of `shape` (rows, columns)."""
    height, width = shape[:2]
    half = subset // 2
    x, y = points[:, 0], points[:, 1]
    return (x - half < 0) | (y - half < 0) | (x + half > width - 1) | (y + half > height - 1)


class Correlator:
    """Integer search followed by IC-GN, for one reference image and one set of points.

    Args:
        subset: side of the square subset, px (odd).
        search: integer search method: "zncc" (cv2.matchTemplate; the default, because it was
            the more robust of the two in every case measured, see the accuracy benchmark),
            "lpq" (LPQ histograms and chi-square, Zhang et al.'s blur-insensitive search) or
            "none" (IC-GN starts from the guess).
        search_radius: half width of the search window around point + guess, px.
        prewarps: first-order deformations (ux, uy, vx, vy) tried by the search on the
            reference subset, for large one-step stretches; None = translation only.
        reference_blur: (length px, direction deg) of the centred motion blur expected in the
            targets; the reference is blurred to match before searching and refining.
            None = targets as sharp as the reference.
        lpq_window: LPQ window size M (odd, <= subset); None = `LPQParams` default (7).
        prefilter_sigma: Gaussian pre-filter for IC-GN, px (see `ICGN`); the pipeline's
            default, 0.8 px, suppresses the noise-induced interpolation bias.
        max_iterations, znssd_tolerance, step_tolerance, threads: passed to `ICGN`.
    """

    def __init__(
        self,
        *,
        subset: int = 41,
        search: SearchMethod = "zncc",
        search_radius: int = 50,
        prewarps: Sequence[tuple[float, float, float, float]] | None = None,
        reference_blur: tuple[float, float] | None = None,
        lpq_window: int | None = None,
        prefilter_sigma: float = DEFAULT_PREFILTER_SIGMA,
        max_iterations: int = 20,
        znssd_tolerance: float = 1e-8,
        step_tolerance: float = 1e-4,
        threads: int | None = None,
    ) -> None:
        if search not in SEARCH_METHODS:
            raise ValueError(f"search must be one of {', '.join(SEARCH_METHODS)}, got {search!r}")
        if search_radius < 0:
            raise ValueError(f"search_radius must be >= 0, got {search_radius}")
        if reference_blur is not None and not (len(reference_blur) == 2 and reference_blur[0] >= 0):
            raise ValueError(f"reference_blur must be (length >= 0, angle), got {reference_blur}")
        if lpq_window is not None and lpq_window > subset:
            raise ValueError(f"lpq_window {lpq_window} exceeds subset {subset}")
        self.search = search
        self.search_radius = search_radius
        self.prewarps = prewarps
        self.reference_blur = reference_blur
        self.lpq_params = LPQParams() if lpq_window is None else LPQParams(window=lpq_window)
        self.icgn = ICGN(
            subset=subset,
            max_iterations=max_iterations,
            znssd_tolerance=znssd_tolerance,
            step_tolerance=step_tolerance,
            prefilter_sigma=prefilter_sigma,
            threads=threads,
        )
        self._reference: np.ndarray | None = None

    @property
    def subset(self) -> int:
        """Side of the square subset, px."""
        return self.icgn.subset

    def prepare(self, reference: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Prepare the reference subsets; returns the preliminary status as `ICGN.prepare`."""
        reference = np.asarray(reference, dtype=np.float64)
        if self.reference_blur is not None:
            reference = motion_blur(reference, *self.reference_blur)
        self._reference = reference
        self._points = np.ascontiguousarray(points, dtype=np.float64)
        return self.icgn.prepare(self._reference, self._points)

    def measure(self, target: np.ndarray, guess: np.ndarray | None = None) -> Measurement:
        """Correlate the prepared points with a target image.

        Args:
            target: 2-D grey image with the reference's shape.
            guess: (n, 2) displacement (u, v) or (n, 6) (u, v, ux, uy, vx, vy) to start from;
                the search window is centred on it. None = zero.

        Returns:
            `Measurement`. Points whose search window left the image keep the guess as the
            IC-GN start.
        """
        if self._reference is None:
            raise RuntimeError("prepare() must be called before measure()")
        n = self._points.shape[0]
        if guess is None:
            start = np.zeros((n, 6))
        else:
            start = np.asarray(guess, dtype=np.float64)
            if start.shape not in ((n, 2), (n, 6)):
                raise ValueError(f"guess must have shape ({n}, 2) or ({n}, 6), got {start.shape}")
        if self.search == "none":
            return Measurement(self.icgn.compute(target, start), None)
        found = self._search(target, start[:, :2])
        seeded = np.zeros((n, 6))
        seeded[:, : start.shape[1]] = start
        use = found.valid
        seeded[use, :2] = found.displacement[use]
        seeded[use, 2:] = found.gradient[use]
        return Measurement(self.icgn.compute(target, seeded), found)

    def _search(self, target: np.ndarray, guess: np.ndarray) -> IntegerMatch:
        common = dict(
            subset=self.subset, radius=self.search_radius, guess=guess, prewarps=self.prewarps
        )
        if self.search == "lpq":
            return integer_search.lpq_search(
                self._reference, target, self._points, params=self.lpq_params, **common
            )
        return integer_search.zncc_search(self._reference, target, self._points, **common)


__all__ = [
    "DEFAULT_PREFILTER_SIGMA",
    "subsets_outside",
    "Correlator",
    "Measurement",
    "PointStatus",
    "SEARCH_METHODS",
    "SearchMethod",
]
