"""`extensometer trigger-check` against the real firmware under simavr, as an installer runs it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from firmware_bridge.messages import PROTOCOL_VERSION, TABLE_HASH
from firmware_bridge.simulator import SimulatedMcu
from tests.system.firmware_peers import firmware_binaries

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))


@pytest.fixture(scope="module")
def binaries() -> dict[str, Path]:
    return firmware_binaries()


def _check(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [EXTENSOMETER, "trigger-check", *args], capture_output=True, text=True, timeout=60
    )


def test_trigger_check_reports_the_firmware_and_its_link(binaries, tmp_path):
    with SimulatedMcu(binaries["elf"], binaries["harness"], tmp_path) as mcu:
        done = _check("--port", str(mcu.port), "--pings", "20", "--json")
        text = _check("--port", str(mcu.port), "--pings", "5")
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert report["protocol_version"] == f"{PROTOCOL_VERSION[0]}.{PROTOCOL_VERSION[1]}"
    assert report["table_hash"] == f"{TABLE_HASH:#010x}" and report["tick_hz"] == 2_000_000
    assert report["pings"] == 20 and report["encoder_position"] == 0
    assert 0 < report["round_trip_ms"]["p50"] <= report["round_trip_ms"]["p99"] < 1000
    assert report["clock_rate_ppm"] is not None and abs(report["clock_rate_ppm"]) < 5000
    assert text.returncode == 0, text.stderr
    assert "matches this host" in text.stdout and "2000000 Hz" in text.stdout


def test_trigger_check_names_a_port_that_does_not_answer(tmp_path):
    silent = tmp_path / "absent-tty"
    done = _check("--port", str(silent), "--pings", "1")
    assert done.returncode == 1
    assert done.stderr.startswith(f"extensometer: trigger-check: {silent}: ")
    assert done.stderr.count("\n") == 1
