"""Painted dots: found in the reference frame at their true centres, refused when missing or
doubled, followed to sub-pixel, and flagged lost (not guessed) when a dot merges with a
reflection, leaves the view or loses its contrast."""

from __future__ import annotations

import numpy as np
import pytest

from appliance.measure.painted_marks import DotSettings, PaintedMarksNotFound, find_dots
from appliance.measure.painted_marks_tracker import PaintedDotTracker
from appliance.measure.tracking import TrackStatus
from appliance.sim.world import PRESETS, SimWorld
from hal.camera.base import Region

SPECKLE = 125.0
PAINT = 245.0


def _speckled(shape=(200, 300), seed=3):
    """A mid-grey speckle of 1-px grain and +-40 grey levels."""
    rng = np.random.default_rng(seed)
    return SPECKLE + rng.uniform(-40.0, 40.0, shape)


def _paint_dot(image, centre, radius=(7.0, 7.0), level=PAINT):
    """A white ellipse of semi-axes `radius` (x, y) px at `centre`, its edge anti-aliased by
    8x8 sub-pixel sampling."""
    rows, cols = image.shape
    sub = (np.arange(8) + 0.5) / 8 - 0.5
    yy, xx = np.mgrid[0:rows, 0:cols]
    cover = np.zeros(image.shape)
    for dy in sub:
        for dx in sub:
            u = (xx + dx - centre[0]) / radius[0]
            v = (yy + dy - centre[1]) / radius[1]
            cover += (u * u + v * v <= 1.0) / 64.0
    image += cover * (level - image)
    return image


def _two_dots(centres=((60.3, 50.2), (59.6, 150.7)), seed=3, **kwargs):
    image = _speckled(seed=seed)
    for centre in centres:
        _paint_dot(image, centre, **kwargs)
    return image


def test_dots_rendered_by_the_simulator_are_found_at_their_true_centres():
    world = SimWorld(PRESETS["rubber"], painted_marks="dots", sensor_size=(256, 640), seed=4)
    scene = world.scene
    image, _ = scene.render(0.0, 0.0, Region(0, 0, scene.sensor_width, scene.sensor_height))
    image += np.random.default_rng(1).normal(0.0, 1.0, image.shape)
    half = 0.5 * world.gauge_length_mm
    truth = scene.image_positions(np.array([[0.0, -half], [0.0, half]]), 0.0, 0.0)
    first, second = find_dots(image)
    found = np.array([first.centre_px, second.centre_px])
    assert np.abs(found - truth).max() < 0.25
    assert abs(found[1, 1] - found[0, 1] - (truth[1, 1] - truth[0, 1])) < 0.1
    assert first.fill == pytest.approx(1.0, abs=0.1)


def test_a_translated_dot_is_followed_to_a_small_fraction_of_a_pixel():
    reference = _two_dots()
    first, second = find_dots(reference)
    tracker = PaintedDotTracker(reference, [first.centre_px, second.centre_px], [(0,), (1,)])
    moved = _two_dots(((60.3, 50.2 - 1.37), (59.6, 150.7 + 2.61)))
    frame = tracker.track(moved, 0.1)
    assert (frame.status == TrackStatus.TRACKED).all() and frame.marks_lost == 0
    shift = frame.positions - np.array([first.centre_px, second.centre_px])
    assert shift[:, 1] == pytest.approx([-1.37, 2.61], abs=0.1)
    assert np.abs(shift[:, 0]).max() < 0.1


def test_a_stretched_dot_becomes_an_ellipse_and_is_still_followed():
    reference = _two_dots()
    first, second = find_dots(reference)
    tracker = PaintedDotTracker(reference, [first.centre_px, second.centre_px], [(0,), (1,)])
    for step, stretch in enumerate((1.2, 1.4, 1.6), start=1):
        centres = ((60.3, 100.45 - 50.25 * stretch), (59.6, 100.45 + 50.25 * stretch))
        image = _two_dots(centres, radius=(7.0 / stretch**0.5, 7.0 * stretch))
        frame = tracker.track(image, 0.1 * step)
        assert frame.marks_lost == 0, stretch
        length = frame.positions[1, 1] - frame.positions[0, 1]
        assert length == pytest.approx(100.5 * stretch, abs=0.25)


@pytest.mark.parametrize(
    ("centres", "message"),
    [
        ((), r"^no painted dot found"),
        (((60.0, 50.0),), r"^painted dots missing: 1 found .* at \(60, 50\) px"),
        (
            ((60.0, 40.0), (60.0, 100.0), (60.0, 160.0)),
            r"^painted dots doubled: 3 found .*\(60, 40\) px.*\(60, 100\) px.*\(60, 160\) px",
        ),
    ],
)
def test_missing_or_doubled_dots_are_refused_naming_what_was_seen(centres, message):
    image = _speckled()
    for centre in centres:
        _paint_dot(image, centre)
    with pytest.raises(PaintedMarksNotFound, match=message):
        find_dots(image)


