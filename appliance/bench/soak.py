"""Soak benchmark: `serve` running test after test, with its memory, files and threads per test.

`run_soak_benchmark(out, as_json, ...)` (the CLI's `extensometer bench soak`) runs
`extensometer serve` as its own process with a service configuration (by default the shipped
one, systemd/extensometer.toml: simulated camera and machine in real time, the Rerun server on),
its Modbus server and Rerun server moved to free ports on 127.0.0.1 and its state directory to a
temporary one (through `$STATE_DIRECTORY`, as systemd passes it). It then acts as the machine's
controller over Modbus TCP, test after test for `duration_s`:

1. writes the start command (register `command` = 1) and waits for `run_state` running;
2. lets the test measure for `test_s`, then writes the stop command (2);
3. waits for `run_state` idle with an `exit_status`, and watches the service's resident memory
   (VmRSS), open file descriptors and threads in /proc for `SETTLE_S` (the test's files are
   written, then the service hands the memory the test freed back to the system): the lowest
   of each seen meanwhile.

The figures are those three after every test, and their slope per test fitted by least squares
over the tests after `warm_up_tests` (the first tests load the kernels, open the servers and
fill caches: 20 by default). With the viewer on, the resident memory also grows until the Rerun
server's history (`[rerun] history_mb`, 64 MB shipped) is full, which takes about 20 tests of
5 s; a test's data kept beyond that bound (static data, which rerun's server keeps while it
holds temporal data) would show as a slope that does not level off.
The service runs with the variables the shipped unit's
`Environment=` lines set (systemd/extensometer.service: jemalloc as the allocator among them),
as systemd would start it. The goal: threads flat (a slope under 0.01 per test) and RSS
growing by less than 0.1 MB per test after warm-up.
Each test's summary in the state directory gives the frames it measured, to show every test
measured. What it does not measure: a test run to its end (each is stopped by the controller),
a viewer connected to the Rerun server (none is), real devices.
"""

from __future__ import annotations

import json
import math
import os
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from appliance.bench.peer_process import free_loopback_port

SHIPPED_CONFIGURATION = Path(__file__).resolve().parents[2] / "systemd" / "extensometer.toml"
SHIPPED_UNIT = SHIPPED_CONFIGURATION.with_name("extensometer.service")
RSS_GOAL_MB_PER_TEST = 0.1
THREADS_GOAL_PER_TEST = 0.01
WARM_UP_TESTS = 20
START_TIMEOUT_S = 180.0
"""The longest a start command may take to reach `run_state` running (reference, warm-up)."""
END_TIMEOUT_S = 120.0
SERVICE_UP_TIMEOUT_S = 180.0
SUMMARY_TIMEOUT_S = 10.0
SETTLE_S = 3.0
"""After a test ends, how long its figures are watched: the service writes the test's files and
then hands the memory it freed back to the system (`appliance.service.release_freed_memory`);
the lowest resident memory in that time, and the descriptors and threads at its end, are the
test's figures."""
_POLL_S = 0.1
_RUN_STATE_IDLE = 0
_RUN_STATE_RUNNING = 2
_COMMAND_START = 1
_COMMAND_STOP = 2
_COMMAND_ACCEPTED = 1


class SoakError(RuntimeError):
    """The service did not do what the soak asked of it (one line, naming the step)."""


def process_figures(pid: int) -> dict[str, float]:
    """Resident memory (MB), open file descriptors and threads of process `pid`, from /proc."""
    rss_kb = 0
    with open(f"/proc/{pid}/status", encoding="ascii") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                rss_kb = int(line.split()[1])
                break
    return {
        "rss_mb": rss_kb / 1024.0,
        "fds": len(os.listdir(f"/proc/{pid}/fd")),
        "threads": len(os.listdir(f"/proc/{pid}/task")),
    }


def settled_figures(pid: int, settle_s: float) -> dict[str, float]:
    """`process_figures` of `pid` once a test's end has settled: the lowest of each figure
    (resident memory, file descriptors, threads) seen over `settle_s`.

    A thread or descriptor still winding down (a flush, a file being closed) is not counted; one
    the service keeps is, so a leak shows in the slope and a transient does not."""
    deadline = time.monotonic() + settle_s
    lowest: dict[str, float] = {}
    while True:
        for key, value in process_figures(pid).items():
            lowest[key] = min(lowest.get(key, math.inf), value)
        if time.monotonic() >= deadline:
            return lowest
        time.sleep(_POLL_S)


