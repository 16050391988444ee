"""The Aravis (GigE Vision) camera backend against real GigE Vision peers on loopback.

Peers (`tests.system.aravis_peers`): Aravis' fake camera (``arv-fake-gv-camera-0.8``) on
127.0.0.3, a second one dropping packets on 127.0.0.4, and the specimen camera (an
in-process ``Aravis.GvFakeCamera`` rendering a stretched speckle specimen) on 127.0.0.2. All
run inside the test's loopback-only network namespace and are opened by address; the tests
are skipped elsewhere. The protocol behaviours common to all cameras are in
``test_camera_contract.py``; these are the Aravis specifics: URL options, settings in force
and refusals, trigger features, statistics and lost frames, reconnection after the camera
disappears, and real images through a real GigE Vision stream.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator

import cv2
import numpy as np
import pytest

from hal.camera.base import CameraSettings, PixelFormat, Region, TriggerInfo, TriggerMode
from hal.errors import HardwareConfigError, HardwareConnectError, HardwareTimeout
from tests.system.aravis_peers import (
    GIGE_SKIP_REASON,
    FakeGvCamera,
    needs_gige,
    specimen_camera,
)

aravis = pytest.importorskip("hal.camera.aravis", reason="Aravis 0.8 / PyGObject not installed")
AravisCamera = aravis.AravisCamera

GENEROUS_S = 5.0


@pytest.fixture(scope="module")
def fake() -> Iterator[FakeGvCamera]:
    if GIGE_SKIP_REASON is not None:
        pytest.skip(GIGE_SKIP_REASON)
    camera = FakeGvCamera("127.0.0.3", "GV03")
    camera.start()
    try:
        yield camera
    finally:
        camera.stop()


@pytest.fixture
def opened(fake) -> Iterator[AravisCamera]:
    camera = AravisCamera(fake.url)
    camera.open(timeout_s=GENEROUS_S)
    try:
        yield camera
    finally:
        camera.close()


def test_url_options_are_parsed_and_bad_ones_named():
    from hal.registry import camera_from_url

    camera = camera_from_url(
        "aravis://127.0.0.3?buffers=8&packet_size=1500&trigger_line=Line0"
        "&packet_timeout_ms=40&liveness_ms=250&gain_raw=2",
        scene="ignored",
    )
    assert isinstance(camera, AravisCamera) and camera.address == "127.0.0.3"
    options = camera.options
    assert (options.buffers, options.packet_size, options.trigger_line) == (8, 1500, "Line0")
    assert (options.packet_timeout_ms, options.liveness_ms, options.gain_raw) == (40.0, 250.0, 2)
    assert AravisCamera("aravis://Aravis-GV01").address == "Aravis-GV01"
    for url, named in (
        ("aravis://127.0.0.3?buffers=1", "buffers='1'"),
        ("aravis://127.0.0.3?bogus=1", "unknown option 'bogus'"),
        ("aravis://127.0.0.3?packet_size=big", "packet_size='big'"),
        ("aravis://127.0.0.3?packet_resend=sometimes", "packet_resend='sometimes'"),
        ("aravis://127.0.0.3?liveness_ms=-5", "liveness_ms='-5'"),
        ("aravis://", "no camera address"),
    ):
        with pytest.raises(HardwareConfigError, match=named) as caught:
            AravisCamera(url)
        assert url in str(caught.value) and "\n" not in str(caught.value)


@needs_gige
def test_an_absent_camera_is_a_connect_error_within_the_open_timeout():
    camera = AravisCamera("aravis://127.0.0.9")
    started = time.monotonic()
    with pytest.raises(HardwareConnectError, match="aravis://127.0.0.9"):
        camera.open(timeout_s=0.5)
    assert time.monotonic() - started < 0.5 + GENEROUS_S
    with pytest.raises(HardwareConfigError, match="not open"):
        camera.configure(CameraSettings(exposure_us=1000.0))


def test_settings_in_force_and_what_the_camera_refuses(opened):
    applied = opened.configure(CameraSettings(exposure_us=1234.0, region=Region(3, 5, 301, 203)))
    assert applied.region == Region(3, 5, 301, 203)
    assert applied.exposure_us == pytest.approx(1234.0)
    assert applied.gain_db == 0.0
    assert opened.feature_value("Width") == "301"
    assert opened.sensor_size == (2048, 2048)
    refusals = (
        (CameraSettings(exposure_us=1000.0, pixel_format=PixelFormat.MONO12), "Mono12.*offers"),
        (CameraSettings(exposure_us=1000.0, gain_db=3.0), "GainRaw"),
        (CameraSettings(exposure_us=1.0), "exposure_us=1 outside"),
        (CameraSettings(exposure_us=1000.0, region=Region(2000, 0, 100, 10)), "exceeds"),
    )
    for settings, named in refusals:
        with pytest.raises(HardwareConfigError, match=named) as caught:
            opened.configure(settings)
        assert opened.url in str(caught.value)
    assert opened.settings == applied


def test_mono16_arrives_as_uint16_with_sixteen_bit_values(opened):
    opened.configure(
        CameraSettings(
            exposure_us=10000.0, region=Region(0, 0, 128, 32), pixel_format=PixelFormat.MONO16
        )
    )
    opened.prepare(TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=100.0))
    opened.arm()
    frame = opened.fetch(GENEROUS_S)
    assert frame.image.dtype == np.uint16 and frame.image.shape == (32, 128)
    assert frame.image.max() > 255


def test_trigger_features_are_set_mode_before_source(opened):
    opened.configure(CameraSettings(exposure_us=10000.0, region=Region(0, 0, 64, 64)))
    opened.prepare(TriggerInfo(mode=TriggerMode.SOFTWARE))
    assert [opened.feature_value(name) for name in ("TriggerSelector", "TriggerMode")] == [
        "FrameStart",
        "On",
    ]
    assert opened.feature_value("TriggerSource") == "Software"
    opened.prepare(TriggerInfo(mode=TriggerMode.EXTERNAL))
    assert opened.feature_value("TriggerSource") == "Line0"
    assert opened.feature_value("TriggerActivation") == "RisingEdge"
    opened.arm()
    with pytest.raises(HardwareTimeout):
        opened.fetch(0.3)
    with pytest.raises(HardwareConfigError, match="external"):
        opened.trigger()
    opened.disarm()
    opened.prepare(TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=40.0))
    assert opened.feature_value("TriggerMode") == "Off"
    assert float(opened.feature_value("AcquisitionFrameRate")) == pytest.approx(40.0)
    low, high = opened.frame_rate_bounds()
    with pytest.raises(HardwareConfigError, match="rate_hz=.*outside"):
        opened.prepare(TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=high * 2))
    opened.close()
    bad_line = AravisCamera(opened.url + "?trigger_line=Line7")
    bad_line.open(timeout_s=GENEROUS_S)
    try:
        with pytest.raises(HardwareConfigError, match="Line7.*offers"):
            bad_line.prepare(TriggerInfo(mode=TriggerMode.EXTERNAL))
    finally:
        bad_line.close()


def _ramp_matches(frame) -> bool:
    """Aravis' fake fills pixel (x, y) with (x + y + block id) % 255 at 10 ms exposure."""
    height, width = frame.image.shape
    rows, columns = np.mgrid[0:height, 0:width]
    expected = (columns + rows + frame.metadata["device_frame_id"]) % 255
    return bool(np.array_equal(frame.image, expected.astype(np.uint8)))


