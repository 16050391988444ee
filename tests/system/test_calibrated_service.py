"""`extensometer serve` with `[optics] calibration`: read at start-up and at every start
command; a file that goes bad refuses that start (log, exit status register) and the service
stays up for the next."""

import json
import sys
import time
from pathlib import Path

import pytest

from tests.system.modbus_peers import MBPOLL, free_tcp_port, mbpoll_read_tcp, mbpoll_tcp
from tests.system.notify_harness import NotifyHarness
from tests.system.test_calibrated_run import ideal_calibration

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))
EXIT_STATUS = 30
FAULT = "5"
COMPLETED = "1"

pytestmark = pytest.mark.skipif(MBPOLL is None, reason="mbpoll is not installed")


def _config(tmp_path: Path, port: int) -> Path:
    path = tmp_path / "service.toml"
    path.write_text(
        f'[modbus]\ntcp = "127.0.0.1:{port}"\n'
        f'[service]\nstate_directory = "{tmp_path / "state"}"\n'
        "[run]\nuntil_strain = 0.05\n"
        "[sim]\nrealtime = true\nsensor_width_px = 512\nsensor_height_px = 1024\n"
        '[optics]\ncalibration = "cal/ideal.json"\n'
    )
    return path


def _exit_status(port: int) -> str:
    return mbpoll_read_tcp(port, "-r", str(EXIT_STATUS), "-c", "1", "-t", "4")[EXIT_STATUS]


def _start(port: int) -> None:
    done = mbpoll_tcp(port, "-r", "100", "-t", "4", write=["1"])
    assert done.returncode == 0, done.stdout + done.stderr


def test_a_calibration_gone_bad_refuses_the_start_and_the_next_start_measures(tmp_path):
    (tmp_path / "cal").mkdir()
    calibration = ideal_calibration(tmp_path / "cal" / "ideal.json")
    good = (tmp_path / "cal" / "ideal.json").read_text()
    port = free_tcp_port()
    config = _config(tmp_path, port)
    with NotifyHarness([EXTENSOMETER, "serve", "--config", str(config)]) as service:
        service.wait_for("READY=1", timeout=180)
        assert calibration.checksum in service.stderr
        document = json.loads(good)
        document["scale_mm_per_px"] *= 1.01
        (tmp_path / "cal" / "ideal.json").write_text(json.dumps(document))
        _start(port)
        refused = service.wait_for(
            lambda n: n.value("STATUS", "").startswith("last test not started"), 60
        )
        assert "checksum mismatch" in refused.value("STATUS", "")
        assert _exit_status(port) == FAULT
        line = next(x for x in service.stderr.splitlines() if "not started" in x)
        assert "[optics] calibration" in line and "ideal.json" in line
        assert service.returncode is None
        (tmp_path / "cal" / "ideal.json").write_text(good)
        time.sleep(0.5)
        _start(port)
        service.wait_for(lambda n: n.value("STATUS", "").startswith("last test completed"), 180)
        assert _exit_status(port) == COMPLETED
        assert service.terminate(timeout=60) == 0
    summaries = sorted((tmp_path / "state").glob("test-*.summary.json"))
    assert len(summaries) == 1
    summary = json.loads(summaries[0].read_text())
    assert summary["measured_in"] == "object plane"
    assert summary["calibration_checksum"] == calibration.checksum


def test_a_bad_calibration_is_named_before_ready(tmp_path):
    port = free_tcp_port()
    config = _config(tmp_path, port)
    with NotifyHarness([EXTENSOMETER, "serve", "--config", str(config)]) as service:
        assert service.wait(timeout=120) == 2
        assert not any(n.matches("READY=1") for n in service.messages)
        assert "[optics] calibration" in service.stderr and "no such calibration" in service.stderr
        assert service.stderr.count("\n") == 1
