"""Faults under `extensometer serve` on real peers: the camera hung, unplugged and back, the
machine's controller lost and back, SIGKILL mid-test, SIGTERM in every run state.

The service runs as a real process under a fake NOTIFY_SOCKET (`notify_harness`) with a
watchdog. Its camera is the GigE Vision specimen camera (`aravis_peers.specimen_camera`, a
process a test stops with SIGSTOP, resumes with SIGCONT, or kills and starts again on the
same address); its machine is a Modbus TCP controller peer (`ControllerServer`) that a test
stops serving and serves again on the same port. mbpoll reads the strain server's registers.

For every fault the test checks what the controller and the operator see: the service stays
up (after SIGKILL a new start serves again), data-valid (status bit 0) is clear while the
strain is not valid, the end is recorded (the summary, `exit_status` in register 30, the
log), and every sample measured before the fault is in the strain file (every row is
written as it is measured, so none is lost). Each test is bounded by its waits' timeouts and
stops what it started.
"""

from __future__ import annotations

import contextlib
import csv
import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from appliance.run.strain_file import COLUMNS
from appliance.sim.controller_server import ControllerServer
from firmware_bridge.simulator import SimulatedMcu
from tests.system.aravis_peers import SpecimenCamera, needs_gige, specimen_camera
from tests.system.firmware_peers import firmware_binaries
from tests.system.machine_controller_peers import SimulatedController
from tests.system.modbus_peers import (
    MBPOLL,
    free_tcp_port,
    mbpoll_read_tcp,
    mbpoll_tcp,
    pty_pair,
)
from tests.system.notify_harness import NotifyHarness

EXTENSOMETER = str(Path(sys.executable).with_name("extensometer"))
ROOT = Path(__file__).resolve().parents[2]

pytestmark = [
    needs_gige,
    pytest.mark.skipif(MBPOLL is None, reason="mbpoll is not installed"),
]

DATA_VALID = 1 << 0
TRACKING = 1 << 1
CALIBRATING = 1 << 4
FAULT = 1 << 5
CAMERA_LOST = 1 << 6
NO_CONTROLLER_DATA = 1 << 7
RUN_STATES = {"idle": 0, "armed": 1, "running": 2, "stopping": 3, "aborted": 4, "fault": 5}
EXIT_STOPPED, EXIT_FAULT = 3, 5

WATCHDOG_USEC = 6_000_000
"""The watchdog interval the service runs under (its unit says 10 s; stricter here)."""

RESTART_S = 5.0
"""systemd's wait before it restarts a failed service (the unit's RestartSec): long enough for
the camera to give up the control a killed process held (GigE Vision heartbeat timeout)."""

OPTICS = "[optics]\nfocal_length_mm = 25.0\nobject_distance_mm = 250.0\npixel_size_um = 5.0\n"


