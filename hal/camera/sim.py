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

In real time, the internal trigger keeps the camera's own time: when the host (or the
renderer) falls behind by more than a frame period, the exposures it missed are lost and the
frame ids skip them, as a camera whose buffers overflow does; as fast as possible, nothing is
ever missed.

The optics and the light are the scene's: a scene may render through a distorting, tilted
lens with flicker, vibration and drift (the simulated bench, `appliance.sim.bench_scene`);
the camera only exposes, adds noise and quantises what it renders.

What it does not model: vignetting, rolling shutter, dark current and fixed pattern noise,
corrupted frames, transport latency or bandwidth limits, trigger jitter (edges are exact), or
readout time limiting the frame rate.
"""

from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import math
import threading
from collections.abc import Sequence
from typing import Any, Protocol, runtime_checkable

import numpy as np

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
        **_: Any,
    ) -> None:
        self.url = url
        self._scene = scene
        self._clock = clock
        self._noise_streams = [
            np.random.default_rng(child)
            for child in np.random.SeedSequence(seed).spawn(NOISE_BANDS)
        ]
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
                if late > period:
                    missed = int(late // period)
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
        return digitise(
            signal,
            self._noise_streams,
            gain_db=self._settings.gain_db,
            electrons_per_grey=self._electrons_per_grey,
            read_noise_grey=self._read_noise,
            pixel_format=self._settings.pixel_format,
        )


def digitise(
    signal: np.ndarray,
    noise_streams: Sequence[np.random.Generator],
    *,
    gain_db: float,
    electrons_per_grey: float,
    read_noise_grey: float,
    pixel_format: PixelFormat,
) -> np.ndarray:
    """Expose `signal` (mean grey levels on the 8-bit scale at unit gain) as the sensor would.

    Gain multiplies the signal; shot noise (Poisson in the electrons collected,
    `electrons_per_grey` per grey level at unit gain; 0 = none) and read noise (standard
    deviation `read_noise_grey`) are added as one Gaussian draw per pixel whose variance is
    their sum, `gain**2 * signal / electrons_per_grey + read_noise_grey**2` (the electrons'
    Poisson variance amplified by the gain, as a sensor's analogue gain does), in float32: the
    mean and the variance of every pixel are the model's, and only the Poisson law's skew
    (1/sqrt(electrons), 0.16 at one grey level of 40 electrons) is left out, far below a
    quantisation step. The result is rounded to the pixel format's counts and clipped.

    The rows are cut into one band per generator of `noise_streams`, each band drawn from its
    own generator on a thread of its own: the frame is the same whatever the number of cores.

    Returns:
        the frame's pixels: uint8 for Mono8, uint16 otherwise.
    """
    signal = np.asarray(signal)
    pixels = np.empty(
        signal.shape, dtype=np.uint8 if pixel_format is PixelFormat.MONO8 else np.uint16
    )
    edges = np.linspace(0, signal.shape[0], len(noise_streams) + 1).astype(int)
    bands = [
        (signal[first:last], pixels[first:last], stream)
        for first, last, stream in zip(edges[:-1], edges[1:], noise_streams, strict=True)
    ]
    noise = dict(
        gain_db=gain_db,
        electrons_per_grey=electrons_per_grey,
        read_noise_grey=read_noise_grey,
        pixel_format=pixel_format,
    )
    if len(bands) == 1:
        _digitise_band(*bands[0], **noise)
    else:
        for done in [_band_pool().submit(_digitise_band, *band, **noise) for band in bands]:
            done.result()
    return pixels


def _digitise_band(
    signal: np.ndarray,
    pixels: np.ndarray,
    rng: np.random.Generator,
    *,
    gain_db: float,
    electrons_per_grey: float,
    read_noise_grey: float,
    pixel_format: PixelFormat,
) -> None:
    gain = np.float32(10.0 ** (gain_db / 20.0))
    grey = np.multiply(signal, gain, dtype=np.float32)
    variance = np.full(grey.shape, np.float32(read_noise_grey) ** 2, dtype=np.float32)
    if electrons_per_grey > 0:
        shot = np.maximum(grey, np.float32(0.0))
        shot *= np.float32(gain / electrons_per_grey)
        variance += shot
    noise = rng.standard_normal(grey.shape, dtype=np.float32)
    np.sqrt(variance, out=variance)
    noise *= variance
    grey += noise
    grey *= np.float32((pixel_format.max_value + 1) / 256.0)
    np.rint(grey, out=grey)
    np.clip(grey, 0, pixel_format.max_value, out=grey)
    pixels[...] = grey


NOISE_BANDS = 2
"""Bands of rows a simulated camera draws its noise in, each from its own generator."""

_BAND_POOL: list[concurrent.futures.ThreadPoolExecutor] = []
_BAND_POOL_LOCK = threading.Lock()


def _band_pool() -> concurrent.futures.ThreadPoolExecutor:
    with _BAND_POOL_LOCK:
        if not _BAND_POOL:
            _BAND_POOL.append(
                concurrent.futures.ThreadPoolExecutor(NOISE_BANDS, thread_name_prefix="sim-noise")
            )
        return _BAND_POOL[0]
