"""The tracker's automatic search: the product's choice for the blur and stretch it measures."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from appliance.config import parse_config
from appliance.dic import synthetic
from appliance.dic.search_choice import choose_search
from appliance.errors import InputError
from appliance.measure.frame_windows import cut_windows, paste_windows
from appliance.measure.tracking import MarkTracker, TrackerSettings, TrackStatus

HEIGHT, WIDTH = 640, 200
CENTRE_X = 100.0
POINTS = np.array(
    [[CENTRE_X, 150.0 + 8 * k] for k in range(3)] + [[CENTRE_X, 300.0 + 8 * k] for k in range(3)]
)
MARKS = [(0, 1, 2), (3, 4, 5)]
FRAME_INTERVAL_S = 0.1
ACCELERATION_PX_S2, RAMP_S = 250.0, 0.4
SPEED_PX_S = ACCELERATION_PX_S2 * RAMP_S
AUTO = TrackerSettings(subset_px=31, reacquire_search="auto")


@pytest.fixture(scope="module")
def pattern() -> synthetic.SpecklePattern:
    return synthetic.dense_speckle(WIDTH, HEIGHT, seed=5, radius=2.5)


def _travel_px(t: float) -> float:
    """Downward travel of the specimen at time t: from rest up to 100 px/s in 0.4 s, then on."""
    if t < RAMP_S:
        return 0.5 * ACCELERATION_PX_S2 * t * t
    return 0.5 * SPEED_PX_S * RAMP_S + SPEED_PX_S * (t - RAMP_S)


def _exposed_frame(
    pattern, k: int, exposure_s: float, slip_px: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Frame k, exposed for `exposure_s` from its time, and the points' mean positions then;
    `slip_px` more along the axis (a slip before the frame, not motion during it)."""
    start = FRAME_INTERVAL_S * k
    samples = max(1, int(np.ceil(SPEED_PX_S * exposure_s / 0.25)))
    image = synthetic.render_exposure(
        pattern,
        HEIGHT,
        WIDTH,
        lambda t: synthetic.AffineMapping.translation(0.0, _travel_px(t) + slip_px),
        start=start,
        stop=start + exposure_s,
        samples=samples,
    )
    times = start + (np.arange(samples) + 0.5) * exposure_s / samples
    return image, POINTS + [0.0, np.mean([_travel_px(t) for t in times]) + slip_px]


def _same_as_tracks_choice(change) -> None:
    """The tracker's choice is the decision function's for the inputs it measured."""
    inputs = change.inputs
    assert change.choice.stretch == inputs.stretch_range()
    expected = choose_search(
        blur_px=inputs.blur_px,
        blur_angle_deg=90.0,
        stretch=inputs.stretch_range(),
        stretch_axis="y",
        subset=31,
    )
    assert change.choice.describe() == expected.describe()


@pytest.mark.parametrize(("exposure_s", "blur_range_px"), [(0.1, (9.0, 10.5)), (0.0005, (0, 0.06))])
def test_reacquisition_takes_the_choice_for_the_blur_it_measures(
    pattern, exposure_s, blur_range_px
):
    """A specimen accelerating to 100 px/s: the re-acquisition's decision is made from each
    mark's blur (speed x exposure: 10 px, or none) and is the choice `track` makes for it; the
    search changes (and is reported) once, when the stretch becomes known, not as the blur
    rises (ZNCC either way, against a reference the tracker blurs to match)."""
    tracker = MarkTracker(synthetic.render(pattern, HEIGHT, WIDTH), POINTS, MARKS, AUTO)
    heard = []
    tracker.follow_search_choices(heard.append)
    assert [c.time_s for c in heard] == [None, None]
    assert all(c.choice.reference_blur_px == 0.0 for c in heard)
    per_frame = []
    for k in range(1, 8):
        image, truth = _exposed_frame(pattern, k, exposure_s)
        frame = tracker.track(image, FRAME_INTERVAL_S * k, exposure_s)
        assert np.all(frame.status == TrackStatus.TRACKED)
        assert np.abs(frame.positions - truth).max() < 0.1
        per_frame.append(len(frame.search_choices))
    assert heard == tracker.search_choices
    assert per_frame == [0, 0, 2, 0, 0, 0, 0]
    for change in tracker.search_decisions():
        _same_as_tracks_choice(change)
        assert change.stages == ("reacquire",)
        assert change.inputs.exposure_s == exposure_s
        assert change.inputs.blur_px == pytest.approx(change.inputs.speed_px_s * exposure_s)
        low, high = blur_range_px
        assert low <= change.choice.reference_blur_px <= high
        assert change.inputs.one_step_stretch == pytest.approx(0.0, abs=1e-4)


