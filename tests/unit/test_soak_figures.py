"""The soak benchmark's figures: a process's memory, files and threads, and slopes per test."""

import os
import threading

import pytest

from appliance.bench.soak import process_figures, slope_per_test


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