def unit_environment(unit: Path = SHIPPED_UNIT) -> dict[str, str]:
    """The variables a systemd unit's `Environment=` lines set, as the service runs with them;
    values holding a systemd specifier (`%C`, `%S`, ...) are left out (they name the unit's
    own directories)."""
    environment: dict[str, str] = {}
    for line in unit.read_text(encoding="utf-8").splitlines():
        key, _, assignments = line.partition("=")
        if key.strip() != "Environment":
            continue
        for assignment in shlex.split(assignments):
            name, equals, value = assignment.partition("=")
            if equals and "%" not in value:
                environment[name] = value
    return environment


def slope_per_test(values: Sequence[float]) -> float | None:
    """The least-squares slope of `values` against their index; None for fewer than 2."""
    if len(values) < 2:
        return None
    index = np.arange(len(values), dtype=np.float64)
    return float(np.polyfit(index, np.asarray(values, dtype=np.float64), 1)[0])


class _Controller:
    """The machine's controller as the soak plays it: start, wait, stop, over Modbus TCP."""

    def __init__(self, port: int) -> None:
        from pymodbus.client import ModbusTcpClient

        from appliance.live.modbus_map import BY_NAME

        self._client = ModbusTcpClient("127.0.0.1", port=port, timeout=5)
        self._command = BY_NAME["command"].address
        self._run_state = BY_NAME["run_state"].address
        self._exit_status = BY_NAME["exit_status"].address
        self._command_result = BY_NAME["command_result"].address

    def connect(self, timeout_s: float, service: subprocess.Popen) -> None:
        deadline = time.monotonic() + timeout_s
        while not self._client.connect():
            if service.poll() is not None:
                raise SoakError(f"the service exited with status {service.returncode}")
            if time.monotonic() > deadline:
                raise SoakError(f"no Modbus server after {timeout_s:g} s")
            time.sleep(0.5)

    def close(self) -> None:
        self._client.close()

    def command(self, code: int, timeout_s: float) -> None:
        """Write a command until the appliance takes it (`command_result` accepted)."""
        deadline = time.monotonic() + timeout_s
        while True:
            reply = self._client.write_register(self._command, code)
            if reply.isError():
                raise SoakError(f"command {code}: exception {reply}")
            result = self._client.read_holding_registers(self._command_result, count=1)
            if result.isError():
                raise SoakError(f"reading command_result: {result}")
            if result.registers[0] == _COMMAND_ACCEPTED:
                return
            if time.monotonic() > deadline:
                raise SoakError(f"command {code} refused for {timeout_s:g} s")
            time.sleep(_POLL_S)

    def state(self) -> tuple[int, int]:
        reply = self._client.read_holding_registers(self._run_state, count=4)
        if reply.isError():
            raise SoakError(f"reading run_state: {reply}")
        words = reply.registers
        return words[0], words[self._exit_status - self._run_state]

    def wait(self, done: Any, timeout_s: float, what: str) -> tuple[int, int]:
        deadline = time.monotonic() + timeout_s
        while True:
            state = self.state()
            if done(*state):
                return state
            if time.monotonic() > deadline:
                raise SoakError(
                    f"{what}: not after {timeout_s:g} s (run_state, exit_status {state})"
                )
            time.sleep(_POLL_S)


def _frames_of(state_directory: Path, known: set[Path]) -> tuple[int | None, int | None]:
    """(frames processed, frames dropped) of the newest test summary not seen before
    ((None, None) if none appeared)."""
    deadline = time.monotonic() + SUMMARY_TIMEOUT_S
    while not (new := sorted(set(state_directory.glob("*.summary.json")) - known)):
        if time.monotonic() > deadline:
            return None, None
        time.sleep(_POLL_S)
    known.update(new)
    summary = json.loads(new[-1].read_text(encoding="utf-8"))
    return summary.get("frames_processed"), summary.get("frames_dropped")


