"""The `Camera` protocol, one set of behaviours run against every camera backend.

Backends: the simulated camera (a trivial scene on a fast simulation clock), the Aravis
backend over Aravis' fake GigE Vision camera on 127.0.0.1 (skipped outside a loopback-only
network namespace), and the V4L2 backend on the first ``/dev/video*`` (skipped where there is
none, as on the CI host). Backends without a software trigger (V4L2) must refuse SOFTWARE
preparation; the trigger and timeout behaviours are skipped for them.

Timing never decides a result except as a generous upper bound.
"""

from __future__ import annotations

import dataclasses
import glob
import time
from collections.abc import Iterator

import numpy as np
import pytest

from hal.camera.base import (
    Camera,
    CameraSettings,
    PixelFormat,
    Region,
    TriggerInfo,
    TriggerMode,
)
from hal.errors import HardwareConfigError, HardwareTimeout
from tests.system.aravis_peers import GIGE_SKIP_REASON, FakeGvCamera

GENEROUS_S = 5.0
"""Fetch timeout and upper bound on waits: a loaded 2-core host still meets it."""

V4L2_DEVICES = sorted(glob.glob("/dev/video*"))


class GradientScene:
    """Grey level = 60 + column + row + 20 * (mid-exposure time in s): frames differ in time."""

    sensor_width = 96
    sensor_height = 64

    def render(self, start_s, stop_s, region):
        rows, columns = np.mgrid[
            region.y : region.y + region.height, region.x : region.x + region.width
        ]
        image = 60.0 + columns + rows + 20.0 * 0.5 * (start_s + stop_s)
        return image.astype(np.float64), {}


@dataclasses.dataclass
class Rig:
    """A camera under test and what to ask of it."""

    name: str
    camera: Camera
    settings: CameraSettings
    rate_hz: float
    software_trigger: bool


@pytest.fixture(scope="module")
def gv_fake() -> Iterator[FakeGvCamera]:
    if GIGE_SKIP_REASON is not None:
        pytest.skip(GIGE_SKIP_REASON)
    with FakeGvCamera("127.0.0.1", "GV01") as fake:
        yield fake


def _make_rig(name: str, request: pytest.FixtureRequest) -> Rig:
    if name == "sim":
        from hal.camera.sim import SimCamera
        from hal.clock import SimClock

        camera = SimCamera(
            "sim://camera",
            scene=GradientScene(),
            clock=SimClock(),
            read_noise=0.0,
            electrons_per_grey=0.0,
        )
        settings = CameraSettings(exposure_us=1000.0, region=Region(8, 4, 40, 24))
        return Rig(name, camera, settings, rate_hz=50.0, software_trigger=True)
    if name == "aravis":
        fake = request.getfixturevalue("gv_fake")
        from hal.camera.aravis import AravisCamera

        settings = CameraSettings(exposure_us=10000.0, region=Region(16, 8, 320, 240))
        return Rig(name, AravisCamera(fake.url), settings, rate_hz=100.0, software_trigger=True)
    if not V4L2_DEVICES:
        pytest.skip("no /dev/video* device here")
    from hal.camera.v4l2 import V4l2Camera

    settings = CameraSettings(exposure_us=10000.0)
    return Rig(name, V4l2Camera(f"v4l2://{V4L2_DEVICES[0]}"), settings, 30.0, False)


@pytest.fixture(params=["sim", "aravis", "v4l2"])
def rig(request: pytest.FixtureRequest) -> Iterator[Rig]:
    made = _make_rig(request.param, request)
    made.camera.open(timeout_s=GENEROUS_S)
    try:
        yield made
    finally:
        made.camera.close()


def _internal(rig: Rig, frames: int = 0) -> TriggerInfo:
    return TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=rig.rate_hz, frames=frames)


def test_open_and_close_are_safe_twice(rig):
    rig.camera.open(timeout_s=GENEROUS_S)
    rig.camera.close()
    rig.camera.close()
    rig.camera.open(timeout_s=GENEROUS_S)
    assert rig.camera.configure(rig.settings).pixel_format is rig.settings.pixel_format


def test_configure_returns_the_settings_in_force(rig):
    applied = rig.camera.configure(rig.settings)
    assert isinstance(applied, CameraSettings)
    assert applied.pixel_format is rig.settings.pixel_format
    assert applied.region is not None
    if rig.settings.region is not None:
        assert applied.region == rig.settings.region
    assert applied.exposure_us > 0


def test_configure_and_prepare_are_refused_while_armed(rig):
    rig.camera.configure(rig.settings)
    rig.camera.prepare(_internal(rig))
    rig.camera.arm()
    with pytest.raises(HardwareConfigError, match="armed"):
        rig.camera.configure(rig.settings)
    with pytest.raises(HardwareConfigError, match="armed"):
        rig.camera.prepare(_internal(rig))


def test_internal_frames_have_increasing_ids_and_timestamps(rig):
    applied = rig.camera.configure(rig.settings)
    rig.camera.prepare(_internal(rig))
    rig.camera.arm()
    frames = [rig.camera.fetch(GENEROUS_S) for _ in range(6)]
    ids = [frame.frame_id for frame in frames]
    stamps = [frame.timestamp_ns for frame in frames]
    assert all(b > a for a, b in zip(ids, ids[1:], strict=False)), ids
    assert all(b > a for a, b in zip(stamps, stamps[1:], strict=False)), stamps
    for frame in frames:
        assert frame.image.shape == (applied.region.height, applied.region.width)
        assert frame.image.dtype == np.uint8
        assert frame.exposure_us == pytest.approx(applied.exposure_us)


