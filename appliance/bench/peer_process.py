"""The benchmarks' peers in processes of their own, and the figures they share.

A benchmark that measures a client against a server (or a server against a client) runs the
other side in a separate Python process, so the two do not share one interpreter lock and the
figures are those of two programs on one host, as in service. The peer is a module run as
`python -m MODULE ARGS...`; it prints `ready` on stdout once it serves, and ends when it reads
`stop` on stdin, printing its own figures (JSON) on stdout if it has any.
"""

from __future__ import annotations

import socket
import subprocess
import sys
from collections.abc import Sequence

import numpy as np


def free_loopback_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now (the kernel's pick)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def start_peer(module: str, args: Sequence[str], what: str) -> subprocess.Popen:
    """Start `python -m module args...` and wait for its `ready` line.

    Raises:
        RuntimeError: the peer said anything else (it is killed), naming `what`.
    """
    process = subprocess.Popen(
        [sys.executable, "-m", module, *args],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert process.stdout is not None
    line = process.stdout.readline()
    if line.strip() != "ready":
        process.kill()
        process.wait(timeout=10)
        raise RuntimeError(f"{what} did not start (said {line!r})")
    return process


def stop_peer(process: subprocess.Popen, what: str, timeout_s: float = 60.0) -> str:
    """Tell the peer to stop; its output after `ready`.

    Raises:
        RuntimeError: it did not stop within `timeout_s` (it is killed), naming `what`.
    """
    try:
        output, _ = process.communicate(input="stop\n", timeout=timeout_s)
    except subprocess.TimeoutExpired:
        process.kill()
        process.communicate(timeout=10)
        raise RuntimeError(f"{what} did not stop") from None
    return output


def percentiles_ms(values_s: Sequence[float] | np.ndarray) -> dict[str, float | int | None]:
    """p50, p99 and max of durations given in seconds, in ms, with their count."""
    values = np.asarray(values_s, dtype=np.float64) * 1e3
    if values.size == 0:
        return {"p50": None, "p99": None, "max": None, "n": 0}
    return {
        "p50": float(np.percentile(values, 50)),
        "p99": float(np.percentile(values, 99)),
        "max": float(values.max()),
        "n": int(values.size),
    }