def _tracker_and_reference():
    reference = _two_dots()
    first, second = find_dots(reference)
    points = [first.centre_px, second.centre_px]
    return PaintedDotTracker(reference, points, [(0,), (1,)]), np.array(points)


def test_a_dot_that_merges_with_a_reflection_is_lost_not_guessed_and_found_again():
    tracker, points = _tracker_and_reference()
    merged = _two_dots()
    merged[40:62, 60:90] = PAINT
    frame = tracker.track(merged, 0.1)
    assert list(frame.status) == [TrackStatus.LOST, TrackStatus.TRACKED]
    assert frame.marks_lost == 1
    assert np.allclose(frame.positions[0], points[0])
    again = tracker.track(_two_dots(), 0.2)
    assert again.marks_lost == 0
    assert np.abs(again.positions - points).max() < 0.05


def test_a_dot_that_leaves_the_view_is_lost():
    tracker, points = _tracker_and_reference()
    frame = tracker.track(_two_dots(((60.3, 50.2), (59.6, 196.0))), 0.1)
    assert list(frame.status) == [TrackStatus.TRACKED, TrackStatus.LOST]


def test_a_dot_that_loses_its_contrast_is_lost():
    tracker, _ = _tracker_and_reference()
    faded = _speckled()
    _paint_dot(faded, (60.3, 50.2))
    _paint_dot(faded, (59.6, 150.7), level=SPECKLE + 45.0)
    frame = tracker.track(faded, 0.1)
    assert list(frame.status) == [TrackStatus.TRACKED, TrackStatus.LOST]


def test_the_tracker_reads_only_the_windows_it_reports():
    tracker, _ = _tracker_and_reference()
    moved = _two_dots(((60.3, 51.0), (59.6, 151.5)))
    expected = tracker.track(moved, 0.1)
    again, _ = _tracker_and_reference()
    blanked = np.zeros_like(moved)
    for region in expected.read_regions:
        window = (
            slice(region.y, region.y + region.height),
            slice(region.x, region.x + region.width),
        )
        blanked[window] = moved[window]
    frame = again.track(blanked, 0.1)
    assert np.array_equal(frame.positions, expected.positions)


def test_lines_rendered_by_the_simulator_are_found_at_their_true_rows():
    world = SimWorld(PRESETS["rubber"], painted_marks="lines", seed=4)
    scene = world.scene
    image, _ = scene.render(0.0, 0.0, Region(0, 0, scene.sensor_width, scene.sensor_height))
    image += np.random.default_rng(1).normal(0.0, 1.0, image.shape)
    half = 0.5 * world.gauge_length_mm
    truth = scene.image_positions(np.array([[0.0, -half], [0.0, half]]), 0.0, 0.0)
    first, second = find_dots(image, DotSettings(kind="lines"))
    rows = np.array([first.centre_px[1], second.centre_px[1]])
    assert np.abs(rows - truth[:, 1]).max() < 0.25


def test_a_line_is_placed_by_its_edges_and_followed_as_it_stretches():
    def band(top, bottom, seed=3):
        image = _speckled((200, 400), seed=seed)
        rows = np.arange(image.shape[0])[:, np.newaxis]
        cover = np.clip(np.minimum(rows + 0.5 - top, bottom - rows + 0.5), 0.0, 1.0)
        cover = cover * (np.abs(np.arange(image.shape[1]) - 60) < 15)
        image += cover * (PAINT - image)
        return image

    def two_bands(first, second):
        image = band(*first)
        lower = band(*second, seed=3)
        image[100:] = lower[100:]
        return image

    lines = DotSettings(kind="lines")
    reference = two_bands((40.3, 52.1), (140.6, 152.8))
    first, second = find_dots(reference, lines)
    assert first.centre_px[1] == pytest.approx(46.2, abs=0.1)
    assert second.centre_px[1] == pytest.approx(146.7, abs=0.1)
    tracker = PaintedDotTracker(
        reference, [first.centre_px, second.centre_px], [(0,), (1,)], dots=lines
    )
    frame = tracker.track(two_bands((37.1, 51.3), (141.9, 156.2)), 0.1)
    assert frame.marks_lost == 0
    assert frame.positions[:, 1] == pytest.approx([44.2, 149.05], abs=0.1)


def test_missing_lines_are_refused_naming_lines():
    image = _speckled()
    _paint_dot(image, (60.0, 50.0), radius=(25.0, 6.0))
    with pytest.raises(PaintedMarksNotFound, match=r"^painted lines missing: 1 found"):
        find_dots(image, DotSettings(kind="lines"))
