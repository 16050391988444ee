"""Cameras: the `Camera` protocol, its value types, and the backends behind it."""

from hal.camera.base import (
    Camera,
    CameraSettings,
    Frame,
    PixelFormat,
    Region,
    Scene,
    TriggerInfo,
    TriggerMode,
)

__all__ = [
    "Camera",
    "CameraSettings",
    "Frame",
    "PixelFormat",
    "Region",
    "Scene",
    "TriggerInfo",
    "TriggerMode",
]
