"""The service's contract with systemd: the unit, its example configuration, the notify harness.

`systemd-analyze verify` lints the unit against a fake root holding a stub at the ExecStart path
(`--recursive-errors=no` makes unknown keys fail instead of only warning; negative controls show
it does), `systemd-analyze security --offline=true` scores its hardening, and the keys the
appliance depends on (Type=notify, the watchdog, restart, directories, device access) are read
from the file. The example configuration must load as the service would load it. Last, the
notify harness (systemd's side of sd_notify, for tests of `extensometer serve`) is shown to see
a small service's readiness, its watchdog pings and their stop when its loop stalls.
"""

import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from appliance.config import load_config
from tests.system.notify_harness import HarnessError, NotifyHarness

ROOT = Path(__file__).resolve().parents[2]
UNIT = ROOT / "systemd" / "extensometer.service"
EXAMPLE_CONFIG = ROOT / "systemd" / "extensometer.toml"
SYSTEMD_ANALYZE = shutil.which("systemd-analyze") or "/usr/bin/systemd-analyze"
EXEC_START = "/opt/extensometer/.venv/bin/extensometer"
CONFIG_PATH = "/etc/extensometer/extensometer.toml"
MAX_EXPOSURE = 3.0
MIN_SYSTEMD_VERSION = 250
"""`--recursive-errors` and `--offline` came with systemd 250."""


def _systemd_version() -> int | None:
    try:
        done = subprocess.run(
            [SYSTEMD_ANALYZE, "--version"], capture_output=True, text=True, timeout=30
        )
    except (FileNotFoundError, PermissionError):
        return None
    found = re.match(r"systemd (\d+)", done.stdout)
    return int(found.group(1)) if found else None


SYSTEMD_VERSION = _systemd_version()
needs_systemd_analyze = pytest.mark.skipif(
    SYSTEMD_VERSION is None or SYSTEMD_VERSION < MIN_SYSTEMD_VERSION,
    reason=(
        f"systemd-analyze {MIN_SYSTEMD_VERSION} or later is needed (found: "
        f"{SYSTEMD_VERSION or 'none'} at {SYSTEMD_ANALYZE}); `apt-get install systemd` "
        "provides it (.ci/setup does)"
    ),
)


def analyze(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [SYSTEMD_ANALYZE, "--no-pager", *args],
        capture_output=True,
        text=True,
        timeout=60,
        env={"SYSTEMD_COLORS": "0", "SYSTEMD_LOG_COLOR": "0", "PATH": "/usr/bin:/bin"},
    )


def fake_root(directory: Path, unit_text: str, *, with_executable: bool = True) -> Path:
    """A root file system with the unit installed and a stub at its ExecStart path."""
    unit_path = directory / "etc" / "systemd" / "system" / UNIT.name
    unit_path.parent.mkdir(parents=True)
    unit_path.write_text(unit_text)
    if with_executable:
        stub = directory / EXEC_START.lstrip("/")
        stub.parent.mkdir(parents=True)
        stub.write_text("#!/bin/sh\nexit 0\n")
        stub.chmod(0o755)
    return unit_path


def verify(directory: Path, unit_text: str, **kwargs) -> subprocess.CompletedProcess:
    unit_path = fake_root(directory, unit_text, **kwargs)
    return analyze("verify", "--recursive-errors=no", f"--root={directory}", str(unit_path))


def overall_exposure(unit_path: Path) -> float:
    done = analyze("security", "--offline=true", str(unit_path))
    found = re.search(r"Overall exposure level for \S+: (\d+(?:\.\d+)?)", done.stdout)
    assert found, done.stdout + done.stderr
    return float(found.group(1))


def unit_entries(text: str) -> dict[str, list[tuple[str, str]]]:
    """Section -> (key, value) in file order; keys may repeat, as systemd allows."""
    sections: dict[str, list[tuple[str, str]]] = {}
    current = None
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("["):
            current = sections.setdefault(line.strip("[]"), [])
            continue
        key, _, value = line.partition("=")
        assert current is not None, f"key outside a section: {raw!r}"
        current.append((key.strip(), value.strip()))
    return sections


def values(entries: list[tuple[str, str]], key: str) -> list[str]:
    return [value for name, value in entries if name == key]


def only(entries: list[tuple[str, str]], key: str) -> str:
    found = values(entries, key)
    assert len(found) == 1, f"{key}: expected one setting, found {found}"
    return found[0]


def seconds(text: str) -> float:
    """A systemd time span with the units this unit uses ("10s", "5min", "90")."""
    total = 0.0
    for number, unit in re.findall(r"(\d+(?:\.\d+)?)\s*(min|ms|s|h)?", text):
        total += float(number) * {"": 1, "s": 1, "ms": 1e-3, "min": 60, "h": 3600}[unit]
    return total


