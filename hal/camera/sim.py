"""Simulated camera: the `Camera` protocol over a rendered `Scene` and a shared `SimClock`.

URL: `sim://camera` (the path is free text). Constructed by the registry as
`SimCamera(url, scene=..., clock=..., seed=..., read_noise=..., full_well_ratio=...)`.

What it models: exposure timing for INTERNAL (fixed rate), SOFTWARE and EXTERNAL triggers
(an external edge is delivered by `external_edge(t_s)`, or asked of the `trigger_line` the
camera is wired to, as a trigger microcontroller's output would drive it);
exposure integration (the scene renders over [start, start + exposure]); gain as a factor on
the signal; read noise and shot noise (see `digitise`); quantisation to Mono8 or Mono12/16
with clipping; the sensor region; frame ids and device timestamps (start of exposure, ns, from
the simulation clock).

Fault injection: `hang_after_s` makes the camera stop answering that long (simulation time)
after it was first armed, as a hung driver does: `fetch` blocks, ignoring its timeout, until
the camera is disarmed or closed, then raises `HardwareConnectError`. It exists to prove that
the service's watchdog catches a measurement that stalls.

In real time, the internal trigger keeps the camera's own time: the frames exposed while the
host (or the renderer) is busy wait in `buffers` host buffers, as a GigE Vision stream's pool
of buffers holds them (the Aravis backend's default is 16); when the host falls behind by more
than that many frame periods, the exposures that found no buffer are lost and the frame ids
skip them. As fast as possible, nothing is ever missed.

The optics and the light are the scene's: a scene may render through a distorting, tilted
lens with flicker, vibration and drift (the simulated bench, `appliance.sim.bench_scene`);
the camera only exposes, adds noise and quantises what it renders.

What it does not model: vignetting, rolling shutter, dark current and fixed pattern noise,
corrupted frames, transport latency or bandwidth limits, trigger jitter (edges are exact), or
readout time limiting the frame rate.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import math
import threading
from typing import Any, Protocol, runtime_checkable

import numba
import numpy as np
from scipy import special

from hal.camera.base import (
    CameraSettings,
    Frame,
    PixelFormat,
    Region,
    Scene,
    TriggerInfo,
    TriggerMode,
)
from hal.clock import Pace, SimClock
from hal.errors import HardwareConfigError, HardwareConnectError, HardwareTimeout


@runtime_checkable
class TriggerLine(Protocol):
    """The simulated trigger input: when the next rising edge comes (a simulated trigger
    microcontroller answers from its configuration and the machine's motion)."""

    def next_edge_s(self, after_s: float) -> float | None:
        """Simulation time of the first edge after `after_s`, s; None = no more edges."""


class SimCamera:
    """A camera that renders its `Scene` at every trigger.

    Args:
        url: the device URL (kept for messages).
        scene: what the camera sees.
        clock: the shared simulation clock.
        seed: seed of the noise generator (frames are reproducible for a seed).
        read_noise: standard deviation of the read noise, grey levels on the 8-bit scale.
        electrons_per_grey: conversion gain for shot noise at unit gain (8-bit scale); 0 =
            no shot noise.
        hang_after_s: simulation time after the first `arm` from which the camera hangs
            (see the module docstring); None = never.
        trigger_line: what drives the trigger input in EXTERNAL mode besides
            `external_edge` calls; None = only those.
        buffers: frames the host's buffers hold in real time with the internal trigger
            (>= 1; see the module docstring).
    """

    def __init__(
        self,
        url: str,
        *,
        scene: Scene,
        clock: SimClock,
        seed: int = 0,
        read_noise: float = 0.5,
        electrons_per_grey: float = 40.0,
        hang_after_s: float | None = None,
        trigger_line: TriggerLine | None = None,
        buffers: int = 16,
        **_: Any,
    ) -> None:
        if buffers < 1:
            raise HardwareConfigError(f"{url}: buffers={buffers} must be >= 1")
        self.url = url
        self._buffers = int(buffers)
        self._scene = scene
        self._clock = clock
        self._seed = seed
        self._noise_frames = 0
        self._read_noise = read_noise
        self._electrons_per_grey = electrons_per_grey
        self._settings = CameraSettings(exposure_us=1000.0)
        self._trigger = TriggerInfo(mode=TriggerMode.SOFTWARE)
        self._open = False
        self._armed = False
        self._pending: collections.deque[float] = collections.deque()
        self._next_internal_s = 0.0
        self._delivered = 0
        self._frame_id = 0
        self._hang_after_s = hang_after_s
        self._first_armed_s: float | None = None
        self._released = threading.Event()
        self._trigger_line = trigger_line
        self._last_edge_s = -math.inf

    def wire_trigger_input(self, line: TriggerLine | None) -> None:
        """Connect the trigger input to `line` (while disarmed); None = edges only from
        `external_edge`."""
        if self._armed:
            raise HardwareConfigError(f"{self.url}: cannot rewire the trigger input while armed")
        self._trigger_line = line

    @property
    def sensor_size(self) -> tuple[int, int]:
        """Sensor (width, height), px."""
        return self._scene.sensor_width, self._scene.sensor_height

    def open(self, timeout_s: float = 5.0) -> None:
        self._open = True

    def close(self) -> None:
        self._armed = False
        self._open = False
        self._released.set()

    def configure(self, settings: CameraSettings) -> CameraSettings:
        if self._armed:
            raise HardwareConfigError(f"{self.url}: cannot configure while armed")
        region = settings.region or Region(0, 0, *self.sensor_size)
        width, height = self.sensor_size
        if region.x + region.width > width or region.y + region.height > height:
            raise HardwareConfigError(
                f"{self.url}: region {region} exceeds the {width}x{height} sensor"
            )
        self._settings = dataclasses.replace(settings, region=region)
        return self._settings

    def prepare(self, trigger: TriggerInfo) -> None:
        if self._armed:
            raise HardwareConfigError(f"{self.url}: cannot prepare while armed")
        self._trigger = trigger
        if trigger.exposure_us is not None:
            self._settings = dataclasses.replace(self._settings, exposure_us=trigger.exposure_us)

    def arm(self) -> None:
        if not self._open:
            raise HardwareConfigError(f"{self.url}: arm before open")
        self._armed = True
        self._released.clear()
        self._pending.clear()
        self._delivered = 0
        self._next_internal_s = self._clock.now_s()
        self._last_edge_s = -math.inf
        if self._first_armed_s is None:
            self._first_armed_s = self._next_internal_s

    def disarm(self) -> None:
        self._armed = False
        self._pending.clear()
        self._released.set()

    def trigger(self) -> None:
        if self._trigger.mode is not TriggerMode.SOFTWARE:
            raise HardwareConfigError(
                f"{self.url}: software trigger in {self._trigger.mode.value} mode"
            )
        self._pending.append(self._clock.now_s())

    def set_exposure(self, exposure_us: float) -> float:
        if not (exposure_us > 0 and math.isfinite(exposure_us)):
            raise HardwareConfigError(f"{self.url}: exposure_us={exposure_us:g} must be > 0")
        self._settings = dataclasses.replace(self._settings, exposure_us=float(exposure_us))
        return self._settings.exposure_us

    def external_edge(self, t_s: float) -> None:
        """An edge on the trigger input at simulation time `t_s` (EXTERNAL mode)."""
        if self._armed and self._trigger.mode is TriggerMode.EXTERNAL:
            self._pending.append(t_s)

    def fetch(self, timeout_s: float) -> Frame:
        if not self._armed:
            raise HardwareConfigError(f"{self.url}: fetch while not armed")
        if self._trigger.frames and self._delivered >= self._trigger.frames:
            raise HardwareTimeout(f"{self.url}: all {self._trigger.frames} frames delivered")
        start = self._next_start(timeout_s)
        hang_from_s = (self._first_armed_s or 0.0) + (self._hang_after_s or 0.0)
        if self._hang_after_s is not None and start >= hang_from_s:
            self._released.wait()
            raise HardwareConnectError(f"{self.url}: the camera stopped answering")
        exposure_s = self._settings.exposure_us * 1e-6
        self._clock.wait_until(start + exposure_s)
        region = self._settings.region or Region(0, 0, *self.sensor_size)
        signal, truth = self._scene.render(start, start + exposure_s, region)
        image = self._digitise(signal)
        frame = Frame(
            image=image,
            frame_id=self._frame_id,
            timestamp_ns=int(round(start * 1e9)),
            exposure_us=self._settings.exposure_us,
            metadata={"truth": truth},
        )
        self._frame_id += 1
        self._delivered += 1
        return frame

    def statistics(self) -> dict[str, Any]:
        """{}: the simulator keeps no transport counters (its frame ids show lost exposures)."""
        return {}

    def _next_start(self, timeout_s: float) -> float:
        mode = self._trigger.mode
        if mode is TriggerMode.INTERNAL:
            period = 1.0 / float(self._trigger.rate_hz)
            start = self._next_internal_s
            if self._clock.pace is Pace.REAL_TIME:
                late = self._clock.now_s() - (start + self._settings.exposure_us * 1e-6)
                if late > self._buffers * period:
                    missed = int(late // period) - (self._buffers - 1)
                    start += missed * period
                    self._frame_id += missed
            self._next_internal_s = start + period
            return start
        if not self._pending and mode is TriggerMode.EXTERNAL and self._trigger_line is not None:
            edge = self._trigger_line.next_edge_s(self._last_edge_s)
            if edge is not None and edge <= self._clock.now_s() + timeout_s:
                self._pending.append(edge)
        if not self._pending:
            self._clock.wait_until(self._clock.now_s() + timeout_s)
            raise HardwareTimeout(f"{self.url}: no trigger within {timeout_s:g} s")
        self._last_edge_s = self._pending[0]
        return self._pending.popleft()

    def _digitise(self, signal: np.ndarray) -> np.ndarray:
        key = frame_noise_key(self._seed, self._noise_frames)
        self._noise_frames += 1
        return digitise(
            signal,
            key,
            gain_db=self._settings.gain_db,
            electrons_per_grey=self._electrons_per_grey,
            read_noise_grey=self._read_noise,
            pixel_format=self._settings.pixel_format,
        )


NOISE_TABLE_BITS = 16
"""The camera noise is drawn from 2**NOISE_TABLE_BITS equally likely levels of the standard
normal law (its quantiles at the levels' centres), see `normal_levels`."""

_GOLDEN = 0x9E3779B97F4A7C15
_MASK64 = (1 << 64) - 1


def splitmix64(value: int) -> int:
    """SplitMix64's output function of a 64-bit integer (Steele, Lea and Flood 2014): a
    bijection of [0, 2**64) whose outputs for consecutive inputs pass BigCrush."""
    z = (value + _GOLDEN) & _MASK64
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _MASK64
    return z ^ (z >> 31)


def frame_noise_key(seed: int, frame: int) -> int:
    """The noise key of a camera's `frame`-th image (from 0) for its `seed`."""
    return splitmix64((splitmix64(seed & _MASK64) + frame * _GOLDEN) & _MASK64)


@functools.cache
def normal_levels(bits: int = NOISE_TABLE_BITS) -> np.ndarray:
    """(2**bits,) float32 levels of a standard normal draw, each equally likely.

    The normal quantiles at the centres of 2**bits equal probability intervals, made exactly
    antisymmetric (mean 0) and scaled to unit variance: the law of a standard normal variable
    to a resolution of 2**-bits in probability, truncated at its most extreme levels (+-4.32
    at 16 bits: a normal draw lies beyond them with probability 1.5e-5).
    """
    count = 1 << bits
    levels = special.ndtri((np.arange(count) + 0.5) / count)
    levels = 0.5 * (levels - levels[::-1])
    levels /= math.sqrt(float(np.mean(levels * levels)))
    return levels.astype(np.float32)


def digitise(
    signal: np.ndarray,
    noise_key: int,
    *,
    gain_db: float,
    electrons_per_grey: float,
    read_noise_grey: float,
    pixel_format: PixelFormat,
) -> np.ndarray:
    """Expose `signal` (mean grey levels on the 8-bit scale at unit gain) as the sensor would.

    Gain multiplies the signal; shot noise (Poisson in the electrons collected,
    `electrons_per_grey` per grey level at unit gain; 0 = none) and read noise (standard
    deviation `read_noise_grey`) are added as one normal draw per pixel whose variance is
    their sum, `gain**2 * signal / electrons_per_grey + read_noise_grey**2` (the electrons'
    Poisson variance amplified by the gain, as a sensor's analogue gain does), in float32: the
    mean and the variance of every pixel are the model's, and only the Poisson law's skew
    (1/sqrt(electrons), 0.16 at one grey level of 40 electrons) is left out, far below a
    quantisation step. The result is rounded to the pixel format's counts and clipped.

    The normal draw of the pixel at flat index i (row-major) is `normal_levels()[k]`, k the
    top `NOISE_TABLE_BITS` bits of ``splitmix64(noise_key + i * 0x9E3779B97F4A7C15)`` (mod
    2**64): a counter-based generator, so a frame is the same whatever the number of cores
    that digitise it, and its rows are digitised in parallel without the GIL. Each frame
    takes its own key (`frame_noise_key`).

    Returns:
        the frame's pixels: uint8 for Mono8, uint16 otherwise.
    """
    signal = np.asarray(signal)
    if signal.ndim != 2:
        raise ValueError(f"signal must be an image (2-D), got {signal.ndim}-D")
    if signal.dtype not in (np.float32, np.float64):
        signal = signal.astype(np.float64)
    pixels = np.empty(
        signal.shape, dtype=np.uint8 if pixel_format is PixelFormat.MONO8 else np.uint16
    )
    gain = np.float32(10.0 ** (gain_db / 20.0))
    shot = np.float32(gain / electrons_per_grey) if electrons_per_grey > 0 else np.float32(0.0)
    _digitise_rows(
        np.ascontiguousarray(signal),
        pixels,
        np.uint64(noise_key & _MASK64),
        normal_levels(),
        gain,
        np.float32(read_noise_grey) ** 2,
        shot,
        np.float32((pixel_format.max_value + 1) / 256.0),
        np.float32(pixel_format.max_value),
    )
    return pixels


@numba.njit(inline="always", cache=True)
def _splitmix64(value: np.uint64) -> np.uint64:
    z = value + np.uint64(_GOLDEN)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@numba.njit(parallel=True, nogil=True, cache=True)
def _digitise_rows(
    signal, pixels, noise_key, levels, gain, read_variance, shot_per_grey, scale, max_count
):
    rows, cols = signal.shape
    shift = np.uint64(64 - NOISE_TABLE_BITS)
    for r in numba.prange(rows):
        counter = noise_key + np.uint64(r) * np.uint64(cols) * np.uint64(_GOLDEN)
        for c in range(cols):
            grey = np.float32(signal[r, c]) * gain
            variance = read_variance + max(grey, np.float32(0.0)) * shot_per_grey
            draw = levels[_splitmix64(counter + np.uint64(c) * np.uint64(_GOLDEN)) >> shift]
            grey = (grey + draw * np.sqrt(variance)) * scale
            grey = min(max(np.rint(grey), np.float32(0.0)), max_count)
            pixels[r, c] = grey
