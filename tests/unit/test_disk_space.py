"""Room on disk for a test's files: the free-space check, the reserve, the retention rule."""

from __future__ import annotations

import os

import pytest

from appliance.errors import InputError
from appliance.recording.retention import enforce_retention, stored_tests
from appliance.run.disk_space import RESERVE_NAME, DiskReserve, check_free_space, free_mb


def test_the_free_space_check_names_the_directory_and_the_key(tmp_path):
    check_free_space([tmp_path], min_free_mb=0.0)
    free = free_mb(tmp_path)
    with pytest.raises(InputError) as refused:
        check_free_space([tmp_path], min_free_mb=free * 2 + 1)
    assert str(refused.value).startswith(f"{tmp_path}: ")
    assert "MB free, below [storage] min_free_mb" in str(refused.value)
    with pytest.raises(InputError, match="cannot read its free space"):
        check_free_space([tmp_path / "missing"], min_free_mb=0.0)


def test_the_reserve_holds_its_room_until_released_once(tmp_path):
    reserve = DiskReserve(tmp_path, 0.25)
    path = tmp_path / RESERVE_NAME
    assert path.stat().st_size == 250_000
    assert os.stat(path).st_blocks * 512 >= 250_000
    assert reserve.release() is True and not path.exists()
    assert reserve.release() is False
    assert DiskReserve(tmp_path, 0.0).release() is False and not path.exists()


def test_a_reserve_that_cannot_be_held_is_refused_in_one_line(tmp_path):
    with pytest.raises(
        InputError, match=r"cannot hold 0.1 MB in reserve \(\[storage\] reserve_mb\)"
    ):
        DiskReserve(tmp_path / "missing", 0.1)


def _test_files(directory, test_id, sizes):
    for suffix, size in sizes.items():
        (directory / f"{test_id}{suffix}").write_bytes(b"x" * size)


def test_retention_deletes_whole_tests_oldest_first_until_under_the_bound(tmp_path):
    _test_files(tmp_path, "test-20260101T000000Z-0002", {".mcap": 400_000, ".summary.json": 10})
    _test_files(tmp_path, "test-20250101T000000Z-0007", {".mcap": 300_000, ".strain.csv": 100_000})
    _test_files(tmp_path, "test-20260301T000000Z-0001", {".mcap": 500_000})
    (tmp_path / "notes.txt").write_bytes(b"y" * 900_000)
    assert [t.test_id for t in stored_tests(tmp_path)] == [
        "test-20250101T000000Z-0007",
        "test-20260101T000000Z-0002",
        "test-20260301T000000Z-0001",
    ]
    said = []
    deleted = enforce_retention(tmp_path, 0.6, said.append)
    assert deleted == ["test-20250101T000000Z-0007", "test-20260101T000000Z-0002"]
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "notes.txt",
        "test-20260301T000000Z-0001.mcap",
    ]
    assert said[0] == (
        "retention: deleted test-20250101T000000Z-0007 (0.4 MB, 2 files): the state directory "
        "exceeded [service] max_state_mb (0.6 MB)"
    )
    assert enforce_retention(tmp_path, 0.6, said.append) == []


def test_no_bound_keeps_everything(tmp_path):
    _test_files(tmp_path, "test-20250101T000000Z-0001", {".mcap": 2_000_000})
    assert enforce_retention(tmp_path, 0.0, print) == []
    assert (tmp_path / "test-20250101T000000Z-0001.mcap").exists()
