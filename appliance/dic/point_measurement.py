"""Search, then IC-GN, of many points against one reference, with recovery and blur matching.

`PointMeasurement` is the pipeline `extensometer track` runs on every image, and the one the
search benchmark scores: the integer search a `SearchChoice` names (the batched ZNCC search
of all points, or LPQ at the choice's window; over the choice's pre-warps, if any) against the
reference blurred as the targets are, then IC-GN. With the choice's recovery on, the points not
accepted are recovered (`appliance.dic.seeded_recovery`) and the points are refined once more
against a reference blurred as it sees the targets' blur through the measured stretch
(`appliance.dic.stretch.blur_in_reference`), with a patient iteration limit; `report` says what
that did for the last image.
"""

from __future__ import annotations

import numpy as np

from appliance.dic import integer_search
from appliance.dic.batched_search import ZNCCSearch
from appliance.dic.blur import motion_blur
from appliance.dic.icgn import ICGN, ICGNResult, PreparedTarget
from appliance.dic.lpq import LPQParams
from appliance.dic.search_choice import SearchChoice
from appliance.dic.seeded_recovery import (
    accepted_points,
    in_place_points,
    nearest_predictions,
    recover_rejected,
)
from appliance.dic.stretch import blur_in_reference

__all__ = ["PointMeasurement"]


