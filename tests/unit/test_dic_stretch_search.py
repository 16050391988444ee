"""The LPQ window rule, pre-warped search of a large one-step stretch, the blur seen from the
reference, and the automatic search choice."""

import math

import numpy as np
import pytest

from appliance.dic.integer_search import zncc_search
from appliance.dic.lpq import LPQParams, max_invariant_line_blur, window_for_blur
from appliance.dic.search_choice import choose_search, explicit_search
from appliance.dic.stretch import blur_in_reference, stretch_prewarps
from appliance.dic.synthetic import AffineMapping, add_gaussian_noise, gaussian_speckle, render


@pytest.mark.parametrize(
    ("length", "angle", "subset", "window"),
    [
        (0.0, 0.0, 41, 7),
        (2.0, 0.0, 41, 7),
        (4.0, 0.0, 41, 13),
        (10.0, 0.0, 41, 31),
        (10.0, 90.0, 41, 31),
        (10.0, 45.0, 61, 43),
        (15.0, 0.0, 41, 41),
        (10.0, 0.0, 21, 21),
    ],
)
def test_window_for_blur_is_three_blur_lengths_rounded_up_to_odd_and_capped(
    length, angle, subset, window
):
    assert window_for_blur(length, angle, subset=subset) == window


@pytest.mark.parametrize("angle", [0.0, 30.0, 45.0, 90.0, 135.0])
def test_window_for_blur_keeps_the_blur_inside_the_invariance_bound(angle):
    for length in (3.0, 5.5, 8.0, 12.0):
        window = window_for_blur(length, angle)
        assert window % 2 == 1
        assert length < max_invariant_line_blur(LPQParams(window=window), angle)


def test_blur_in_reference_shortens_a_blur_along_a_stretch():
    length, angle = blur_in_reference(10.0, 0.0, (1 / 3, 0.0, 0.0, -0.134))
    assert length == pytest.approx(7.5)
    assert angle == pytest.approx(0.0)
    length, angle = blur_in_reference(6.0, 90.0, (0.0, 0.0, 0.0, 0.5))
    assert length == pytest.approx(4.0)
    assert angle == pytest.approx(90.0)
    assert blur_in_reference(8.0, 30.0, (0.0, 0.0, 0.0, 0.0)) == pytest.approx((8.0, 30.0))


def test_stretch_prewarps_span_the_range_with_incompressible_contraction():
    warps = stretch_prewarps(0.0, 0.5)
    assert len(warps) == 11
    assert warps[0] == pytest.approx([0, 0, 0, 0])
    assert warps[-1] == pytest.approx([0.5, 0, 0, 1.5**-0.5 - 1])
    along_y = stretch_prewarps(0.3, 0.42, axis="y")
    assert along_y[:, 3] == pytest.approx([0.3, 0.35, 0.4, 0.42])
    assert (1 + along_y[:, 0]) ** 2 * (1 + along_y[:, 3]) == pytest.approx(np.ones(4))


def test_prewarped_search_finds_a_40_percent_stretch_that_plain_zncc_misses():
    width, height = 480, 320
    pattern = gaussian_speckle(width, height, count=900, radius=4.0, seed=5)
    stretch = 0.4
    mapping = AffineMapping(
        u=12.0, v=3.0, ux=stretch, vy=(1 + stretch) ** -0.5 - 1, xc=width / 2, yc=height / 2
    )
    reference = add_gaussian_noise(render(pattern, height, width), 2.0, seed=1)
    target = add_gaussian_noise(render(pattern, height, width, mapping), 2.0, seed=2)
    ys, xs = np.mgrid[120:201:20, 180:301:20]
    points = np.c_[xs.ravel(), ys.ravel()].astype(float)
    x, y = mapping.forward(points[:, 0], points[:, 1])
    true = np.c_[x - points[:, 0], y - points[:, 1]]

    def found(**options) -> float:
        match = zncc_search(reference, target, points, subset=41, radius=50, **options)
        hit = match.valid & np.all(np.abs(match.displacement - true) <= 1.0, axis=1)
        return float(hit.mean())

    assert found() < 0.5
    assert found(prewarps=stretch_prewarps(0.0, 0.5)) >= 0.95


def test_the_automatic_choice_matches_the_blur_and_says_why():
    choice = choose_search(blur_px=10.0, stretch=None)
    assert choice.method == "zncc"
    assert choice.reference_blur_px == 10.0
    assert choice.prewarps is None and choice.recover
    assert "10 px" in choice.reason
    told = choose_search(blur_px=0.0, stretch=(0.3, 0.45), stretch_axis="y")
    assert len(told.prewarps) == 4 and told.stretch_axis == "y"
    assert told.describe()["prewarps"] == 4


def test_an_explicit_lpq_search_takes_the_rules_window_unless_given():
    assert explicit_search("lpq", blur_px=10.0).lpq_window == 31
    assert explicit_search("lpq", blur_px=10.0, lpq_window=21).lpq_window == 21
    assert explicit_search("lpq", blur_px=20.0, subset=41).lpq_window == 41
    assert explicit_search("zncc", blur_px=10.0).lpq_window is None
    assert math.isclose(explicit_search("zncc", blur_px=3.0).reference_blur_px, 3.0)
