import numba
import numpy as np
import pytest

from hal.camera.base import CameraSettings, PixelFormat, Region, TriggerInfo, TriggerMode
from hal.camera.sim import NOISE_TABLE_BITS, digitise, frame_noise_key, normal_levels
from hal.clock import Pace, SimClock
from hal.errors import HardwareConfigError, HardwareTimeout
from hal.machine.base import MachineState
from hal.registry import camera_from_url, machine_from_url


class RampScene:
    """Grey level = 100 + 10 * (mid-exposure time in s), plus the column index."""

    sensor_width = 64
    sensor_height = 48

    def __init__(self):
        self.calls = []

    def render(self, start_s, stop_s, region):
        self.calls.append((start_s, stop_s, region))
        mid = 0.5 * (start_s + stop_s)
        cols = np.arange(region.x, region.x + region.width, dtype=float)
        image = np.tile(100.0 + 10.0 * mid + cols, (region.height, 1))
        return image, {"mid_s": mid}


class LinearMachine:
    def __init__(self):
        self.speed = 0.0
        self.t0 = 0.0
        self.x0 = 0.0

    def state(self, t_s):
        x = self.x0 + self.speed / 60.0 * (t_s - self.t0)
        return MachineState(x, self.speed, 2.0 * x, self.speed != 0, int(t_s * 1e9))

    def start(self, speed_mm_min, t_s):
        self.x0, self.t0, self.speed = self.state(t_s).crosshead_mm, t_s, speed_mm_min

    def stop(self, t_s):
        self.start(0.0, t_s)

    def return_to_start(self, speed_mm_min, t_s):
        self.start(-abs(speed_mm_min), t_s)


def noiseless_camera(scene, clock, **kwargs):
    camera = camera_from_url(
        "sim://camera", scene=scene, clock=clock, read_noise=0.0, electrons_per_grey=0.0, **kwargs
    )
    camera.open()
    return camera


def test_internal_trigger_timestamps_exposure_and_values():
    clock, scene = SimClock(), RampScene()
    camera = noiseless_camera(scene, clock)
    camera.configure(CameraSettings(exposure_us=2000.0))
    camera.prepare(TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=50.0, frames=3))
    camera.arm()
    frames = [camera.fetch(1.0) for _ in range(3)]
    assert [f.frame_id for f in frames] == [0, 1, 2]
    assert [f.timestamp_ns for f in frames] == [0, 20_000_000, 40_000_000]
    assert frames[1].image.dtype == np.uint8 and frames[1].image.shape == (48, 64)
    assert frames[1].image[0, 5] == round(100 + 10 * 0.021 + 5)
    assert clock.now_s() == pytest.approx(0.042)
    with pytest.raises(HardwareTimeout):
        camera.fetch(0.1)


def test_software_and_external_triggers():
    clock, scene = SimClock(), RampScene()
    camera = noiseless_camera(scene, clock)
    camera.prepare(TriggerInfo(mode=TriggerMode.SOFTWARE))
    camera.arm()
    with pytest.raises(HardwareTimeout, match="no trigger"):
        camera.fetch(0.5)
    assert clock.now_s() == pytest.approx(0.5)
    camera.trigger()
    assert camera.fetch(0.5).timestamp_ns == 500_000_000
    camera.disarm()
    camera.prepare(TriggerInfo(mode=TriggerMode.EXTERNAL))
    camera.arm()
    with pytest.raises(HardwareConfigError, match="software trigger"):
        camera.trigger()
    camera.external_edge(1.25)
    frame = camera.fetch(0.5)
    assert frame.timestamp_ns == 1_250_000_000
    assert frame.metadata["truth"]["mid_s"] == pytest.approx(1.25 + 0.0005)


