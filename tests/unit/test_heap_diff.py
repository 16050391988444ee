"""The service's heap diff between two tests (`EXTENSOMETER_HEAP_DIFF`): what grew, where."""

import tracemalloc

import pytest

from appliance.errors import InputError
from appliance.service import HeapDiff

KEPT: list[bytearray] = []


def _keep_a_megabyte() -> None:
    KEPT.append(bytearray(1_000_000))


def test_the_growth_between_two_tests_is_written_with_its_site(tmp_path):
    path = tmp_path / "heap.txt"
    logged = []
    try:
        diff = HeapDiff(f"2,4,{path}")
        for test in range(1, 6):
            if test >= 3:
                _keep_a_megabyte()
            diff.after_test(test, logged.append)
            assert path.exists() == (test >= 4)
    finally:
        tracemalloc.stop()
        KEPT.clear()
    text = path.read_text()
    assert text.startswith("Python heap growth from test 2 to test 4: +2.0")
    assert "Objects the garbage collector tracks" in text
    first_site = text.split("Allocation sites, most grown:\n\n", 1)[1].splitlines()
    assert first_site[0].strip().startswith("+2000.")
    assert "_keep_a_megabyte" in "\n".join(first_site[1:6])
    assert logged == [f"heap growth from test 2 to 4 written to {path}"]


@pytest.mark.parametrize("setting", ["3,2,x", "1,2", "a,b,c", "0,3,x"])
def test_a_malformed_setting_is_named(setting):
    with pytest.raises(InputError, match="EXTENSOMETER_HEAP_DIFF: must be FIRST,LAST,FILE"):
        HeapDiff(setting)
    tracemalloc.stop()
