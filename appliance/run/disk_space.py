"""Room on disk for a test's files: the check before it starts, and the reserve it ends on.

A test writes its strain file row by row, its recording chunk by chunk and its summary at the
end. Two rules keep a full disk from costing a measured sample (`[storage]` in
appliance/CONFIGURATION.md):

* before the test, every directory it writes to must have `min_free_mb` free, or the test is
  refused in one line naming the directory (`check_free_space`);
* while it runs, a reserve file of `reserve_mb` holds room beside the strain file
  (`DiskReserve`). When the disk fills, the reserve is released: the test ends as a fault, and
  the rows still in flight and the summary are written into the room it held.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

from appliance.errors import InputError

RESERVE_NAME = ".extensometer-reserve"
"""The reserve file's name in the strain file's directory (replaced by the next test's when a
killed test left it behind)."""

MB = 1_000_000


def free_mb(directory: Path) -> float:
    """Space an unprivileged writer may still use on `directory`'s file system, MB."""
    stats = os.statvfs(directory)
    return stats.f_bavail * stats.f_frsize / MB


def check_free_space(directories: Iterable[Path], min_free_mb: float) -> None:
    """Refuse a test that would start on a disk with less than `min_free_mb` free.

    Raises:
        InputError: "DIR: 12 MB free, below [storage] min_free_mb (1000 MB): ..." for the first
            directory short of room, or one that cannot be examined.
    """
    for directory in directories:
        try:
            free = free_mb(directory)
        except OSError as exc:
            raise InputError(f"{directory}: cannot read its free space ({exc.strerror})") from None
        if free < min_free_mb:
            raise InputError(
                f"{directory}: {free:.1f} MB free, below [storage] min_free_mb "
                f"({min_free_mb:g} MB): make room (or lower the limit) before a test"
            )


class DiskReserve:
    """Room held on a disk by a file of zeros, given back when the disk is full.

    Args:
        directory: where to hold it (the strain file's directory).
        size_mb: how much; 0 holds nothing.

    Raises:
        InputError: the reserve cannot be created (names the file and the cause).
    """

    def __init__(self, directory: Path, size_mb: float) -> None:
        self.path = directory / RESERVE_NAME
        self.held = False
        size = int(size_mb * MB)
        if size <= 0:
            return
        try:
            with self.path.open("wb") as file:
                os.posix_fallocate(file.fileno(), 0, size)
        except OSError as exc:
            self.path.unlink(missing_ok=True)
            raise InputError(
                f"{self.path}: cannot hold {size_mb:g} MB in reserve ([storage] reserve_mb) "
                f"({exc.strerror})"
            ) from None
        self.held = True

    def release(self) -> bool:
        """Give the room back; True when it was held until now (idempotent)."""
        if not self.held:
            return False
        self.held = False
        self.path.unlink(missing_ok=True)
        return True