class Bench:
    """A served appliance on its peers: the specimen camera, the controller, the service."""

    def __init__(self, tmp_path: Path, camera: SpecimenCamera, controller_port: int) -> None:
        self.tmp_path = tmp_path
        self.camera = camera
        self.controller_port = controller_port
        self.port = free_tcp_port()
        self.state = tmp_path / "state"
        self.service: NotifyHarness | None = None

    def config(self, *, outage_timeout_s: float = 20.0, frame_rate_hz: float = 10.0) -> Path:
        tables = {
            "camera": f'url = "{self.camera.url}"\nexposure_us = 1000\n'
            f"frame_rate_hz = {frame_rate_hz}\noutage_timeout_s = {outage_timeout_s}",
            "machine": f'url = "modbus-tcp://127.0.0.1:{self.controller_port}"\n'
            "accepts_commands = true\npoll_rate_hz = 20",
            "gauge": "length_mm = 10.0\npoints_per_mark = 3",
            "run": "speed_mm_min = 30.0\nuntil_break = false",
            "tracking": "subset_px = 31\nmin_subset_px = 11",
            "modbus": f'tcp = "127.0.0.1:{self.port}"',
            "service": f'state_directory = "{self.state}"',
        }
        path = self.tmp_path / "service.toml"
        path.write_text(OPTICS + "".join(f"[{name}]\n{body}\n" for name, body in tables.items()))
        return path

    def serve(self, config: Path) -> NotifyHarness:
        self.service = NotifyHarness(
            [EXTENSOMETER, "serve", "--config", str(config)], watchdog_usec=WATCHDOG_USEC
        )
        return self.service

    def registers(self) -> dict[str, int]:
        words = mbpoll_read_tcp(self.port, "-r", "10", "-c", "21", "-t", "4")
        return {
            "status": int(words[10]),
            "heartbeat": int(words[11]),
            "frame": (int(words[12]) << 16) | int(words[13]),
            "run_state": int(words[27]),
            "exit_status": int(words[30]),
        }

    def wait(
        self, condition: Callable[[dict[str, int]], bool], what: str, timeout_s: float = 60.0
    ) -> dict[str, int]:
        deadline = time.monotonic() + timeout_s
        while True:
            registers = self.registers()
            if condition(registers):
                return registers
            if time.monotonic() > deadline:
                log = self.service.stderr[-3000:] if self.service is not None else ""
                raise AssertionError(f"timed out waiting for {what}: {registers}\n{log}")
            time.sleep(0.1)

    def command(self, code: int) -> None:
        done = mbpoll_tcp(self.port, "-r", "100", "-t", "4", write=[str(code)])
        assert done.returncode == 0, done.stdout + done.stderr
        assert mbpoll_read_tcp(self.port, "-r", "102", "-c", "1", "-t", "4")[102] == "1"

    def measuring(self, frames: int = 10, timeout_s: float = 60.0) -> dict[str, int]:
        """Wait until `frames` valid frames more than now have been measured."""
        first = self.wait(lambda r: r["status"] & DATA_VALID, "a valid sample", timeout_s)
        return self.wait(
            lambda r: r["status"] & DATA_VALID and r["frame"] >= first["frame"] + frames,
            f"{frames} more frames",
            timeout_s,
        )

    def start_measuring(self, attempts: int = 3) -> None:
        """Start a test on a camera that was just resumed: the camera may still be settling
        (its first frames lost while it drops the control it held), and a test whose
        reference frame does not come ends as a fault naming it; the next start measures."""
        assert self.service is not None
        for _ in range(attempts):
            since = len(self.service.messages)
            self.command(1)
            news = self.service.wait_for(
                lambda n: n.value("STATUS", "").startswith(("running test", "last test")),
                60,
                since=since,
            )
            if news.value("STATUS").startswith("running test"):
                self.measuring(5)
                return
        raise AssertionError(f"no test measured in {attempts} starts:\n{self.service.stderr}")

    def tests(self) -> list[tuple[dict, list[dict[str, str]]]]:
        """Each test's summary and strain file rows, oldest first."""
        found = []
        for summary in sorted(self.state.glob("test-*.summary.json")):
            strain = summary.with_name(summary.name.replace(".summary.json", ".strain.csv"))
            found.append((json.loads(summary.read_text()), _rows(strain)))
        return found


def _rows(path: Path) -> list[dict[str, str]]:
    """The strain file's rows; every row whole (all columns, the last line ended)."""
    text = path.read_text()
    assert text.endswith("\n"), f"{path}: a partial last row"
    rows = list(csv.DictReader(text.splitlines()))
    for row in rows:
        assert None not in row and None not in row.values(), row
        assert set(COLUMNS) <= row.keys(), row
    assert [int(row["index"]) for row in rows] == list(range(len(rows)))
    return rows


def _every_sample_kept(summary: dict, rows: list[dict[str, str]], seen_frames: list[int]) -> None:
    """Every sample measured is a row, and every frame the controller read is among them."""
    assert len(rows) == summary["frames_processed"] == summary["strain_file_rows"]
    written = {int(row["frame_id"]) for row in rows}
    assert set(seen_frames) - {0} <= written