def test_statistics_count_lost_frames_as_the_frame_ids_show_them():
    if GIGE_SKIP_REASON is not None:
        pytest.skip(GIGE_SKIP_REASON)
    with FakeGvCamera("127.0.0.4", "GV04", lost_per_thousand=2) as lossy:
        camera = AravisCamera(lossy.url + "?frame_retention_ms=30&packet_timeout_ms=5")
        camera.open(timeout_s=GENEROUS_S)
        try:
            camera.configure(CameraSettings(exposure_us=10000.0, region=Region(0, 0, 512, 256)))
            camera.prepare(TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=100.0))
            camera.arm()
            frames = [camera.fetch(GENEROUS_S) for _ in range(60)]
            statistics = camera.statistics()
        finally:
            camera.close()
    assert all(_ramp_matches(frame) for frame in frames)
    ids = [frame.frame_id for frame in frames]
    gaps = sum(b - a - 1 for a, b in zip(ids, ids[1:], strict=False)) + ids[0]
    assert statistics["frames_delivered"] == 60
    assert statistics["incomplete_buffers"] > 0 and statistics["failures"] > 0
    assert statistics["missing_packets"] > 0
    assert statistics["frames_lost"] >= gaps > 0
    assert statistics["frames_lost"] - gaps <= 2
    assert statistics["incomplete_by_status"]
    assert json.dumps(statistics)


