"""ClockSync against synthetic round trips with a known offset, drift and delay jitter."""

from __future__ import annotations

import random
from dataclasses import dataclass

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_bridge.clocksync import ClockNotSynced, ClockSync, RoundTrip

NOMINAL_HZ = 2_000_000


@dataclass
class SyntheticMcu:
    """A firmware clock: tick = (host_ns - boot_host_ns) * rate / 1e9, rate off by drift."""

    drift_ppm: float
    boot_host_ns: int

    @property
    def rate_hz(self) -> float:
        return NOMINAL_HZ * (1.0 + self.drift_ppm * 1e-6)

    def tick(self, host_ns: float) -> int:
        return int((host_ns - self.boot_host_ns) * self.rate_hz / 1e9)

    def host_ns(self, tick: int) -> float:
        return self.boot_host_ns + tick * 1e9 / self.rate_hz


def round_trips(
    mcu: SyntheticMcu,
    count: int,
    *,
    start_ns: int = 5_000_000_000,
    interval_ns: int = 50_000_000,
    out_ns: float = 300_000.0,
    back_ns: float = 300_000.0,
    jitter_ns: float = 100_000.0,
    seed: int = 1,
) -> list[RoundTrip]:
    """Pings every interval; each direction takes its base delay plus exponential jitter."""
    rng = random.Random(seed)
    samples = []
    for i in range(count):
        sent = start_ns + i * interval_ns + rng.randrange(0, 1_000_000)
        reception = sent + out_ns + rng.expovariate(1.0 / jitter_ns)
        received = reception + back_ns + rng.expovariate(1.0 / jitter_ns)
        samples.append(RoundTrip(sent, mcu.tick(reception), round(received)))
    return samples


def fed(samples: list[RoundTrip], **kwargs) -> ClockSync:
    sync = ClockSync(NOMINAL_HZ, **kwargs)
    for sample in samples:
        sync.add(sample)
    return sync


def test_before_any_sample_conversions_refuse():
    sync = ClockSync(NOMINAL_HZ)
    assert not sync.synced
    assert sync.rate_hz == NOMINAL_HZ
    with pytest.raises(ClockNotSynced):
        sync.host_time_ns(0)
    with pytest.raises(ClockNotSynced):
        sync.tick_at(0)


def test_one_sample_gives_the_nominal_rate_through_its_midpoint():
    sync = ClockSync(NOMINAL_HZ)
    assert sync.add(RoundTrip(1_000_000, 4000, 1_600_000))
    assert sync.host_time_ns(4000) == 1_300_000
    assert sync.host_time_ns(6000) == 1_300_000 + 1_000_000
    assert sync.rate_hz == pytest.approx(NOMINAL_HZ)


@pytest.mark.parametrize("drift_ppm", [-150.0, 0.0, 42.0, 3000.0])
def test_symmetric_jittery_delays_give_small_error_and_the_drift(drift_ppm):
    mcu = SyntheticMcu(drift_ppm, boot_host_ns=1_234_567_891)
    samples = round_trips(mcu, 200)
    sync = fed(samples)
    estimate = sync.estimate
    assert estimate is not None and estimate.samples == 64
    assert sync.rate_hz == pytest.approx(mcu.rate_hz, rel=5e-6)
    last = samples[-1]
    for tick in (last.tick, last.tick + 200_000, estimate.tick_ref):
        error = sync.host_time_ns(tick) - mcu.host_ns(tick)
        assert abs(error) < 30_000
        assert abs(error) < 6 * sync.uncertainty_ns(tick) + 2_000
    assert estimate.consistent
    assert abs(sync.host_time_ns(last.tick) - mcu.host_ns(last.tick)) <= (
        estimate.causal_bound_ns + 1_000
    )
    assert sync.rejected == 0


def test_tick_at_inverts_host_time():
    mcu = SyntheticMcu(25.0, boot_host_ns=0)
    sync = fed(round_trips(mcu, 80))
    for tick in (10_000_000, 12_345_678, 20_000_000):
        assert abs(sync.tick_at(sync.host_time_ns(tick)) - tick) <= 1