def test_region_pixel_formats_and_settings_guard():
    clock, scene = SimClock(), RampScene()
    camera = noiseless_camera(scene, clock)
    applied = camera.configure(
        CameraSettings(
            exposure_us=100.0, region=Region(10, 4, 20, 8), pixel_format=PixelFormat.MONO12
        )
    )
    assert applied.region == Region(10, 4, 20, 8)
    camera.prepare(TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=10.0))
    camera.arm()
    frame = camera.fetch(1.0)
    assert frame.image.shape == (8, 20) and frame.image.dtype == np.uint16
    assert frame.image[0, 0] == round((100 + 10 * 0.00005 + 10) * 16)
    with pytest.raises(HardwareConfigError, match="armed"):
        camera.configure(CameraSettings(exposure_us=10.0))
    camera.disarm()
    with pytest.raises(HardwareConfigError, match="exceeds"):
        camera.configure(CameraSettings(exposure_us=10.0, region=Region(60, 0, 10, 10)))


def test_noise_is_seeded_and_has_the_requested_level():
    def grab(seed):
        camera = camera_from_url(
            "sim://camera",
            scene=RampScene(),
            clock=SimClock(),
            seed=seed,
            read_noise=2.0,
            electrons_per_grey=0.0,
        )
        camera.open()
        camera.configure(CameraSettings(exposure_us=10.0, pixel_format=PixelFormat.MONO16))
        camera.prepare(TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=1.0))
        camera.arm()
        return camera.fetch(1.0).image.astype(float) / 256.0

    a, b, c = grab(1), grab(1), grab(2)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    clean = np.tile(100.0 + 10 * 5e-6 + np.arange(64.0), (48, 1))
    assert np.std(a - clean) == pytest.approx(2.0, rel=0.1)


def test_shot_and_read_noise_have_the_model_mean_and_variance():
    """Per grey level, the digitised pixels' mean is the signal times the gain and their
    variance gain * grey / electrons_per_grey + read_noise**2 (Mono16: quantisation apart)."""
    levels = [2.0, 20.0, 60.0, 110.0]
    signal = np.repeat(np.float32(levels), 200_000).reshape(len(levels), -1)
    for gain_db in (0.0, 6.0):
        gain = 10.0 ** (gain_db / 20.0)
        counts = digitise(
            signal,
            frame_noise_key(3, int(gain_db)),
            gain_db=gain_db,
            electrons_per_grey=40.0,
            read_noise_grey=0.5,
            pixel_format=PixelFormat.MONO16,
        )
        grey = counts.astype(float) / 256.0
        for level, row in zip(levels, grey, strict=True):
            expected_var = gain * gain * level / 40.0 + 0.25
            assert row.mean() == pytest.approx(
                gain * level, abs=5 * np.sqrt(expected_var / row.size)
            )
            assert row.var() == pytest.approx(expected_var, rel=0.02)


def test_digitised_pixels_clip_at_the_format_limits():
    signal = np.array([[-5.0, 0.0, 300.0, 255.0]], dtype=np.float32)
    common = {"gain_db": 0.0, "electrons_per_grey": 0.0, "read_noise_grey": 0.0}
    mono8 = digitise(signal, 0, pixel_format=PixelFormat.MONO8, **common)
    mono16 = digitise(signal, 0, pixel_format=PixelFormat.MONO16, **common)
    assert mono8.dtype == np.uint8 and mono8.tolist() == [[0, 0, 255, 255]]
    assert mono16.dtype == np.uint16 and mono16.tolist() == [[0, 0, 65535, 65280]]