@needs_systemd_analyze
def test_systemd_analyze_verify_accepts_the_unit_without_a_word(tmp_path):
    done = verify(tmp_path, UNIT.read_text())
    output = done.stdout + done.stderr
    assert done.returncode == 0, output
    assert not [line for line in output.splitlines() if UNIT.name in line or "/opt" in line]


@needs_systemd_analyze
def test_verify_reports_a_misspelt_key(tmp_path):
    broken = UNIT.read_text().replace("WatchdogSec=", "WatchdogSecs=", 1)
    done = verify(tmp_path, broken)
    assert done.returncode != 0
    assert "Unknown key 'WatchdogSecs'" in done.stdout + done.stderr


@needs_systemd_analyze
def test_verify_reports_a_missing_executable(tmp_path):
    done = verify(tmp_path, UNIT.read_text(), with_executable=False)
    assert done.returncode != 0
    assert EXEC_START in done.stdout + done.stderr


@needs_systemd_analyze
def test_hardening_exposure_is_at_most_3(capsys):
    exposure = overall_exposure(UNIT)
    with capsys.disabled():
        print(f"\nsystemd-analyze security --offline=true {UNIT.name}: exposure {exposure}")
    assert exposure <= MAX_EXPOSURE


@needs_systemd_analyze
def test_an_unhardened_unit_scores_above_the_bound(tmp_path):
    bare = tmp_path / "bare.service"
    bare.write_text(f"[Service]\nType=notify\nExecStart={EXEC_START}\n")
    assert overall_exposure(bare) > MAX_EXPOSURE


def test_the_unit_runs_extensometer_serve_as_a_notify_service_with_a_watchdog():
    service = unit_entries(UNIT.read_text())["Service"]
    assert only(service, "Type") == "notify"
    assert only(service, "NotifyAccess") == "main"
    assert only(service, "ExecStart") == f"{EXEC_START} serve --config {CONFIG_PATH}"
    assert only(service, "Restart") == "on-failure"
    assert seconds(only(service, "RestartSec")) > 0
    assert only(service, "KillSignal") == "SIGTERM"
    assert seconds(only(service, "TimeoutStopSec")) >= 30
    watchdog_s = seconds(only(service, "WatchdogSec"))
    longest_frame_period_s = 1 / load_config(EXAMPLE_CONFIG).camera.min_frame_rate_hz
    assert watchdog_s > 2 * longest_frame_period_s
    assert seconds(only(service, "TimeoutStartSec")) > watchdog_s


def test_the_unit_gives_the_directories_and_devices_the_appliance_needs():
    service = unit_entries(UNIT.read_text())["Service"]
    assert only(service, "DynamicUser") == "yes"
    assert {"video", "dialout"} <= set(" ".join(values(service, "SupplementaryGroups")).split())
    assert only(service, "StateDirectory") == "extensometer"
    assert only(service, "CacheDirectory") == "extensometer"
    assert only(service, "ConfigurationDirectory") == "extensometer"
    assert Path(CONFIG_PATH).parent == Path("/etc") / only(service, "ConfigurationDirectory")
    assert "NUMBA_CACHE_DIR=%C/extensometer/numba" in values(service, "Environment")
    assert only(service, "DevicePolicy") == "closed"
    allowed = {value.split()[0] for value in values(service, "DeviceAllow")}
    assert {"char-video4linux", "char-ttyS", "char-ttyUSB", "char-ttyACM"} <= allowed
    families = set(only(service, "RestrictAddressFamilies").split())
    assert {"AF_UNIX", "AF_INET", "AF_INET6"} <= families


def test_the_unit_is_hardened_without_breaking_numba_or_the_devices():
    service = unit_entries(UNIT.read_text())["Service"]
    required = {
        "ProtectSystem": "strict",
        "ProtectHome": "yes",
        "PrivateTmp": "yes",
        "NoNewPrivileges": "yes",
        "ProtectKernelTunables": "yes",
        "ProtectKernelModules": "yes",
        "ProtectKernelLogs": "yes",
        "ProtectControlGroups": "yes",
        "ProtectClock": "yes",
        "ProtectHostname": "yes",
        "RestrictNamespaces": "yes",
        "RestrictRealtime": "yes",
        "RestrictSUIDSGID": "yes",
        "LockPersonality": "yes",
        "CapabilityBoundingSet": "",
        "SystemCallArchitectures": "native",
    }
    for key, value in required.items():
        assert only(service, key) == value, key
    assert "@system-service" in values(service, "SystemCallFilter")
    assert re.fullmatch(r"0[0-7]{3}", only(service, "UMask"))
    assert not values(service, "MemoryDenyWriteExecute"), "numba's LLVM JIT needs W+X pages"
    assert not values(service, "PrivateDevices"), "it would hide /dev/video* and serial ports"


