"""The V4L2 camera backend.

No V4L2 device exists on the CI host: the tests that need one are skipped unless
``/dev/video*`` exists (the protocol behaviours run against it in ``test_camera_contract.py``
there too). What needs no device (URL parsing, the refusals that come before any ioctl) runs
everywhere.
"""

from __future__ import annotations

import glob

import numpy as np
import pytest

from hal.camera.base import CameraSettings, PixelFormat, Region, TriggerInfo, TriggerMode
from hal.errors import HardwareConfigError, HardwareConnectError

v4l2 = pytest.importorskip("hal.camera.v4l2", reason="OpenCV is not installed")
V4l2Camera = v4l2.V4l2Camera

DEVICES = sorted(glob.glob("/dev/video*"))
needs_device = pytest.mark.skipif(not DEVICES, reason="no /dev/video* device here")


def test_url_parsing_names_the_bad_part():
    path, index, options = v4l2.parse_v4l2_url("v4l2:///dev/video3?queue=2&fourcc=YUYV&gain=7")
    assert (path, index) == ("/dev/video3", 3)
    assert (options.queue, options.fourcc, options.gain) == (2, "YUYV", 7)
    for url, named in (
        ("v4l2://", "expected v4l2:///dev/videoN"),
        ("v4l2:///dev/ttyS0", "not a /dev/videoN device"),
        ("v4l2:///dev/video0?queue=0", "queue='0'"),
        ("v4l2:///dev/video0?gain=loud", "gain='loud'"),
        ("v4l2:///dev/video0?colour=1", "unknown option 'colour'"),
    ):
        with pytest.raises(HardwareConfigError, match=named) as caught:
            V4l2Camera(url)
        assert url in str(caught.value)


def test_triggers_are_refused_honestly_without_a_device():
    camera = V4l2Camera("v4l2:///dev/video0")
    for mode in (TriggerMode.SOFTWARE, TriggerMode.EXTERNAL):
        with pytest.raises(HardwareConfigError, match="no trigger"):
            camera.prepare(TriggerInfo(mode=mode))
    with pytest.raises(HardwareConfigError, match="no software trigger"):
        camera.trigger()
    with pytest.raises(HardwareConfigError, match="not open"):
        camera.configure(CameraSettings(exposure_us=1000.0))


def test_an_absent_device_is_a_connect_error():
    if "/dev/video63" in DEVICES:
        pytest.skip("/dev/video63 exists here")
    with pytest.raises(HardwareConnectError, match="/dev/video63"):
        V4l2Camera("v4l2:///dev/video63").open()


@needs_device
def test_refusals_that_need_the_device():
    camera = V4l2Camera(f"v4l2://{DEVICES[0]}")
    camera.open()
    try:
        with pytest.raises(HardwareConfigError, match="Mono12"):
            camera.configure(CameraSettings(exposure_us=10000.0, pixel_format=PixelFormat.MONO12))
        with pytest.raises(HardwareConfigError, match="gain_db"):
            camera.configure(CameraSettings(exposure_us=10000.0, gain_db=6.0))
        with pytest.raises(HardwareConfigError, match="offset"):
            camera.configure(CameraSettings(exposure_us=10000.0, region=Region(8, 8, 64, 64)))
    finally:
        camera.close()


@needs_device
def test_frames_arrive_with_backend_ids_and_a_named_timestamp_source():
    camera = V4l2Camera(f"v4l2://{DEVICES[0]}")
    camera.open()
    try:
        try:
            applied = camera.configure(CameraSettings(exposure_us=10000.0))
        except HardwareConfigError as exc:
            pytest.skip(f"this device offers no uncompressed grey stream: {exc}")
        camera.prepare(TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=30.0))
        camera.arm()
        frames = [camera.fetch(5.0) for _ in range(5)]
    finally:
        camera.close()
    assert all(f.image.dtype == np.uint8 for f in frames)
    assert all(f.image.shape == (applied.region.height, applied.region.width) for f in frames)
    assert all(f.metadata["timestamp_source"] in ("v4l2-buffer", "host-monotonic") for f in frames)
    ids = [f.frame_id for f in frames]
    assert ids == sorted(set(ids))
