"""Recovery of the points a search missed: scale-searched seeds, then their neighbours.

After an integer search and IC-GN, a point is *accepted* when IC-GN converged with a ZNCC of
at least `min_zncc`. Under a one-step stretch a translation-only search misses most points
(the subset's ends have moved by e S / 2), and where the displacement field is larger than the
search window it misses the far ones whatever the search. `recover_rejected` gets them back at
a fraction of the cost of searching every point over a set of pre-warps:

1. Seeds. Fewer than `MIN_SEEDS` points accepted: the rejected points nearest the points'
   centroid (where a stretch about the middle moves them least), at most `seed_points` of
   them, are searched over the full pre-warp set (`scale_prewarps`, for instance
   `appliance.dic.stretch.stretch_prewarps` over 0 ... 50 % along x and along y) and refined;
   the accepted ones are the seeds.
2. Waves. Every rejected point takes its nearest accepted point as parent, as in
   reliability-guided propagation (`appliance.dic.propagation`): its first-order prediction
   u_p + ux_p dx + uy_p dy, v_p + vx_p dx + vy_p dy is the centre of a small search
   (`local_radius`) with the parent's gradient as the only pre-warp, then IC-GN starts from
   the winner. The newly accepted points are parents of the next wave, until a wave accepts
   none or `max_waves` have run.

An accepted point that disagrees with its neighbours (`inconsistent_points`: a match of a
few speckles in the wrong place can score a ZNCC of 0.97) counts as rejected.
A point's result is replaced only by an accepted one: what recovery cannot improve is left as
the caller measured it. The counts of the work done come back with the result (`Recovery`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from appliance.dic.icgn import ICGN, ICGNResult, PointStatus, PreparedTarget
from appliance.dic.integer_search import zncc_search

__all__ = [
    "MIN_SEEDS",
    "Recovery",
    "accepted_points",
    "in_place_points",
    "inconsistent_points",
    "nearest_predictions",
    "predict_from",
    "recover_rejected",
]

MIN_SEEDS = 3
"""Accepted points below which seeds are scale-searched first."""


@dataclass(frozen=True)
class Recovery:
    """Outcome of `recover_rejected`.

    Attributes:
        result: every point's result, the recovered ones replaced.
        scale_searched: points searched over the full pre-warp set for seeds.
        recovered: points rejected before and accepted now.
        waves: neighbour waves run.
    """

    result: ICGNResult
    scale_searched: int
    recovered: int
    waves: int


def accepted_points(result: ICGNResult, min_zncc: float) -> np.ndarray:
    """(n,) bool: converged with a ZNCC of at least `min_zncc`."""
    zncc = np.nan_to_num(np.asarray(result.zncc, dtype=np.float64), nan=-1.0)
    return (np.asarray(result.status) == PointStatus.CONVERGED) & (zncc >= min_zncc)


def recover_rejected(
    reference: np.ndarray,
    target: np.ndarray,
    prepared: PreparedTarget,
    icgn: ICGN,
    result: ICGNResult,
    guess: np.ndarray,
    *,
    radius: int,
    scale_prewarps: np.ndarray,
    min_zncc: float = 0.9,
    seed_points: int = 8,
    local_radius: int = 10,
    max_waves: int = 8,
    leave: np.ndarray | None = None,
) -> Recovery:
    """Search again, and refine, the points of `result` that were not accepted.

    Args:
        reference: the reference image the searches use (blurred to match, if it is).
        target: the target image; `prepared` its `icgn.prepare_target`.
        icgn: the `ICGN` prepared on the reference and the points.
        result: the points' results so far, in `icgn.points` order.
        guess: (n, 2) displacement guesses the seeds' search windows are centred on, px.
        radius: search half-width of the seeds, px.
        scale_prewarps: (k, 4) pre-warps of the seeds' search.
        min_zncc: acceptance threshold of a refined point.
        seed_points: most points scale-searched for seeds.
        local_radius: search half-width around a parent's prediction, px.
        max_waves: most neighbour waves.
        leave: (n,) bool, points not to search again (`in_place_points`), or None.

    Returns:
        `Recovery`.
    """
    points = icgn.points
    left = np.zeros(len(points), dtype=bool) if leave is None else np.asarray(leave, bool)
    values = np.c_[result.u, result.v, result.ux, result.uy, result.vx, result.vy].astype(float)
    zncc = np.asarray(result.zncc, dtype=np.float64).copy()
    iterations = np.asarray(result.iterations).copy()
    status = np.asarray(result.status).copy()
    accepted = accepted_points(result, min_zncc) & ~inconsistent_points(points, result, min_zncc)
    before = accepted.copy()
    subset = icgn.subset
    scale_searched = 0

    def refine(indices: np.ndarray, found_u, found_v, gradient: np.ndarray, ok: np.ndarray):
        use = indices[ok]
        if use.size == 0:
            return
        start = np.c_[found_u[ok], found_v[ok], gradient[ok]]
        refined = icgn.compute(prepared, start, indices=use)
        good = accepted_points(refined, min_zncc)
        keep = use[good]
        values[keep] = np.c_[refined.u, refined.v, refined.ux, refined.uy, refined.vx, refined.vy][
            good
        ]
        zncc[keep] = refined.zncc[good]
        iterations[keep] = refined.iterations[good]
        status[keep] = refined.status[good]
        accepted[keep] = True

    if accepted.sum() < MIN_SEEDS and (~accepted & ~left).any():
        rejected = np.flatnonzero(~accepted & ~left)
        centre = points.mean(axis=0)
        order = np.argsort(np.hypot(*(points[rejected] - centre).T), kind="stable")
        seeds = rejected[order[:seed_points]]
        scale_searched = seeds.size
        found = zncc_search(
            reference,
            target,
            points[seeds],
            subset=subset,
            radius=radius,
            guess=guess[seeds],
            prewarps=scale_prewarps,
        )
        refine(seeds, found.u, found.v, found.gradient, found.valid)

    waves = 0
    while waves < max_waves and accepted.any() and (~accepted & ~left).any():
        parents_of = np.flatnonzero(accepted)
        rejected = np.flatnonzero(~accepted & ~left)
        _, nearest = cKDTree(points[parents_of]).query(points[rejected])
        parents = parents_of[np.atleast_1d(nearest)]
        start = predict_from(points, values, parents, rejected)
        predicted, gradient = start[:, :2], start[:, 2:]
        found_u = np.zeros(rejected.size)
        found_v = np.zeros(rejected.size)
        valid = np.zeros(rejected.size, dtype=bool)
        for warp in np.unique(np.round(gradient, 3), axis=0):
            group = np.flatnonzero(np.all(np.round(gradient, 3) == warp, axis=1))
            found = zncc_search(
                reference,
                target,
                points[rejected[group]],
                subset=subset,
                radius=local_radius,
                guess=predicted[group],
                prewarps=warp[None, :]
                if np.linalg.det(np.eye(2) + warp.reshape(2, 2)) > 0
                else None,
            )
            found_u[group], found_v[group], valid[group] = found.u, found.v, found.valid
        count = int(accepted.sum())
        refine(rejected, found_u, found_v, gradient, valid)
        waves += 1
        if int(accepted.sum()) == count:
            break

    merged = ICGNResult(
        u=values[:, 0],
        v=values[:, 1],
        ux=values[:, 2],
        uy=values[:, 3],
        vx=values[:, 4],
        vy=values[:, 5],
        zncc=zncc,
        iterations=iterations,
        status=status,
    )
    return Recovery(merged, scale_searched, int((accepted & ~before).sum()), waves)


def predict_from(
    points: np.ndarray, values: np.ndarray, parents: np.ndarray, children: np.ndarray
) -> np.ndarray:
    """(m, 6) first-order predictions (u, v, ux, uy, vx, vy) of `children` from `parents`
    (indices into `points`, (n, 2) px, and `values`, (n, 6) results)."""
    offset = points[children] - points[parents]
    u, v, ux, uy, vx, vy = values[parents].T
    return np.c_[
        u + ux * offset[:, 0] + uy * offset[:, 1],
        v + vx * offset[:, 0] + vy * offset[:, 1],
        ux,
        uy,
        vx,
        vy,
    ]


def nearest_predictions(
    points: np.ndarray, result: ICGNResult, accepted: np.ndarray, children: np.ndarray
) -> np.ndarray:
    """(m, 6) predictions of `children` from their nearest accepted point (`predict_from`);
    `accepted` must hold at least one point."""
    values = np.c_[result.u, result.v, result.ux, result.uy, result.vx, result.vy]
    parents_of = np.flatnonzero(accepted)
    _, nearest = cKDTree(points[parents_of]).query(points[children])
    return predict_from(points, values, parents_of[np.atleast_1d(nearest)], children)


CONSISTENCY_NEIGHBOURS = 4
CONSISTENCY_PX = 2.0


def inconsistent_points(points: np.ndarray, result: ICGNResult, min_zncc: float) -> np.ndarray:
    """(n,) bool: accepted points whose displacement lies more than `CONSISTENCY_PX` from the
    median of the first-order predictions of their `CONSISTENCY_NEIGHBOURS` nearest accepted
    points; none when fewer than `CONSISTENCY_NEIGHBOURS` + 1 points are accepted."""
    accepted = accepted_points(result, min_zncc)
    out = np.zeros(accepted.shape, dtype=bool)
    ids = np.flatnonzero(accepted)
    if ids.size <= CONSISTENCY_NEIGHBOURS:
        return out
    values = np.c_[result.u, result.v, result.ux, result.uy, result.vx, result.vy]
    _, near = cKDTree(points[ids]).query(points[ids], k=CONSISTENCY_NEIGHBOURS + 1)
    deviation = np.empty((ids.size, CONSISTENCY_NEIGHBOURS))
    for j in range(CONSISTENCY_NEIGHBOURS):
        predicted = predict_from(points, values, ids[near[:, j + 1]], ids)
        deviation[:, j] = np.hypot(*(predicted[:, :2] - values[ids, :2]).T)
    out[ids] = np.median(deviation, axis=1) > CONSISTENCY_PX
    return out


def in_place_points(points: np.ndarray, result: ICGNResult, min_zncc: float) -> np.ndarray:
    """(n,) bool: points IC-GN left at its iteration limit with a ZNCC of at least `min_zncc`
    within `CONSISTENCY_PX` of their nearest accepted point's prediction: found, only slow to
    converge (a subset of few speckles, or one smeared by blur), so searching them again
    gains nothing. None when no point is accepted."""
    accepted = accepted_points(result, min_zncc)
    zncc = np.nan_to_num(np.asarray(result.zncc, dtype=np.float64), nan=-1.0)
    slow = (
        (np.asarray(result.status) == PointStatus.MAX_ITERATIONS)
        & (zncc >= min_zncc)
        & np.isfinite(result.u)
        & np.isfinite(result.v)
    )
    out = np.zeros(accepted.shape, dtype=bool)
    ids = np.flatnonzero(slow)
    if ids.size == 0 or not accepted.any():
        return out
    predicted = nearest_predictions(points, result, accepted, ids)
    off = np.hypot(predicted[:, 0] - result.u[ids], predicted[:, 1] - result.v[ids])
    out[ids] = off <= CONSISTENCY_PX
    return out