@contextlib.contextmanager
def _camera_peer(tmp_path: Path, name: str, address: str) -> Iterator[SpecimenCamera]:
    """The specimen camera; the test may stop (SIGSTOP) or kill it meanwhile."""
    with contextlib.ExitStack() as stack:
        camera = stack.enter_context(
            specimen_camera(
                tmp_path / f"{name}.jsonl", address=address, strain_rate_per_s=0.0, max_strain=0.0
            )
        )
        try:
            yield camera
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.kill(camera.process.pid, signal.SIGCONT)
            if camera.process.poll() is not None:
                stack.pop_all()


@contextlib.contextmanager
def _bench(tmp_path: Path, address: str) -> Iterator[tuple[Bench, ControllerServer]]:
    controller_port = free_tcp_port()
    with (
        _camera_peer(tmp_path, "camera", address) as camera,
        ControllerServer(SimulatedController()) as controller,
    ):
        controller.serve_tcp(controller_port)
        yield Bench(tmp_path, camera, controller_port), controller


def _pings_kept_up(service: NotifyHarness, since_s: float, until_s: float) -> float:
    """The longest time without a watchdog ping between two moments (monotonic s)."""
    pings = [t for t in service.watchdog_times() if since_s <= t <= until_s]
    marks = [since_s, *pings, until_s]
    return max(b - a for a, b in zip(marks, marks[1:], strict=False))


def test_a_hung_camera_is_an_outage_the_test_waits_through_then_a_fault_and_the_watchdog_keeps_time(
    tmp_path,
):
    """SIGSTOP on the camera: no frame within the fetch timeout is a camera outage. Data-valid
    is cleared and `camera lost` set, the outage logged, the watchdog pinged (the loop is in
    control), and after SIGCONT the test goes on. Stopped for longer than the outage timeout,
    the test ends as a fault that says so; the service stays up and runs the next test."""
    with (
        _bench(tmp_path, "127.0.0.11") as (bench, _),
        bench.serve(bench.config(outage_timeout_s=8)) as service,
    ):
        service.wait_for("READY=1", timeout=180)
        bench.command(1)
        seen = [bench.measuring()["frame"]]
        hung_at = time.monotonic()
        os.kill(bench.camera.process.pid, signal.SIGSTOP)
        lost = bench.wait(lambda r: r["status"] & CAMERA_LOST, "the camera reported lost", 30)
        cleared_s = time.monotonic() - hung_at
        assert not lost["status"] & DATA_VALID and lost["run_state"] == RUN_STATES["running"]
        seen.append(lost["frame"])
        time.sleep(2.0)
        os.kill(bench.camera.process.pid, signal.SIGCONT)
        resumed_at = time.monotonic()
        bench.wait(
            lambda r: (
                r["status"] & DATA_VALID
                and not r["status"] & CAMERA_LOST
                and r["frame"] > lost["frame"]
            ),
            "valid samples after SIGCONT",
            60,
        )
        recovered_s = time.monotonic() - resumed_at
        seen.append(bench.measuring(5)["frame"])
        os.kill(bench.camera.process.pid, signal.SIGSTOP)
        faulted = bench.wait(lambda r: r["exit_status"] == EXIT_FAULT, "the test to fault", 60)
        ended_at = time.monotonic()
        assert faulted["run_state"] == RUN_STATES["fault"] and faulted["status"] & FAULT
        assert not faulted["status"] & DATA_VALID
        gap_s = _pings_kept_up(service, hung_at, ended_at)
        assert gap_s < WATCHDOG_USEC / 1e6, f"{gap_s:.1f} s without a watchdog ping"
        status = service.wait_for(lambda n: n.value("STATUS", "").startswith("last test fault"), 30)
        assert "camera away" in status.value("STATUS")
        os.kill(bench.camera.process.pid, signal.SIGCONT)
        bench.start_measuring()
        bench.command(2)
        bench.wait(lambda r: r["exit_status"] == EXIT_STOPPED, "the next test to stop", 60)
        assert service.terminate(timeout=60) == 0
        log = service.stderr
    (hung, hung_rows), *_, (after, _) = bench.tests()
    assert hung["exit_status"] == "fault" and "camera away for" in hung["reason"]
    assert "outage timeout 8 s" in hung["reason"] and hung["camera_outages"] == 2
    assert after["exit_status"] == "stopped"
    _every_sample_kept(hung, hung_rows, seen)
    assert "camera lost" in log and "camera restored" in log
    print(
        f"camera hung: data valid cleared after {cleared_s:.1f} s, back {recovered_s:.1f} s "
        f"after SIGCONT, longest watchdog gap {gap_s:.1f} s"
    )