def _splitmix64(values):
    """SplitMix64's output function on uint64 arrays (numpy wraps modulo 2**64)."""
    z = values + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def _digitise_by_definition(signal, key, gain_db, electrons_per_grey, read_noise_grey, fmt):
    """`digitise` as its docstring defines it, in whole-array numpy operations."""
    gain = np.float32(10.0 ** (gain_db / 20.0))
    grey = signal.astype(np.float32) * gain
    shot = np.float32(gain / electrons_per_grey) if electrons_per_grey else np.float32(0.0)
    variance = np.float32(read_noise_grey) ** 2 + np.maximum(grey, np.float32(0.0)) * shot
    index = np.arange(signal.size, dtype=np.uint64).reshape(signal.shape)
    with np.errstate(over="ignore"):
        counter = np.uint64(key) + index * np.uint64(0x9E3779B97F4A7C15)
        draws = normal_levels()[_splitmix64(counter) >> np.uint64(64 - NOISE_TABLE_BITS)]
    grey = (grey + draws * np.sqrt(variance)) * np.float32((fmt.max_value + 1) / 256.0)
    counts = np.clip(np.rint(grey), np.float32(0.0), np.float32(fmt.max_value))
    return counts.astype(np.uint8 if fmt is PixelFormat.MONO8 else np.uint16)


@pytest.mark.parametrize("fmt", [PixelFormat.MONO8, PixelFormat.MONO16])
def test_digitised_pixels_are_their_definition_bit_for_bit(fmt):
    signal = np.random.default_rng(5).uniform(-10.0, 270.0, (37, 53))
    for gain_db, electrons in ((0.0, 40.0), (6.0, 25.0), (3.0, 0.0)):
        key = frame_noise_key(11, int(gain_db))
        counts = digitise(
            signal,
            key,
            gain_db=gain_db,
            electrons_per_grey=electrons,
            read_noise_grey=0.7,
            pixel_format=fmt,
        )
        expected = _digitise_by_definition(signal, key, gain_db, electrons, 0.7, fmt)
        assert counts.dtype == expected.dtype
        assert np.array_equal(counts, expected)


def test_a_frame_is_the_same_on_any_number_of_threads():
    signal = np.random.default_rng(6).uniform(0.0, 255.0, (301, 257))
    noise = {
        "gain_db": 0.0,
        "electrons_per_grey": 40.0,
        "read_noise_grey": 0.5,
        "pixel_format": PixelFormat.MONO16,
    }
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        alone = digitise(signal, 7, **noise)
    finally:
        numba.set_num_threads(threads)
    assert np.array_equal(digitise(signal, 7, **noise), alone)
    assert not np.array_equal(digitise(signal, 8, **noise), alone)


def test_the_normal_levels_are_a_standard_normal_law():
    levels = normal_levels().astype(np.float64)
    assert levels.size == 2**NOISE_TABLE_BITS
    assert np.all(np.diff(levels) > 0)
    assert np.array_equal(levels, -levels[::-1])
    assert np.mean(levels**2) == pytest.approx(1.0, abs=1e-6)
    assert levels[-1] == pytest.approx(4.325, abs=0.002)
    quartile = levels[3 * levels.size // 4]
    assert quartile == pytest.approx(0.6745, abs=1e-3)
    assert np.mean(levels**4) == pytest.approx(3.0, rel=2e-3)


def test_sim_machine_reads_the_shared_clock_and_obeys_configuration():
    clock, machine = SimClock(), LinearMachine()
    controller = machine_from_url("sim://machine", machine=machine, clock=clock)
    controller.open()
    controller.start(60.0)
    clock.wait_until(2.0)
    state = controller.read_state()
    assert state.crosshead_mm == pytest.approx(2.0) and state.running
    assert state.timestamp_ns == 2_000_000_000
    locked = machine_from_url("sim://machine", machine=machine, clock=clock, accepts_commands=False)
    with pytest.raises(HardwareConfigError, match="command stop"):
        locked.stop()


def test_registry_names_the_bad_url():
    with pytest.raises(HardwareConfigError, match="unknown scheme gige://"):
        camera_from_url("gige://1.2.3.4")
    with pytest.raises(HardwareConfigError, match="no scheme"):
        machine_from_url("localhost:502")


def test_real_time_clock_sleeps_with_the_injected_sleep():
    now = [100.0]
    slept = []

    def sleep(seconds):
        slept.append(seconds)
        now[0] += seconds

    clock = SimClock(Pace.REAL_TIME, wall=lambda: now[0], sleep=sleep)
    clock.wait_until(0.25)
    assert slept == [pytest.approx(0.25)] and clock.now_s() == pytest.approx(0.25)
    clock.wait_until(0.1)
    assert len(slept) == 1


def test_a_real_time_camera_loses_the_exposures_a_slow_host_misses():
    now = [0.0]

    def sleep(seconds):
        now[0] += seconds

    clock = SimClock(Pace.REAL_TIME, wall=lambda: now[0], sleep=sleep)
    camera = noiseless_camera(RampScene(), clock, buffers=1)
    camera.configure(CameraSettings(exposure_us=1000.0))
    camera.prepare(TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=100.0))
    camera.arm()
    first = camera.fetch(1.0)
    now[0] += 0.035
    late = camera.fetch(1.0)
    on_time = camera.fetch(1.0)
    assert (first.frame_id, late.frame_id, on_time.frame_id) == (0, 3, 4)
    assert [f.timestamp_ns for f in (first, late, on_time)] == [0, 30_000_000, 40_000_000]


