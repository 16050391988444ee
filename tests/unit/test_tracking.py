"""Tracking marks over many frames: reference updates, subset shrinking, loss and re-acquisition."""

from __future__ import annotations

import numpy as np
import pytest

from appliance.dic import synthetic
from appliance.measure.frame_windows import cut_windows, paste_windows
from appliance.measure.tracking import MarkTracker, TrackerSettings, TrackStatus

HEIGHT, WIDTH = 640, 200
CENTRE_X = 100.0
POINTS = np.array(
    [[CENTRE_X, 150.0 + 8 * k] for k in range(3)] + [[CENTRE_X, 250.0 + 8 * k] for k in range(3)]
)
MARKS = [(0, 1, 2), (3, 4, 5)]


@pytest.fixture(scope="module")
def pattern() -> synthetic.SpecklePattern:
    return synthetic.dense_speckle(WIDTH, HEIGHT, seed=3, radius=2.5)


def _stretch(lam: float) -> synthetic.UniaxialStretch:
    return synthetic.UniaxialStretch(lam, axis="y", xc=CENTRE_X, yc=100.0)


def _gauge(positions: np.ndarray) -> float:
    return float(positions[3:, 1].mean() - positions[:3, 1].mean())


def test_large_stretch_updates_references_and_keeps_gauge_length(pattern):
    tracker = MarkTracker(
        synthetic.render(pattern, HEIGHT, WIDTH), POINTS, MARKS, TrackerSettings(subset_px=31)
    )
    updates = 0
    for k in range(1, 26):
        mapping = _stretch(1 + 0.04 * k)
        frame = tracker.track(synthetic.render(pattern, HEIGHT, WIDTH, mapping), 0.1 * k)
        x, y = mapping.forward(POINTS[:, 0], POINTS[:, 1])
        truth = np.stack([x, y], axis=1)
        assert np.all(frame.status == TrackStatus.TRACKED)
        assert np.abs(frame.positions - truth).max() < 0.05
        assert abs(_gauge(frame.positions) / _gauge(truth) - 1) < 1e-4
        updates += frame.reference_updates
    assert updates >= 4
    assert tracker.reference_updates == updates
    # lateral stretch at lambda = 2 is 0.71: the subsets shrank with the specimen
    assert all(s < 31 for s in tracker.subsets)
    assert all(s >= 19 for s in tracker.subsets)


def test_prediction_follows_fast_translation_beyond_the_search_radius(pattern):
    settings = TrackerSettings(subset_px=31, search_radius_px=4)
    tracker = MarkTracker(synthetic.render(pattern, HEIGHT, WIDTH), POINTS, MARKS, settings)
    for k in range(1, 12):
        shift = 9.3 * k
        image = synthetic.render(
            pattern, HEIGHT, WIDTH, synthetic.AffineMapping.translation(0.0, -shift)
        )
        frame = tracker.track(image, 0.05 * k)
        assert np.all(frame.measured)
        assert np.abs(frame.positions[:, 1] - (POINTS[:, 1] - shift)).max() < 0.02
    assert np.count_nonzero(frame.status == TrackStatus.TRACKED) == 6


def test_occluded_point_is_estimated_then_reacquired(pattern):
    points = np.array([[CENTRE_X, 150.0], [CENTRE_X, 250.0], [CENTRE_X, 300.0], [CENTRE_X, 350.0]])
    tracker = MarkTracker(
        synthetic.render(pattern, HEIGHT, WIDTH),
        points,
        [(0,), (1, 2, 3)],
        TrackerSettings(subset_px=31),
    )
    mapping = synthetic.AffineMapping.translation(0.0, -2.0)
    image = synthetic.render(pattern, HEIGHT, WIDTH, mapping)
    occluded = image.copy()
    occluded[285:305, 70:131] = 128.0
    frame = tracker.track(occluded, 0.1)
    assert frame.status.tolist() == [TrackStatus.TRACKED] * 2 + [
        TrackStatus.LOST,
        TrackStatus.TRACKED,
    ]
    assert frame.marks_lost == 0
    assert np.hypot(*(frame.positions[2] - (points[2] - [0, 2]))) < 0.05
    frame = tracker.track(synthetic.render(pattern, HEIGHT, WIDTH, mapping), 0.2)
    assert np.all(frame.measured)
    assert np.abs(frame.positions - (points - [0, 2])).max() < 0.02


def test_sudden_jump_is_reacquired_with_the_wider_search(pattern):
    settings = TrackerSettings(subset_px=31, search_radius_px=3, reacquire_radius_px=30)
    tracker = MarkTracker(synthetic.render(pattern, HEIGHT, WIDTH), POINTS, MARKS, settings)
    image = synthetic.render(pattern, HEIGHT, WIDTH, synthetic.AffineMapping.translation(0, 17))
    frame = tracker.track(image, 0.1)
    assert np.all(frame.status == TrackStatus.REACQUIRED)
    assert np.abs(frame.positions - (POINTS + [0, 17])).max() < 0.02