def measure_soak(
    config: Path = SHIPPED_CONFIGURATION,
    *,
    duration_s: float = 600.0,
    test_s: float = 5.0,
    warm_up_tests: int = WARM_UP_TESTS,
    viewer: bool = True,
    heap_diff_tests: tuple[int, int] | None = None,
) -> dict[str, Any]:
    """Serve back-to-back tests for `duration_s`; the service's figures after every test.

    With `heap_diff_tests` (FIRST, LAST) the service traces its Python allocations and writes
    what grew between the end of test FIRST and of test LAST, by allocation site
    (`appliance.service.HEAP_DIFF_VARIABLE`): the figures' `heap_diff`, its lines (None when
    the soak ended before test LAST). Tracing slows the service: its figures are not those of
    an untraced soak.

    Raises:
        SoakError: the service did not start, start a test, or end one in time (one line).
    """
    modbus_port = free_loopback_port()
    rerun_port = free_loopback_port()
    state_directory = Path(tempfile.mkdtemp(prefix="extensometer-soak-"))
    unit_variables = unit_environment()
    environment = {**os.environ, **unit_variables, "STATE_DIRECTORY": str(state_directory)}
    heap_path = state_directory / "heap-diff.txt"
    if heap_diff_tests is not None:
        from appliance.service import HEAP_DIFF_VARIABLE

        first, last = heap_diff_tests
        environment[HEAP_DIFF_VARIABLE] = f"{first},{last},{heap_path}"
    command = [sys.executable, "-m", "appliance.cli", "serve", "--config", str(config)]
    command += ["--modbus-tcp", f"127.0.0.1:{modbus_port}"]
    command += ["--rerun-serve", f"127.0.0.1:{rerun_port}" if viewer else ""]
    log_path = state_directory / "service.log"
    tests: list[dict[str, Any]] = []
    summaries: set[Path] = set()
    started = time.monotonic()
    with open(log_path, "w", encoding="utf-8") as log:
        service = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=environment)
        controller = _Controller(modbus_port)
        try:
            controller.connect(SERVICE_UP_TIMEOUT_S, service)
            controller.wait(lambda s, _e: s == _RUN_STATE_IDLE, SERVICE_UP_TIMEOUT_S, "idle")
            soak_start = time.monotonic()
            while time.monotonic() - soak_start < duration_s:
                test_start = time.monotonic()
                controller.command(_COMMAND_START, START_TIMEOUT_S)
                controller.wait(
                    lambda s, _e: s == _RUN_STATE_RUNNING, START_TIMEOUT_S, "test running"
                )
                time.sleep(test_s)
                controller.command(_COMMAND_STOP, END_TIMEOUT_S)
                _, exit_status = controller.wait(
                    lambda s, e: s == _RUN_STATE_IDLE and e != 0, END_TIMEOUT_S, "test ended"
                )
                figures = settled_figures(service.pid, SETTLE_S)
                figures["exit_status"] = exit_status
                figures["frames"], figures["dropped"] = _frames_of(state_directory, summaries)
                figures["test_s"] = time.monotonic() - test_start
                tests.append(figures)
        finally:
            controller.close()
            service.send_signal(signal.SIGTERM)
            try:
                service.wait(60)
            except subprocess.TimeoutExpired:
                service.kill()
                service.wait(10)
    log_tail = log_path.read_text(encoding="utf-8", errors="replace").splitlines()[-5:]
    heap_diff = heap_path.read_text(encoding="utf-8").splitlines() if heap_path.exists() else None
    shutil.rmtree(state_directory, ignore_errors=True)
    figures = _figures(tests, warm_up_tests, time.monotonic() - started, viewer, config, log_tail)
    figures["unit_environment"] = unit_variables
    if heap_diff_tests is not None:
        figures["heap_diff_tests"] = list(heap_diff_tests)
        figures["heap_diff"] = heap_diff
    return figures


