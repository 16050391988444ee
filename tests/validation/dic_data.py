"""Shared loader and tracking helpers for the validation tests on third-party DIC image sets.

The image sets and their truth tables live outside the repository, in `shared/data/dic` next
to the project checkout (see its README.md); the environment variable `EXTENSOMETER_DIC_DATA`
points elsewhere. A missing data set is a test failure, never a skip: CI always has it.

Only the product's IC-GN (`appliance.dic.icgn.ICGN`) measures anything here. The helpers add
what a test needs around it:

- `refine` runs IC-GN on the window of the two images that holds the subsets of a batch of
  points, so that the many small batches of a propagation do not each pay for the B-spline
  prefilter of a whole frame. The cubic B-spline prefilter is a recursive filter whose
  influence decays by a factor 0.268 per pixel, and the Gaussian pre-filter reaches 4 sigma;
  with `CROP_MARGIN` px of image kept beyond every subset and every guessed position, the
  window changes the result by far less than 1e-6 px.
- `propagate` is a seed-and-propagate (reliability-guided) scheme: starting from seeds with
  known guesses, each wave refines the untried neighbours of the points accepted so far, each
  starting from the first-order prediction of its best (highest ZNCC) accepted neighbour,
  u + ux dx + uy dy, v + vx dx + vy dy, with that neighbour's gradients. IC-GN only needs a
  guess within about half a speckle, which the prediction gives wherever the field is smooth
  on the scale of the point spacing.
- `integer_seed` finds the integer displacement of a single seed point by normalised
  cross-correlation (`cv2.matchTemplate`) over translations and optional pre-warps: test
  scaffolding to start a propagation, never a measured value.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from appliance.dic.icgn import ICGN, ICGNResult

DATA_ENV = "EXTENSOMETER_DIC_DATA"
CROP_MARGIN = 24
"""Pixels of image kept around every subset (and its guessed position) by `refine`."""

_FIELDS = ("u", "v", "ux", "uy", "vx", "vy")
_UNTRIED = -1


def data_dir() -> Path:
    """Root of the third-party DIC data; fails the calling test when it is missing."""
    override = os.environ.get(DATA_ENV)
    if override:
        root = Path(override)
    else:
        root = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "dic"
    if not root.is_dir():
        pytest.fail(
            f"DIC validation data not found at {root}: check out shared/data/dic next to the "
            f"project or set {DATA_ENV} to its location",
            pytrace=False,
        )
    return root


def data_file(*parts: str) -> Path:
    """Path of one file of the data set; fails the calling test when it is missing."""
    path = data_dir().joinpath(*parts)
    if not path.is_file():
        pytest.fail(f"DIC validation file missing: {path}", pytrace=False)
    return path


@functools.cache
def _read_image(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None or image.ndim != 2 or image.dtype != np.uint8:
        pytest.fail(f"{path} is not an 8-bit grey image", pytrace=False)
    data = image.astype(np.float64)
    data.flags.writeable = False
    return data


def load_image(*parts: str) -> np.ndarray:
    """8-bit grey PNG of the data set as a read-only float64 array (H, W), cached."""
    return _read_image(data_file(*parts))


def load_csv(*parts: str, skip_header: int = 0) -> np.ndarray:
    """Numeric comma-separated table of the data set as a 2-D float64 array."""
    return np.loadtxt(data_file(*parts), delimiter=",", skiprows=skip_header, ndmin=2)


def grid_points(xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """(len(ys) * len(xs), 2) points (x, y) of a grid, x fastest."""
    gx, gy = np.meshgrid(np.asarray(xs, dtype=float), np.asarray(ys, dtype=float))
    return np.c_[gx.ravel(), gy.ravel()]


def grid_neighbours(rows: int, columns: int) -> list[np.ndarray]:
    """4-neighbours of every point of a `grid_points` grid with `rows` x `columns` points."""
    index = np.arange(rows * columns).reshape(rows, columns)
    out = []
    for r in range(rows):
        for c in range(columns):
            near = [(r - 1, c), (r + 1, c), (r, c - 1), (r, c + 1)]
            out.append(
                np.array([index[a, b] for a, b in near if 0 <= a < rows and 0 <= b < columns])
            )
    return out


def neighbours_within(points: np.ndarray, radius: float) -> list[np.ndarray]:
    """For every point, the indices of the other points at most `radius` px away."""
    tree = cKDTree(points)
    return [
        np.array([j for j in near if j != i], dtype=int)
        for i, near in enumerate(tree.query_ball_point(points, radius))
    ]


def refine(
    reference: np.ndarray,
    target: np.ndarray,
    points: np.ndarray,
    guess: np.ndarray,
    **icgn,
) -> ICGNResult:
    """IC-GN of `points` with `guess` (n, 2) or (n, 6), on the image window holding them.

    `icgn` are the keyword arguments of `ICGN`. The result is the same as that of
    `ICGN.prepare(reference, points)` and `ICGN.compute(target, guess)` on the whole images
    (see the module docstring for why the window does not matter).
    """
    solver = ICGN(**icgn)
    points = np.asarray(points, dtype=float)
    guess = np.asarray(guess, dtype=float)
    stretch = np.abs(guess[:, 2:]).max() if guess.shape[1] == 6 else 0.0
    pad = solver.half * (1.0 + stretch) + CROP_MARGIN
    ends = np.r_[points, points + guess[:, :2]]
    height, width = reference.shape
    x0 = max(0, int(np.floor(ends[:, 0].min() - pad)))
    y0 = max(0, int(np.floor(ends[:, 1].min() - pad)))
    x1 = min(width, int(np.ceil(ends[:, 0].max() + pad)) + 1)
    y1 = min(height, int(np.ceil(ends[:, 1].max() + pad)) + 1)
    solver.prepare(reference[y0:y1, x0:x1], points - (x0, y0))
    return solver.compute(target[y0:y1, x0:x1], guess)


def integer_seed(
    reference: np.ndarray,
    target: np.ndarray,
    point: tuple[int, int],
    subset: int,
    radius: int,
    prewarps: tuple[tuple[float, float, float, float], ...] = ((0.0, 0.0, 0.0, 0.0),),
) -> tuple[np.ndarray, float]:
    """Best normalised cross-correlation match of one subset, over translations and pre-warps.

    For every pre-warp (ux, uy, vx, vy) the reference around the integer `point` (x, y) is
    resampled (bilinear) onto a `subset` x `subset` template as it would look in the target
    under that first-order deformation, and searched for in the target within +- `radius` px
    (`cv2.matchTemplate`, TM_CCOEFF_NORMED), the window clipped to the image.

    Returns:
        (6,) guess (u, v, ux, uy, vx, vy) with integer u, v and the best pre-warp's
        gradients, and the best score.
    """
    x, y = point
    h = subset // 2
    height, width = target.shape
    top, left = max(0, y - h - radius), max(0, x - h - radius)
    bottom, right = min(height, y + h + radius + 1), min(width, x + h + radius + 1)
    window = target[top:bottom, left:right].astype(np.float32)
    dy, dx = np.mgrid[-h : h + 1, -h : h + 1].astype(np.float64)
    best = (np.zeros(6), -np.inf)
    for ux, uy, vx, vy in prewarps:
        inverse = np.linalg.inv([[1.0 + ux, uy], [vx, 1.0 + vy]])
        map_x = (x + inverse[0, 0] * dx + inverse[0, 1] * dy).astype(np.float32)
        map_y = (y + inverse[1, 0] * dx + inverse[1, 1] * dy).astype(np.float32)
        template = cv2.remap(reference.astype(np.float32), map_x, map_y, cv2.INTER_LINEAR)
        scores = cv2.matchTemplate(window, template, cv2.TM_CCOEFF_NORMED)
        row, col = np.unravel_index(int(np.argmax(scores)), scores.shape)
        if scores[row, col] > best[1]:
            guess = np.array([left + col + h - x, top + row + h - y, ux, uy, vx, vy], dtype=float)
            best = (guess, float(scores[row, col]))
    return best


def propagate(
    reference: np.ndarray,
    target: np.ndarray,
    points: np.ndarray,
    neighbours: list[np.ndarray],
    seeds: list[int],
    seed_guesses: np.ndarray,
    *,
    min_zncc: float,
    **icgn,
) -> ICGNResult:
    """Seed-and-propagate IC-GN over `points` from one or more seeds (see the module docstring).

    Args:
        reference, target: grey images of equal shape.
        points: (n, 2) reference positions (x, y).
        neighbours: for every point, the indices of the points its result may seed.
        seeds: indices of the first points.
        seed_guesses: (len(seeds), 2) or (len(seeds), 6) guesses for the seeds, as for
            `ICGN.compute`.
        min_zncc: a converged point with a lower ZNCC is not accepted and seeds nothing.
        icgn: keyword arguments of `ICGN`.

    Returns:
        `ICGNResult` over all points, in their order. Points never reached have status -1
        and NaN values; points reached but rejected keep their IC-GN status, except that a
        converged point below `min_zncc` is reported DIVERGED (4).
    """
    n = len(points)
    values = {name: np.full(n, np.nan) for name in (*_FIELDS, "zncc")}
    iterations = np.zeros(n, dtype=np.int32)
    status = np.full(n, _UNTRIED, dtype=np.int8)
    front = np.asarray(seeds, dtype=int)
    start = np.atleast_2d(np.asarray(seed_guesses, dtype=float))
    guesses = np.zeros((len(front), 6))
    guesses[:, : start.shape[1]] = start
    while front.size:
        result = refine(reference, target, points[front], guesses, **icgn)
        good = result.ok() & (result.zncc >= min_zncc)
        for name in (*_FIELDS, "zncc"):
            values[name][front] = getattr(result, name)
        iterations[front] = result.iterations
        status[front] = np.where(result.ok() & ~good, 4, result.status)
        best: dict[int, int] = {}
        for i in front[good]:
            for j in neighbours[i]:
                if status[j] == _UNTRIED and (
                    j not in best or values["zncc"][i] > values["zncc"][best[j]]
                ):
                    best[j] = i
        front = np.array(sorted(best), dtype=int)
        parents = np.array([best[j] for j in front], dtype=int)
        d = points[front] - points[parents]
        u, v, ux, uy, vx, vy = (values[name][parents] for name in _FIELDS)
        guesses = np.c_[
            u + ux * d[:, 0] + uy * d[:, 1], v + vx * d[:, 0] + vy * d[:, 1], ux, uy, vx, vy
        ]
    return ICGNResult(**values, iterations=iterations, status=status)
