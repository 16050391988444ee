"""The real rerun CLI as the peer of the viewer tests, on loopback, and .rrd files read back.

The `rerun` script in .venv/bin is a wrapper around the binary inside the `rerun_cli` package;
killing the wrapper would orphan the server, so every peer here runs the binary itself. Every
peer binds 127.0.0.1, and `disable_analytics()` (run once before any CLI use) switches the
CLI's usage analytics off in its configuration (`rerun analytics disable`), so nothing tries
DNS. The SDK itself (the viewer under test) keeps no analytics.

Peers:
    receiver(url, save)  a headless viewer: connects to a gRPC server and saves what it gets;
                         exits 0 with a complete file when that server's process goes away
    grpc_proxy()         a headless gRPC server (`--serve-grpc`) the viewer can push to
"""

from __future__ import annotations

import functools
import json
import os
import signal
import socket
import subprocess
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import rerun_cli
from rerun.chunk import ChunkStore, RrdReader

HOST = "127.0.0.1"


def rerun_binary() -> Path:
    """The rerun CLI binary (not the .venv/bin wrapper script)."""
    return Path(os.path.dirname(rerun_cli.__file__)) / "rerun"


@functools.cache
def disable_analytics() -> None:
    """Switch the CLI's analytics off (idempotent) and check that the configuration says so."""
    binary = str(rerun_binary())
    subprocess.run([binary, "analytics", "disable"], check=True, capture_output=True, timeout=30)
    shown = subprocess.run(
        [binary, "analytics", "config"], check=True, capture_output=True, text=True, timeout=30
    )
    if json.loads(shown.stdout).get("analytics_enabled") is not False:
        raise RuntimeError(f"rerun analytics still enabled: {shown.stdout}")


def free_port() -> int:
    """A TCP port free on 127.0.0.1 at the time of asking."""
    with socket.socket() as probe:
        probe.bind((HOST, 0))
        return probe.getsockname()[1]


class Peer:
    """A rerun CLI process; a context manager that always ends it.

    Args:
        args: the CLI arguments (after the binary).
        log_path: where its stdout and stderr go.
    """

    def __init__(self, args: list[str], log_path: Path) -> None:
        disable_analytics()
        self.log_path = log_path
        self._log = open(log_path, "wb")  # noqa: SIM115
        self.process = subprocess.Popen(
            [str(rerun_binary()), *args], stdout=self._log, stderr=subprocess.STDOUT
        )

    def alive(self) -> bool:
        """Whether the process is still running."""
        return self.process.poll() is None

    def wait(self, timeout_s: float) -> int:
        """Wait for the process to exit by itself; its exit status."""
        return self.process.wait(timeout_s)

    def terminate(self, timeout_s: float = 10.0) -> int:
        """SIGTERM, then wait; its exit status."""
        if self.alive():
            self.process.send_signal(signal.SIGTERM)
        return self.process.wait(timeout_s)

    def output(self) -> str:
        """What it printed so far."""
        return self.log_path.read_text(errors="replace")

    def __enter__(self) -> Peer:
        return self

    def __exit__(self, *exc_info: object) -> None:
        if self.alive():
            self.process.kill()
        self.process.wait(10)
        self._log.close()


def receiver(url: str, save: Path, log_path: Path) -> Peer:
    """A headless viewer connected to the gRPC server at `url`, saving to `save`."""
    return Peer(["--bind", HOST, "--port", str(free_port()), "--save", str(save), url], log_path)


def grpc_proxy(port: int, log_path: Path) -> Peer:
    """A headless gRPC server on 127.0.0.1:`port` that SDKs push to and viewers read from."""
    return Peer(["--serve-grpc", "--bind", HOST, "--port", str(port)], log_path)


def verify(path: Path) -> subprocess.CompletedProcess:
    """`rerun rrd verify` on a file (exit status 0 = complete and readable)."""
    return subprocess.run(
        [str(rerun_binary()), "rrd", "verify", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
    )


def recordings(path: Path) -> dict[str, ChunkStore]:
    """The recordings of an .rrd file, by recording id."""
    reader = RrdReader(path)
    return {
        entry.recording_id: reader.stream(store=entry).collect() for entry in reader.recordings()
    }


def blueprint_count(path: Path) -> int:
    """How many blueprint stores an .rrd file holds."""
    return len(RrdReader(path).blueprints())


def _chunks(store: ChunkStore, entity: str) -> Iterator:
    path = "/" + entity.strip("/")
    return (chunk for chunk in store.stream() if chunk.entity_path == path)


def entity_paths(store: ChunkStore) -> set[str]:
    """Every entity path with data in a recording (without the leading slash)."""
    return {chunk.entity_path.lstrip("/") for chunk in store.stream()}


def series(store: ChunkStore, entity: str, index: str = "frame") -> dict[int, float]:
    """A Scalars series: index value -> scalar."""
    values: dict[int, float] = {}
    for chunk in _chunks(store, entity):
        batch = chunk.to_record_batch()
        if "Scalars:scalars" not in batch.schema.names or index not in batch.schema.names:
            continue
        keys = batch.column(index).cast("int64").to_numpy(zero_copy_only=False)
        scalars = batch.column("Scalars:scalars").to_pylist()
        for key, scalar in zip(keys, scalars, strict=True):
            if scalar:
                values[int(key)] = float(scalar[0])
    return values


def rows(store: ChunkStore, entity: str, component: str, index: str = "frame") -> dict[int, list]:
    """The values of one component of an entity, by index value (rows without it left out)."""
    found: dict[int, list] = {}
    for chunk in _chunks(store, entity):
        batch = chunk.to_record_batch()
        if component not in batch.schema.names or index not in batch.schema.names:
            continue
        keys = batch.column(index).cast("int64").to_numpy(zero_copy_only=False)
        for key, value in zip(keys, batch.column(component).to_pylist(), strict=True):
            if value is not None:
                found[int(key)] = value
    return found


def static(store: ChunkStore, entity: str) -> dict[str, object]:
    """The static components of an entity: column name -> first value."""
    values: dict[str, object] = {}
    for chunk in _chunks(store, entity):
        if not chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        for name in batch.schema.names:
            if not name.startswith("rerun.controls"):
                value = batch.column(name).to_pylist()[-1]
                values[name] = value[0] if isinstance(value, list) and len(value) == 1 else value
    return values


def latest(store: ChunkStore, entity: str) -> dict[str, object]:
    """The components of an entity, static or logged on a timeline: column name -> last value."""
    values: dict[str, object] = {}
    for chunk in _chunks(store, entity):
        batch = chunk.to_record_batch()
        for field in batch.schema:
            if (field.metadata or {}).get(b"rerun:kind") == b"data":
                value = batch.column(field.name).to_pylist()[-1]
                values[field.name] = (
                    value[0] if isinstance(value, list) and len(value) == 1 else value
                )
    return values


def strains(samples) -> dict[int, float]:
    """The finite axial engineering strains of samples, by sample index."""
    return {
        s.index: s.reading.engineering_strain
        for s in samples
        if np.isfinite(s.reading.engineering_strain)
    }