def _figures(
    tests: Sequence[Mapping[str, Any]],
    warm_up_tests: int,
    elapsed_s: float,
    viewer: bool,
    config: Path,
    log_tail: Sequence[str],
) -> dict[str, Any]:
    after = list(tests[warm_up_tests:])
    slopes = {key: slope_per_test([t[key] for t in after]) for key in ("rss_mb", "fds", "threads")}
    threads_after = [t["threads"] for t in after]
    rss_slope = slopes["rss_mb"]
    return {
        "configuration": _shown(config),
        "viewer": viewer,
        "elapsed_s": elapsed_s,
        "tests": len(tests),
        "warm_up_tests": warm_up_tests,
        "per_test": list(tests),
        "rss_mb_per_test": rss_slope,
        "fds_per_test": slopes["fds"],
        "threads_per_test": slopes["threads"],
        "threads_range_after_warm_up": (
            [min(threads_after), max(threads_after)] if threads_after else None
        ),
        "goal_rss_mb_per_test": RSS_GOAL_MB_PER_TEST,
        "goal_met": bool(
            rss_slope is not None
            and rss_slope < RSS_GOAL_MB_PER_TEST
            and slopes["threads"] is not None
            and abs(slopes["threads"]) < THREADS_GOAL_PER_TEST
        ),
        "service_log_tail": list(log_tail),
    }


def _shown(path: Path) -> str:
    """`path` relative to the project (as the shipped configuration is named), else whole."""
    project = SHIPPED_CONFIGURATION.parents[1]
    try:
        return str(path.resolve().relative_to(project))
    except ValueError:
        return str(path)


def format_table(figures: Mapping[str, Any]) -> str:
    """The figures as the report's table."""

    def number(value: float | None, digits: int = 3) -> str:
        return "-" if value is None else f"{value:.{digits}f}"

    lines = [
        f"configuration {figures['configuration']}, viewer {'on' if figures['viewer'] else 'off'}",
        f"{figures['tests']} tests in {figures['elapsed_s']:.0f} s; slopes fitted after the "
        f"first {figures['warm_up_tests']}",
        "",
        "test  exit  frames  dropped  rss_mb  fds  threads",
    ]
    for index, test in enumerate(figures["per_test"]):
        frames = "-" if test["frames"] is None else str(test["frames"])
        dropped = "-" if test["dropped"] is None else str(test["dropped"])
        lines.append(
            f"{index:4d}  {test['exit_status']:4d}  {frames:>6}  {dropped:>7}  "
            f"{test['rss_mb']:6.1f}  {test['fds']:3d}  {test['threads']:7d}"
        )
    lines += [
        "",
        f"RSS per test after warm-up:     {number(figures['rss_mb_per_test'])} MB "
        f"(goal < {figures['goal_rss_mb_per_test']} MB)",
        f"threads per test after warm-up: {number(figures['threads_per_test'])} "
        f"(range {figures['threads_range_after_warm_up']})",
        f"fds per test after warm-up:     {number(figures['fds_per_test'])}",
        f"goal met: {'yes' if figures['goal_met'] else 'no'}",
    ]
    if "heap_diff" in figures:
        first, last = figures["heap_diff_tests"]
        lines += ["", f"Python heap growth, test {first} to test {last} (traced):", ""]
        lines += figures["heap_diff"] or ["(the soak ended before that test)"]
    return "\n".join(lines)


def run_soak_benchmark(
    out: Path | None,
    as_json: bool,
    *,
    config: Path = SHIPPED_CONFIGURATION,
    duration_s: float = 600.0,
    test_s: float = 5.0,
    viewer: bool = True,
    warm_up_tests: int = WARM_UP_TESTS,
    heap_diff_tests: tuple[int, int] | None = None,
) -> int:
    """Entry point of `extensometer bench soak`; prints the figures and writes the report into
    `out` (when given). Returns 0 when measured (goal met or not), 1 when the service failed
    the soak (the reason on stderr)."""
    from appliance.bench.results import emit_figures

    try:
        figures = measure_soak(
            config,
            duration_s=duration_s,
            test_s=test_s,
            viewer=viewer,
            warm_up_tests=warm_up_tests,
            heap_diff_tests=heap_diff_tests,
        )
    except SoakError as exc:
        sys.stderr.write(f"extensometer: bench soak: {exc}\n")
        return 1
    emit_figures(
        "soak",
        "Soak: serve running back-to-back tests",
        figures,
        format_table(figures),
        as_json=as_json,
        out=out,
    )
    return 0
