"""A real small file system for the disk-full tests: a tmpfs of a few hundred kB to a few MB.

Mounting needs root (CI runs as root); elsewhere the tests that need it are skipped with the
reason. The mount is removed when the test ends, whatever happened.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest


@contextlib.contextmanager
def small_disk(path: Path, size_kb: int) -> Iterator[Path]:
    """Mount a tmpfs of `size_kb` KiB at `path` (created); yields `path`."""
    if os.geteuid() != 0:
        pytest.skip("mounting a small file system needs root")
    path.mkdir(parents=True, exist_ok=True)
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size_kb}k,mode=0755", "tmpfs", str(path)],
        capture_output=True,
        text=True,
        check=False,
    )
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs: {mounted.stderr.strip()}")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], capture_output=True, check=False)


def fill(path: Path, leave_kb: int) -> Path:
    """Fill the file system of directory `path` with a file `filler.bin` until `leave_kb`
    KiB are free; returns the file."""
    filler = path / "filler.bin"
    stats = os.statvfs(path)
    free = stats.f_bavail * stats.f_frsize
    with filler.open("wb") as file:
        os.posix_fallocate(file.fileno(), 0, max(free - leave_kb * 1024, 0))
    return filler