def test_exactly_the_prepared_frames_and_clean_statistics(opened):
    opened.configure(CameraSettings(exposure_us=10000.0, region=Region(0, 0, 256, 128)))
    opened.prepare(TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=100.0, frames=4))
    opened.arm()
    frames = [opened.fetch(GENEROUS_S) for _ in range(4)]
    with pytest.raises(HardwareTimeout, match="all 4 frames delivered"):
        opened.fetch(0.2)
    statistics = opened.statistics()
    assert [f.frame_id - frames[0].frame_id for f in frames] == [0, 1, 2, 3]
    assert all(_ramp_matches(frame) for frame in frames)
    assert frames[0].metadata["system_timestamp_ns"] > 0
    assert statistics["frames_delivered"] == 4 and statistics["frames_lost"] == 0
    assert statistics["completed_buffers"] >= 4 and statistics["underruns"] == 0
    assert statistics["connected"] and statistics["armed"]


def test_it_reconnects_after_the_camera_disappears(fake):
    camera = AravisCamera(fake.url + "?liveness_ms=200&reconnect_min_ms=200&reconnect_max_ms=800")
    camera.open(timeout_s=GENEROUS_S)
    try:
        region = Region(0, 0, 256, 128)
        camera.configure(CameraSettings(exposure_us=10000.0, region=region))
        camera.prepare(TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=50.0))
        camera.arm()
        before = [camera.fetch(GENEROUS_S) for _ in range(3)]
        fake.kill()
        outcomes = _fetch_until(camera, HardwareConnectError, within_s=20.0)
        assert {type(o) for o in outcomes[:-1]} <= {HardwareTimeout}
        lost = outcomes[-1]
        assert "aravis://127.0.0.3" in str(lost) and "\n" not in str(lost)
        assert camera.statistics()["reconnecting"]
        fake.start()
        outcomes = _fetch_until(camera, None, within_s=30.0)
        assert {type(o) for o in outcomes[:-1]} <= {HardwareTimeout, HardwareConnectError}
        after = outcomes[-1]
        assert after.frame_id > before[-1].frame_id
        assert after.image.shape == (region.height, region.width) and _ramp_matches(after)
        more = [camera.fetch(GENEROUS_S) for _ in range(3)]
        assert [f.frame_id - after.frame_id for f in more] == [1, 2, 3]
        statistics = camera.statistics()
        assert statistics["connection_losses"] == 1 and statistics["reconnects"] == 1
        assert statistics["connected"] and not statistics["reconnecting"]
    finally:
        camera.close()