def test_the_example_configuration_loads_with_the_service_defaults():
    config = load_config(EXAMPLE_CONFIG)
    assert config.camera.url == "sim://camera" and config.machine.url == "sim://machine"
    assert config.modbus.tcp == "127.0.0.1:5020"
    assert config.modbus.allow_write_from == ("127.0.0.1", "::1"), "writes from this PC only"
    assert config.rerun.serve == "127.0.0.1:9876"
    assert config.record.path == ""
    state_directory = only(unit_entries(UNIT.read_text())["Service"], "StateDirectory")
    assert Path(config.service.state_directory) == Path("/var/lib") / state_directory


SERVICE_STANDIN = """
import signal, subprocess, sys, time
from appliance.live.sd_notify import ServiceNotifier

mode, frames, frame_period_s = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
if mode == "fail-at-start":
    sys.exit("stand-in: cannot open the camera")
terminated = []
signal.signal(signal.SIGTERM, lambda *_: terminated.append(True))
if mode == "ignore-sigterm":
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
if mode == "leave-grandchild":
    grandchild = subprocess.Popen(["sh", "-c", "trap '' TERM; exec sleep 300"])
    print(grandchild.pid, flush=True)
notifier = ServiceNotifier()
notifier.ready(f"watchdog {notifier.watchdog_interval_s}")
for _ in range(frames):
    notifier.watchdog()
    time.sleep(frame_period_s)
notifier.status("stalled")
while not terminated:
    time.sleep(0.01)
notifier.stopping()
"""
"""A service in miniature: READY, a watchdog ping per frame, then a stall until SIGTERM."""

WATCHDOG_USEC = 200_000
HALF_INTERVAL_S = WATCHDOG_USEC / 2e6


def standin(mode: str = "stall", frames: int = 200, frame_period_s: float = 0.005) -> list[str]:
    return [sys.executable, "-c", SERVICE_STANDIN, mode, str(frames), str(frame_period_s)]


def is_running(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state not in ("Z", "X")


@pytest.mark.parametrize("abstract_socket", [False, True], ids=["path", "abstract"])
def test_the_harness_sees_the_pings_of_a_running_loop_stop_when_it_stalls(abstract_socket):
    frames = 200
    with NotifyHarness(
        standin(frames=frames), watchdog_usec=WATCHDOG_USEC, abstract_socket=abstract_socket
    ) as run:
        ready = run.wait_for("READY=1", timeout=60)
        assert ready.value("STATUS") == f"watchdog {WATCHDOG_USEC / 1e6}"
        stalled = run.wait_for("STATUS=stalled", timeout=60)
        last_ping = run.wait_for_silence("WATCHDOG=1", quiet_s=3 * HALF_INTERVAL_S, timeout=30)
        pings = run.watchdog_times()
        assert 3 <= len(pings) <= frames / 4, run.describe()
        assert last_ping == pings[-1] and last_ping <= stalled.received_s
        assert run.returncode is None
        assert run.terminate(timeout=30) == 0, run.describe()
        run.wait_for("STOPPING=1", timeout=10)
        assert {n.pid for n in run.messages} == {run.pid}
        assert run.messages[0] == ready


@pytest.mark.parametrize(
    ("watchdog_pid", "pings"), [("child", True), (None, True), ("foreign", False)]
)
def test_watchdog_pid_decides_whether_the_child_pings(watchdog_pid, pings):
    pid = os.getpid() if watchdog_pid == "foreign" else watchdog_pid
    with NotifyHarness(
        standin(frames=40, frame_period_s=0.01), watchdog_usec=WATCHDOG_USEC, watchdog_pid=pid
    ) as run:
        ready = run.wait_for("READY=1", timeout=60)
        run.wait_for("STATUS=stalled", timeout=60)
        assert ready.value("STATUS") == f"watchdog {WATCHDOG_USEC / 1e6 if pings else None}"
        assert bool(run.watchdog_times()) is pings
        assert run.terminate(timeout=30) == 0


def test_a_child_that_exits_before_ready_fails_the_wait_at_once_with_its_stderr():
    with NotifyHarness(standin("fail-at-start"), watchdog_usec=WATCHDOG_USEC) as run:
        with pytest.raises(HarnessError, match="exited with status 1") as failure:
            run.wait_for("READY=1", timeout=600)
        assert "stand-in: cannot open the camera" in str(failure.value)
        assert run.returncode == 1 and "cannot open the camera" in run.stderr


def test_what_a_child_leaves_running_is_killed_when_it_exits():
    with NotifyHarness(standin("leave-grandchild", frames=0)) as run:
        run.wait_for("STATUS=stalled", timeout=60)
        grandchild = int(run.stdout.split()[0])
        assert is_running(grandchild)
        assert run.terminate(timeout=30) == 0
        assert not is_running(grandchild)


def test_a_child_that_ignores_sigterm_is_killed_after_the_timeout():
    with NotifyHarness(standin("ignore-sigterm", frames=0)) as run:
        run.wait_for("STATUS=stalled", timeout=60)
        assert run.terminate(timeout=0.5) == -signal.SIGKILL
        with pytest.raises(HarnessError, match="exited with status -9"):
            run.wait_for("STOPPING=1", timeout=60)
