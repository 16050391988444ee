"""The retention rule of the service's state directory: the newest tests, up to a size.

`extensometer serve` writes every test's files into its state directory, named after the test:
`test-<UTC start>-<number>.mcap` (the recording), `.strain.csv` and `.summary.json`. Before
each test, `enforce_retention` deletes whole tests, oldest first (test ids sort by their start
time), while the tests in the directory together exceed `[service] max_state_mb`. Nothing
else in the directory is touched, and a test's files go together.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

TEST_PREFIX = "test-"
MB = 1_000_000


@dataclass
class StoredTest:
    """One test's files in the state directory.

    Attributes:
        test_id: the name they share before the first dot.
        paths: the files.
        size_bytes: their total size.
    """

    test_id: str
    paths: list[Path] = field(default_factory=list)
    size_bytes: int = 0


def stored_tests(directory: Path) -> list[StoredTest]:
    """The tests whose files are in `directory`, oldest first."""
    tests: dict[str, StoredTest] = {}
    for path in directory.iterdir():
        if not path.name.startswith(TEST_PREFIX) or not path.is_file():
            continue
        test_id = path.name.split(".", 1)[0]
        test = tests.setdefault(test_id, StoredTest(test_id))
        test.paths.append(path)
        test.size_bytes += path.stat().st_size
    return [tests[k] for k in sorted(tests)]


def enforce_retention(
    directory: Path, max_state_mb: float, log: Callable[[str], None]
) -> list[str]:
    """Delete the oldest tests while all of them together exceed `max_state_mb`.

    Args:
        directory: the state directory.
        max_state_mb: the bound, MB; 0 = no bound (nothing is deleted).
        log: told one line per test deleted.

    Returns:
        The ids of the tests deleted, oldest first.

    Raises:
        OSError: the directory cannot be listed or a file cannot be deleted.
    """
    if max_state_mb <= 0:
        return []
    tests = stored_tests(directory)
    total = sum(t.size_bytes for t in tests)
    limit = max_state_mb * MB
    deleted: list[str] = []
    for test in tests:
        if total <= limit:
            break
        for path in test.paths:
            path.unlink(missing_ok=True)
        total -= test.size_bytes
        deleted.append(test.test_id)
        log(
            f"retention: deleted {test.test_id} ({test.size_bytes / MB:.1f} MB, "
            f"{len(test.paths)} files): the state directory exceeded [service] max_state_mb "
            f"({max_state_mb:g} MB)"
        )
    return deleted
