"""`extensometer serve` as systemd runs it: notifications, watchdog, Modbus commands, recordings.

The service runs as a real process under a fake NOTIFY_SOCKET (`notify_harness`), with the
simulated devices in real time; mbpoll (libmodbus) reads and writes its registers over TCP on
loopback; its recordings are checked by replaying them.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from appliance.live.viewer import proxy_url
from appliance.recording.reader import RecordingReader
from tests.system import rerun_peers
from tests.system.modbus_peers import MBPOLL, free_tcp_port, mbpoll_read_tcp, mbpoll_tcp
from tests.system.notify_harness import NotifyHarness
from tests.system.test_recording import cli, rerun_mcap_check

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))

pytestmark = pytest.mark.skipif(MBPOLL is None, reason="mbpoll is not installed")

STATUS_TRACKING = 1 << 1


def _config(tmp_path: Path, port: int, **extra: str) -> Path:
    tables = {
        "modbus": f'tcp = "127.0.0.1:{port}"',
        "service": f'state_directory = "{tmp_path / "state"}"',
        "run": "until_strain = 0.3",
        "sim": "realtime = true\nsensor_width_px = 512\nsensor_height_px = 1024",
        **extra,
    }
    path = tmp_path / "service.toml"
    path.write_text("".join(f"[{name}]\n{body}\n" for name, body in tables.items()))
    return path


def _registers(port: int) -> dict[str, float]:
    floats = mbpoll_read_tcp(port, "-r", "0", "-c", "5", "-t", "4:float", "-B")
    words = mbpoll_read_tcp(port, "-r", "10", "-c", "4", "-t", "4")
    return {
        "strain": float(floats[0]),
        "status": int(words[10]),
        "heartbeat": int(words[11]),
        "frame": (int(words[12]) << 16) | int(words[13]),
    }


def _wait_registers(port: int, condition, timeout: float) -> dict[str, float]:
    deadline = time.monotonic() + timeout
    while True:
        registers = _registers(port)
        if condition(registers):
            return registers
        assert time.monotonic() < deadline, f"registers never matched: {registers}"
        time.sleep(0.2)


def test_a_served_test_is_read_live_commanded_and_recorded(tmp_path):
    port = free_tcp_port()
    config = _config(tmp_path, port)
    with NotifyHarness(
        [EXTENSOMETER, "serve", "--config", str(config)], watchdog_usec=1_000_000
    ) as service:
        ready = service.wait_for("READY=1", timeout=180)
        assert ready.pid == service.pid and "idle" in ready.value("STATUS", "")
        idle = _registers(port)
        time.sleep(1.0)
        assert _registers(port)["heartbeat"] != idle["heartbeat"]
        assert idle["status"] & STATUS_TRACKING == 0
        start = mbpoll_tcp(port, "-r", "100", "-t", "4", write=["1"])
        assert start.returncode == 0, start.stdout + start.stderr
        running = service.wait_for(lambda n: n.value("STATUS", "").startswith("running test"), 60)
        first = _wait_registers(
            port, lambda r: r["status"] & STATUS_TRACKING and r["strain"] == r["strain"], 30
        )
        later = _wait_registers(port, lambda r: r["frame"] > first["frame"] + 5, 30)
        assert first["strain"] < later["strain"] < 0.35 and later["strain"] > 0
        ended = service.wait_for(
            lambda n: n.value("STATUS", "").startswith("last test completed"), 120
        )
        pings = service.watchdog_times()
        assert sum(running.received_s < t < ended.received_s for t in pings) >= 2
        assert all(b - a < 1.0 for a, b in zip(pings, pings[1:], strict=False))
        refused = mbpoll_tcp(port, "-r", "100", "-t", "4", write=["2"])
        assert refused.returncode == 0
        assert mbpoll_read_tcp(port, "-r", "102", "-c", "1", "-t", "4")[102] == "2"
        assert service.terminate(timeout=60) == 0
        service.wait_for("STOPPING=1", timeout=5)
    recordings = sorted((tmp_path / "state").glob("test-*.mcap"))
    assert len(recordings) == 1
    summary = json.loads(recordings[0].with_suffix(".summary.json").read_text())
    assert summary["exit_status"] == "completed" and summary["final_strain"] >= 0.3
    replay = cli("replay", str(recordings[0]), "--json")
    assert replay.returncode == 0, replay.stderr
    assert json.loads(replay.stdout)["max_abs_diff_to_recorded"] == 0.0


def test_a_served_test_is_read_by_mbpoll_watched_in_rerun_and_replays_bit_for_bit(tmp_path):
    """The issue's acceptance: a simulated test served as a service is read live by mbpoll and
    watched by a headless Rerun receiver; its MCAP file passes `rerun mcap check`, opens with
    the Foxglove schemas and replays bit for bit."""
    port = free_tcp_port()
    viewer_port = rerun_peers.free_port()
    config = _config(tmp_path, port, rerun=f'serve = "127.0.0.1:{viewer_port}"')
    watched = tmp_path / "watched.rrd"
    with NotifyHarness(
        [EXTENSOMETER, "serve", "--config", str(config)], watchdog_usec=2_000_000
    ) as service:
        service.wait_for("READY=1", timeout=180)
        with rerun_peers.receiver(
            proxy_url("127.0.0.1", viewer_port), watched, tmp_path / "receiver.log"
        ) as receiver:
            start = mbpoll_tcp(port, "-r", "100", "-t", "4", write=["1"])
            assert start.returncode == 0, start.stdout + start.stderr
            live = _wait_registers(
                port, lambda r: r["status"] & STATUS_TRACKING and r["strain"] > 0.05, 60
            )
            service.wait_for(lambda n: n.value("STATUS", "").startswith("last test completed"), 120)
            assert service.terminate(timeout=60) == 0
            assert receiver.wait(60) == 0, receiver.log_path.read_text()
    assert rerun_peers.verify(watched).returncode == 0
    (recording,) = sorted((tmp_path / "state").glob("test-*.mcap"))
    reader = RecordingReader(recording)
    recorded = {s.index: s.strain["engineering_strain"] for s in reader.samples()}
    reader.close()
    assert live["frame"] > 0 and 0.05 < live["strain"] < 0.35
    (store,) = [v for k, v in rerun_peers.recordings(watched).items() if k.startswith("test-")]
    assert rerun_peers.series(store, "strain/axial") == {
        k: v for k, v in recorded.items() if v is not None
    }
    rerun_mcap_check(recording)
    with recording.open("rb") as f:
        decoded = make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
            topics=["/camera/full"]
        )
        image = next(iter(decoded))[3]
        assert type(image).__name__ == "RawImage" and (image.width, image.height) == (512, 1024)
    replay = cli("replay", str(recording), "--json")
    assert replay.returncode == 0, replay.stderr
    replayed = json.loads(replay.stdout)
    assert replayed["max_abs_diff_to_recorded"] == 0.0 and replayed["samples_differing"] == 0
    assert replayed["frames_processed"] == len(recorded)


def test_a_stalled_measurement_stops_the_watchdog_and_sigterm_still_closes_the_recording(
    tmp_path,
):
    port = free_tcp_port()
    config = _config(
        tmp_path,
        port,
        service=f'state_directory = "{tmp_path / "state"}"\nstart = "auto"',
        run="until_strain = 0",
        sim="realtime = true\nsensor_width_px = 512\nsensor_height_px = 1024\n"
        "camera_hang_after_s = 2.0",
    )
    with NotifyHarness(
        [EXTENSOMETER, "serve", "--config", str(config)], watchdog_usec=2_000_000
    ) as service:
        service.wait_for("READY=1", timeout=180)
        service.wait_for(lambda n: n.value("STATUS", "").startswith("running test"), 60)
        last_ping = service.wait_for_silence("WATCHDOG=1", quiet_s=4.0, timeout=60)
        assert service.returncode is None
        assert _registers(port)["frame"] > 0
        silent_since = time.monotonic() - last_ping
        assert silent_since >= 4.0
        assert service.terminate(timeout=60) == 0
    recordings = sorted((tmp_path / "state").glob("test-*.mcap"))
    summary = json.loads(recordings[0].with_suffix(".summary.json").read_text())
    assert summary["exit_status"] == "fault" and "fetch did not return" in summary["reason"]
    replay = cli("replay", str(recordings[0]), "--json")
    assert replay.returncode == 0, replay.stderr
    replayed = json.loads(replay.stdout)
    assert replayed["frames_processed"] == summary["frames_processed"] > 10
    assert replayed["max_abs_diff_to_recorded"] == 0.0


def test_a_stop_command_and_sigterm_end_a_test_as_stopped_with_their_reason(tmp_path):
    port = free_tcp_port()
    config = _config(
        tmp_path, port, service=f'state_directory = "{tmp_path / "state"}"', run="until_strain = 0"
    )
    with NotifyHarness([EXTENSOMETER, "serve", "--config", str(config)]) as service:
        service.wait_for("READY=1", timeout=180)
        for stop in ("modbus", "signal"):
            before = _registers(port)["frame"]
            start = mbpoll_tcp(port, "-r", "100", "-t", "4", write=["1"])
            assert start.returncode == 0, start.stdout + start.stderr
            _wait_registers(
                port, lambda r, b=before: r["status"] & STATUS_TRACKING and r["frame"] != b, 60
            )
            if stop == "modbus":
                stopped = mbpoll_tcp(port, "-r", "100", "-t", "4", write=["2"])
                assert stopped.returncode == 0, stopped.stdout + stopped.stderr
                service.wait_for(
                    lambda n: n.value("STATUS", "").startswith("last test stopped"), 60
                )
                assert mbpoll_read_tcp(port, "-r", "30", "-c", "1", "-t", "4")[30] == "3"
            else:
                assert service.terminate(timeout=60) == 0
    summaries = sorted((tmp_path / "state").glob("test-*.summary.json"))
    assert len(summaries) == 2
    for path, reason in zip(summaries, ("stop command", "SIGTERM"), strict=True):
        summary = json.loads(path.read_text())
        assert summary["exit_status"] == "stopped" and reason in summary["reason"]
        assert summary["frames_processed"] > 0


def test_a_start_command_as_soon_as_a_test_has_ended_is_taken(tmp_path):
    """The controller may start the next test the moment `run_state` reads idle after a test:
    the start is accepted (`command_result` 1) while the service still closes the last test's
    files, and the next test runs."""
    from pymodbus.client import ModbusTcpClient

    port = free_tcp_port()
    config = _config(
        tmp_path, port, service=f'state_directory = "{tmp_path / "state"}"', run="until_strain = 0"
    )
    with NotifyHarness([EXTENSOMETER, "serve", "--config", str(config)]) as service:
        service.wait_for("READY=1", timeout=180)
        client = ModbusTcpClient("127.0.0.1", port=port, timeout=5)
        assert client.connect()
        try:
            client.write_register(100, 1)
            service.wait_for(lambda n: n.value("STATUS", "").startswith("running test"), 60)
            client.write_register(100, 2)
            deadline = time.monotonic() + 60
            while True:
                words = client.read_holding_registers(27, count=4).registers
                if words[0] in (0, 4, 5) and words[3] != 0:
                    break
                assert time.monotonic() < deadline, words
            client.write_register(100, 1)
            assert client.read_holding_registers(102, count=1).registers == [1]
        finally:
            client.close()
        service.wait_for(
            lambda n: (
                n.value("STATUS", "").startswith("running test")
                and n.value("STATUS", "") != f"running test {_first_test(tmp_path)}"
            ),
            60,
        )
        assert service.terminate(timeout=60) == 0
    assert len(sorted((tmp_path / "state").glob("test-*.summary.json"))) == 2


def _first_test(tmp_path: Path) -> str:
    return sorted((tmp_path / "state").glob("test-*.mcap"))[0].name.removesuffix(".mcap")


@pytest.mark.parametrize(
    ("camera", "watchdog_usec", "message"),
    [
        ('url = "gige://192.0.2.1"\n[machine]\nurl = ""', None, "unknown scheme gige://"),
        ('url = "aravis://192.0.2.1"', None, "[machine] url: sim://machine is simulated"),
        ("min_frame_rate_hz = 0.5", 3_000_000, "[camera] min_frame_rate_hz: a frame period of 2"),
    ],
)
def test_bad_service_configuration_is_named_before_ready(tmp_path, camera, watchdog_usec, message):
    port = free_tcp_port()
    config = _config(tmp_path, port, camera=camera)
    with NotifyHarness(
        [EXTENSOMETER, "serve", "--config", str(config)], watchdog_usec=watchdog_usec
    ) as service:
        assert service.wait(timeout=120) == 2
        assert not any(n.matches("READY=1") for n in service.messages)
        assert message in service.stderr
        assert service.stderr.count("\n") == 1
