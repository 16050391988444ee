import numpy as np
import pytest

from appliance.dic.correlation import Correlator, PointStatus
from appliance.dic.synthetic import (
    AffineMapping,
    UniaxialStretch,
    dense_speckle,
    motion_blur,
    quantize,
    render,
)

SIZE = 260


@pytest.fixture(scope="module")
def pattern():
    return dense_speckle(SIZE, SIZE, seed=5)


def grid(half=60, step=30):
    c = SIZE // 2
    ys, xs = np.mgrid[c - half : c + half + 1 : step, c - half : c + half + 1 : step]
    return np.c_[xs.ravel(), ys.ravel()].astype(float)


def scene(pattern, mapping, blur=0.0):
    reference = quantize(render(pattern, SIZE, SIZE), 8).astype(float)
    target = render(pattern, SIZE, SIZE, mapping)
    if blur:
        target = motion_blur(target, blur, 0.0)
    points = grid()
    x, y = mapping.forward(points[:, 0], points[:, 1])
    return reference, quantize(target, 8).astype(float), points, x - points[:, 0], y - points[:, 1]


@pytest.mark.parametrize("search", ["zncc", "lpq"])
def test_search_then_refine_finds_a_large_translation(pattern, search):
    reference, target, points, tu, tv = scene(pattern, AffineMapping.translation(12.4, -7.7))
    correlator = Correlator(subset=41, search=search, search_radius=20, lpq_window=11)
    correlator.prepare(reference, points)
    measured = correlator.measure(target)
    assert measured.search is not None and measured.search.valid.all()
    assert np.all(measured.refinement.status == PointStatus.CONVERGED)
    np.testing.assert_allclose(measured.refinement.u, tu, atol=0.01)
    np.testing.assert_allclose(measured.refinement.v, tv, atol=0.01)


def test_without_search_the_guess_seeds_refinement(pattern):
    reference, target, points, tu, tv = scene(pattern, AffineMapping.translation(12.4, -7.7))
    correlator = Correlator(subset=41, search="none")
    correlator.prepare(reference, points)
    lost = correlator.measure(target)
    assert not np.any(np.abs(lost.refinement.u - tu) < 0.01)
    seeded = correlator.measure(target, np.c_[np.round(tu), np.round(tv)])
    assert seeded.search is None
    np.testing.assert_allclose(seeded.refinement.u, tu, atol=0.01)


def test_blur_matched_reference_removes_the_blur_error(pattern):
    reference, target, points, tu, tv = scene(
        pattern, AffineMapping.translation(5.3, 0.4), blur=8.0
    )
    errors = {}
    for blur in (None, (8.0, 0.0)):
        correlator = Correlator(subset=41, reference_blur=blur, search_radius=10)
        correlator.prepare(reference, points)
        result = correlator.measure(target).refinement
        errors[blur] = np.sqrt(np.mean((result.u - tu) ** 2 + (result.v - tv) ** 2))
    assert errors[(8.0, 0.0)] < 0.02
    assert errors[None] > 3 * errors[(8.0, 0.0)]


def test_prewarped_search_carries_a_large_stretch_into_refinement(pattern):
    centre = SIZE / 2
    mapping = UniaxialStretch(1.35, axis="x", xc=centre, yc=centre)
    reference, target, points, tu, tv = scene(pattern, mapping)
    warps = [(e, 0.0, 0.0, (1 + e) ** -0.5 - 1) for e in np.arange(0, 0.51, 0.05)]
    correlator = Correlator(subset=41, search_radius=30, prewarps=warps)
    correlator.prepare(reference, points)
    measured = correlator.measure(target)
    assert np.all(measured.refinement.ok())
    np.testing.assert_allclose(measured.refinement.u, tu, atol=0.02)
    np.testing.assert_allclose(measured.refinement.ux, 0.35, atol=2e-3)
    np.testing.assert_allclose(measured.refinement.vy, 1.35**-0.5 - 1, atol=2e-3)


def test_bad_configuration_is_refused():
    with pytest.raises(ValueError, match="search"):
        Correlator(search="sift")
    with pytest.raises(ValueError, match="search_radius"):
        Correlator(search_radius=-1)
    with pytest.raises(ValueError, match="reference_blur"):
        Correlator(reference_blur=(-2.0, 0.0))
    correlator = Correlator(subset=11)
    with pytest.raises(RuntimeError, match="prepare"):
        correlator.measure(np.zeros((40, 40)))
    correlator.prepare(np.random.default_rng(1).uniform(0, 255, (40, 40)), np.array([[20.0, 20]]))
    with pytest.raises(ValueError, match="guess"):
        correlator.measure(np.zeros((40, 40)), np.zeros((1, 3)))
