"""Specimen detection on arbitrary images: random polygons, bars, noise, blank and tiny images
either give a detection with finite figures or are refused with `SpecimenNotFound`, never
anything else; and the random-polygon image that once made the edge search read past the
resampled strip is refused."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from appliance.measure.specimen_detection import SpecimenNotFound, detect_specimen


def _random_image(seed: int) -> np.ndarray:
    """A background with polygons (often running off the image), a bar, or nothing; noise."""
    rng = np.random.default_rng(seed)
    height = int(rng.integers(1, 48)) if seed % 5 == 0 else int(rng.integers(1, 700))
    width = int(rng.integers(1, 700))
    image = np.full((height, width), rng.uniform(0, 255))
    kind = seed % 4
    if kind in (0, 1):
        for _ in range(int(rng.integers(1, 4))):
            corners = rng.uniform(-0.1, 1.1, (int(rng.integers(3, 8)), 2)) * [width, height]
            cv2.fillPoly(image, [corners.astype(np.int32)], float(rng.uniform(0, 255)))
    elif kind == 2:
        x0, x1 = sorted(rng.uniform(-0.1, 1.1, 2) * width)
        y0, y1 = sorted(rng.uniform(-0.1, 1.1, 2) * height)
        image[max(0, int(y0)) : int(y1), max(0, int(x0)) : int(x1)] = rng.uniform(0, 255)
    image += rng.normal(0, rng.uniform(0, 30), image.shape)
    return image.astype(np.float32)


def _detects_or_refuses(image: np.ndarray) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            found = detect_specimen(image)
        except SpecimenNotFound as refusal:
            assert "\n" not in str(refusal)
            return
    assert np.isfinite(found.centre_px).all()
    assert np.isfinite([found.axis_deg, found.width_px, found.parallel_length_px]).all()
    assert 0.0 <= found.axis_deg < 180.0


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 2**32 - 1))
def test_any_image_is_detected_or_refused(seed):
    _detects_or_refuses(_random_image(seed))


@pytest.mark.parametrize(
    "image",
    [
        np.zeros((0, 0)),
        np.zeros((1, 1)),
        np.full((31, 400), 200.0),
        np.full((480, 640), 0.0),
        np.full((480, 640), 255.0),
        np.random.default_rng(1).normal(128, 40, (480, 640)),
        np.random.default_rng(2).uniform(0, 255, (64, 64, 3)),
    ],
    ids=["empty", "one pixel", "31 rows", "black", "white", "noise", "tiny colour noise"],
)
def test_blank_noise_and_tiny_images_are_refused(image):
    with pytest.raises(SpecimenNotFound):
        detect_specimen(image)


def test_the_random_polygon_image_whose_edge_search_left_the_strip_is_refused():
    """The 70th image of this seeded series has an edge whose second search, re-centred on the
    first, reached past the resampled strip's side."""
    rng = np.random.default_rng(3)
    for _ in range(70):
        height, width = int(rng.integers(200, 1400)), int(rng.integers(200, 1400))
        image = np.full((height, width), rng.uniform(0, 255))
        for _ in range(int(rng.integers(1, 4))):
            corners = rng.uniform(0, 1, (int(rng.integers(3, 8)), 2)) * [width, height]
            cv2.fillPoly(image, [corners.astype(np.int32)], float(rng.uniform(0, 255)))
        image += rng.normal(0, rng.uniform(0, 30), image.shape)
    assert image.shape == (230, 491)
    with pytest.raises(SpecimenNotFound, match="touches the image's edge"):
        detect_specimen(image.astype(np.float32))