@pytest.mark.parametrize(
    ("busy_s", "frame_ids"), [(0.025, [0, 1, 2, 3, 4]), (0.065, [0, 4, 5, 6, 7])]
)
def test_a_real_time_camera_buffers_the_frames_a_busy_host_has_not_fetched(busy_s, frame_ids):
    """Three buffers at 100 Hz: a host 25 ms late gets every frame; 65 ms late (frames 1 to
    6 exposed meanwhile), the three latest wait for it and the others are lost."""
    now = [0.0]

    def sleep(seconds):
        now[0] += seconds

    clock = SimClock(Pace.REAL_TIME, wall=lambda: now[0], sleep=sleep)
    camera = noiseless_camera(RampScene(), clock, buffers=3)
    camera.configure(CameraSettings(exposure_us=1000.0))
    camera.prepare(TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=100.0))
    camera.arm()
    frames = [camera.fetch(1.0)]
    now[0] += busy_s
    frames += [camera.fetch(1.0) for _ in range(4)]
    assert [f.frame_id for f in frames] == frame_ids
    assert [f.timestamp_ns for f in frames] == [i * 10_000_000 for i in frame_ids]
    assert now[0] == pytest.approx(max(busy_s + 0.001, frame_ids[-1] * 0.01 + 0.001))


def test_a_sim_camera_needs_a_buffer():
    with pytest.raises(HardwareConfigError, match="buffers=0"):
        camera_from_url("sim://camera", scene=RampScene(), clock=SimClock(), buffers=0)


def test_the_noise_is_white_within_a_frame_and_independent_between_frames():
    """Flat frames' noise: no correlation between a pixel and its neighbours, and none between
    consecutive frames (or two seeds' frames) at any offset of the pixels' order, as a sum of
    independent draws would show (largest |r| within 7 / sqrt(pixels))."""
    signal = np.full((256, 256), 100.0, dtype=np.float32)
    noise = {
        "gain_db": 0.0,
        "electrons_per_grey": 0.0,
        "read_noise_grey": 3.0,
        "pixel_format": PixelFormat.MONO16,
    }

    def frame(seed, index):
        counts = digitise(signal, frame_noise_key(seed, index), **noise).astype(float)
        return (counts - counts.mean()) / counts.std()

    first, second, other_seed = frame(1, 0), frame(1, 1), frame(2, 0)
    bound = 7.0 / np.sqrt(signal.size)
    for dy, dx in ((0, 1), (1, 0), (1, 1), (0, 2), (2, 0)):
        r = np.mean(first[dy:, dx:] * first[: first.shape[0] - dy, : first.shape[1] - dx])
        assert abs(r) < bound, (dy, dx, r)
    spectrum = np.fft.rfft(first.ravel())
    for later in (second, other_seed):
        lagged = np.fft.irfft(np.conj(spectrum) * np.fft.rfft(later.ravel()), n=first.size)
        assert np.max(np.abs(lagged)) / first.size < bound
