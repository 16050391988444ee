"""`ICGN.prepare_target` releases the GIL and still computes `spline_coefficients`' numbers."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from appliance.dic.bspline import spline_coefficients
from appliance.dic.icgn import ICGN


@pytest.mark.parametrize("sigma", [0.0, 0.8])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32, np.float64])
def test_prepared_coefficients_are_the_spline_filters_bit_for_bit(sigma, dtype):
    rng = np.random.default_rng(5)
    image = (rng.random((90, 130)) * 250).astype(dtype)
    for view in (image, image[7:80:2, 3:120]):
        prepared = ICGN(prefilter_sigma=sigma).prepare_target(view)
        expected = spline_coefficients(view, gaussian_sigma=sigma)
        assert prepared.coefficients.tobytes() == expected.tobytes()


def test_targets_prepared_on_other_threads_refine_to_the_same_numbers():
    rng = np.random.default_rng(9)
    reference = rng.random((120, 120)) * 200
    target = np.roll(reference, (1, 2), axis=(0, 1))
    icgn = ICGN(subset=21, prefilter_sigma=0.8, threads=1)
    points = np.array([[40.0, 40.0], [60.0, 70.0], [80.0, 50.0]])
    icgn.prepare(reference, points)
    prepared = []
    workers = [
        threading.Thread(target=lambda: prepared.append(icgn.prepare_target(target)))
        for _ in range(3)
    ]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join()
    here = icgn.compute(target, np.tile([2.0, 1.0], (3, 1)))
    for other in prepared:
        there = icgn.compute(other, np.tile([2.0, 1.0], (3, 1)))
        for name in ("u", "v", "ux", "uy", "vx", "vy", "zncc", "iterations", "status"):
            np.testing.assert_array_equal(getattr(there, name), getattr(here, name))
