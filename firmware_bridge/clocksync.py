"""The microcontroller's clock as seen from the host: a line fitted to ping round trips.

The trigger microcontroller stamps everything in its own tick (`messages`: Timer1 at 2 MHz,
extended to 64 bits). The host needs those stamps on its own clock (a trigger edge's host
time, to pair it with a camera frame) and the reverse (a start tick for "trigger at host time
T"). Like Klipper's `klippy/clocksync.py`, this module fits the mapping from round trips:

* the host notes its time `sent_ns` just before it writes a PING, the firmware answers PONG
  with the `tick` at which it received the PING, and the host notes `received_ns` when the
  PONG is decoded. The PING's reception lies somewhere in [`sent_ns`, `received_ns`]; the
  round trip's midpoint is the estimate of its host time (`RoundTrip`).
* `ClockSync` keeps the last `window` accepted round trips and fits ``host_ns = a + b * tick``
  by weighted least squares. A round trip longer than the shortest one in the window was
  delayed somewhere, in an unknown direction, so its midpoint is less certain: its weight is
  ``1 / (jitter**2 + excess**2 / 12)`` with ``excess`` the extra round-trip time (an error
  spread evenly over +-excess/2 has that variance); the scatter about the data's own line
  scales the weights to the noise really seen. The slope carries a prior at the nominal tick
  rate (`rate_prior_ppm`), so one sample already gives a usable line and a few jittery round
  trips a few ms apart cannot produce an absurd rate.
* A new round trip whose interval [`sent_ns`, `received_ns`] misses the current prediction by
  more than a few predicted sigmas plus `outlier_floor_ns` is rejected (the host or the line
  stalled in a way the round trip does not show). A long run of rejections means the clock
  itself jumped (a reset the host missed): the window is restarted from the new samples.

This module is pure arithmetic on given numbers; it does no I/O and reads no clock, so it is
tested with synthetic round trips. `firmware_bridge.link.McuLink` feeds it from its pings.

Error model (what `ClockEstimate` reports, all in host nanoseconds):

* **statistical** (`uncertainty_ns(tick)`): 1 sigma of the fitted line at that tick, from the
  weighted residual scatter (never assumed smaller than the weights say); it grows away from
  the window's centre through the slope's uncertainty. It shrinks with more samples.
* **path asymmetry**, which no number of round trips can reveal: if the way out (PING) always
  takes longer than the way back (PONG), every midpoint is early by half the difference. The
  caller may correct a known asymmetry (`asymmetry_ns`, e.g. from the two packets' lengths on
  the wire); what remains is bounded by causality: the true line must pass through every
  round trip's interval, so the line may be shifted by any ``d`` in [`causal_low_ns`,
  `causal_high_ns`] and still be consistent with what was seen. `causal_bound_ns` is the
  largest such shift: the worst-case offset error if the slope is right. It is about half
  the shortest round trip and does not shrink with more samples.

What it does not do: it does not model changes of rate within the window (the default, 64
round trips of the link's 100 ms sync, spans 6.4 s, over which a crystal is straight to well
under 1 ppm), and it cannot detect a constant asymmetry of the path: over simavr's pty, whose
way back is the slower, `appliance.bench.clock_sync` measures the midpoint fit a few hundred
us late against the simulation's pacing.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from dataclasses import dataclass

NS_PER_S = 1_000_000_000


class ClockNotSynced(RuntimeError):
    """A conversion was asked for before any round trip was accepted."""


@dataclass(frozen=True)
class RoundTrip:
    """One PING/PONG round trip.

    Attributes:
        sent_ns: host time just before the PING was written (ns, the host clock).
        tick: the firmware's tick at which it received the PING (ticks).
        received_ns: host time at which the PONG was decoded (ns, the host clock).
    """

    sent_ns: int
    tick: int
    received_ns: int

    @property
    def rtt_ns(self) -> int:
        """Round-trip time (ns)."""
        return self.received_ns - self.sent_ns

    @property
    def midpoint_ns(self) -> float:
        """The round trip's midpoint (host ns): the estimate of the PING's reception."""
        return self.sent_ns + 0.5 * (self.received_ns - self.sent_ns)


@dataclass(frozen=True)
class ClockEstimate:
    """One fit of ``host_ns = host_ref_ns + ns_per_tick * (tick - tick_ref)``; immutable.

    Attributes:
        tick_ref: the weighted centre of the window's ticks (ticks); the line is most certain
            here.
        host_ref_ns: host time of `tick_ref` (ns).
        ns_per_tick: the slope (host ns per tick).
        offset_sigma_ns: 1 sigma of `host_ref_ns` (ns).
        slope_sigma: 1 sigma of `ns_per_tick` (ns per tick).
        residual_rms_ns: weighted RMS of the midpoints about the line (ns).
        min_rtt_ns: shortest round trip in the window (ns).
        causal_low_ns, causal_high_ns: the shifts of the line that keep it inside every round
            trip's [sent, received] interval (ns); low > high when no shift does (the slope or
            the timestamps are off by more than the intervals allow).
        samples: round trips in the fit.
        span_ticks: ticks between the window's first and last sample.
    """

    tick_ref: int
    host_ref_ns: float
    ns_per_tick: float
    offset_sigma_ns: float
    slope_sigma: float
    residual_rms_ns: float
    min_rtt_ns: int
    causal_low_ns: float
    causal_high_ns: float
    samples: int
    span_ticks: int

    @property
    def rate_hz(self) -> float:
        """The estimated tick rate in host seconds (ticks per s)."""
        return NS_PER_S / self.ns_per_tick

    @property
    def rate_ppm(self) -> float:
        """1 sigma of the rate estimate relative to the rate (parts per million)."""
        return 1e6 * self.slope_sigma / self.ns_per_tick

    @property
    def causal_bound_ns(self) -> float:
        """Worst-case offset error allowed by causality, if the slope is right (ns)."""
        return max(abs(self.causal_low_ns), abs(self.causal_high_ns))

    @property
    def consistent(self) -> bool:
        """Whether the line can be shifted into every round trip's interval."""
        return self.causal_low_ns <= self.causal_high_ns

    def host_time_ns(self, tick: int) -> int:
        """Host time (ns, rounded) of a firmware tick."""
        return round(self.host_ref_ns + self.ns_per_tick * (tick - self.tick_ref))

    def tick_at(self, host_ns: int) -> int:
        """The firmware tick (rounded) at a host time (ns)."""
        return self.tick_ref + round((host_ns - self.host_ref_ns) / self.ns_per_tick)

    def uncertainty_ns(self, tick: int | None = None) -> float:
        """1 sigma statistical error of `host_time_ns(tick)` (ns); at the window's centre when
        `tick` is None. Excludes a constant path asymmetry (see `causal_bound_ns`)."""
        distance = 0 if tick is None else tick - self.tick_ref
        return math.hypot(self.offset_sigma_ns, self.slope_sigma * distance)


