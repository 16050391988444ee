"""Build the trigger firmware (avr-gcc) and its simavr harness (gcc + libsimavr) from source.

    from firmware_bridge.firmware_build import build_firmware, build_harness
    elf = build_firmware(Path("build/firmware"))                  # .../trigger.elf
    test_elf = build_firmware(out, test_hooks=True)               # .../trigger-test.elf
    harness = build_harness(Path("build/firmware"))               # .../harness

`build_firmware` compiles every firmware source in `firmware_bridge/firmware/` in one
avr-gcc call for the ATmega328P at 16 MHz (`-Os`); `test_hooks=True` adds `test_hooks.c` and
`-DTRIGGER_TEST_HOOKS` (the watchdog test's hang pin, see test_hooks.h) and writes a separate
ELF, so the production image never contains it. `build_harness` compiles `firmware/sim/
harness.c` against the installed libsimavr. Both skip the compiler when the output is newer
than every source and header it depends on (and than this module, which holds the flags);
both write to a temporary name and rename, so concurrent builds never see half a file.

Errors are `FirmwareBuildError` with a one-line message: a missing compiler, missing
avr-libc or libsimavr headers, or the compiler's first error line (the full compiler output
is kept in `.output`). Nothing here runs the firmware; see `firmware_bridge.simulator`.

Outputs go where the caller says; the tests and the benchmark use `default_build_dir()`,
`<repository>/build/firmware`, which lies under the ignored `build/`.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from pathlib import Path

FIRMWARE_DIR = Path(__file__).resolve().parent / "firmware"
HARNESS_SOURCE = FIRMWARE_DIR / "sim" / "harness.c"
SOURCES = ("main.c", "clock.c", "uart.c", "protocol.c", "trigger.c", "encoder.c")
TEST_SOURCES = (*SOURCES, "test_hooks.c")
MCU = "atmega328p"
F_CPU = 16_000_000
AVR_FLAGS = (
    f"-mmcu={MCU}",
    f"-DF_CPU={F_CPU}UL",
    "-Os",
    "-flto",
    "-std=gnu11",
    "-Wall",
    "-Wextra",
    "-ffunction-sections",
    "-fdata-sections",
    "-Wl,--gc-sections",
)
SIMAVR_INCLUDE = Path(os.environ.get("SIMAVR_INCLUDE_DIR", "/usr/include/simavr"))
HARNESS_LIBS = ("-lsimavr", "-lutil", "-lm")


class FirmwareBuildError(RuntimeError):
    """The firmware or the harness could not be built; the message is one line."""

    def __init__(self, message: str, output: str = "") -> None:
        super().__init__(message)
        self.output = output


def default_build_dir() -> Path:
    """`<repository>/build/firmware`: where the tests and the benchmark build (ignored by git)."""
    return Path(__file__).resolve().parents[1] / "build" / "firmware"


def build_firmware(out_dir: Path, *, test_hooks: bool = False) -> Path:
    """Compile the firmware ELF into `out_dir` (made if missing) and return its path:
    `trigger.elf`, or `trigger-test.elf` with `test_hooks`. Skips the compiler when the ELF
    is up to date.

    Raises:
        FirmwareBuildError: avr-gcc or avr-libc missing, or the compilation failed.
    """
    sources = [FIRMWARE_DIR / name for name in (TEST_SOURCES if test_hooks else SOURCES)]
    output = Path(out_dir) / ("trigger-test.elf" if test_hooks else "trigger.elf")
    depends = [*sources, *sorted(FIRMWARE_DIR.glob("*.h")), Path(__file__).resolve()]
    if _up_to_date(output, depends):
        return output
    compiler = _tool("avr-gcc", "apt-get install gcc-avr avr-libc")
    flags = [*AVR_FLAGS, *(["-DTRIGGER_TEST_HOOKS"] if test_hooks else [])]
    _compile(
        [compiler, *flags, f"-I{FIRMWARE_DIR}", *map(str, sources)],
        output,
        missing_headers={"avr/io.h": "avr-libc headers not found (apt-get install avr-libc)"},
    )
    return output


def build_harness(out_dir: Path) -> Path:
    """Compile the simavr harness into `out_dir` (made if missing) and return its path
    (`harness`). Skips the compiler when it is up to date.

    Raises:
        FirmwareBuildError: gcc or the libsimavr headers missing, or the compilation failed.
    """
    output = Path(out_dir) / "harness"
    if _up_to_date(output, [HARNESS_SOURCE, Path(__file__).resolve()]):
        return output
    compiler = _tool("gcc", "apt-get install gcc")
    if not (SIMAVR_INCLUDE / "sim_avr.h").is_file():
        raise FirmwareBuildError(
            f"libsimavr headers not found in {SIMAVR_INCLUDE} "
            "(apt-get install simavr libsimavr-dev)"
        )
    command = [
        compiler,
        "-O2",
        "-Wall",
        f"-I{SIMAVR_INCLUDE}",
        str(HARNESS_SOURCE),
        *HARNESS_LIBS,
    ]
    _compile(
        command,
        output,
        missing_headers={
            "sim_avr.h": "libsimavr headers not found (apt-get install libsimavr-dev)"
        },
        missing_libraries="libsimavr not found (apt-get install simavr libsimavr-dev)",
    )
    return output


def _tool(name: str, install_hint: str) -> str:
    path = shutil.which(name)
    if path is None:
        raise FirmwareBuildError(f"{name} not found on PATH ({install_hint})")
    return path


def _up_to_date(output: Path, depends: list[Path]) -> bool:
    try:
        built = output.stat().st_mtime
    except FileNotFoundError:
        return False
    return all(path.stat().st_mtime < built for path in depends)


def _compile(
    command: list[str],
    output: Path,
    *,
    missing_headers: dict[str, str],
    missing_libraries: str = "",
) -> None:
    output.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=output.name + ".", dir=output.parent)
    os.close(handle)
    try:
        done = subprocess.run(
            [*command[:1], "-o", temporary, *command[1:]],
            capture_output=True,
            text=True,
            timeout=300,
        )
        if done.returncode != 0:
            text = done.stdout + done.stderr
            raise FirmwareBuildError(_diagnosis(text, missing_headers, missing_libraries), text)
        os.chmod(temporary, 0o755)
        os.replace(temporary, output)
    finally:
        if os.path.exists(temporary):
            os.unlink(temporary)


def _diagnosis(text: str, missing_headers: dict[str, str], missing_libraries: str) -> str:
    for header, message in missing_headers.items():
        if header in text and "No such file" in text:
            return message
    if missing_libraries and "cannot find -lsimavr" in text:
        return missing_libraries
    errors = [line for line in text.splitlines() if "error" in line]
    first = (errors or text.strip().splitlines() or ["no output"])[0]
    return f"compilation failed: {first.strip()}"
