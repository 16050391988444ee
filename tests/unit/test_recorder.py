"""The MCAP recorder's policies: full frames at their rate, degradation on a slow disk (a pipe
read slowly), every other record kept, write failures reported."""

from __future__ import annotations

import io
import math
import os
import threading
import time

import numpy as np
import pytest

from appliance.config import Config, RecordConfig
from appliance.measure.frame_measurer import StrainSample
from appliance.measure.frame_windows import cut_windows
from appliance.measure.gauges import Calibration, Gauge, StrainGaugesLayout, StrainReading
from appliance.measure.tracking import ReadRegion
from appliance.recording.reader import RecordingReader
from appliance.recording.writer import McapRecorder, RecordingError
from appliance.run.loop import LoopResult
from appliance.run.outputs import RunFacts
from hal.camera.base import Frame

SIZE = 256
POINTS = np.array([[100.0, 60.0], [100.0, 190.0]])


def _image(k: int) -> np.ndarray:
    return np.random.default_rng(k).integers(0, 256, (SIZE, SIZE), dtype=np.uint8)


def _facts() -> RunFacts:
    return RunFacts(
        config=Config(),
        reference=Frame(_image(0), 0, 0, 100.0),
        points=POINTS,
        marks=((0,), (1,)),
        layout=StrainGaugesLayout(Gauge((0,), (1,)), None),
        calibration=Calibration(0.1),
        gauge_length_mm=13.0,
        epoch_offset_ns=1_700_000_000_000_000_000,
    )


def _sample(k: int, period_ns: int) -> StrainSample:
    image = _image(k + 1)
    strain = 1e-3 * k + 1e-7 / 3
    regions = [ReadRegion(80, 40, 41, 41), ReadRegion(80, 170, 41, 41)]
    return StrainSample(
        index=k,
        frame_id=k + 1,
        timestamp_ns=(k + 1) * period_ns,
        time_s=(k + 1) * period_ns * 1e-9,
        exposure_us=100.0,
        reading=StrainReading(130.0, strain, math.log1p(strain), 13 * strain, 13.0, math.nan, 0.3),
        positions=POINTS + [0.0, 0.1 * k],
        status=np.zeros(2, dtype=np.int8),
        zncc=np.array([0.99, 0.98]),
        gradients=np.zeros((2, 4)),
        data_valid=True,
        reference_updates=0,
        machine=None,
        latency_s=0.001,
        windows=cut_windows(image, regions),
        image=image,
    )


def _read(data: bytes, tmp_path) -> RecordingReader:
    path = tmp_path / "read.mcap"
    path.write_bytes(data)
    return RecordingReader(path)


def test_full_frames_follow_their_rate_on_a_fast_disk(tmp_path):
    recorder = McapRecorder(tmp_path / "a.mcap", RecordConfig(full_frame_rate_hz=10.0))
    recorder.begin(_facts())
    for k in range(50):
        recorder(_sample(k, period_ns=20_000_000))
    recorder.end(LoopResult(frames_processed=50))
    # 50 frames at 50 Hz with full frames at 10 Hz: every fifth, plus the reference
    assert recorder.full_frames_recorded == 11 and recorder.full_frames_skipped == 0
    reader = RecordingReader(tmp_path / "a.mcap")
    samples = list(reader.samples())
    assert reader.complete and len(samples) == 50
    assert reader.message_counts["/camera/full"] == 11
    assert [s.strain["engineering_strain"] for s in samples] == [
        1e-3 * k + 1e-7 / 3 for k in range(50)
    ]
    assert all(s.strain["transverse_strain"] is None for s in samples)
    assert reader.meta("run_stop")["recording_full_frames_skipped"] == "0"


def test_a_slow_disk_degrades_full_frames_first_and_keeps_every_sample(tmp_path):
    read_fd, write_fd = os.pipe()
    received = io.BytesIO()

    def slow_disk() -> None:
        with os.fdopen(read_fd, "rb", buffering=0) as pipe:
            while chunk := pipe.read(16384):
                received.write(chunk)
                time.sleep(0.01)

    disk = threading.Thread(target=slow_disk)
    disk.start()
    config = RecordConfig(
        full_frame_rate_hz=1000.0, backlog_mb=0.25, flush_interval_s=0.05, fsync=True
    )
    recorder = McapRecorder(
        tmp_path / "pipe.mcap", config, stream=os.fdopen(write_fd, "wb", buffering=0)
    )
    recorder.begin(_facts())
    for k in range(120):
        recorder(_sample(k, period_ns=1_000_000))
    recorder.end(LoopResult(frames_processed=120))
    disk.join(timeout=60)
    assert recorder.full_frames_skipped > 0 and recorder.max_degradation_level > 0
    assert recorder.full_frames_recorded + recorder.full_frames_skipped == 121
    reader = _read(received.getvalue(), tmp_path)
    samples = list(reader.samples())
    assert reader.complete and [s.index for s in samples] == list(range(120))
    assert all(set(s.windows) == {0, 1} for s in samples)
    assert reader.message_counts["/recorder/status"] >= 1
    stop = reader.meta("run_stop")
    assert int(stop["recording_full_frames_skipped"]) == recorder.full_frames_skipped


def test_a_failing_disk_ends_the_recording_with_its_cause(tmp_path):
    read_fd, write_fd = os.pipe()

    def disk_that_fails() -> None:
        taken = 0
        with os.fdopen(read_fd, "rb", buffering=0) as pipe:
            while taken < 300_000 and (chunk := pipe.read(65536)):
                taken += len(chunk)

    disk = threading.Thread(target=disk_that_fails)
    disk.start()
    recorder = McapRecorder(
        tmp_path / "broken.mcap",
        RecordConfig(flush_interval_s=0.01),
        stream=os.fdopen(write_fd, "wb", buffering=0),
    )
    recorder.begin(_facts())
    with pytest.raises(RecordingError, match="broken.mcap: recording failed: .*Broken pipe"):
        for k in range(200):
            recorder(_sample(k, period_ns=1_000_000))
            time.sleep(0.005)
    with pytest.raises(RecordingError, match="broken.mcap"):
        recorder.end(LoopResult())
    disk.join(timeout=10)


def test_an_existing_file_is_never_overwritten(tmp_path):
    path = tmp_path / "kept.mcap"
    path.write_bytes(b"earlier test")
    with pytest.raises(Exception, match="kept.mcap: exists"):
        McapRecorder(path, RecordConfig())
    assert path.read_bytes() == b"earlier test"