def _fetch_until(camera, wanted, *, within_s: float, timeout_s: float = 0.4) -> list:
    """Fetch until `wanted` is raised (an exception class) or a frame arrives (None); every
    outcome in order. Each fetch must return within its timeout (generous bound)."""
    outcomes: list = []
    deadline = time.monotonic() + within_s
    while time.monotonic() < deadline:
        started = time.monotonic()
        try:
            outcome = camera.fetch(timeout_s)
        except (HardwareTimeout, HardwareConnectError) as exc:
            outcome = exc
        assert time.monotonic() - started < timeout_s + 1.0
        outcomes.append(outcome)
        if (wanted is None and not isinstance(outcome, Exception)) or (
            wanted is not None and isinstance(outcome, wanted)
        ):
            return outcomes
    raise AssertionError(f"nothing like {wanted} within {within_s:g} s: {outcomes[-3:]}")


def _locate(template: np.ndarray, image: np.ndarray, centre: tuple[int, int]) -> float:
    """Row (subpixel) where `template` matches `image` best near `centre` (x, y)."""
    half = template.shape[0] // 2
    x, y = centre
    margin = 24
    window = image[y - half - margin : y + half + margin + 1, x - half : x + half + 1]
    scores = cv2.matchTemplate(window, template, cv2.TM_CCOEFF_NORMED)[:, 0]
    best = int(np.argmax(scores))
    offset = 0.0
    if 0 < best < scores.size - 1:
        below, peak, above = scores[best - 1], scores[best], scores[best + 1]
        offset = 0.5 * (below - above) / (below - 2 * peak + above)
    return y - margin + best + offset


@needs_gige
def test_the_specimen_camera_stretches_as_its_truth_says(tmp_path):
    truth_path = tmp_path / "truth.jsonl"
    with specimen_camera(truth_path, strain_rate_per_s=0.05, max_strain=0.2) as specimen:
        camera = AravisCamera(specimen.url)
        camera.open(timeout_s=GENEROUS_S)
        try:
            camera.configure(CameraSettings(exposure_us=1000.0))
            camera.prepare(TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=25.0))
            camera.arm()
            frames = [camera.fetch(GENEROUS_S) for _ in range(30)]
        finally:
            camera.close()
        truth = specimen.truth()
    assert truth.header["centre_y"] == pytest.approx(255.5)
    records = [truth.record_of(frame) for frame in frames]
    assert [r.frame_id for r in records] == [f.metadata["device_frame_id"] for f in frames]
    assert [r.region for r in records] == [(0, 0, 512, 512)] * len(frames)
    strains = [r.strain for r in records]
    assert all(b > a for a, b in zip(strains, strains[1:], strict=False))
    first, last = frames[0], frames[-1]
    expected = truth.strain_between(first, last)
    assert expected > 0.04
    rows = (255 - 150, 255 + 150)
    templates = [first.image[y - 20 : y + 21, 236:277].astype(np.float32) for y in rows]
    found = [
        _locate(t, last.image.astype(np.float32), (256, y))
        for t, y in zip(templates, rows, strict=True)
    ]
    measured = (found[1] - found[0]) / (rows[1] - rows[0]) - 1.0
    assert measured == pytest.approx(expected, abs=2e-3)


def test_the_camera_benchmark_reports_its_figures(fake, tmp_path):
    from appliance.bench.camera import run_camera_benchmark

    out = tmp_path / "results"
    assert run_camera_benchmark(out, True, url=fake.url, frames=40, exposures_us=(1000.0,)) == 0
    figures = json.loads((out / "camera.json").read_text())["figures"]
    (run,) = figures["runs"]
    assert run["frames"] == 40 and run["fps"] > 0
    assert {"lost_frames", "failures", "resent_packets", "interval_ms"} <= set(run)


def test_a_camera_controlled_by_another_application_is_a_connect_error(opened):
    second = AravisCamera(opened.url)
    with pytest.raises(HardwareConnectError, match="another application controls"):
        second.open(timeout_s=GENEROUS_S)
    second.close()
    assert opened.configure(CameraSettings(exposure_us=10000.0)).exposure_us == 10000.0
