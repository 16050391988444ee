"""The Rerun viewer against the real rerun CLI on loopback: served, pushed and saved tests.

Every test runs a short simulated measurement (the real loop, tracker and gauges) through
`appliance.live.viewer.RerunViewer`, lets a headless rerun CLI receive it, checks the file with
`rerun rrd verify` and reads the strain back from it. The CLI's analytics are switched off
before it first runs; every peer binds 127.0.0.1.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import queue
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from appliance.config import RerunConfig
from appliance.live.viewer import (
    AXIAL_STRAIN,
    EVENTS,
    FORCE,
    IMAGE,
    POINTS,
    RESULT,
    STRAIN_TIMELINE,
    RerunViewer,
    proxy_url,
)
from tests.system import rerun_peers, viewer_sender

ROOT = Path(__file__).resolve().parents[2]
ENTITIES = {
    "camera",
    "camera/image",
    "camera/points",
    "camera/gauges",
    "strain/axial",
    "strain/true",
    "strain/transverse",
    "gauge/elongation_mm",
    "machine/force_n",
    "machine/crosshead_mm",
    "status/points_lost",
    "status/state",
    "status/log",
    "status/result",
    "facts/calibration",
    "facts/summary",
}


@pytest.fixture(scope="module", autouse=True)
def _analytics_off():
    rerun_peers.disable_analytics()


class _Lines:
    """The lines a child process prints, read on a thread so that waiting can time out."""

    def __init__(self, stream) -> None:
        self._lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._read, args=(stream,), daemon=True).start()

    def _read(self, stream) -> None:
        for line in stream:
            self._lines.put(line.rstrip("\n"))

    def next(self, timeout_s: float = 60.0) -> str:
        return self._lines.get(timeout=timeout_s)


def _wait_for(condition, timeout_s: float = 20.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


def _port_free(port: int) -> bool:
    with socket.socket() as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((rerun_peers.HOST, port))
        except OSError:
            return False
        return True


def _listening(port: int) -> bool:
    try:
        with socket.create_connection((rerun_peers.HOST, port), timeout=0.2):
            return True
    except OSError:
        return False


def _has_content(path: Path) -> bool:
    return path.exists() and path.stat().st_size > 0


def test_served_tests_reach_a_remote_viewer_that_stays_connected_across_tests(tmp_path):
    port = rerun_peers.free_port()
    sender = subprocess.Popen(
        [sys.executable, "-m", "tests.system.viewer_sender", "--serve", f"127.0.0.1:{port}"]
        + ["--tests", "2", "--frames", "30", "--prefix", "served", "--out", str(tmp_path)],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    seen = tmp_path / "seen.rrd"
    try:
        lines = _Lines(sender.stdout)
        serving = lines.next()
        assert serving == f"serving {proxy_url('127.0.0.1', port)}"
        with rerun_peers.receiver(serving.split()[1], seen, tmp_path / "receiver.log") as peer:
            for k in range(2):
                sender.stdin.write("go\n")
                sender.stdin.flush()
                assert lines.next() == f"done {k}"
                assert peer.alive(), peer.output()
            sender.stdin.close()
            assert sender.wait(30) == 0
            assert peer.wait(30) == 0, peer.output()
    finally:
        if sender.poll() is None:
            sender.kill()
        sender.wait(10)
    assert rerun_peers.verify(seen).returncode == 0
    recordings = rerun_peers.recordings(seen)
    assert {"served-0", "served-1"} <= set(recordings)
    for k in range(2):
        report = json.loads((tmp_path / f"test-{k}.json").read_text())
        assert report["exit_status"] == "completed" and report["problem"] is None
        assert report["dropped"] == 0 and report["shown"] == 30
        store = recordings[f"served-{k}"]
        expected = {int(index): strain for index, strain in report["strains"].items()}
        assert len(expected) == 30
        assert rerun_peers.series(store, AXIAL_STRAIN) == expected
        assert ENTITIES <= rerun_peers.entity_paths(store)
        assert rerun_peers.latest(store, RESULT)["exit_status"] == "completed"


def test_viewer_goes_on_when_a_remote_viewer_hangs_up_and_frees_its_port(tmp_path):
    recorded = viewer_sender.record(20)
    port = rerun_peers.free_port()
    viewer = RerunViewer(RerunConfig(serve=f"127.0.0.1:{port}", queue_size=1000))
    viewer.start()
    seen = tmp_path / "seen.rrd"
    with rerun_peers.receiver(viewer.service.url, seen, tmp_path / "receiver.log") as peer:
        viewer.begin(recorded.facts)
        for sample in recorded.samples[:10]:
            viewer(sample)
        assert _wait_for(lambda: _has_content(seen)), peer.output()
        peer.process.kill()
        peer.wait(10)
        for sample in recorded.samples[10:]:
            viewer(sample)
        viewer.end(recorded.result)
    assert viewer.problem is None
    assert viewer.samples_shown == 20 and viewer.samples_dropped == 0
    viewer.close()
    assert _wait_for(lambda: _port_free(port))


def test_save_writes_one_complete_file_per_test(tmp_path):
    viewer = RerunViewer(
        RerunConfig(save=str(tmp_path / "{test}.rrd"), image_rate_hz=5.0, queue_size=1000)
    )
    runs = {}
    for test_id, frames in (("saved-a", 25), ("saved-b", 10)):
        samples, result = viewer_sender.measure(viewer, frames, test_id)
        assert result.exit_status == "completed" and viewer.problem is None
        runs[test_id] = samples
    images_of_last = viewer.images_shown
    viewer.close()
    for test_id, samples in runs.items():
        path = tmp_path / f"{test_id}.rrd"
        assert rerun_peers.verify(path).returncode == 0
        assert rerun_peers.blueprint_count(path) >= 1
        (store,) = rerun_peers.recordings(path).values()
        assert ENTITIES <= rerun_peers.entity_paths(store)
        assert rerun_peers.series(store, AXIAL_STRAIN) == rerun_peers.strains(samples)
        assert rerun_peers.series(store, FORCE, index=STRAIN_TIMELINE) == {
            round(s.reading.engineering_strain * 1e6): s.machine.force_n for s in samples
        }
        reference_points = rerun_peers.rows(store, POINTS, "Points2D:positions")[-1]
        assert reference_points == viewer_sender.POINTS.tolist()
        result = rerun_peers.latest(store, RESULT)
        assert result["viewer_samples_shown"] == len(samples)
        assert result["viewer_samples_dropped"] == 0
        log = rerun_peers.rows(store, EVENTS, "TextLog:text")
        assert log[-1][0].startswith(f"test {test_id} started")
        assert log[len(samples) - 1][0].startswith("test completed: frame limit")
    (last,) = rerun_peers.recordings(tmp_path / "saved-b.rrd").values()
    images = rerun_peers.rows(last, IMAGE, "Image:buffer")
    assert sorted(images) == [-1, 0, 2, 4, 6, 8] and images_of_last == 6


def test_connect_pushes_each_test_to_a_remote_viewer(tmp_path):
    port = rerun_peers.free_port()
    url = proxy_url(rerun_peers.HOST, port)
    seen = tmp_path / "seen.rrd"
    with rerun_peers.grpc_proxy(port, tmp_path / "proxy.log") as proxy:
        assert _wait_for(lambda: _listening(port)), proxy.output()
        with rerun_peers.receiver(url, seen, tmp_path / "receiver.log") as peer:
            viewer = RerunViewer(RerunConfig(connect=url, queue_size=1000))
            samples, result = viewer_sender.measure(viewer, 25, "pushed")
            viewer.close()
            assert viewer.problem is None and viewer.samples_shown == 25
            assert _wait_for(lambda: _has_content(seen)), peer.output()
            proxy.terminate()
            assert peer.wait(20) == 0, peer.output()
    assert rerun_peers.verify(seen).returncode == 0
    store = rerun_peers.recordings(seen)["pushed"]
    assert rerun_peers.series(store, AXIAL_STRAIN) == rerun_peers.strains(samples)


def test_a_remote_viewer_that_went_away_costs_one_warning_and_no_error(tmp_path, caplog):
    recorded = viewer_sender.record(20)
    port = rerun_peers.free_port()
    url = proxy_url(rerun_peers.HOST, port)
    viewer = RerunViewer(RerunConfig(connect=url, queue_size=1000), close_timeout_s=3.0)
    with rerun_peers.grpc_proxy(port, tmp_path / "proxy.log") as proxy:
        assert _wait_for(lambda: _listening(port)), proxy.output()
        viewer.begin(recorded.facts)
        for sample in recorded.samples[:10]:
            viewer(sample)
        assert _wait_for(lambda: viewer.samples_shown == 10)
        proxy.process.kill()
        proxy.wait(10)
    for sample in recorded.samples[10:]:
        viewer(sample)
    with caplog.at_level(logging.WARNING, logger="appliance.live.viewer"):
        viewer.end(recorded.result)
        viewer.close()
    warnings = [r for r in caplog.records if r.name == "appliance.live.viewer"]
    assert len(warnings) == 1, [r.getMessage() for r in warnings]
    assert "\n" not in warnings[0].getMessage() and viewer.problem
    assert viewer.samples_shown == 20


def test_a_full_queue_drops_and_counts_samples_and_never_blocks_the_measurement(tmp_path):
    recorded = viewer_sender.record(10)
    reference_ns = recorded.facts.reference.timestamp_ns
    template = recorded.samples
    samples = [
        viewer_sender.renumbered(template[k % len(template)], k, reference_ns + (k + 1) * 1_000_000)
        for k in range(2000)
    ]
    path = tmp_path / "dropping.rrd"
    viewer = RerunViewer(
        RerunConfig(save=str(path), image_rate_hz=1000.0, image_scale=1.0, queue_size=1)
    )
    viewer.begin(recorded.facts)
    slowest_s = 0.0
    for sample in samples:
        started = time.perf_counter()
        viewer(sample)
        slowest_s = max(slowest_s, time.perf_counter() - started)
    viewer.end(recorded.result)
    viewer.close()
    assert viewer.samples_dropped > 0
    assert viewer.samples_shown + viewer.samples_dropped == len(samples)
    # Generous bound: a call only queues; logging one sample with its image takes far longer.
    assert slowest_s < 0.1
    (store,) = rerun_peers.recordings(path).values()
    assert len(rerun_peers.series(store, AXIAL_STRAIN)) == viewer.samples_shown
    result = rerun_peers.latest(store, RESULT)
    assert result["viewer_samples_dropped"] == viewer.samples_dropped


def _settled_thread_count(window_s: float = 1.0) -> int:
    """The fewest threads seen over ``window_s``.

    A thread still winding down is not counted; a kept one is.
    """
    fewest = len(os.listdir("/proc/self/task"))
    deadline = time.monotonic() + window_s
    while time.monotonic() < deadline:
        time.sleep(0.05)
        fewest = min(fewest, len(os.listdir("/proc/self/task")))
    return fewest


def test_a_served_viewer_keeps_no_thread_of_a_finished_test(tmp_path):
    recorded = viewer_sender.record(10)
    port = rerun_peers.free_port()
    viewer = RerunViewer(RerunConfig(serve=f"127.0.0.1:{port}", queue_size=1000))
    viewer.start()
    counts = []
    try:
        for k in range(6):
            facts = dataclasses.replace(
                recorded.facts, facts={**recorded.facts.facts, "test_id": f"flat-{k}"}
            )
            viewer.begin(facts)
            for sample in recorded.samples:
                viewer(sample)
            viewer.end(recorded.result)
            assert viewer.problem is None and viewer.samples_shown == len(recorded.samples)
            counts.append(_settled_thread_count())
    finally:
        viewer.close()
    assert counts[-1] <= counts[1], counts
