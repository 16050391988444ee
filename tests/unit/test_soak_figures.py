"""The soak benchmark's figures: a process's memory, files and threads, and slopes per test."""

import os
import subprocess
import sys
import threading

import pytest

from appliance.bench.soak import process_figures, slope_per_test, unit_environment


def test_slope_per_test_is_the_least_squares_slope():
    assert slope_per_test([]) is None and slope_per_test([5.0]) is None
    assert slope_per_test([1.0, 1.0, 1.0]) == pytest.approx(0.0)
    assert slope_per_test([10.0, 12.0, 14.0, 16.0]) == pytest.approx(2.0)
    assert slope_per_test([0.0, 1.0, 0.0, 1.0]) == pytest.approx(0.2)


def test_process_figures_count_this_process_s_threads_and_files():
    before = process_figures(os.getpid())
    release = threading.Event()
    worker = threading.Thread(target=release.wait)
    worker.start()
    with open(__file__, encoding="utf-8"):
        during = process_figures(os.getpid())
    release.set()
    worker.join()
    assert during["threads"] == before["threads"] + 1
    assert during["fds"] == before["fds"] + 1
    assert during["rss_mb"] > 10


def test_the_soak_runs_the_service_with_the_unit_s_environment(tmp_path):
    unit = tmp_path / "x.service"
    unit.write_text(
        "[Service]\n"
        "Environment=NUMBA_CACHE_DIR=%C/extensometer/numba\n"
        "Environment=PYTHONUNBUFFERED=1\n"
        'Environment="A=one two" B=3\n'
        "ExecStart=/bin/true\n"
    )
    assert unit_environment(unit) == {"PYTHONUNBUFFERED": "1", "A": "one two", "B": "3"}


def test_the_shipped_unit_s_allocator_is_installed_and_loads():
    environment = unit_environment()
    assert environment["LD_PRELOAD"] == "libjemalloc.so.2"
    result = subprocess.run(
        [sys.executable, "-c", "print('jemalloc' in open('/proc/self/maps').read())"],
        env={**os.environ, **environment},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0
    assert result.stdout == "True\n"
    assert result.stderr == ""
