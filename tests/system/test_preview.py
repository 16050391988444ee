"""`extensometer preview` as an installer runs it: the simulated bench's camera and a GigE
Vision camera on loopback streamed to a Rerun viewer (a file, or the real rerun CLI as a
headless viewer of its server), ended by its duration, SIGTERM or SIGINT."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from appliance.live.viewer.preview import QUALITY_SERIES
from appliance.plan.optics import Optics
from appliance.sim.world import PRESETS
from tests.system import rerun_peers
from tests.system.aravis_peers import needs_gige, specimen_camera

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))

OVERLAYS = {
    "camera/image",
    "camera/specimen/outline",
    "camera/specimen/axis",
    "camera/specimen/ends",
    "camera/gauge/points",
    "camera/gauge/marks",
    "camera/gauge/subsets",
    "status/placement",
    "status/log",
}
FIGURES = {f"quality/{name}" for name in QUALITY_SERIES}
GAUGE_ONLY = OVERLAYS - {f"camera/specimen/{part}" for part in ("outline", "axis", "ends")}


def _cli(*args: str, timeout_s: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([EXTENSOMETER, *args], capture_output=True, text=True, timeout=timeout_s)


def _start(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [EXTENSOMETER, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )


def _end(process: subprocess.Popen, number: int, timeout_s: float = 30) -> tuple[int, str, str]:
    process.send_signal(number)
    try:
        out, err = process.communicate(timeout=timeout_s)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate(timeout=10)
    return process.returncode, out, err


def _preview(store_by_id: dict) -> object:
    ids = [rid for rid in store_by_id if rid.startswith("preview-")]
    assert len(ids) == 1, list(store_by_id)
    return store_by_id[ids[0]]


def _frames_in(summary: str) -> int:
    return int(summary.removeprefix("preview: ").split()[0])


def _marks(store) -> list:
    found = rerun_peers.rows(store, "camera/gauge/marks", "Points2D:positions")
    assert found
    return found[max(found)]


def test_the_simulated_bench_streams_frames_figures_and_the_gauge_a_test_would_place(tmp_path):
    saved = tmp_path / "preview.rrd"
    done = _cli(
        "preview", "--camera", "sim://camera", "--duration-s", "5", "--rerun-save", str(saved)
    )
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert len(lines) == 1 and lines[0].startswith("preview: "), done.stdout
    assert lines[0].endswith("ended by its duration") and "gauge detected: 25.000 mm" in lines[0]
    assert rerun_peers.verify(saved).returncode == 0
    store = _preview(rerun_peers.recordings(saved))
    assert OVERLAYS | FIGURES <= rerun_peers.entity_paths(store)
    focus = rerun_peers.series(store, "quality/focus_gradient")
    assert len(focus) == _frames_in(lines[0]) >= 5
    assert min(focus.values()) > 3.8
    assert max(rerun_peers.series(store, "quality/saturated_fraction").values()) < 0.01
    speckle = list(rerun_peers.series(store, "quality/speckle_size_px").values())
    assert speckle and all(2.0 < size < 8.0 for size in speckle)
    scale = PRESETS["rubber"].optics.scale_mm_per_px
    first, second = np.asarray(_marks(store), dtype=np.float64)
    assert math.dist(first, second) * scale == pytest.approx(25.0, abs=scale)
    points = rerun_peers.rows(store, "camera/gauge/points", "Points2D:positions")
    subsets = rerun_peers.rows(store, "camera/gauge/subsets", "Boxes2D:half_sizes")
    assert len(points[max(points)]) == len(subsets[max(subsets)]) == 6
    assert np.allclose(subsets[max(subsets)], 20.5)


def test_sigterm_ends_the_preview_cleanly_with_its_file_complete(tmp_path):
    saved = tmp_path / "preview.rrd"
    process = _start("preview", "--camera", "sim://camera", "--rerun-save", str(saved))
    deadline = time.monotonic() + 60
    while not (saved.exists() and saved.stat().st_size > 5_000_000):
        assert process.poll() is None, process.communicate()
        assert time.monotonic() < deadline, "no frames saved within 60 s"
        time.sleep(0.2)
    stopped = time.monotonic()
    status, out, err = _end(process, signal.SIGTERM)
    assert status == 0, err
    assert time.monotonic() - stopped < 15
    assert out.count("\n") == 1 and out.rstrip().endswith("ended by SIGTERM"), out
    assert "Traceback" not in err
    assert rerun_peers.verify(saved).returncode == 0
    store = _preview(rerun_peers.recordings(saved))
    assert len(rerun_peers.series(store, "quality/focus_gradient")) == _frames_in(out)


@pytest.mark.parametrize(
    ("args", "culprit"),
    [
        (["--camera", "sim://camera"], "preview: no viewer: give --rerun-serve"),
        (["--rate-hz", "0", "--rerun-save", "x.rrd"], "argument --rate-hz"),
        (["--duration-s", "-1", "--rerun-save", "x.rrd"], "argument --duration-s"),
        (["--camera", "gige://1.2.3.4", "--rerun-save", "x.rrd"], "unknown scheme gige://"),
        (["--rerun-save", "no/such/dir/x.rrd"], "[rerun] save: no/such/dir/x.rrd"),
        (["--rerun-serve", "localhost:9876"], "HOST must be an IP address"),
    ],
)
def test_bad_input_is_one_line_naming_it(tmp_path, args, culprit):
    done = subprocess.run(
        [EXTENSOMETER, "preview", *args], capture_output=True, text=True, timeout=60, cwd=tmp_path
    )
    assert done.returncode == 2, done.stderr
    assert done.stderr.count("\n") == 1 and culprit in done.stderr, done.stderr
    assert done.stderr.startswith("extensometer: error: ") and done.stdout == ""
    assert not (tmp_path / "x.rrd").exists()


@needs_gige
def test_a_gige_camera_is_served_to_a_remote_viewer_until_sigint(tmp_path):
    config = tmp_path / "site.toml"
    config.write_text(
        "[optics]\nfocal_length_mm = 35.0\nobject_distance_mm = 400.0\npixel_size_um = 5.5\n"
        "[gauge]\nlength_mm = 10.0\n"
    )
    port = rerun_peers.free_port()
    seen = tmp_path / "seen.rrd"
    with specimen_camera(tmp_path / "truth.jsonl", strain_rate_per_s=0.0) as camera:
        process = _start(
            "preview",
            "--camera",
            camera.url,
            "--config",
            str(config),
            "--rerun-serve",
            f"127.0.0.1:{port}",
        )
        try:
            announced = process.stderr.readline()
            assert announced.strip().endswith(f"rerun+http://127.0.0.1:{port}/proxy"), announced
            url = announced.split()[-1]
            with rerun_peers.receiver(url, seen, tmp_path / "receiver.log") as peer:
                time.sleep(6)
                assert peer.alive(), peer.output()
                status, out, err = _end(process, signal.SIGINT)
                assert peer.wait(30) == 0, peer.output()
        finally:
            if process.poll() is None:
                process.kill()
                process.communicate(timeout=10)
    assert status == 0, err
    assert out.rstrip().endswith("ended by SIGINT") and "gauge image centre" in out, out
    assert rerun_peers.verify(seen).returncode == 0
    store = _preview(rerun_peers.recordings(seen))
    assert GAUGE_ONLY | FIGURES <= rerun_peers.entity_paths(store)
    focus = rerun_peers.series(store, "quality/focus_gradient")
    assert focus and min(focus.values()) > 3.8
    rates = list(rerun_peers.series(store, "quality/frame_rate_hz").values())
    assert rates and 3.0 < np.median(rates) < 5.0
    scale = Optics(35.0, 400.0, 5.5).scale_mm_per_px
    first, second = np.asarray(_marks(store), dtype=np.float64)
    assert math.dist(first, second) * scale == pytest.approx(10.0, rel=0.01)
    assert np.allclose((first + second) / 2, [255.5, 255.5], atol=1.0)


@needs_gige
def test_an_absent_gige_camera_is_one_line_and_exit_status_1(tmp_path):
    done = _cli(
        "preview",
        "--camera",
        "aravis://127.0.0.9",
        "--rerun-save",
        str(tmp_path / "p.rrd"),
        "--duration-s",
        "5",
    )
    assert done.returncode == 1, done.stderr
    assert done.stderr.count("\n") == 1, done.stderr
    assert done.stderr.startswith("extensometer: preview: aravis://127.0.0.9: ")
    assert done.stdout.startswith("preview: 0 frames") and "ended by the camera" in done.stdout
    assert os.path.exists(tmp_path / "p.rrd")
