"""The trigger firmware for the system tests: built from source once per session, or skipped.

`firmware_binaries()` builds the production firmware, the test build (with its watchdog hang
pin) and the simavr harness into `build/firmware/` (`firmware_bridge.firmware_build`; a
rebuild happens only when a source changed) and skips the calling test, with the package to
install, when avr-gcc or libsimavr is missing.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from firmware_bridge.firmware_build import (
    SIMAVR_INCLUDE,
    FirmwareBuildError,
    build_firmware,
    build_harness,
    default_build_dir,
)


def firmware_binaries() -> dict[str, Path]:
    """{"elf", "test_elf", "harness"}: paths of the built binaries."""
    if shutil.which("avr-gcc") is None:
        pytest.skip("avr-gcc not installed (apt-get install gcc-avr avr-libc)")
    if not (SIMAVR_INCLUDE / "sim_avr.h").is_file():
        pytest.skip("libsimavr headers not installed (apt-get install simavr libsimavr-dev)")
    out = default_build_dir()
    try:
        return {
            "elf": build_firmware(out),
            "test_elf": build_firmware(out, test_hooks=True),
            "harness": build_harness(out),
        }
    except FirmwareBuildError as error:
        if "not found" in str(error):
            pytest.skip(str(error))
        raise
