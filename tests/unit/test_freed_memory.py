"""Between tests the service hands the memory a test freed back to the system, under the
unit's jemalloc and under glibc's allocator alike."""

import os
import subprocess
import sys

import pytest

from appliance.bench.soak import unit_environment

PROGRAM = """
import os, numpy as np
from appliance.bench.soak import process_figures
from appliance.service import release_freed_memory
rss = lambda: process_figures(os.getpid())["rss_mb"]
base = rss()
blocks = [np.ones(BLOCK // 8) for _ in range(300_000_000 // BLOCK)]
del blocks
held = rss()
release_freed_memory()
print(held - base, rss() - base)
"""


@pytest.mark.parametrize(
    ("allocator", "block_bytes"),
    [("jemalloc", 262_144), ("glibc", 16_384)],
)
def test_memory_a_test_freed_goes_back_to_the_system(allocator, block_bytes):
    environment = {**os.environ}
    if allocator == "jemalloc":
        environment["LD_PRELOAD"] = unit_environment()["LD_PRELOAD"]
        environment["MALLOC_CONF"] = "dirty_decay_ms:-1,muzzy_decay_ms:-1"
    result = subprocess.run(
        [sys.executable, "-c", PROGRAM.replace("BLOCK", str(block_bytes))],
        env=environment,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr
    held_mb, after_mb = (float(word) for word in result.stdout.split())
    assert held_mb > 30
    assert after_mb < 15