def test_a_jump_is_reacquired_with_the_automatic_choice(pattern):
    settings = TrackerSettings(
        subset_px=31, search_radius_px=3, reacquire_radius_px=30, reacquire_search="auto"
    )
    tracker = MarkTracker(synthetic.render(pattern, HEIGHT, WIDTH), POINTS, MARKS, settings)
    image = synthetic.render(pattern, HEIGHT, WIDTH, synthetic.AffineMapping.translation(0, 17))
    frame = tracker.track(image, 0.1, 0.001)
    assert np.all(frame.status == TrackStatus.REACQUIRED)
    assert np.abs(frame.positions - (POINTS + [0, 17])).max() < 0.02
    assert [c.choice.method for c in tracker.search_choices] == ["zncc", "zncc"]


def test_the_one_step_stretch_is_the_strain_rate_between_frames(pattern):
    """A stretch of 3 % a frame: the choice's pre-warps span the step the marks' relative
    speed gives (in steps of 2.5 %), along the loading axis, and the tracker follows it."""
    settings = TrackerSettings(subset_px=31, search="auto", reacquire_search="auto")
    tracker = MarkTracker(synthetic.render(pattern, HEIGHT, WIDTH), POINTS, MARKS, settings)
    for k in range(1, 5):
        mapping = synthetic.UniaxialStretch(1.03**k, axis="y", xc=CENTRE_X, yc=100.0)
        frame = tracker.track(synthetic.render(pattern, HEIGHT, WIDTH, mapping), 0.1 * k)
        x, y = mapping.forward(POINTS[:, 0], POINTS[:, 1])
        assert np.all(frame.status == TrackStatus.TRACKED)
        assert np.abs(frame.positions - np.c_[x, y]).max() < 0.05
    change = tracker.search_choices[-1]
    _same_as_tracks_choice(change)
    assert change.stages == ("track", "reacquire")
    assert change.inputs.one_step_stretch == pytest.approx(0.03, abs=0.002)
    assert change.inputs.strain_rate_per_s == pytest.approx(np.log(1.03) / 0.1, rel=0.05)
    assert change.choice.stretch == (0.0, 0.025)
    stretches = change.choice.prewarps[:, 3]
    assert stretches[0] == 0.0 and stretches[-1] == 0.025
    assert f"one-step stretch {change.inputs.one_step_stretch * 100:.3g} %" in change.describe()


