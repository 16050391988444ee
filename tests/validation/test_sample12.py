"""DIC Challenge 1.0 Sample 12: open-hole tension of a CFRP plate, against DICe and OpenCorr.

No truth: the references are two independent DIC codes run on the same images (README), which
agree with each other to a median of 0.002 px (u) and 0.005 px (v) on frame 04.

- OpenCorr (`opencorr/frame04_fftcc_icgn1_r16.csv`): FFT-CC then first-order IC-GN, subset 33,
  frame 00 -> 04, 1200 points on a 10 px grid, in the coordinates of a crop: image (x, y) =
  CSV (x + 49, y + 69); displacements unchanged.
- DICe (`dice/DICe_solution_NN.txt`): ZNSSD, subset 27, step 35, Keys fourth-order
  interpolation, shape functions translation plus normal strain; frames 00 -> 04, 08, 11. The
  file has a 20-line `***` header, then a line of column names, then x, y, u, v, strains and
  match per point.

Each comparison runs the product's IC-GN at that code's own points with that code's subset
size and, like both codes, on the raw images (no pre-filter), so that the comparison is like
for like. Points whose subset reaches the hole or leaves the specimen are skipped, the specimen
and the hole being the DICe region of interest (`dice/roi_subset_file.dat`: a 313 x 977 px
rectangle centred at (195, 517) and an excluded circle of radius 51 px at (194, 543)), with
2 px of extra clearance from the hole's edge. Guesses come from one seed found by the product's
normalised cross-correlation search (`zncc_search`, +-20 px) and its seed-and-propagate from
neighbours within 1.01 grid spacings (`appliance.dic.propagation`); frame 11 has v up to
-12 px.

Tolerance: median |difference| <= 0.01 px for u and for v separately, the README's "0.005 to
0.01 px is realistic" upper end (two codes of the same family agree to 0.002 to 0.005 px).
"""

import re

import numpy as np
import pytest

from appliance.dic.propagation import Neighbours
from tests.validation import dic_data

TOLERANCE = 0.01
HOLE_CLEARANCE = 2.0
OPENCORR_SUBSET = 33
DICE_SUBSET = 27


def _roi() -> tuple[tuple[float, float, float, float], tuple[float, float, float]]:
    """DICe region of interest: (x0, y0, x1, y1) of the rectangle and (xc, yc, r) of the hole."""
    text = dic_data.data_file("sample12", "dice", "roi_subset_file.dat").read_text()

    def number(key: str, count: int = 1, after: str = "") -> list[float]:
        start = text.lower().index(after.lower()) if after else 0
        match = re.search(
            rf"^\s*{key}" + r"\s+([-\d.]+)" * count, text[start:], re.IGNORECASE | re.MULTILINE
        )
        assert match, f"roi_subset_file.dat: no {key}"
        return [float(g) for g in match.groups()]

    cx, cy = number("center", 2, "rectangle")
    (width,) = number("width", 1, "rectangle")
    (height,) = number("height", 1, "rectangle")
    hx, hy = number("center", 2, "circle")
    (radius,) = number("radius", 1, "circle")
    rectangle = (cx - width / 2, cy - height / 2, cx + width / 2, cy + height / 2)
    return rectangle, (hx, hy, radius)


def usable(points: np.ndarray, half: int) -> np.ndarray:
    """Points whose square subset lies inside the specimen and clear of the hole."""
    (x0, y0, x1, y1), (hx, hy, radius) = _roi()
    x, y = points[:, 0], points[:, 1]
    inside = (x - half >= x0) & (x + half <= x1) & (y - half >= y0) & (y + half <= y1)
    gap_x = np.maximum(np.abs(x - hx) - half, 0.0)
    gap_y = np.maximum(np.abs(y - hy) - half, 0.0)
    return inside & (np.hypot(gap_x, gap_y) > radius + HOLE_CLEARANCE)


def load_dice(frame: str) -> np.ndarray:
    """DICe solution of frame 00 -> `frame`: columns x, y, u, v, ... after the header."""
    path = dic_data.data_file("sample12", "dice", f"DICe_solution_{frame}.txt")
    lines = path.read_text().splitlines()
    names = next(i for i, line in enumerate(lines) if line.startswith("COORDINATE_X"))
    assert lines[names].split(",")[:4] == [
        "COORDINATE_X",
        "COORDINATE_Y",
        "DISPLACEMENT_X",
        "DISPLACEMENT_Y",
    ]
    return np.loadtxt(lines[names + 1 :], delimiter=",", ndmin=2)


def track(frame: str, points: np.ndarray, subset: int, spacing: float):
    """IC-GN of frame 00 -> `frame` at `points` (a grid of `spacing` px), seeded near y = 250."""
    reference = dic_data.load_image("sample12", "oht_cfrp_00.png")
    target = dic_data.load_image("sample12", f"oht_cfrp_{frame}.png")
    seed = int(np.argmin(np.hypot(points[:, 0] - 195, points[:, 1] - 250)))
    return dic_data.seed_and_propagate(
        reference,
        target,
        points,
        Neighbours.within(points, 1.01 * spacing),
        [seed],
        search_radius=20,
        min_zncc=0.9,
        subset=subset,
    )


def assert_medians(label: str, result, u_ref: np.ndarray, v_ref: np.ndarray, figures) -> None:
    ok = result.ok()
    assert ok.mean() >= 0.95, f"{label}: only {ok.sum()} of {ok.size} points tracked"
    du = np.median(np.abs(result.u[ok] - u_ref[ok]))
    dv = np.median(np.abs(result.v[ok] - v_ref[ok]))
    figures.record(f"{label}: median |du|, px, {ok.sum()} points", du, f"<= {TOLERANCE}")
    figures.record(f"{label}: median |dv|, px, {ok.sum()} points", dv, f"<= {TOLERANCE}")
    assert du <= TOLERANCE and dv <= TOLERANCE, (
        f"{label}: median |du| {du:.4f} px, |dv| {dv:.4f} px over {ok.sum()} points"
    )


def test_frame04_agrees_with_opencorr(figures):
    """Frame 04: median |difference| to OpenCorr <= 0.01 px in u and in v.

    Compared at 1030 of OpenCorr's 1200 points (the other 170 have subsets reaching the hole;
    OpenCorr reports displacements of several px there), subset 33 as OpenCorr.
    """
    table = dic_data.load_csv("sample12", "opencorr", "frame04_fftcc_icgn1_r16.csv", skip_header=1)
    points = table[:, :2] + (49.0, 69.0)
    keep = usable(points, OPENCORR_SUBSET // 2)
    assert keep.sum() >= 1000, f"only {keep.sum()} OpenCorr points usable"
    result = track("04", points[keep], OPENCORR_SUBSET, spacing=10.0)
    assert_medians("OpenCorr frame 04", result, table[keep, 2], table[keep, 3], figures)


@pytest.mark.parametrize("frame", ["04", "08", "11"])
def test_agrees_with_dice(frame, figures):
    """Frames 04, 08, 11: median |difference| to DICe <= 0.01 px in u and in v.

    Compared at 203 of DICe's 230 points, subset 27 as DICe: the other 27 form the column
    x = 341, whose subsets reach past the specimen's right edge (x = 351.5); none reaches the
    hole.
    """
    table = load_dice(frame)
    points = table[:, :2]
    keep = usable(points, DICE_SUBSET // 2)
    assert keep.sum() >= 200, f"only {keep.sum()} DICe points usable"
    result = track(frame, points[keep], DICE_SUBSET, spacing=35.0)
    assert_medians(f"DICe frame {frame}", result, table[keep, 2], table[keep, 3], figures)