class PointMeasurement:
    """Search, then IC-GN, of a set of points against one reference (see the module
    docstring).

    Args:
        reference: the reference image (sharp: it is blurred here to match `blur`).
        points: (n, 2) reference positions (x, y), px.
        choice: the search (`appliance.dic.search_choice`).
        subset: subset side, px (odd).
        radius: search half-width, px.
        prefilter_sigma: IC-GN's Gaussian pre-filter, px.
        threads: worker threads (None = numba's).
        blur: (length px, direction degrees) of the targets' known motion blur.
        search: False to start IC-GN from the guesses without searching.
    """

    MIN_ZNCC = 0.9
    """ZNCC below which a converged point counts as missed (recovery, blur re-matching)."""
    BLUR_REMATCH_PX = 0.5
    """Change of the blur seen from the reference above which IC-GN's reference is re-blurred."""
    REMATCH_ITERATIONS = 60
    """IC-GN's iteration limit of the last pass: along a long blur the displacement across it
    converges slowly, and these points already start close."""

    def __init__(
        self,
        reference: np.ndarray,
        points: np.ndarray,
        choice: SearchChoice,
        *,
        subset: int,
        radius: int,
        prefilter_sigma: float,
        threads: int | None = None,
        blur: tuple[float, float] = (0.0, 0.0),
        search: bool = True,
    ) -> None:
        self.choice = choice
        self.method = choice.method if search else "none"
        self.radius = radius
        self.subset = subset
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        window = choice.lpq_window
        self.lpq = LPQParams() if window is None else LPQParams(window=window)
        self.raw_reference = np.asarray(reference, dtype=np.float64)
        self.reference = self.raw_reference
        self.blur = (float(blur[0]), float(blur[1]))
        if self.blur[0] > 0:
            self.reference = motion_blur(self.reference, *self.blur)
        self.settings = dict(subset=subset, prefilter_sigma=prefilter_sigma, threads=threads)
        self.icgn = ICGN(**self.settings)
        self.icgn.prepare(self.reference, self.points)
        self._rematched: dict[tuple[float, float], ICGN] = {}
        self.report: dict | None = None
        self.zncc: ZNCCSearch | None = None
        if self.method == "zncc":
            self.zncc = ZNCCSearch(
                subset=subset, radius=radius, threads=threads, coarse_to_fine=True
            )
            self.zncc.prepare(self.reference, self.points)

    def measure(self, image: np.ndarray, guess: np.ndarray, prepared: PreparedTarget) -> ICGNResult:
        """IC-GN result of every point in `image` (`prepared` by `self.icgn.prepare_target`),
        the search window centred on `guess` ((n, 2) px)."""
        if self.method == "none":
            return self.icgn.compute(prepared, guess)
        prewarps = self.choice.prewarps
        if self.zncc is not None:
            found = self.zncc.search(image, guess, prewarps=prewarps)
        else:
            found = integer_search.lpq_search(
                self.reference,
                image,
                self.points,
                subset=self.subset,
                radius=self.radius,
                guess=guess,
                params=self.lpq,
                prewarps=prewarps,
            )
        seeded = np.zeros((len(self.points), 6))
        seeded[:, :2] = guess
        use = found.valid
        seeded[use, :2] = found.displacement[use]
        seeded[use, 2:] = found.gradient[use]
        result = self.icgn.compute(prepared, seeded)
        if not self.choice.recover:
            return result
        report: dict = {"recovered": 0, "scale_searched": 0, "waves": 0}
        slow = in_place_points(self.points, result, self.MIN_ZNCC)
        if (~accepted_points(result, self.MIN_ZNCC) & ~slow).any():
            recovery = recover_rejected(
                self.reference,
                image,
                prepared,
                self.icgn,
                result,
                guess,
                radius=self.radius,
                scale_prewarps=self.choice.scale_prewarps(),
                min_zncc=self.MIN_ZNCC,
                leave=slow,
            )
            result = recovery.result
            report = {
                "recovered": recovery.recovered,
                "scale_searched": recovery.scale_searched,
                "waves": recovery.waves,
            }
        result, report["icgn_reference_blur_px"] = self._rematch_blur(prepared, result, slow)
        self.report = report
        return result

    def _rematch_blur(
        self, prepared: PreparedTarget, result: ICGNResult, slow: np.ndarray
    ) -> tuple[ICGNResult, float]:
        """Refine the points again against a reference blurred as it sees the targets' blur
        through the accepted points' median gradient, when that differs from the blur given by
        more than `BLUR_REMATCH_PX` (the points not accepted only, otherwise), with a patient
        iteration limit: an accepted point from its estimate, a point not accepted from its
        nearest accepted point's prediction and, where its estimate's ZNCC reaches `MIN_ZNCC`
        (even at the iteration limit), from that estimate too; the accepted outcome with the
        highest ZNCC wins; the points `slow` to converge in place (`in_place_points`) only
        from their estimate. Returns the result and the reference blur IC-GN used."""
        length, angle = self.blur
        accepted = accepted_points(result, self.MIN_ZNCC)
        if not accepted.any():
            return result, float(length)
        gradient = np.median(np.c_[result.ux, result.uy, result.vx, result.vy][accepted], axis=0)
        seen, seen_angle = blur_in_reference(length, angle, gradient)
        if abs(seen - length) <= self.BLUR_REMATCH_PX:
            seen, seen_angle = length, angle
            if accepted.all():
                return result, float(length)
        key = (round(seen * 4) / 4, round(seen_angle))
        icgn = self._rematched.get(key)
        if icgn is None:
            icgn = ICGN(**self.settings, max_iterations=self.REMATCH_ITERATIONS)
            icgn.prepare(motion_blur(self.raw_reference, *key), self.points)
            self._rematched[key] = icgn
        zncc = np.nan_to_num(np.asarray(result.zncc, dtype=np.float64), nan=-1.0)
        close = np.isfinite(result.u) & (zncc >= self.MIN_ZNCC)
        if (seen, seen_angle) == (length, angle):
            close &= ~accepted
        indices = np.flatnonzero(close)
        start = np.c_[result.u, result.v, result.ux, result.uy, result.vx, result.vy][indices]
        others = np.flatnonzero(~accepted & ~slow)
        if others.size:
            indices = np.r_[indices, others]
            parents = accepted_points(result, self.MIN_ZNCC)
            start = np.r_[start, nearest_predictions(self.points, result, parents, others)]
        again = icgn.compute(prepared, start, indices=indices)
        better = accepted_points(again, self.MIN_ZNCC)
        fields = {
            name: np.array(getattr(result, name), copy=True)
            for name in ("u", "v", "ux", "uy", "vx", "vy", "zncc", "iterations", "status")
        }
        order = np.argsort(np.nan_to_num(again.zncc, nan=-1.0), kind="stable")
        keep = order[better[order]]
        for name, column in fields.items():
            column[indices[keep]] = np.asarray(getattr(again, name))[keep]
        return ICGNResult(**fields), float(key[0])
