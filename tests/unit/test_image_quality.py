"""Whether an image can be measured: speckle under a mark, and a whole camera view."""

import numpy as np

from appliance.dic import synthetic
from appliance.measure.image_quality import speckle_problem, view_quality, window_quality


def _speckle(size: int = 41) -> np.ndarray:
    pattern = synthetic.dense_speckle(size, size, seed=3, radius=2.5)
    return np.clip(synthetic.render(pattern, size, size), 0, 255)


def test_a_speckle_is_fit_and_flat_noisy_ramped_or_burnt_windows_are_not():
    rng = np.random.default_rng(1)
    assert speckle_problem(_speckle(), 255) is None
    flat_noise = 128 + rng.normal(0, 2, (41, 41))
    assert speckle_problem(flat_noise, 255).startswith("no contrast")
    ramp = np.add.outer(np.arange(41.0), np.arange(41.0)) * 3
    assert speckle_problem(ramp, 255).startswith("no sharp speckle")
    burnt = np.minimum(_speckle() * 4, 255)
    assert "saturated" in speckle_problem(burnt, 255)
    blurred = synthetic.render(synthetic.dense_speckle(41, 41, seed=3, radius=12.0), 41, 41)
    assert speckle_problem(blurred, 255) is not None


def test_figures_are_fractions_of_full_scale_whatever_the_bit_depth():
    eight = window_quality(_speckle(), 255)
    twelve = window_quality(_speckle() * 4095 / 255, 4095)
    assert np.isclose(eight.mean_gradient, twelve.mean_gradient)
    assert np.isclose(eight.contrast, twelve.contrast)


def test_a_view_is_judged_by_its_sharpest_tiles_so_a_narrow_specimen_is_fit():
    view = np.zeros((512, 512))
    view[:, 240:280] = _speckle(512)[:, 240:280]
    fit = view_quality(view, 255)
    assert fit.problems == () and fit.whole.mean_grey < 0.1
    dark = view_quality(np.zeros((128, 128)), 255)
    assert any(p.startswith("too dark") for p in dark.problems)
    assert any(p.startswith("no sharp texture") for p in dark.problems)
    over = view_quality(np.full((128, 128), 255.0), 255)
    assert any(p.startswith("overexposed") for p in over.problems)