def test_auto_tracks_to_the_same_numbers_from_the_pixels_it_read(pattern):
    """What a replay does: frames rebuilt from the windows the tracker read give the same
    numbers and the same choices, through a re-acquisition and reference updates."""
    settings = TrackerSettings(
        subset_px=31, search="auto", reacquire_search="auto", search_radius_px=3
    )
    reference = np.rint(synthetic.render(pattern, HEIGHT, WIDTH)).astype(np.uint8)
    live = MarkTracker(reference, POINTS, MARKS, settings)
    rebuilt = MarkTracker(reference, POINTS, MARKS, settings)
    reacquired = 0
    for k in range(1, 8):
        jump = 12.0 if k == 4 else 0.0
        mapping = synthetic.UniaxialStretch(1 + 0.04 * k, axis="y", xc=CENTRE_X, yc=60.0 - jump)
        image = np.rint(synthetic.render(pattern, HEIGHT, WIDTH, mapping)).astype(np.uint8)
        frame = live.track(image, 0.1 * k, 0.01)
        sparse = paste_windows(image.shape, image.dtype, cut_windows(image, frame.read_regions))
        again = rebuilt.track(sparse, 0.1 * k, 0.01)
        assert np.array_equal(again.positions, frame.positions)
        assert np.array_equal(again.zncc, frame.zncc, equal_nan=True)
        assert [c.to_json() for c in again.search_choices] == [
            c.to_json() for c in frame.search_choices
        ]
        reacquired += int((frame.status == TrackStatus.REACQUIRED).sum())
    assert reacquired > 0 and live.reference_updates > 0


def test_the_configuration_accepts_auto_and_names_the_key_of_a_bad_value(tmp_path):
    config = parse_config("[tracking]\nsearch = 'auto'\nreacquire_search = 'auto'\n")
    assert config.tracking.search == config.tracking.reacquire_search == "auto"
    with pytest.raises(InputError) as info:
        parse_config("[tracking]\nreacquire_search = 'best'\n", "run.toml")
    message = str(info.value)
    assert "run.toml: [tracking] reacquire_search: must be one of zncc, lpq, auto" in message
    assert "\n" not in message
    bad = tmp_path / "bad.toml"
    bad.write_text("[tracking]\nsearch = 'fastest'\n")
    extensometer = str(Path(sys.executable).with_name("extensometer"))
    done = subprocess.run(
        [extensometer, "run", "--sim", "--config", str(bad)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1 and "[tracking] search: must be one of" in done.stderr


@pytest.mark.parametrize("reacquire_search", ["zncc", "auto"])
def test_a_sudden_jump_under_a_long_blur_is_not_taken_as_speed(pattern, reacquire_search):
    """A specimen at 100 px/s exposed for a whole frame (10 px of blur) slips 16 px between
    two frames: the mark is re-acquired there, and followed within 0.1 px after it, with the
    velocity it predicts with and the blur it expects left as they were before the slip."""
    settings = TrackerSettings(subset_px=41, reacquire_search=reacquire_search)
    tracker = MarkTracker(synthetic.render(pattern, HEIGHT, WIDTH), POINTS, MARKS, settings)
    exposure_s, slip_frame, slip_px = 0.1, 9, 16.0
    for k in range(1, 14):
        image, truth = _exposed_frame(pattern, k, exposure_s, slip_px if k >= slip_frame else 0)
        frame = tracker.track(image, FRAME_INTERVAL_S * k, exposure_s)
        if k >= 4:
            assert np.all(frame.measured), k
            assert np.abs(frame.positions - truth).max() < 0.1, k
        if k == slip_frame:
            assert np.all(frame.status == TrackStatus.REACQUIRED)
    for decision in tracker.search_decisions():
        if reacquire_search == "auto":
            assert decision.inputs.blur_px == pytest.approx(SPEED_PX_S * exposure_s, abs=0.5)


def test_a_jump_before_the_speed_is_known_stays_measured(pattern):
    """The same slip in the second frame, before the marks' speed is known: the jump is taken
    as speed, and the match against the reference blurred for it fails; the re-acquired match
    is kept, and the marks are measured in every frame."""
    tracker = MarkTracker(
        synthetic.render(pattern, HEIGHT, WIDTH), POINTS, MARKS, TrackerSettings(subset_px=41)
    )
    for k in range(1, 8):
        image, truth = _exposed_frame(pattern, k, 0.1, 16.0 if k >= 2 else 0.0)
        frame = tracker.track(image, FRAME_INTERVAL_S * k, 0.1)
        assert np.all(frame.measured), k
        assert np.abs(frame.positions - truth).max() < 0.5, k
