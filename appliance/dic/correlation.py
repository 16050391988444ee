"""Correlation of points of interest between a reference and target images: search, then refine.

`Correlator` joins an integer-pixel search (LPQ histograms, ZNCC, or none) to IC-GN subpixel
refinement for one reference image and one set of points, the two phases of Zhang et al.
(2016): the integer search brings every point within a pixel of its match, whatever the
motion blur; IC-GN then finds the subpixel displacement and the displacement gradients.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from appliance.dic import integer_search
from appliance.dic.icgn import ICGN, ICGNResult, PointStatus
from appliance.dic.integer_search import IntegerMatch

SearchMethod = Literal["lpq", "zncc", "none"]
SEARCH_METHODS: tuple[str, ...] = ("lpq", "zncc", "none")


@dataclass(frozen=True)
class Measurement:
    """Result of correlating the prepared points with one target image.

    Attributes:
        refinement: IC-GN result, the measurement proper.
        search: the integer search that seeded it, or None when searching was off.
    """

    refinement: ICGNResult
    search: IntegerMatch | None


class Correlator:
    """Integer search followed by IC-GN, for one reference image and one set of points.

    Args:
        subset: side of the square subset, px (odd).
        search: integer search method: "lpq" (LPQ histograms and chi-square, blur-insensitive),
            "zncc" (cv2.matchTemplate, the conventional baseline) or "none" (IC-GN starts
            from the guess). See `appliance.dic.integer_search` for when each one wins.
        search_radius: half width of the search window around point + guess, px.
        prewarps: first-order deformations (ux, uy, vx, vy) tried by the search on the
            reference subset, for large one-step stretches; None = translation only.
        prefilter_sigma: Gaussian pre-filter for IC-GN, px (see `ICGN`).
        max_iterations, znssd_tolerance, step_tolerance, threads: passed to `ICGN`.
    """

    def __init__(
        self,
        *,
        subset: int = 41,
        search: SearchMethod = "lpq",
        search_radius: int = 50,
        prewarps: Sequence[tuple[float, float, float, float]] | None = None,
        prefilter_sigma: float = 0.0,
        max_iterations: int = 20,
        znssd_tolerance: float = 1e-8,
        step_tolerance: float = 1e-4,
        threads: int | None = None,
    ) -> None:
        if search not in SEARCH_METHODS:
            raise ValueError(f"search must be one of {', '.join(SEARCH_METHODS)}, got {search!r}")
        if search_radius < 0:
            raise ValueError(f"search_radius must be >= 0, got {search_radius}")
        self.search = search
        self.search_radius = search_radius
        self.prewarps = prewarps
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
        self._reference = np.asarray(reference)
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
        start = np.zeros((n, 6))
        if guess is not None:
            g = np.asarray(guess, dtype=np.float64)
            if g.shape not in ((n, 2), (n, 6)):
                raise ValueError(f"guess must have shape ({n}, 2) or ({n}, 6), got {g.shape}")
            start[:, : g.shape[1]] = g
        if self.search == "none":
            return Measurement(self.icgn.compute(target, start), None)
        found = self._search(target, start[:, :2])
        use = found.valid
        start[use, 0] = found.u[use]
        start[use, 1] = found.v[use]
        start[use, 2] = found.ux[use]
        start[use, 3] = found.uy[use]
        start[use, 4] = found.vx[use]
        start[use, 5] = found.vy[use]
        return Measurement(self.icgn.compute(target, start), found)

    def _search(self, target: np.ndarray, guess: np.ndarray) -> IntegerMatch:
        method = {
            "lpq": integer_search.lpq_search,
            "zncc": integer_search.zncc_search,
        }[self.search]
        return method(
            self._reference,
            target,
            self._points,
            subset=self.subset,
            radius=self.search_radius,
            guess=guess,
            prewarps=self.prewarps,
        )


__all__ = ["Correlator", "Measurement", "PointStatus", "SEARCH_METHODS", "SearchMethod"]
