"""Thin-lens optics (Zhang et al. 2016, Eq. 7-8): lens law, magnification, scale."""

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from appliance.plan.optics import Optics


@given(
    focal=st.floats(1.0, 500.0),
    extra=st.floats(0.01, 1e4),
    pixel=st.floats(0.5, 50.0),
)
def test_the_image_distance_satisfies_the_lens_law(focal, extra, pixel):
    optics = Optics(focal, focal + extra, pixel)
    u, v = optics.object_distance_mm, optics.image_distance_mm
    assert 1 / u + 1 / v == pytest.approx(1 / focal, rel=1e-9)
    assert optics.magnification == pytest.approx(v / u, rel=1e-12)
    assert optics.magnification == pytest.approx(focal / (u - focal), rel=1e-9)


def test_known_values():
    optics = Optics(50.0, 300.0, 5.2)
    assert optics.image_distance_mm == pytest.approx(60.0)
    assert optics.magnification == pytest.approx(0.2)
    assert optics.scale_mm_per_px == pytest.approx(0.026)
    assert optics.image_um(1.0) == pytest.approx(200.0)
    assert optics.image_px(1.0) == pytest.approx(200.0 / 5.2)


def test_unit_magnification_at_twice_the_focal_length():
    optics = Optics(25.0, 50.0, 4.0)
    assert optics.image_distance_mm == pytest.approx(50.0)
    assert optics.magnification == pytest.approx(1.0)
    assert optics.scale_mm_per_px == pytest.approx(0.004)


def test_scale_and_image_size_are_inverse():
    optics = Optics(35.0, 700.0, 3.45)
    assert optics.image_px(optics.scale_mm_per_px) == pytest.approx(1.0)
    assert optics.image_px(10.0) * optics.scale_mm_per_px == pytest.approx(10.0)


@pytest.mark.parametrize(
    ("args", "name"),
    [
        ((0.0, 300.0, 5.2), "focal_length_mm"),
        ((-50.0, 300.0, 5.2), "focal_length_mm"),
        ((math.nan, 300.0, 5.2), "focal_length_mm"),
        ((50.0, 0.0, 5.2), "object_distance_mm"),
        ((50.0, math.inf, 5.2), "object_distance_mm"),
        ((50.0, 300.0, 0.0), "pixel_size_um"),
        ((50.0, 300.0, -1.0), "pixel_size_um"),
    ],
)
def test_bad_values_are_refused_by_name(args, name):
    with pytest.raises(ValueError, match=name):
        Optics(*args)


@pytest.mark.parametrize("distance", [50.0, 20.0])
def test_an_object_inside_the_focal_length_gives_no_real_image(distance):
    with pytest.raises(ValueError, match="object_distance_mm .* must exceed focal_length_mm"):
        Optics(50.0, distance, 5.2)