def test_a_camera_unplugged_and_back_on_the_same_address_is_waited_for(tmp_path):
    """SIGKILL on the camera, then a new camera process on the same address: data-valid is
    clear while it is away, the test goes on when it is back, nothing measured is lost."""
    with _bench(tmp_path, "127.0.0.12") as (bench, _), bench.serve(bench.config()) as service:
        service.wait_for("READY=1", timeout=180)
        bench.command(1)
        seen = [bench.measuring()["frame"]]
        unplugged_at = time.monotonic()
        bench.camera.process.kill()
        bench.camera.process.wait(timeout=10)
        lost = bench.wait(lambda r: r["status"] & CAMERA_LOST, "the camera reported lost", 30)
        assert not lost["status"] & DATA_VALID
        with specimen_camera(
            tmp_path / "again.jsonl",
            address=bench.camera.address,
            strain_rate_per_s=0.0,
            max_strain=0.0,
        ):
            plugged_at = time.monotonic()
            bench.wait(
                lambda r: r["status"] & DATA_VALID and not r["status"] & CAMERA_LOST,
                "valid samples from the camera back",
                60,
            )
            recovered_s = time.monotonic() - plugged_at
            seen.append(bench.measuring(5)["frame"])
            bench.command(2)
            bench.wait(lambda r: r["exit_status"] == EXIT_STOPPED, "the test to stop", 60)
            gap_s = _pings_kept_up(service, unplugged_at, time.monotonic())
            assert gap_s < WATCHDOG_USEC / 1e6, f"{gap_s:.1f} s without a watchdog ping"
            assert service.terminate(timeout=60) == 0
            camera_log = [line for line in service.stderr.splitlines() if "camera" in line]
    ((summary, rows),) = bench.tests()
    assert summary["exit_status"] == "stopped"
    assert summary["camera_outages"] == 1, "\n".join(camera_log)
    _every_sample_kept(summary, rows, seen)
    stamps = [int(row["timestamp_ns"]) for row in rows]
    assert all(b > a for a, b in zip(stamps, stamps[1:], strict=False))
    print(
        f"camera unplugged: valid again {recovered_s:.1f} s after it was back, "
        f"longest watchdog gap {gap_s:.1f} s"
    )


def test_a_controller_lost_and_back_flags_its_samples_and_the_strain_stays_valid(tmp_path):
    """The controller's Modbus server stops, then serves again on the same port: the samples
    without its readings carry `no controller data` (force and crosshead NaN in the strain
    file) while the strain itself stays valid; its readings come back."""
    with (
        _bench(tmp_path, "127.0.0.13") as (bench, controller),
        bench.serve(bench.config()) as service,
    ):
        service.wait_for("READY=1", timeout=180)
        bench.command(1)
        seen = [bench.measuring()["frame"]]
        controller.stop()
        away = bench.wait(lambda r: r["status"] & NO_CONTROLLER_DATA, "no controller data", 30)
        assert away["status"] & DATA_VALID
        seen.append(bench.measuring(5)["frame"])
        controller.serve_tcp(bench.controller_port)
        back_at = time.monotonic()
        bench.wait(
            lambda r: r["status"] & DATA_VALID and not r["status"] & NO_CONTROLLER_DATA,
            "controller readings again",
            60,
        )
        recovered_s = time.monotonic() - back_at
        bench.command(2)
        bench.wait(lambda r: r["exit_status"] == EXIT_STOPPED, "the test to stop", 60)
        assert service.terminate(timeout=60) == 0
        log = service.stderr
    ((summary, rows),) = bench.tests()
    assert summary["exit_status"] == "stopped" and summary["controller_outages"] >= 1
    assert summary["frames_without_controller"] > 0
    _every_sample_kept(summary, rows, seen)
    without = [row for row in rows if math.isnan(float(row["force_n"] or "nan"))]
    assert len(without) == summary["frames_without_controller"]
    assert all(row["data_valid"] == "1" for row in rows)
    assert "machine lost" in log and "machine restored" in log
    print(
        f"controller lost: {len(without)} samples flagged, readings back {recovered_s:.1f} s "
        "after it served again"
    )


