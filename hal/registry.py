"""Backends chosen by URL-like strings from configuration (after python-can's interfaces).

A device is named by a URL whose scheme picks the backend: `sim://camera`, `sim://frame`
(simulators), `aravis://ADDRESS` (GigE Vision), `v4l2:///dev/videoN`, `modbus-tcp://HOST:PORT`
and `modbus-rtu:///dev/ttyX?baud=...` (frame controllers). The table maps each scheme to
the module and class that implement it; modules are imported only when their scheme is used,
so an appliance without Aravis installed still runs on a Modbus frame and a V4L2 camera.

Backends are constructed as `Class(url, **resources)`: `resources` are objects the caller
already holds that a backend needs (a simulator's `Scene` and clock, for instance), passed by
keyword and ignored by backends that do not take them.
"""

from __future__ import annotations

import importlib
from typing import Any
from urllib.parse import urlsplit

from hal.camera.base import Camera
from hal.errors import HardwareConfigError
from hal.frame.base import TensileFrame

CAMERA_BACKENDS: dict[str, str] = {
    "sim": "hal.camera.sim:SimCamera",
    "aravis": "hal.camera.aravis:AravisCamera",
    "v4l2": "hal.camera.v4l2:V4l2Camera",
}
"""Camera URL scheme -> "module:Class"."""

FRAME_BACKENDS: dict[str, str] = {
    "sim": "hal.frame.sim:SimFrame",
    "modbus-tcp": "hal.frame.modbus:ModbusFrame",
    "modbus-rtu": "hal.frame.modbus:ModbusFrame",
}
"""Tensile-frame URL scheme -> "module:Class"."""


def _load(table: dict[str, str], url: str, kind: str) -> type:
    scheme = urlsplit(url).scheme if "://" in url else ""
    if not scheme:
        raise HardwareConfigError(f"{kind} URL {url!r} has no scheme (e.g. sim://)")
    if scheme not in table:
        known = ", ".join(f"{s}://" for s in sorted(table))
        raise HardwareConfigError(f"{kind} URL {url!r}: unknown scheme {scheme}:// ({known})")
    module_name, _, class_name = table[scheme].partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise HardwareConfigError(
            f"{kind} URL {url!r}: backend {module_name} unavailable ({exc})"
        ) from None
    return getattr(module, class_name)


def camera_from_url(url: str, **resources: Any) -> Camera:
    """Construct (not open) the camera named by `url`. Raises HardwareConfigError."""
    return _load(CAMERA_BACKENDS, url, "camera")(url, **resources)


def frame_from_url(url: str, **resources: Any) -> TensileFrame:
    """Construct (not open) the tensile frame named by `url`. Raises HardwareConfigError."""
    return _load(FRAME_BACKENDS, url, "frame")(url, **resources)
