"""The set-up figures of a live frame: focus, exposure, and the speckle in the gauge's subsets."""

import math

import numpy as np
import pytest

from appliance.dic import synthetic
from appliance.measure.image_quality import view_quality
from appliance.measure.speckle_quality import (
    focus_gradient,
    frame_quality,
    speckle_size_px,
    subset_quality,
)


def _speckle(width: int, height: int, radius: float, seed: int = 3) -> np.ndarray:
    pattern = synthetic.dense_speckle(width, height, seed=seed, radius=radius)
    return np.clip(synthetic.render(pattern, height, width), 0, 255)


@pytest.mark.parametrize("shape", [(300, 200), (517, 389)])
def test_focus_is_the_camera_checks_sharpest_tiles_gradient(shape):
    rng = np.random.default_rng(4)
    image = np.zeros(shape)
    image[40:200, 60:150] = _speckle(90, 160, 2.5)
    image += rng.normal(0, 1.5, shape)
    expected = view_quality(image, 255).sharpest_gradient * 255
    assert focus_gradient(image, 255) == pytest.approx(expected, rel=1e-12)
    assert focus_gradient(image * 4095 / 255, 4095) == pytest.approx(expected, rel=1e-12)


def test_focus_falls_as_the_speckle_blurs():
    sharp = _speckle(256, 256, 2.0)
    blurred = _speckle(256, 256, 6.0)
    assert focus_gradient(blurred, 255) < 0.5 * focus_gradient(sharp, 255)


def test_speckle_size_is_the_spots_width_at_half_maximum():
    small = speckle_size_px(_speckle(400, 400, 2.0)[100:141, 100:141])
    coarse_field = _speckle(400, 400, 4.0)
    windows = [coarse_field[y : y + 41, x : x + 41] for y in (50, 150, 250) for x in (50, 250)]
    coarse = speckle_size_px(windows)
    assert small == pytest.approx(2 * 2.0 * math.sqrt(math.log(2)), rel=0.1)
    assert coarse == pytest.approx(2 * 4.0 * math.sqrt(math.log(2)), rel=0.2)
    assert coarse > 1.6 * small
    assert math.isnan(speckle_size_px(np.full((41, 41), 100.0)))


def test_subset_gradients_of_a_plane_are_exact():
    a, b = 3.0, 0.5
    y, x = np.mgrid[0:200, 0:300].astype(np.float64)
    image = a * x + b * y
    q = subset_quality(image, [(100, 80), (150.4, 120.6)], 21, 255)
    assert q is not None and q.subsets == 2 and q.subset_px == 21
    assert q.mean_intensity_gradient == pytest.approx(math.hypot(a, b), rel=1e-12)
    assert q.sssig == pytest.approx(b * b * 21 * 21, rel=1e-12)
    twelve = subset_quality(image * 4095 / 255, [(100, 80)], 21, 4095)
    assert twelve.sssig == pytest.approx(q.sssig, rel=1e-12)


def test_subsets_beyond_the_image_are_left_out():
    image = _speckle(120, 100, 2.5)
    inside = subset_quality(image, [(60, 50), (5, 50), (60, 95), (math.nan, 3)], 41, 255)
    assert inside is not None and inside.subsets == 1
    assert subset_quality(image, [(5, 5), (118, 50)], 41, 255) is None
    assert inside.speckles_per_subset == pytest.approx(41 / inside.speckle_size_px)


def test_a_finer_speckle_has_more_gradient_in_its_subsets():
    fine = subset_quality(_speckle(200, 200, 2.0), [(100, 100)], 41, 255)
    coarse = subset_quality(_speckle(200, 200, 5.0), [(100, 100)], 41, 255)
    assert fine.mean_intensity_gradient > 1.5 * coarse.mean_intensity_gradient
    assert fine.sssig > 2 * coarse.sssig


def test_exposure_fractions_and_grey_on_the_eight_bit_scale():
    image = np.full((100, 100), 2048, dtype=np.uint16)
    image[:10, :] = 4095
    image[10:15, :] = 0
    q = frame_quality(image, 4095, [(50, 50)], 21)
    assert q.saturated_fraction == pytest.approx(0.10)
    assert q.dark_fraction == pytest.approx(0.05)
    expected_grey = (10 * 4095 + 85 * 2048) / 100 * 255 / 4095
    assert q.mean_grey == pytest.approx(expected_grey)
    assert q.subsets is not None and q.subsets.sssig == 0.0
