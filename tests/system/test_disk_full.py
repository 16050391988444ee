"""A full disk, on a real small file system (`small_disk`): refused before a test, a fault
during one, and never a lost sample or a dead service.

`run` and `serve` run as real processes; their files go to a tmpfs of a few hundred kB, so the
disk fills for real (ENOSPC from the kernel) at the moment it would on a lab PC.
"""

from __future__ import annotations

import csv
import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from appliance.live.modbus_map import BY_NAME, EXIT_STATUS_CODES, StatusBit
from appliance.run.state import ExitStatus
from tests.system.modbus_peers import MBPOLL, free_tcp_port, mbpoll_read_tcp, mbpoll_tcp
from tests.system.notify_harness import NotifyHarness
from tests.system.small_disk import fill, small_disk

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))
RESERVE = ".extensometer-reserve"


def run(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run(
        [EXTENSOMETER, "run", *args], capture_output=True, text=True, timeout=timeout, check=False
    )


def storage_config(tmp_path: Path, min_free_mb: float, reserve_mb: float) -> Path:
    """A simulated test on a small sensor (fast to render) with the given storage rules."""
    path = tmp_path / "storage.toml"
    path.write_text(
        f"[storage]\nmin_free_mb = {min_free_mb}\nreserve_mb = {reserve_mb}\n"
        "[sim]\nsensor_width_px = 512\nsensor_height_px = 1024\n"
    )
    return path


def strain_rows(path: Path) -> list[dict[str, str]]:
    """The strain file's rows; every one whole (as many fields as the header)."""
    with path.open(newline="") as file:
        rows = list(csv.reader(file))
    header, body = rows[0], rows[1:]
    assert all(len(row) == len(header) for row in body), "a partial row in the strain file"
    return [dict(zip(header, row, strict=True)) for row in body]


def test_a_test_is_refused_before_it_starts_on_a_disk_without_room(tmp_path):
    with small_disk(tmp_path / "disk", 512) as disk:
        out = disk / "out"
        done = run("--sim", "--until-strain", "0.1", "--out", str(out), "--record", f"{out}/r.mcap")
        assert done.returncode == 2
        assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr
        assert f"{out}: 0.5 MB free, below [storage] min_free_mb (1000 MB)" in done.stderr
        assert sorted(p.name for p in out.iterdir()) == []


def test_a_recording_that_fills_the_disk_ends_the_test_as_a_fault_with_every_sample_kept(
    tmp_path,
):
    config = storage_config(tmp_path, min_free_mb=0.5, reserve_mb=0.1)
    with small_disk(tmp_path / "disk", 3072) as disk:
        out = disk / "out"
        recording = out / "test.mcap"
        done = run(
            "--sim", "--config", str(config), "--until-strain", "3", "--json",
            "--out", str(out), "--record", str(recording),
        )  # fmt: skip
        assert done.returncode == 1, done.stderr
        assert "Traceback" not in done.stderr
        summary = json.loads(done.stdout)
        assert summary["exit_status"] == "fault"
        assert (
            f"{recording}: recording failed: [Errno 28] No space left on device"
            in (summary["reason"])
        )
        assert 0 < summary["final_strain"] < 3
        rows = strain_rows(out / "strain.csv")
        assert [int(r["index"]) for r in rows] == list(range(summary["frames_processed"]))
        assert summary["strain_file_rows"] == len(rows)
        assert summary["recording_samples"] < len(rows)
        assert json.loads((out / "summary.json").read_text()) == summary
        assert not (out / RESERVE).exists()
        info = subprocess.run(
            [EXTENSOMETER, "info", str(recording)], capture_output=True, text=True, check=False
        )
        assert info.returncode == 1 and "damaged after byte" in info.stderr


def test_a_strain_file_that_fills_the_disk_keeps_every_sample_and_the_summary(tmp_path):
    config = storage_config(tmp_path, min_free_mb=0.01, reserve_mb=0.008)
    with small_disk(tmp_path / "disk", 32) as disk:
        out = disk / "out"
        done = run(
            "--sim", "--config", str(config), "--until-strain", "3", "--json", "--out", str(out)
        )
        assert done.returncode == 1, done.stderr
        summary = json.loads(done.stdout)
        assert summary["exit_status"] == "fault"
        assert summary["reason"] == (
            f"strain file: OSError: [Errno 28] No space left on device: '{out / 'strain.csv'}'"
        )
        rows = strain_rows(out / "strain.csv")
        assert [int(r["index"]) for r in rows] == list(range(summary["frames_processed"]))
        assert summary["strain_file_rows"] == len(rows) > 20
        assert json.loads((out / "summary.json").read_text()) == summary
        assert not (out / RESERVE).exists()


def _service_registers(port: int) -> tuple[int, int, int]:
    """(status, heartbeat, exit_status) as mbpoll reads them."""
    status, heartbeat = BY_NAME["status"].address, BY_NAME["heartbeat"].address
    exit_status = BY_NAME["exit_status"].address
    words = mbpoll_read_tcp(port, "-r", str(status), "-c", str(exit_status - status + 1), "-t", "4")
    return int(words[status]), int(words[heartbeat]), int(words[exit_status])


@pytest.mark.skipif(MBPOLL is None, reason="mbpoll is not installed")
def test_the_service_refuses_a_test_without_room_makes_room_by_retention_and_outlives_a_full_disk(
    tmp_path,
):
    port = free_tcp_port()
    with small_disk(tmp_path / "disk", 3072) as state:
        config = tmp_path / "service.toml"
        config.write_text(
            f'[modbus]\ntcp = "127.0.0.1:{port}"\n'
            f'[service]\nstate_directory = "{state}"\nmax_state_mb = 1.0\n'
            "[storage]\nmin_free_mb = 0.5\nreserve_mb = 0.1\n"
            "[sim]\nrealtime = true\nsensor_width_px = 512\nsensor_height_px = 1024\n"
        )
        filler = fill(state, leave_kb=256)
        with NotifyHarness(
            [EXTENSOMETER, "serve", "--config", str(config)], watchdog_usec=2_000_000
        ) as service:
            service.wait_for("READY=1", timeout=180)
            assert mbpoll_tcp(port, "-r", "100", "-t", "4", write=["1"]).returncode == 0
            refused = service.wait_for(
                lambda n: n.value("STATUS", "").startswith("last test not started"), 60
            )
            assert "MB free, below [storage] min_free_mb (0.5 MB)" in refused.value("STATUS")
            status, _, exit_status = _service_registers(port)
            assert status & StatusBit.FAULT and exit_status == EXIT_STATUS_CODES[ExitStatus.FAULT]

            filler.unlink()
            old = state / "test-20200101T000000Z-0001"
            fill(state, leave_kb=200).rename(old.with_suffix(".mcap"))
            old.with_suffix(".summary.json").write_text("{}")
            assert mbpoll_tcp(port, "-r", "100", "-t", "4", write=["1"]).returncode == 0
            ended = service.wait_for(
                lambda n: n.value("STATUS", "").startswith("last test fault"), 120
            )
            assert "No space left on device" in ended.value("STATUS")
            assert not old.with_suffix(".mcap").exists()
            assert not old.with_suffix(".summary.json").exists()
            status, heartbeat, exit_status = _service_registers(port)
            assert status & StatusBit.FAULT and not status & StatusBit.DATA_VALID
            assert exit_status == EXIT_STATUS_CODES[ExitStatus.FAULT]
            time.sleep(0.5)
            assert _service_registers(port)[1] != heartbeat
            assert service.terminate(timeout=60) == 0
            assert "retention: deleted test-20200101T000000Z-0001" in service.stderr
        (summary_path,) = state.glob("test-*.summary.json")
        summary = json.loads(summary_path.read_text())
        assert summary["exit_status"] == "fault"
        strain_path = summary_path.with_name(
            summary_path.name.replace("summary.json", "strain.csv")
        )
        rows = strain_rows(strain_path)
        assert [int(r["index"]) for r in rows] == list(range(summary["frames_processed"]))
        assert summary["frames_processed"] > 0
        assert not (state / RESERVE).exists()
