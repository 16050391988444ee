"""Backends chosen by URL-like strings from configuration (after python-can's interfaces).

A device is named by a URL whose scheme picks the backend: `sim://camera`, `sim://machine`
(simulators), `aravis://ADDRESS` (GigE Vision), `v4l2:///dev/videoN`, `modbus-tcp://HOST:PORT`
and `modbus-rtu:///dev/ttyX?baud=...` (machine controllers). The table maps each scheme to
the module and class that implement it; modules are imported only when their scheme is used,
so an appliance without Aravis installed still runs on a Modbus machine and a V4L2 camera.

Backends are constructed as `Class(url, **resources)`: `resources` are objects the caller
already holds that a backend needs (a simulator's `Scene` and clock, for instance), passed by
keyword and ignored by backends that do not take them.
"""

from __future__ import annotations

import importlib
from typing import Any

from hal.camera.base import Camera
from hal.errors import HardwareConfigError
from hal.machine.base import TestingMachine
from hal.urls import split_url

CAMERA_BACKENDS: dict[str, str] = {
    "sim": "hal.camera.sim:SimCamera",
    "aravis": "hal.camera.aravis:AravisCamera",
    "v4l2": "hal.camera.v4l2:V4l2Camera",
}
"""Camera URL scheme -> "module:Class"."""

MACHINE_BACKENDS: dict[str, str] = {
    "sim": "hal.machine.sim:SimMachine",
    "modbus-tcp": "hal.machine.modbus:ModbusMachine",
    "modbus-rtu": "hal.machine.modbus:ModbusMachine",
}
"""Testing machine URL scheme -> "module:Class"."""


def _load(table: dict[str, str], url: str, kind: str) -> type:
    scheme = split_url(url, kind).scheme if "://" in url else ""
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


def machine_from_url(url: str, **resources: Any) -> TestingMachine:
    """Construct (not open) the testing machine named by `url`. Raises HardwareConfigError."""
    return _load(MACHINE_BACKENDS, url, "machine")(url, **resources)
