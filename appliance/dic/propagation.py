"""Reliability-guided seed-and-propagate IC-GN over a set of points.

IC-GN (`appliance.dic.icgn`) converges only from a guess within about half a speckle of the
truth, and an integer search (`appliance.dic.integer_search`) only finds displacements inside
its window. A tensile specimen stretched 40 % over a 2000 px gauge moves its ends 400 px apart:
no single window covers that, and a window wide enough to would be slow and ambiguous. The
classic answer (Pan, "Reliability-guided digital image correlation for image deformation
measurement", Appl. Opt. 48, 2009) is to find a few seed points by search and let every
accepted point start its neighbours: where the displacement field is smooth on the scale of
the point spacing, the first-order prediction of a neighbour's result is far closer to the
truth than any search needs to be,

    u_j = u_i + ux_i dx + uy_i dy,    v_j = v_i + vx_i dx + vy_i dy,    (dx, dy) = p_j - p_i,

with the gradients (ux, uy, vx, vy) of point i carried over as the start of point j's.

The scheme (`propagate`):

1. The seeds are refined from the guesses given (from `integer_search.zncc_search`, with
   pre-warps for large one-step stretches, or from a previous frame).
2. A refined point is *accepted* when IC-GN converged and its ZNCC is at least `min_zncc`.
   Only accepted points start others.
3. The next *wave* is every point that has not been tried yet and is a neighbour of a point
   accepted in this wave. Each starts from the prediction of its most reliable (highest
   ZNCC) accepted neighbour; ties go to the lower point index. The whole wave is refined in
   one batch (`ICGN.compute` with `indices`, on a target prepared once).
4. Repeat until the next wave is empty: no point accepted in the last one has an untried
   neighbour.

Every point is tried at most once. Waves advance breadth first from the seeds, so a point's
start comes from the best of its neighbours accepted in the wave before it, which are all of
its accepted neighbours at that time (a neighbour accepted earlier would have tried it
earlier). This is Pan's reliability guidance at the granularity of a wave: it chooses the most
reliable parent for every point, while keeping batches large enough for the parallel kernel.
The result of a point depends only on the images, the points, the neighbour structure, the
seeds and their guesses, never on thread counts.

Outcomes, per point (`PointStatus`):

- CONVERGED: tried and accepted.
- LOW_ZNCC: IC-GN converged but the ZNCC is below `min_zncc`; the estimate is reported but
  starts no neighbour.
- MAX_ITERATIONS, OUT_OF_IMAGE, FLAT_SUBSET, DIVERGED: tried, IC-GN's own verdict; starts no
  neighbour.
- NOT_REACHED: never tried: no chain of accepted neighbours leads to it from a seed (an
  untextured island, a region cut off by rejected points, a neighbour structure that does not
  connect it). Its values are NaN.

Neighbour structures (`Neighbours`): the points within a radius of each other
(`Neighbours.within`), the 4- or 8-neighbourhood of a regular grid (`Neighbours.grid`), or any
lists (`Neighbours.from_lists`). The relation need not be symmetric: the neighbours of i are
the points i's result may start.

Coordinates are reference pixel coordinates (x, y) in px, as in `ICGN.prepare`; displacements
in px, gradients dimensionless.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from appliance.dic.icgn import ICGN, ICGNResult, PointStatus, PreparedTarget

__all__ = ["Neighbours", "propagate"]


@dataclass(frozen=True, eq=False)
class Neighbours:
    """Neighbour lists of n points in compressed sparse row form.

    The neighbours of point i, the points its accepted result may start, are
    `targets[offsets[i]:offsets[i + 1]]`. Build one with `within`, `grid` or `from_lists`.

    Attributes:
        offsets: read-only int64 (n + 1,), non-decreasing, offsets[0] = 0 and
            offsets[n] = len(targets).
        targets: read-only int64 (offsets[n],) point indices in [0, n).
    """

    offsets: np.ndarray
    targets: np.ndarray

    def __post_init__(self) -> None:
        offsets = np.array(self.offsets, dtype=np.int64)
        targets = np.array(self.targets, dtype=np.int64)
        if offsets.ndim != 1 or offsets.size < 1 or offsets[0] != 0:
            raise ValueError("offsets must be a 1-D array starting at 0")
        if np.any(np.diff(offsets) < 0) or targets.ndim != 1 or offsets[-1] != targets.size:
            raise ValueError("offsets must be non-decreasing and end at len(targets)")
        n = offsets.size - 1
        if targets.size and (targets.min() < 0 or targets.max() >= n):
            raise ValueError(f"neighbour indices must lie in [0, {n})")
        offsets.flags.writeable = False
        targets.flags.writeable = False
        object.__setattr__(self, "offsets", offsets)
        object.__setattr__(self, "targets", targets)

    def __len__(self) -> int:
        """Number of points n."""
        return self.offsets.size - 1

    def of(self, point: int) -> np.ndarray:
        """Read-only int64 indices of the neighbours of `point`."""
        return self.targets[self.offsets[point] : self.offsets[point + 1]]

    @classmethod
    def from_lists(cls, lists: Sequence[npt.ArrayLike]) -> Neighbours:
        """Neighbours from one sequence of point indices per point.

        Args:
            lists: `lists[i]` holds the indices of the neighbours of point i (any integer
                sequence; may be empty).
        """
        arrays = [np.asarray(item, dtype=np.int64).reshape(-1) for item in lists]
        counts = np.array([a.size for a in arrays], dtype=np.int64)
        targets = np.concatenate(arrays) if arrays else np.zeros(0, dtype=np.int64)
        return cls(offsets=np.r_[0, np.cumsum(counts)], targets=targets)

    @classmethod
    def within(cls, points: npt.ArrayLike, radius: float) -> Neighbours:
        """Every pair of distinct points at most `radius` apart, in both directions.

        Args:
            points: (n, 2) positions (x, y), px; the prepared points of the `ICGN`.
            radius: largest distance between neighbours, px. For a grid of spacing s, a
                radius a little over s gives the 4-neighbourhood, a little over s sqrt(2) the
                8-neighbourhood.

        Returns:
            `Neighbours` with each list in increasing index order.
        """
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2 or not np.all(np.isfinite(pts)):
            raise ValueError(f"points must be a finite (n, 2) array, got shape {pts.shape}")
        if not radius > 0:
            raise ValueError(f"radius must be > 0, got {radius}")
        pairs = cKDTree(pts).query_pairs(float(radius), output_type="ndarray")
        source = np.r_[pairs[:, 0], pairs[:, 1]].astype(np.int64)
        target = np.r_[pairs[:, 1], pairs[:, 0]].astype(np.int64)
        return cls._from_edges(len(pts), source, target)

    @classmethod
    def grid(cls, rows: int, columns: int, *, diagonal: bool = False) -> Neighbours:
        """Neighbours on a regular grid of `rows` x `columns` points, x fastest.

        Point (row r, column c) has index r * columns + c, the order of the points
        (x_c, y_r) listed row by row with x varying fastest (`numpy.meshgrid(xs, ys)`,
        raveled).

        Args:
            rows: number of grid rows (distinct y), >= 1.
            columns: number of grid columns (distinct x), >= 1.
            diagonal: False = the 4 edge neighbours, True = also the 4 diagonal ones.

        Returns:
            `Neighbours` with each list in increasing index order.
        """
        if rows < 1 or columns < 1:
            raise ValueError(f"grid must have at least one row and column, got {rows} x {columns}")
        r, c = np.divmod(np.arange(rows * columns, dtype=np.int64), columns)
        steps = [(-1, 0), (1, 0), (0, -1), (0, 1)]
        if diagonal:
            steps += [(-1, -1), (-1, 1), (1, -1), (1, 1)]
        sources, targets = [], []
        for dr, dc in steps:
            rr, cc = r + dr, c + dc
            inside = (rr >= 0) & (rr < rows) & (cc >= 0) & (cc < columns)
            sources.append(np.flatnonzero(inside))
            targets.append(rr[inside] * columns + cc[inside])
        return cls._from_edges(rows * columns, np.concatenate(sources), np.concatenate(targets))

    @classmethod
    def _from_edges(cls, n: int, source: np.ndarray, target: np.ndarray) -> Neighbours:
        order = np.lexsort((target, source))
        counts = np.bincount(source, minlength=n)
        return cls(offsets=np.r_[0, np.cumsum(counts)], targets=target[order])


def propagate(
    icgn: ICGN,
    target: PreparedTarget | np.ndarray,
    neighbours: Neighbours | Sequence[npt.ArrayLike],
    seeds: npt.ArrayLike,
    seed_guesses: npt.ArrayLike,
    *,
    min_zncc: float = 0.9,
) -> ICGNResult:
    """Refine all prepared points of `icgn` by seed-and-propagate (see the module docstring).

    Args:
        icgn: an `ICGN` after `prepare(reference, points)`; its n prepared points are the
            points propagated over, and its settings (subset, pre-filter, tolerances,
            threads) apply to every refinement.
        target: 2-D grey image with the reference's shape, or its `PreparedTarget` from
            `icgn.prepare_target` (the image is prepared once either way).
        neighbours: `Neighbours` over the n points, or one sequence of neighbour indices per
            point (`Neighbours.from_lists`).
        seeds: (k,) distinct indices of the points refined first, k >= 1.
        seed_guesses: their initial estimates, (k, 2) as (u, v) px or (k, 6) as
            (u, v, ux, uy, vx, vy), as for `ICGN.compute`: within about half a speckle of the
            truth (integer search), with gradients close enough that the subset's ends are
            too (pre-warped search) when the deformation is large.
        min_zncc: acceptance threshold in [-1, 1]: a converged point with a lower ZNCC is
            reported LOW_ZNCC and starts no neighbour. 0.9 suits speckle images of ordinary
            quality; raise it to stop propagation at damaged texture sooner, lower it for
            noisy or low-contrast images.

    Returns:
        `ICGNResult` over the n prepared points, in their order. Tried points carry IC-GN's
        estimate, ZNCC, iterations and status (LOW_ZNCC in place of CONVERGED below
        `min_zncc`); points never tried have status NOT_REACHED, NaN values and ZNCC, and 0
        iterations. `result.ok()` marks the accepted points.
    """
    points = icgn.points
    n = points.shape[0]
    graph = neighbours if isinstance(neighbours, Neighbours) else Neighbours.from_lists(neighbours)
    if len(graph) != n:
        raise ValueError(f"neighbours cover {len(graph)} points, the ICGN has {n} prepared")
    front = np.asarray(seeds)
    if front.ndim != 1 or front.size == 0 or not np.issubdtype(front.dtype, np.integer):
        raise ValueError(f"seeds must be a non-empty 1-D integer array, got {front.shape}")
    front = front.astype(np.int64)
    if front.min() < 0 or front.max() >= n or np.unique(front).size != front.size:
        raise ValueError(f"seeds must be distinct indices in [0, {n})")
    start = np.asarray(seed_guesses, dtype=np.float64)
    if start.shape not in ((front.size, 2), (front.size, 6)):
        raise ValueError(
            f"seed_guesses must have shape ({front.size}, 2) or ({front.size}, 6), "
            f"got {start.shape}"
        )
    if not -1.0 <= min_zncc <= 1.0:
        raise ValueError(f"min_zncc must lie in [-1, 1], got {min_zncc}")
    prepared = target if isinstance(target, PreparedTarget) else icgn.prepare_target(target)

    values = np.full((n, 6), np.nan)
    zncc = np.full(n, np.nan)
    iterations = np.zeros(n, dtype=np.int32)
    status = np.full(n, PointStatus.NOT_REACHED, dtype=np.int8)
    guesses = np.zeros((front.size, 6))
    guesses[:, : start.shape[1]] = start
    while front.size:
        result = icgn.compute(prepared, guesses, indices=front)
        converged = result.ok()
        accepted = converged & (result.zncc >= min_zncc)
        values[front] = np.c_[result.u, result.v, result.ux, result.uy, result.vx, result.vy]
        zncc[front] = result.zncc
        iterations[front] = result.iterations
        status[front] = np.where(converged & ~accepted, PointStatus.LOW_ZNCC, result.status)
        front, parents = _next_wave(graph, front[accepted], zncc, status)
        guesses = _predict(values[parents], points[front] - points[parents])
    return ICGNResult(
        u=values[:, 0].copy(),
        v=values[:, 1].copy(),
        ux=values[:, 2].copy(),
        uy=values[:, 3].copy(),
        vx=values[:, 4].copy(),
        vy=values[:, 5].copy(),
        zncc=zncc,
        iterations=iterations,
        status=status,
    )


def _next_wave(
    graph: Neighbours, accepted: np.ndarray, zncc: np.ndarray, status: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Untried neighbours of the accepted points (ascending) and the best parent of each."""
    starts = graph.offsets[accepted]
    counts = graph.offsets[accepted + 1] - starts
    total = int(counts.sum())
    if total == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty
    skip = np.repeat(starts - np.r_[0, np.cumsum(counts)[:-1]], counts)
    children = graph.targets[skip + np.arange(total)]
    parents = np.repeat(accepted, counts)
    untried = status[children] == PointStatus.NOT_REACHED
    children, parents = children[untried], parents[untried]
    order = np.lexsort((parents, -zncc[parents], children))
    children, parents = children[order], parents[order]
    first = np.r_[True, children[1:] != children[:-1]] if children.size else np.zeros(0, bool)
    return children[first], parents[first]


def _predict(parent: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """(m, 6) first-order predictions from parent rows (u, v, ux, uy, vx, vy) and (dx, dy)."""
    u, v, ux, uy, vx, vy = parent.T
    dx, dy = offset.T
    return np.c_[u + ux * dx + uy * dy, v + vx * dx + vy * dy, ux, uy, vx, vy]