def test_path_asymmetry_is_a_bias_within_the_causal_bound_and_can_be_subtracted():
    mcu = SyntheticMcu(0.0, boot_host_ns=0)
    samples = round_trips(mcu, 120, out_ns=500_000, back_ns=100_000, jitter_ns=20_000)
    tick = samples[-1].tick
    biased = fed(samples)
    error = biased.host_time_ns(tick) - mcu.host_ns(tick)
    assert error == pytest.approx(-200_000, abs=25_000)
    assert abs(error) <= biased.estimate.causal_bound_ns + 1_000
    assert biased.estimate.causal_bound_ns < 0.5 * biased.estimate.min_rtt_ns + 30_000
    corrected = fed(samples, asymmetry_ns=200_000)
    assert abs(corrected.host_time_ns(tick) - mcu.host_ns(tick)) < 15_000


def test_long_round_trips_weigh_little():
    mcu = SyntheticMcu(10.0, boot_host_ns=0)
    samples = round_trips(mcu, 100, jitter_ns=10_000)
    stalled = []
    for i, s in enumerate(samples):
        if i % 3 == 0:
            s = RoundTrip(s.sent_ns, s.tick, s.received_ns + 40_000_000)
        stalled.append(s)
    sync = fed(stalled)
    tick = samples[-1].tick
    assert abs(sync.host_time_ns(tick) - mcu.host_ns(tick)) < 15_000


def test_an_inconsistent_sample_is_rejected_and_leaves_the_fit_alone():
    mcu = SyntheticMcu(0.0, boot_host_ns=0)
    samples = round_trips(mcu, 40, jitter_ns=10_000)
    sync = fed(samples)
    before = sync.estimate
    last = samples[-1]
    ten_ms_late = last.tick + 100_000 + 20_000
    wrong = RoundTrip(last.sent_ns + 50_000_000, ten_ms_late, last.received_ns + 50_000_000)
    assert not sync.add(wrong)
    assert sync.rejected == 1
    assert sync.estimate is before


def test_a_clock_that_jumps_restarts_the_window():
    first = SyntheticMcu(0.0, boot_host_ns=0)
    second = SyntheticMcu(0.0, boot_host_ns=9_000_000_000)
    sync = fed(round_trips(first, 30))
    later = round_trips(second, 30, start_ns=10_000_000_000, seed=2)
    for sample in later:
        sync.add(sample)
    assert sync.restarts >= 1
    tick = later[-1].tick
    assert abs(sync.host_time_ns(tick) - second.host_ns(tick)) < 40_000


def test_reset_forgets():
    sync = fed(round_trips(SyntheticMcu(0.0, boot_host_ns=0), 10))
    sync.reset()
    assert not sync.synced


def test_a_round_trip_that_ends_before_it_starts_is_refused():
    with pytest.raises(ValueError):
        ClockSync(NOMINAL_HZ).add(RoundTrip(10, 0, 5))


@settings(max_examples=40, deadline=None)
@given(
    offset_ns=st.integers(0, 10**15),
    drift_ppm=st.floats(-500, 500),
    out_ns=st.floats(50_000, 2_000_000),
    jitter_ns=st.floats(1_000, 300_000),
    seed=st.integers(0, 2**16),
)
def test_error_stays_within_half_the_round_trip_plus_jitter(
    offset_ns, drift_ppm, out_ns, jitter_ns, seed
):
    mcu = SyntheticMcu(drift_ppm, boot_host_ns=offset_ns)
    samples = round_trips(
        mcu,
        70,
        start_ns=offset_ns + 1_000_000_000,
        out_ns=out_ns,
        back_ns=out_ns,
        jitter_ns=jitter_ns,
        seed=seed,
    )
    sync = fed(samples)
    tick = samples[-1].tick
    error = sync.host_time_ns(tick) - mcu.host_ns(tick)
    assert abs(error) < 0.5 * jitter_ns + 10_000
    assert sync.rate_hz == pytest.approx(mcu.rate_hz, rel=100e-6)


def test_a_few_jittery_round_trips_close_together_give_no_absurd_rate():
    mcu = SyntheticMcu(0.0, boot_host_ns=0)
    samples = round_trips(mcu, 8, interval_ns=2_000_000, jitter_ns=150_000, seed=7)
    sync = fed(samples)
    assert abs(sync.rate_hz / NOMINAL_HZ - 1) < 1000e-6


def test_the_rate_prior_does_not_hold_back_a_clock_far_from_nominal():
    mcu = SyntheticMcu(4000.0, boot_host_ns=0)
    sync = fed(round_trips(mcu, 64, interval_ns=100_000_000, jitter_ns=150_000, seed=3))
    assert sync.rate_hz == pytest.approx(mcu.rate_hz, rel=20e-6)
