"""`extensometer camera-check` and `machine-check` as an installer runs them, on real peers:
Aravis' fake GigE Vision camera and a pymodbus machine controller, both on loopback."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import pytest

from appliance.sim.controller_server import ControllerServer
from tests.system.aravis_peers import FakeGvCamera, needs_gige, specimen_camera
from tests.system.machine_controller_peers import SimulatedController
from tests.system.modbus_peers import free_tcp_port

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([EXTENSOMETER, *args], capture_output=True, text=True, timeout=120)


@needs_gige
def test_camera_check_reports_what_the_camera_delivers(tmp_path):
    config = tmp_path / "camera.toml"
    config.write_text(
        "[camera]\nregion_x_px = 0\nregion_y_px = 0\nregion_width_px = 256\n"
        "region_height_px = 128\n"
    )
    with FakeGvCamera("127.0.0.5", "GV05") as camera:
        done = _cli(
            "camera-check",
            "--camera",
            camera.url,
            "--config",
            str(config),
            "--frames",
            "20",
            "--rate",
            "50",
            "--json",
        )
        text = _cli("camera-check", "--camera", camera.url, "--frames", "5")
    assert done.returncode == 1, done.stderr
    report = json.loads(done.stdout)
    assert report["fit"] is False
    assert [p for p in report["problems"] if p.startswith("no sharp texture in view")]
    for key in ("frames", "width", "height", "pixel_format", "fps", "lost"):
        assert key in report
    assert (report["frames"], report["width"], report["height"]) == (20, 256, 128)
    assert report["pixel_format"] == "Mono8" and report["lost"] == 0
    assert report["timestamps_increasing"] and 25 < report["device_fps"] < 100
    assert report["statistics"]["frames_delivered"] >= 20
    assert text.returncode == 1 and "frames             5 (0 lost" in text.stdout
    assert "verdict            NOT fit to measure" in text.stdout


@needs_gige
def test_camera_check_finds_a_camera_on_a_speckled_specimen_fit_to_measure(tmp_path):
    saved = tmp_path / "check.png"
    with specimen_camera(tmp_path / "truth.jsonl", strain_rate_per_s=0.0) as camera:
        done = _cli(
            "camera-check",
            "--camera",
            camera.url,
            "--frames",
            "20",
            "--rate",
            "20",
            "--save",
            str(saved),
            "--json",
        )
    assert done.returncode == 0, done.stdout + done.stderr
    report = json.loads(done.stdout)
    assert report["fit"] is True and report["problems"] == [] and report["lost"] == 0
    assert report["sharpest_gradient"] > 3.8
    overlay = cv2.imread(str(saved), cv2.IMREAD_COLOR)
    assert report["saved"] == str(saved)
    assert overlay is not None and overlay.shape[:2] == (report["height"], report["width"])


@needs_gige
def test_camera_check_names_an_absent_camera_and_a_bad_option():
    absent = _cli("camera-check", "--camera", "aravis://127.0.0.9", "--frames", "2")
    assert absent.returncode == 1 and absent.stderr.count("\n") == 1
    assert absent.stderr.startswith("extensometer: camera-check: aravis://127.0.0.9: ")
    bad = _cli("camera-check", "--camera", "aravis://127.0.0.9?buffers=x")
    assert bad.returncode == 2 and "option buffers='x'" in bad.stderr
    assert bad.stderr.count("\n") == 1


def test_machine_check_reads_the_controller_state_and_names_a_dead_one():
    controller = SimulatedController()
    port = free_tcp_port()
    with ControllerServer(controller) as server:
        server.serve_tcp(port)
        done = _cli("machine-check", "--machine", f"modbus-tcp://127.0.0.1:{port}", "--json")
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    state = controller.machine.state_at(controller.machine.clock())
    assert report["reads"] == 50 and report["rate_hz"] > 0
    assert report["state"]["crosshead_mm"] == pytest.approx(state["crosshead_mm"], rel=1e-6)
    assert report["state"]["force_n"] == pytest.approx(state["force_n"], rel=1e-6)
    assert report["latency_ms"]["p50"] <= report["latency_ms"]["p99"]
    dead = _cli("machine-check", "--machine", f"modbus-tcp://127.0.0.1:{port}")
    assert dead.returncode == 1 and dead.stderr.count("\n") == 1
    assert f"modbus-tcp://127.0.0.1:{port}" in dead.stderr
    bad = _cli("machine-check", "--machine", "modbus-tcp://127.0.0.1:99999")
    assert bad.returncode == 2 and bad.stderr.startswith("extensometer: error: machine-check: ")


@pytest.mark.parametrize(
    ("command", "option", "url"),
    [
        ("camera-check", "--camera", "aravis://[::1"),
        ("camera-check", "--camera", "v4l2://[x"),
        ("machine-check", "--machine", "modbus-tcp://[::1"),
    ],
)
def test_a_url_that_cannot_be_split_is_one_line_naming_it(command, option, url):
    done = _cli(command, option, url)
    assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
    assert f"URL {url!r}: Invalid IPv6 URL" in done.stderr and "Traceback" not in done.stderr