class ClockSync:
    """Fits the firmware tick -> host time mapping from round trips; thread-safe.

    Args:
        nominal_hz: the tick rate the firmware claims (HELLO_REPLY's `tick_hz`), the slope's
            prior and the rate used before any fit.
        window: how many accepted round trips the fit keeps (the oldest leaves first).
        jitter_ns: the least timing noise assumed of a round trip of the shortest length
            (host scheduling, USB or pty polling, firmware stamping), the floor of each
            sample's sigma (ns); the fit scales it up when the scatter says so, never down.
        rate_prior_ppm: 1 sigma of the prior on the rate around `nominal_hz` (ppm). It
            matters only while the window is short (it keeps a few jittery round trips a few
            ms apart from making a rate off by percent); a clock further off (a ceramic
            resonator is within 0.5 %) is reached as the window grows.
        asymmetry_ns: how much later than its round trip's midpoint a PING is known to be
            received: half the excess of the way out over the way back (ns), added to every
            midpoint. 0 unless the path is known to be asymmetric.
        outlier_sigmas, outlier_floor_ns: a sample whose [sent, received] interval misses the
            prediction by more than ``outlier_sigmas`` predicted sigmas plus the floor is
            rejected once the fit has `min_samples`.
        min_samples: accepted samples before outliers are judged.
        restart_after: consecutive rejections after which the window is restarted.
    """

    def __init__(
        self,
        nominal_hz: float,
        *,
        window: int = 64,
        jitter_ns: float = 100_000.0,
        rate_prior_ppm: float = 500.0,
        asymmetry_ns: float = 0.0,
        outlier_sigmas: float = 5.0,
        outlier_floor_ns: float = 200_000.0,
        min_samples: int = 4,
        restart_after: int = 8,
    ) -> None:
        if nominal_hz <= 0:
            raise ValueError(f"nominal_hz must be positive, got {nominal_hz}")
        if window < 2:
            raise ValueError(f"window must hold at least 2 samples, got {window}")
        if jitter_ns <= 0 or rate_prior_ppm <= 0:
            raise ValueError("jitter_ns and rate_prior_ppm must be positive")
        self.nominal_hz = float(nominal_hz)
        self.jitter_ns = float(jitter_ns)
        self.asymmetry_ns = float(asymmetry_ns)
        self.outlier_sigmas = float(outlier_sigmas)
        self.outlier_floor_ns = float(outlier_floor_ns)
        self.min_samples = int(min_samples)
        self.restart_after = int(restart_after)
        self._nominal_slope = NS_PER_S / self.nominal_hz
        self._prior_precision = 1.0 / (self._nominal_slope * rate_prior_ppm * 1e-6) ** 2
        self._samples: deque[RoundTrip] = deque(maxlen=window)
        self._rejected_run: list[RoundTrip] = []
        self._lock = threading.Lock()
        self._estimate: ClockEstimate | None = None
        self.accepted = 0
        """Round trips accepted since construction."""
        self.rejected = 0
        """Round trips rejected as outliers since construction."""
        self.restarts = 0
        """Times the window was restarted after a run of rejections."""

    def add(self, sample: RoundTrip) -> bool:
        """Offer one round trip; True when it was accepted into the fit.

        Raises:
            ValueError: a round trip that ends before it starts.
        """
        if sample.received_ns < sample.sent_ns:
            raise ValueError(f"round trip ends before it starts: {sample}")
        with self._lock:
            estimate = self._estimate
            if (
                estimate is not None
                and estimate.samples >= self.min_samples
                and not self._plausible(estimate, sample)
            ):
                self.rejected += 1
                self._rejected_run.append(sample)
                if len(self._rejected_run) < self.restart_after:
                    return False
                self.restarts += 1
                self._samples.clear()
                self._samples.extend(self._rejected_run)
                self._rejected_run = []
                self.accepted += 1
                self._estimate = self._fit()
                return True
            self._rejected_run = []
            if self._samples and sample.tick < self._samples[-1].tick:
                self._samples.clear()
                self.restarts += 1
            self._samples.append(sample)
            self.accepted += 1
            self._estimate = self._fit()
            return True

    def reset(self) -> None:
        """Forget every sample (the firmware restarted: its ticks begin again)."""
        with self._lock:
            self._samples.clear()
            self._rejected_run = []
            self._estimate = None

    @property
    def estimate(self) -> ClockEstimate | None:
        """The current fit (an immutable snapshot), or None before the first sample."""
        return self._estimate

    @property
    def synced(self) -> bool:
        """Whether at least one round trip has been accepted."""
        return self._estimate is not None

    @property
    def rate_hz(self) -> float:
        """Estimated tick rate (ticks per host second); `nominal_hz` before the first fit."""
        estimate = self._estimate
        return self.nominal_hz if estimate is None else estimate.rate_hz

    def host_time_ns(self, tick: int) -> int:
        """Host time (ns) of a firmware tick, from the current fit.

        Raises:
            ClockNotSynced: no round trip accepted yet.
        """
        return self._require().host_time_ns(tick)

    def tick_at(self, host_ns: int) -> int:
        """Firmware tick at a host time (ns), from the current fit.

        Raises:
            ClockNotSynced: no round trip accepted yet.
        """
        return self._require().tick_at(host_ns)

    def uncertainty_ns(self, tick: int | None = None) -> float:
        """1 sigma statistical error of `host_time_ns(tick)` (ns); see the module's error
        model. Raises ClockNotSynced before the first sample."""
        return self._require().uncertainty_ns(tick)

    def _require(self) -> ClockEstimate:
        estimate = self._estimate
        if estimate is None:
            raise ClockNotSynced("no PING round trip has been accepted yet")
        return estimate

    def _plausible(self, estimate: ClockEstimate, sample: RoundTrip) -> bool:
        predicted = estimate.host_ref_ns + estimate.ns_per_tick * (sample.tick - estimate.tick_ref)
        margin = self.outlier_sigmas * math.hypot(
            estimate.uncertainty_ns(sample.tick), estimate.residual_rms_ns
        )
        margin += self.outlier_floor_ns
        return sample.sent_ns - margin <= predicted <= sample.received_ns + margin

    def _fit(self) -> ClockEstimate:
        samples = list(self._samples)
        tick0 = samples[0].tick
        host0 = samples[0].sent_ns
        min_rtt = min(s.rtt_ns for s in samples)
        xs = [float(s.tick - tick0) for s in samples]
        ys = [s.midpoint_ns - host0 + self.asymmetry_ns for s in samples]
        weights = [1.0 / (self.jitter_ns**2 + (s.rtt_ns - min_rtt) ** 2 / 12.0) for s in samples]
        total = sum(weights)
        x_mean = sum(w * x for w, x in zip(weights, xs, strict=True)) / total
        y_mean = sum(w * y for w, y in zip(weights, ys, strict=True)) / total
        sxx = sum(w * (x - x_mean) ** 2 for w, x in zip(weights, xs, strict=True))
        sxy = sum(w * (x - x_mean) * (y - y_mean) for w, x, y in zip(weights, xs, ys, strict=True))
        n = len(samples)

        def chi2_of(slope: float) -> float:
            return sum(
                w * (y - y_mean - slope * (x - x_mean)) ** 2
                for w, x, y in zip(weights, xs, ys, strict=True)
            )

        # The weights are only relative: the noise scale comes from the scatter about the
        # data's own line, so the prior competes with what the data really says (and a rate
        # far from nominal does not inflate the scale by its misfit to the prior).
        scale = 1.0
        if n > 2 and sxx > 0:
            scale = max(1.0, chi2_of(sxy / sxx) / (n - 2))
        precision = sxx / scale + self._prior_precision
        slope = (sxy / scale + self._prior_precision * self._nominal_slope) / precision
        residual_rms = math.sqrt(chi2_of(slope) / total)
        tick_ref = tick0 + round(x_mean)
        host_ref = host0 + y_mean + slope * (tick_ref - tick0 - x_mean)
        low = -math.inf
        high = math.inf
        for s in samples:
            on_line = host_ref + slope * (s.tick - tick_ref)
            low = max(low, s.sent_ns - on_line)
            high = min(high, s.received_ns - on_line)
        return ClockEstimate(
            tick_ref=tick_ref,
            host_ref_ns=host_ref,
            ns_per_tick=slope,
            offset_sigma_ns=math.sqrt(scale / total),
            slope_sigma=math.sqrt(1.0 / precision),
            residual_rms_ns=residual_rms,
            min_rtt_ns=min_rtt,
            causal_low_ns=low,
            causal_high_ns=high,
            samples=n,
            span_ticks=samples[-1].tick - tick0,
        )