def test_a_mark_with_no_texture_is_lost_and_keeps_its_prediction(pattern):
    tracker = MarkTracker(
        synthetic.render(pattern, HEIGHT, WIDTH), POINTS, MARKS, TrackerSettings(subset_px=31)
    )
    blank = synthetic.render(pattern, HEIGHT, WIDTH)
    blank[200:360] = 100.0
    frame = tracker.track(blank, 0.1)
    assert frame.marks_lost == 1
    assert np.all(frame.status[3:] == TrackStatus.LOST)
    assert np.all(frame.status[:3] == TrackStatus.TRACKED)
    assert np.allclose(frame.positions[3:], POINTS[3:])


@pytest.mark.parametrize(
    "kwargs",
    [
        {"subset_px": 40},
        {"min_subset_px": 51},
        {"search": "ssd"},
        {"search_radius_px": 50, "reacquire_radius_px": 10},
        {"min_zncc": 0.99, "update_zncc": 0.9},
        {"update_deformation": 0.0},
        {"axis": (0.0, 0.0)},
    ],
)
def test_bad_settings_are_refused(kwargs):
    with pytest.raises(ValueError):
        TrackerSettings(**kwargs)


def test_every_point_must_belong_to_one_mark(pattern):
    image = synthetic.render(pattern, 100, 100)
    with pytest.raises(ValueError, match="exactly one mark"):
        MarkTracker(image, POINTS[:2], [(0,), (0, 1)])


def test_frame_dtype_and_layout_do_not_change_the_numbers(pattern):
    """A uint8 frame, the same values as float64 and a view into a larger buffer track alike,
    windows clipped at the edge included."""
    settings = TrackerSettings(subset_px=31)
    points = np.vstack([POINTS, [[CENTRE_X, 20.0]]])
    marks = [*MARKS, (6,)]
    reference = np.rint(synthetic.render(pattern, HEIGHT, WIDTH)).astype(np.uint8)
    trackers = [MarkTracker(reference, points, marks, settings) for _ in range(3)]
    canvas = np.zeros((HEIGHT + 10, WIDTH + 20), dtype=np.uint8)
    for k in range(1, 5):
        mapping = synthetic.UniaxialStretch(1 + 0.03 * k, axis="y", xc=CENTRE_X, yc=40.0)
        image = np.rint(synthetic.render(pattern, HEIGHT, WIDTH, mapping)).astype(np.uint8)
        canvas[5 : 5 + HEIGHT, 7 : 7 + WIDTH] = image
        frames = [
            tracker.track(frame, 0.1 * k)
            for tracker, frame in zip(
                trackers,
                (image, image.astype(np.float64), canvas[5 : 5 + HEIGHT, 7 : 7 + WIDTH]),
                strict=True,
            )
        ]
        assert np.all(frames[0].measured)
        for frame in frames[1:]:
            assert np.array_equal(frame.positions, frames[0].positions)
            assert np.array_equal(frame.gradients, frames[0].gradients)
            assert np.array_equal(frame.zncc, frames[0].zncc)
            assert np.array_equal(frame.status, frames[0].status)
            assert frame.read_regions == frames[0].read_regions
    assert any(r.y == 0 for r in frames[0].read_regions)


def test_the_pixels_read_alone_track_to_the_same_numbers(pattern):
    """Frames rebuilt from the read regions only (zeros elsewhere) give identical results,
    through reference updates, a re-acquisition and windows clipped at the image edge."""
    settings = TrackerSettings(subset_px=31, search_radius_px=3, reacquire_radius_px=30)
    points = np.vstack([POINTS, [[CENTRE_X, 20.0]]])
    marks = [*MARKS, (6,)]
    reference = np.rint(synthetic.render(pattern, HEIGHT, WIDTH)).astype(np.uint8)
    live = MarkTracker(reference, points, marks, settings)
    rebuilt = MarkTracker(reference, points, marks, settings)
    kinds = []
    for k in range(1, 9):
        jump = 14.0 if k == 5 else 0.0
        mapping = synthetic.UniaxialStretch(1 + 0.05 * k, axis="y", xc=CENTRE_X, yc=40.0 - jump)
        image = np.rint(synthetic.render(pattern, HEIGHT, WIDTH, mapping)).astype(np.uint8)
        frame = live.track(image, 0.1 * k)
        assert len(frame.read_regions) == len(marks)
        sparse = paste_windows(image.shape, image.dtype, cut_windows(image, frame.read_regions))
        again = rebuilt.track(sparse, 0.1 * k)
        assert np.array_equal(again.positions, frame.positions)
        assert np.array_equal(again.zncc, frame.zncc, equal_nan=True)
        assert again.read_regions == frame.read_regions
        kinds.append((frame.reference_updates, int((frame.status == TrackStatus.REACQUIRED).sum())))
    assert sum(u for u, _ in kinds) > 0 and sum(r for _, r in kinds) > 0
    assert any(r.y == 0 for r in frame.read_regions)
    area = sum(r.width * r.height for r in frame.read_regions)
    assert area < 0.2 * HEIGHT * WIDTH
