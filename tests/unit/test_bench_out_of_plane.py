"""The out-of-plane measurement's scale fit and its command line."""

import numpy as np

from appliance.bench.out_of_plane import _scale_change, main


def test_the_scale_fit_recovers_a_small_scale_change_whatever_the_translation():
    rng = np.random.default_rng(3)
    before = rng.uniform(-10.0, 10.0, (21, 2))
    after = before * (1.0 - 2.5e-4) + np.array([3.0, -40.0])
    assert abs(_scale_change(before, after, slice(0, 2)) - -2.5e-4) < 1e-12
    assert abs(_scale_change(before, after, slice(0, 1)) - -2.5e-4) < 1e-12


def test_the_scale_fit_across_ignores_a_stretch_along():
    before = np.array([[x, y] for x in (-5.0, 0.0, 5.0) for y in (-2.0, 0.0, 2.0)])
    after = before * np.array([1.0, 1.01])
    assert abs(_scale_change(before, after, slice(0, 1))) < 1e-12
    assert _scale_change(before, after, slice(0, 2)) > 1e-3


def test_an_unknown_material_is_refused_with_exit_2(capsys):
    assert main(["wood"]) == 2
    assert main(["metal", "x"]) == 2
    assert "metal|rubber" in capsys.readouterr().err
