"""The camera interface every backend implements, and the values it exchanges.

A camera's life: `open()`; `configure(CameraSettings)` (exposure, gain, region, pixel
format); `prepare(TriggerInfo)` (how frames are triggered and how many); `arm()`; `fetch()`
frames until done; `disarm()`; `close()`. Settings may be changed between acquisitions, not
while armed. Every blocking call takes a timeout.

Errors (see `hal.errors`): `HardwareConfigError` for a setting the camera refuses,
`HardwareConnectError` when it cannot be opened or goes away, `HardwareTimeout` when no
frame arrives in time, `HardwareFault` when the device reports a failure.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np


class PixelFormat(enum.Enum):
    """Pixel formats the appliance accepts: 8 bit, and 12 bit delivered in 16-bit words."""

    MONO8 = "Mono8"
    MONO12 = "Mono12"
    MONO16 = "Mono16"

    @property
    def max_value(self) -> int:
        """Largest grey value of the format."""
        return {"Mono8": 255, "Mono12": 4095, "Mono16": 65535}[self.value]


@dataclass(frozen=True)
class Region:
    """Sensor region of interest: offset (x, y) and size, in sensor pixels."""

    x: int
    y: int
    width: int
    height: int

    def __post_init__(self) -> None:
        if self.x < 0 or self.y < 0 or self.width <= 0 or self.height <= 0:
            raise ValueError(f"region must have x, y >= 0 and a positive size, got {self}")


@dataclass(frozen=True)
class CameraSettings:
    """Acquisition settings.

    Attributes:
        exposure_us: exposure time, microseconds (> 0).
        gain_db: analogue gain, dB (>= 0).
        region: sensor region; None = the full sensor.
        pixel_format: delivered pixel format.
    """

    exposure_us: float
    gain_db: float = 0.0
    region: Region | None = None
    pixel_format: PixelFormat = PixelFormat.MONO8

    def __post_init__(self) -> None:
        if not self.exposure_us > 0:
            raise ValueError(f"exposure_us must be > 0, got {self.exposure_us}")
        if not self.gain_db >= 0:
            raise ValueError(f"gain_db must be >= 0, got {self.gain_db}")


class TriggerMode(enum.Enum):
    """What starts an exposure.

    INTERNAL: the camera's own timer at `TriggerInfo.rate_hz`.
    SOFTWARE: `Camera.trigger()` from the host.
    EXTERNAL: an edge on the camera's trigger input (from the trigger microcontroller).
    """

    INTERNAL = "internal"
    SOFTWARE = "software"
    EXTERNAL = "external"


@dataclass(frozen=True)
class TriggerInfo:
    """One acquisition described in one value (after ophyd-async's TriggerInfo).

    Attributes:
        mode: what starts each exposure.
        frames: frames to acquire; 0 = until disarmed.
        rate_hz: frame rate for INTERNAL mode (> 0); ignored otherwise.
        exposure_us: exposure per frame, microseconds; None = keep the configured one.
    """

    mode: TriggerMode = TriggerMode.INTERNAL
    frames: int = 0
    rate_hz: float | None = None
    exposure_us: float | None = None

    def __post_init__(self) -> None:
        if self.frames < 0:
            raise ValueError(f"frames must be >= 0, got {self.frames}")
        if self.mode is TriggerMode.INTERNAL and not (self.rate_hz and self.rate_hz > 0):
            raise ValueError("INTERNAL triggering needs rate_hz > 0")
        if self.exposure_us is not None and not self.exposure_us > 0:
            raise ValueError(f"exposure_us must be > 0, got {self.exposure_us}")


@dataclass(frozen=True)
class Frame:
    """One acquired image.

    Attributes:
        image: 2-D array (height, width) of grey values (uint8 or uint16). The array belongs
            to the frame; a backend never reuses it after handing it out.
        frame_id: camera frame counter, increasing by one per exposure (a gap means a frame
            was lost).
        timestamp_ns: device time of the start of exposure, ns.
        exposure_us: exposure actually used, microseconds.
        metadata: backend-specific facts (e.g. trigger sequence number, ground truth of a
            simulator), never needed to measure.
    """

    image: np.ndarray
    frame_id: int
    timestamp_ns: int
    exposure_us: float
    metadata: Mapping[str, Any] = field(default_factory=dict)


@runtime_checkable
class Scene(Protocol):
    """What a simulated camera looks at: renders the view during an exposure.

    The simulated camera owns timing, triggering, noise and quantisation; the scene owns the
    physics. `render` returns noise-free grey values on the 8-bit scale (float), integrated
    over [start_s, stop_s] of the scene's clock, for the given sensor region, plus the ground
    truth of that moment as a mapping (stored in `Frame.metadata["truth"]`).
    """

    sensor_width: int
    sensor_height: int

    def render(
        self, start_s: float, stop_s: float, region: Region
    ) -> tuple[np.ndarray, Mapping[str, Any]]: ...


@runtime_checkable
class Camera(Protocol):
    """A camera as the appliance drives it."""

    url: str

    def open(self, timeout_s: float = 5.0) -> None:
        """Connect to the camera. Raises HardwareConnectError."""

    def close(self) -> None:
        """Release the camera; safe to call twice."""

    def configure(self, settings: CameraSettings) -> CameraSettings:
        """Apply settings; returns the settings in force (rounded to what the device does).

        Raises HardwareConfigError for a setting the camera cannot take, or when armed.
        """

    def prepare(self, trigger: TriggerInfo) -> None:
        """Set up the next acquisition. Raises HardwareConfigError."""

    def arm(self) -> None:
        """Start acquiring as prepared."""

    def disarm(self) -> None:
        """Stop acquiring; frames not fetched yet are discarded."""

    def trigger(self) -> None:
        """Software trigger (SOFTWARE mode only). Raises HardwareConfigError otherwise."""

    def set_exposure(self, exposure_us: float) -> float:
        """Change the exposure, armed or not; returns the exposure in force, us.

        While armed the change reaches the sensor from a later exposure on (the next one in
        simulation; on real cameras an exposure or two later, as the camera applies it);
        `Frame.exposure_us` reports the exposure in force when the frame was fetched.
        Raises HardwareConfigError for an exposure the camera cannot take (the one in force
        stays), HardwareConnectError when the camera cannot be reached.
        """

    def fetch(self, timeout_s: float) -> Frame:
        """Next frame. Raises HardwareTimeout when none arrives in time."""

    def statistics(self) -> dict[str, Any]:
        """The backend's counters since construction (frames delivered and lost, transport
        figures), JSON-ready; {} for a backend that keeps none."""
