"""Shared loader and tracking helper for the validation tests on third-party DIC image sets.

The image sets and their truth tables live outside the repository, in `shared/data/dic` next
to the project checkout (see its README.md); the environment variable `EXTENSOMETER_DIC_DATA`
points elsewhere. A missing data set is a test failure, never a skip: CI always has it.

Only the product measures anything here: `seed_and_propagate` chains its three parts on whole
images, as an application would,

- `appliance.dic.icgn.ICGN`, prepared once on the reference and the points (and once on the
  target, inside the propagation);
- `appliance.dic.integer_search.zncc_search`, the integer displacement (and, with pre-warps,
  the first-order deformation) of the seed points by normalised cross-correlation;
- `appliance.dic.propagation.propagate`, reliability-guided seed-and-propagate from the seeds
  over a neighbour structure (`appliance.dic.propagation.Neighbours`): each wave refines the
  untried neighbours of the points accepted so far, each starting from the first-order
  prediction of its best (highest ZNCC) accepted neighbour, u + ux dx + uy dy,
  v + vx dx + vy dy, with that neighbour's gradients.

The rest is loading: images, tables and the grids of points.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import pytest

from appliance.dic.icgn import ICGN, ICGNResult
from appliance.dic.integer_search import zncc_search
from appliance.dic.propagation import Neighbours, propagate

DATA_ENV = "EXTENSOMETER_DIC_DATA"


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


def seed_and_propagate(
    reference: np.ndarray,
    target: np.ndarray,
    points: np.ndarray,
    neighbours: Neighbours,
    seeds: Sequence[int],
    *,
    search_radius: int,
    prewarps: Sequence[tuple[float, float, float, float]] | None = None,
    min_zncc: float,
    **icgn,
) -> ICGNResult:
    """Track `points` from `reference` to `target` with the product, from integer-searched seeds.

    Args:
        reference, target: grey images of equal shape.
        points: (n, 2) reference positions (x, y), px.
        neighbours: the propagation's neighbour structure over the points.
        seeds: indices of the points searched for and refined first.
        search_radius: half width of the seeds' ZNCC search window, px.
        prewarps: (ux, uy, vx, vy) deformations tried by the seed search; None = translation.
        min_zncc: a converged point with a lower ZNCC is rejected and starts no neighbour.
        icgn: keyword arguments of `ICGN`; the seed search uses the same subset.

    Returns:
        `ICGNResult` over all points, in their order (`appliance.dic.propagation.propagate`).
    """
    solver = ICGN(**icgn)
    solver.prepare(reference, points)
    seeds = np.asarray(seeds, dtype=int)
    found = zncc_search(
        reference,
        target,
        solver.points[seeds],
        subset=solver.subset,
        radius=search_radius,
        prewarps=prewarps,
    )
    if not found.valid.all():
        pytest.fail(f"seed search failed at points {solver.points[seeds][~found.valid]}")
    guesses = np.c_[found.displacement, found.gradient]
    return propagate(solver, target, neighbours, seeds, guesses, min_zncc=min_zncc)