def test_the_exposure_changes_while_armed_and_frames_report_it(rig):
    applied = rig.camera.configure(rig.settings)
    rig.camera.prepare(_internal(rig))
    rig.camera.arm()
    rig.camera.fetch(GENEROUS_S)
    wanted = applied.exposure_us * 2
    in_force = rig.camera.set_exposure(wanted)
    assert in_force == pytest.approx(wanted, rel=0.1)
    frames = [rig.camera.fetch(GENEROUS_S) for _ in range(3)]
    assert frames[-1].exposure_us == pytest.approx(in_force)
    assert rig.camera.set_exposure(applied.exposure_us) == pytest.approx(
        applied.exposure_us, rel=0.1
    )


def test_an_exposure_the_camera_cannot_take_is_refused_and_the_old_one_stays(rig):
    applied = rig.camera.configure(rig.settings)
    with pytest.raises(HardwareConfigError, match="exposure"):
        rig.camera.set_exposure(-5.0)
    rig.camera.prepare(_internal(rig))
    rig.camera.arm()
    assert rig.camera.fetch(GENEROUS_S).exposure_us == pytest.approx(applied.exposure_us)


def test_mono16_frames_are_uint16_or_refused_by_name(rig):
    wanted = dataclasses.replace(rig.settings, pixel_format=PixelFormat.MONO16)
    try:
        applied = rig.camera.configure(wanted)
    except HardwareConfigError as exc:
        assert "Mono16" in str(exc) or "Y16" in str(exc)
        return
    rig.camera.prepare(_internal(rig))
    rig.camera.arm()
    frame = rig.camera.fetch(GENEROUS_S)
    assert frame.image.dtype == np.uint16
    assert frame.image.shape == (applied.region.height, applied.region.width)


def test_an_image_is_not_modified_by_later_fetches(rig):
    rig.camera.configure(rig.settings)
    rig.camera.prepare(_internal(rig))
    rig.camera.arm()
    first = rig.camera.fetch(GENEROUS_S)
    kept = first.image.copy()
    later = [rig.camera.fetch(GENEROUS_S) for _ in range(4)]
    assert np.array_equal(first.image, kept)
    assert not any(np.shares_memory(first.image, frame.image) for frame in later)
    assert not np.array_equal(later[-1].image, kept)


def test_exactly_the_prepared_number_of_frames_then_a_timeout(rig):
    rig.camera.configure(rig.settings)
    rig.camera.prepare(_internal(rig, frames=3))
    rig.camera.arm()
    frames = [rig.camera.fetch(GENEROUS_S) for _ in range(3)]
    assert len({frame.frame_id for frame in frames}) == 3
    with pytest.raises(HardwareTimeout):
        rig.camera.fetch(0.2)


def test_software_trigger_gives_one_frame_and_none_without(rig):
    rig.camera.configure(rig.settings)
    if not rig.software_trigger:
        with pytest.raises(HardwareConfigError, match="trigger"):
            rig.camera.prepare(TriggerInfo(mode=TriggerMode.SOFTWARE))
        return
    rig.camera.prepare(TriggerInfo(mode=TriggerMode.SOFTWARE))
    rig.camera.arm()
    with pytest.raises(HardwareTimeout):
        rig.camera.fetch(0.3)
    rig.camera.trigger()
    frame = rig.camera.fetch(GENEROUS_S)
    assert frame.image.size > 0
    with pytest.raises(HardwareTimeout):
        rig.camera.fetch(0.3)


def test_a_fetch_timeout_is_a_hardware_timeout_within_a_generous_bound(rig):
    if not rig.software_trigger:
        pytest.skip(f"{rig.name}: no way to keep a free-running camera from sending frames")
    rig.camera.configure(rig.settings)
    rig.camera.prepare(TriggerInfo(mode=TriggerMode.SOFTWARE))
    rig.camera.arm()
    started = time.monotonic()
    with pytest.raises(HardwareTimeout):
        rig.camera.fetch(0.25)
    assert time.monotonic() - started < 0.25 + GENEROUS_S


def test_trigger_outside_software_mode_and_fetch_while_disarmed_are_refused(rig):
    rig.camera.configure(rig.settings)
    rig.camera.prepare(_internal(rig))
    with pytest.raises(HardwareConfigError):
        rig.camera.fetch(0.1)
    rig.camera.arm()
    with pytest.raises(HardwareConfigError, match="trigger"):
        rig.camera.trigger()


def test_disarm_then_arm_again_delivers_frames_again(rig):
    rig.camera.configure(rig.settings)
    rig.camera.prepare(_internal(rig))
    rig.camera.arm()
    before = rig.camera.fetch(GENEROUS_S)
    rig.camera.disarm()
    rig.camera.disarm()
    rig.camera.arm()
    after = rig.camera.fetch(GENEROUS_S)
    assert after.frame_id > before.frame_id
    assert after.timestamp_ns > before.timestamp_ns