def test_sigkill_mid_test_keeps_every_row_written_and_a_restart_serves_again(tmp_path):
    """SIGKILL (no chance to close anything): the strain file holds every sample the
    controller had read, in whole rows; a new start of the service serves and measures."""
    with _bench(tmp_path, "127.0.0.14") as (bench, _):
        config = bench.config()
        with bench.serve(config) as service:
            service.wait_for("READY=1", timeout=180)
            bench.command(1)
            seen = bench.measuring(20)["frame"]
            time.sleep(0.5)
            os.kill(service.pid, signal.SIGKILL)
            assert service.wait(timeout=30) == -signal.SIGKILL
        (killed,) = sorted(bench.state.glob("test-*.strain.csv"))
        rows = _rows(killed)
        assert seen in {int(row["frame_id"]) for row in rows}
        unit = (ROOT / "systemd" / "extensometer.service").read_text(encoding="utf-8")
        assert f"RestartSec={RESTART_S:g}s" in unit
        time.sleep(RESTART_S)
        restarted_at = time.monotonic()
        with bench.serve(config) as service:
            service.wait_for("READY=1", timeout=180)
            ready_s = time.monotonic() - restarted_at
            bench.start_measuring()
            assert service.terminate(timeout=60) == 0
    *settling, (measured, again_rows) = bench.tests()
    assert measured["exit_status"] == "stopped" and len(again_rows) >= 5
    assert all(summary["exit_status"] == "fault" for summary, _ in settling)
    info = subprocess.run(
        [EXTENSOMETER, "info", str(killed.with_suffix("").with_suffix(".mcap"))],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert "Traceback" not in info.stderr, info.stderr
    print(f"SIGKILL: {len(rows)} rows kept, ready again {ready_s:.1f} s after the restart")


@pytest.mark.parametrize("state", ["idle", "armed", "running", "stopping"])
def test_sigterm_in_every_run_state_ends_the_service_cleanly(tmp_path, state):
    """SIGTERM stops the service with status 0 and STOPPING=1 in every run state; a test under
    way ends with its reason, its outputs closed and every sample kept. While the reference is
    taken (armed) the crosshead is never started."""
    address = {
        "idle": "127.0.0.21",
        "armed": "127.0.0.22",
        "running": "127.0.0.23",
        "stopping": "127.0.0.24",
    }[state]
    controller_port = free_tcp_port()
    machine = SimulatedController()
    with (
        _camera_peer(tmp_path, "camera", address) as camera,
        ControllerServer(machine) as server,
    ):
        server.serve_tcp(controller_port)
        bench = Bench(tmp_path, camera, controller_port)
        config = bench.config(frame_rate_hz=0.5 if state == "armed" else 10.0)
        with bench.serve(config) as service:
            service.wait_for("READY=1", timeout=180)
            seen: list[int] = []
            if state == "armed":
                bench.command(1)
                bench.wait(lambda r: r["run_state"] == RUN_STATES["armed"], "armed", 60)
            elif state == "running":
                bench.command(1)
                seen.append(bench.measuring()["frame"])
            elif state == "stopping":
                bench.command(1)
                seen.append(bench.measuring()["frame"])
                os.kill(camera.process.pid, signal.SIGSTOP)
                bench.command(2)
                bench.wait(lambda r: r["run_state"] == RUN_STATES["stopping"], "stopping", 30)
            terminated_at = time.monotonic()
            assert service.terminate(timeout=60) == 0
            stopped_s = time.monotonic() - terminated_at
            service.wait_for("STOPPING=1", timeout=5)
    found = bench.tests()
    if state == "idle":
        assert found == []
        return
    ((summary, rows),) = found
    reason = {"armed": "SIGTERM", "running": "SIGTERM", "stopping": "stop command"}[state]
    assert reason in summary["reason"], summary["reason"]
    if state == "armed" and "running" not in summary["run_states"]:
        assert summary["exit_status"] == "fault" and summary["frames_processed"] == 0
        assert "start" not in [name for name, _ in machine.commands()]
    elif state == "armed":
        # The reference frame came before the signal was handled: the test had started.
        assert summary["exit_status"] in ("stopped", "fault")
        assert [name for name, _ in machine.commands()][-1] == "stop"
    else:
        assert summary["exit_status"] == "stopped"
        _every_sample_kept(summary, rows, seen)
    print(
        f"SIGTERM while {state}: exit 0 after {stopped_s:.1f} s, "
        f"{summary['exit_status']}: {summary['reason']}"
    )


def test_a_camera_call_that_never_returns_faults_the_test_and_the_watchdog_restarts_the_service(
    tmp_path,
):
    """A hung driver (the simulated camera's fetch blocks, ignoring its timeout): the loop is
    not in control any more. Within the fetch's bound the test ends as a fault that says so,
    data-valid is cleared and `camera lost` set, every sample measured is in the strain file;
    then the watchdog pings stop (systemd restarts the service), start commands are refused,
    and SIGTERM still ends the service cleanly."""
    port = free_tcp_port()
    config = tmp_path / "service.toml"
    config.write_text(
        f'[modbus]\ntcp = "127.0.0.1:{port}"\n'
        f'[service]\nstate_directory = "{tmp_path / "state"}"\nstart = "auto"\n'
        "[run]\nuntil_strain = 0\n"
        "[sim]\nrealtime = true\nsensor_width_px = 512\nsensor_height_px = 1024\n"
        "camera_hang_after_s = 2.0\n"
    )
    bench = Bench(tmp_path, None, 0)  # type: ignore[arg-type]
    bench.port = port
    with bench.serve(config) as service:
        service.wait_for("READY=1", timeout=180)
        service.wait_for(lambda n: n.value("STATUS", "").startswith("running test"), 60)
        seen = [bench.wait(lambda r: r["status"] & DATA_VALID, "a valid sample", 60)["frame"]]
        faulted = bench.wait(lambda r: r["exit_status"] == EXIT_FAULT, "the test to fault", 60)
        assert faulted["status"] & CAMERA_LOST and not faulted["status"] & DATA_VALID
        seen.append(faulted["frame"])
        status = service.wait_for(lambda n: n.value("STATUS", "").startswith("needs a restart"), 30)
        last_ping = service.wait_for_silence("WATCHDOG=1", quiet_s=WATCHDOG_USEC / 1e6, timeout=60)
        assert last_ping is not None and last_ping < status.received_s + WATCHDOG_USEC / 1e6
        assert service.returncode is None
        refused = mbpoll_tcp(port, "-r", "100", "-t", "4", write=["1"])
        assert refused.returncode == 0
        assert mbpoll_read_tcp(port, "-r", "102", "-c", "1", "-t", "4")[102] == "2"
        assert service.terminate(timeout=60) == 0
    ((summary, rows),) = bench.tests()
    assert summary["exit_status"] == "fault" and "fetch did not return within" in summary["reason"]
    assert summary["hung_call"] and summary["frames_processed"] > 0
    _every_sample_kept(summary, rows, seen)


def test_a_trigger_microcontroller_reset_mid_test_ends_it_as_a_fault_that_says_so(tmp_path):
    """The trigger firmware (its test build, under simavr) hangs on its hang pin and its
    watchdog resets it mid-test: no further trigger comes, so `run` ends the test as a fault
    naming the reset instead of waiting for frames; every sample measured is kept. (`run`:
    the simulated camera on the real firmware needs `--sim`, which `serve` takes from its
    configuration's URLs alike; the run is the shorter harness.)"""
    binaries = firmware_binaries()
    port = free_tcp_port()
    with SimulatedMcu(binaries["test_elf"], binaries["harness"], tmp_path / "mcu") as mcu:
        config = tmp_path / "run.toml"
        config.write_text(
            f'[trigger]\nsource = "period"\nurl = "{mcu.port}"\n'
            "[sim]\nrealtime = true\nsensor_width_px = 512\nsensor_height_px = 1024\n"
            f'[modbus]\ntcp = "127.0.0.1:{port}"\n'
        )
        out = tmp_path / "out"
        process = subprocess.Popen(
            [EXTENSOMETER, "run", "--sim", "--config", str(config), "--until-strain", "5"]
            + ["--json", "--out", str(out)],
            stdout=subprocess.PIPE,
            stderr=(tmp_path / "run.log").open("w"),
            text=True,
            preexec_fn=lambda: os.nice(10),
        )
        try:
            bench = Bench(tmp_path, None, 0)  # type: ignore[arg-type]
            bench.port = port
            deadline = time.monotonic() + 120
            while mbpoll_tcp(port, "-1", "-r", "10", "-c", "1", "-t", "4").returncode != 0:
                assert process.poll() is None and time.monotonic() < deadline, "no Modbus server"
                time.sleep(0.2)
            try:
                seen = [bench.measuring(5)["frame"]]
            except AssertionError:
                raise AssertionError((tmp_path / "run.log").read_text()) from None
            mcu.drive_pin("C0", 0)
            stdout, _ = process.communicate(timeout=60)
        finally:
            if process.poll() is None:
                process.kill()
                process.communicate()
        resets = mcu.resets()
    assert process.returncode == 1, (tmp_path / "run.log").read_text()
    assert len(resets) == 1
    summary = json.loads(stdout)
    assert summary["exit_status"] == "fault", summary["reason"]
    assert "trigger microcontroller restarted (reset cause WATCHDOG)" in summary["reason"]
    _every_sample_kept(summary, _rows(out / "strain.csv"), seen)


def test_garbage_on_the_trigger_serial_line_is_refused_before_the_test_in_one_line(tmp_path):
    """A pty peer that answers every byte with random bytes where the trigger microcontroller
    should be: the handshake never completes, and `run` refuses in one line naming
    `[trigger] url` (exit 2) within the handshake's timeout, nothing measured. (Garbage
    injected into a live link needs a second writer on simavr's pty, which it does not
    offer; the link's own tests feed its parser corrupted packets.)"""
    with pty_pair(tmp_path) as (peer_end, appliance_end):
        stop = threading.Event()

        def babble() -> None:
            random = np.random.default_rng(3)
            with open(peer_end, "r+b", buffering=0) as line:
                while not stop.is_set():
                    line.write(random.integers(0, 256, 64, dtype=np.uint8).tobytes())
                    stop.wait(0.01)

        peer = threading.Thread(target=babble, daemon=True)
        peer.start()
        config = tmp_path / "run.toml"
        config.write_text(
            f'[trigger]\nsource = "period"\nurl = "{appliance_end}"\n'
            "[sim]\nrealtime = true\nsensor_width_px = 512\nsensor_height_px = 1024\n"
        )
        try:
            done = subprocess.run(
                [
                    EXTENSOMETER,
                    "run",
                    "--sim",
                    "--config",
                    str(config),
                    "--out",
                    str(tmp_path / "out"),
                ],
                capture_output=True,
                text=True,
                timeout=120,
            )
        finally:
            stop.set()
            peer.join(timeout=10)
    assert done.returncode == 2, done.stderr
    assert done.stderr.startswith(f"extensometer: error: [trigger] url: {appliance_end}: ")
    assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr
    assert not (tmp_path / "out" / "strain.csv").exists()
