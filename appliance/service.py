"""`extensometer serve`: the appliance as a long-running service under systemd.

The service starts its outputs that outlive a test (the Modbus strain server, the Rerun
viewer's server), checks the devices and warms up the measurement kernels, then tells the
service manager it is ready (`READY=1`, `appliance.live.sd_notify`). From then on it runs one test
after another, each started by the controller's start command (Modbus register 100 = 1) or,
with `[service] start = "auto"`, the first one at once:

* every test is recorded to a new MCAP file (`--record FILE.mcap` names the first, later ones
  get `-2`, `-3`, ... before the suffix; by default a timestamped file in the state
  directory, `$STATE_DIRECTORY` under systemd), with its strain file (`.strain.csv`) and its
  summary (`.summary.json`) beside it; before each test in the state directory the oldest
  tests are deleted while the directory holds more than `[service] max_state_mb`
  (`appliance.recording.retention`);
* during a test the registers are written on the measurement thread with every frame, and
  the watchdog (`WATCHDOG=1`) is pinged while the measurement loop is in control: frames
  coming, or a camera outage being waited through (data-valid cleared, the `camera lost`
  bit set, the outage logged; the test faults when it outlasts `[camera] outage_timeout_s`);
  between tests the service's own wait loop pings. A camera call that does not return (a
  hung driver) ends the test as a fault with its outputs closed; the process cannot use
  that camera again, so it stops pinging, refuses start commands and lets systemd's
  watchdog restart it (without a watchdog it exits with status 1 for `Restart=on-failure`);
* `STATUS=` says what it is doing (idle, the test running, how the last one ended);
* stop and zero commands act on the running test; the gauge length set point applies to the
  next test;
* `[optics] calibration` is read at start-up (a bad file is named before the service is
  ready) and read again at each start command, before any device opens, so a test measures
  with the file in place when it starts and never loads one half-way (a recalibration takes
  effect at the next test, without a restart); a file that has become unreadable, altered or
  made for another sensor size refuses that start: the reason is logged and the exit status
  register says fault, and the service waits for the next start command;
* after each test the memory it freed is handed back to the system (`release_freed_memory`:
  jemalloc's purge, or glibc's `malloc_trim`), so the resident memory between tests is what
  the service holds;
* SIGTERM (or SIGINT) ends the running test as an operator stop, closes its recording, sends
  `STOPPING=1` and exits 0.

With the simulated devices (`sim://` URLs) every test gets a new simulated specimen. With
real devices each test opens the camera and the controller and closes them at its end; a
device that cannot be opened is logged and reported (`STATUS=`, the `fault` bit), and the
service waits for the next start command instead of exiting. So does a test that cannot start
or that fails in any other way (a disk without room: `appliance.run.disk_space`): the service
outlives its tests.
"""

from __future__ import annotations

import collections
import ctypes
import dataclasses
import datetime
import gc
import os
import signal
import sys
import threading
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

from appliance.config import Config
from appliance.errors import InputError
from appliance.live.link import LiveLink
from appliance.live.sd_notify import ServiceNotifier
from appliance.live.viewer import RerunViewer
from appliance.measure.tracking import warm_up_kernels
from appliance.recording.retention import enforce_retention
from appliance.rig import check_devices
from appliance.run.loop import DeviceEvent
from appliance.run.object_plane import calibration_file
from appliance.run.outputs import RunHooks
from appliance.run.state import ExitStatus, RunState, Transition
from appliance.runner import OutputFiles, run_test
from hal.errors import HardwareError

IDLE_TICK_S = 0.1
HEAP_DIFF_VARIABLE = "EXTENSOMETER_HEAP_DIFF"
"""`FIRST,LAST,FILE` in the environment: trace Python allocations (`tracemalloc`) from the end of
test FIRST to the end of test LAST and write what was allocated in between and is still held,
by allocation site with its call stack, to FILE. For finding where memory goes over many tests
(`extensometer bench soak`); tracing slows the tests it spans."""
_JEMALLOC_ALL_ARENAS = 4096
"""jemalloc's MALLCTL_ARENAS_ALL: `arena.<i>.purge` of every arena."""
HEAP_DIFF_FRAMES = 3
HEAP_DIFF_SITES = 40
HEAP_DIFF_TYPES = 20
_ENDED = (RunState.IDLE, RunState.ABORTED, RunState.FAULT)
"""Run states a test ends in (and the service waits in): a start command is taken in one of
them, once the test under way, if any, has reached it."""


def state_directory(config: Config) -> Path:
    """Where the service keeps recordings: `$STATE_DIRECTORY` (systemd), else the config's."""
    return Path(
        os.environ.get("STATE_DIRECTORY", "").split(":")[0] or config.service.state_directory
    )


def numbered(path: Path, number: int) -> Path:
    """`path` for the first test, `stem-N.suffix` for the N-th."""
    return path if number == 1 else path.with_name(f"{path.stem}-{number}{path.suffix}")


def release_freed_memory() -> None:
    """Hand the memory freed by the test that ended back to the system: a garbage collection,
    then jemalloc's purge of every arena (the unit preloads jemalloc) or glibc's
    `malloc_trim`. Allocators keep freed pages for reuse (jemalloc for about ten seconds);
    between tests, which may be hours apart, they are better returned, and the service's
    resident memory then says what it holds."""
    gc.collect()
    library = ctypes.CDLL(None)
    if hasattr(library, "mallctl"):
        mallctl = library.mallctl
        mallctl.argtypes = [
            ctypes.c_char_p,
            ctypes.c_void_p,
            ctypes.c_void_p,
            ctypes.c_void_p,
            ctypes.c_size_t,
        ]
        mallctl(f"arena.{_JEMALLOC_ALL_ARENAS}.purge".encode(), None, None, None, 0)
    elif hasattr(library, "malloc_trim"):
        library.malloc_trim(ctypes.c_size_t(0))


def _object_types() -> collections.Counter[str]:
    return collections.Counter(type(o).__qualname__ for o in gc.get_objects())


def _compiled_signatures() -> dict[str, set[str]]:
    """The signatures every numba dispatcher in the process has compiled, by function."""
    from numba.core.dispatcher import Dispatcher

    compiled: dict[str, set[str]] = {}
    for thing in gc.get_objects():
        if isinstance(thing, Dispatcher):
            name = f"{thing.py_func.__module__}.{thing.py_func.__qualname__}"
            compiled.setdefault(name, set()).update(str(s) for s in thing.signatures)
    return compiled


def _rss_mb() -> float:
    try:
        with open("/proc/self/statm", encoding="ascii") as statm:
            return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6
    except OSError:
        return float("nan")


class HeapDiff:
    """The Python heap's growth between two tests (see `HEAP_DIFF_VARIABLE`).

    Args:
        setting: `FIRST,LAST,FILE` (FIRST < LAST, both >= 1).

    Raises:
        InputError: a malformed setting, naming the variable.
    """

    def __init__(self, setting: str) -> None:
        first, _, rest = setting.partition(",")
        last, _, path = rest.partition(",")
        try:
            self.first, self.last = int(first), int(last)
        except ValueError:
            self.first = self.last = 0
        if not (1 <= self.first < self.last and path):
            raise InputError(f"{HEAP_DIFF_VARIABLE}: must be FIRST,LAST,FILE, got {setting!r}")
        self.path = Path(path)
        self._before: tracemalloc.Snapshot | None = None
        self._types_before: collections.Counter[str] = collections.Counter()
        self._compiled_before: dict[str, set[str]] = {}
        self._rss_before_mb = 0.0

    @classmethod
    def from_environment(cls) -> HeapDiff | None:
        """The diff `$EXTENSOMETER_HEAP_DIFF` asks for, or None."""
        setting = os.environ.get(HEAP_DIFF_VARIABLE, "")
        return cls(setting) if setting else None

    def after_test(self, number: int, log: Callable[[str], None]) -> None:
        """Start tracing after test FIRST; after test LAST, write what was allocated since and
        is still held to the file, and stop tracing."""
        if number not in (self.first, self.last):
            return
        gc.collect()
        if number == self.first:
            self._types_before = _object_types()
            self._compiled_before = _compiled_signatures()
            self._rss_before_mb = _rss_mb()
            tracemalloc.start(HEAP_DIFF_FRAMES)
            self._before = tracemalloc.take_snapshot()
            return
        if self._before is None:
            return
        snapshot = tracemalloc.take_snapshot().filter_traces(
            [tracemalloc.Filter(False, tracemalloc.__file__)]
        )
        tracemalloc.stop()
        rss_mb = _rss_mb()
        types = _object_types()
        types.subtract(self._types_before)
        compiled = _compiled_signatures()
        new_signatures = [
            f"  {name}: {signature}"
            for name, signatures in sorted(compiled.items())
            for signature in sorted(signatures - self._compiled_before.get(name, set()))
        ]
        grown = snapshot.compare_to(self._before, "traceback")
        total = sum(stat.size_diff for stat in grown)
        tests = self.last - self.first
        lines = [
            f"Python heap growth from test {self.first} to test {self.last}: "
            f"{total / 1e6:+.3f} MB in all ({(total / 1e6) / tests:+.4f} MB per test); "
            f"resident memory {rss_mb - self._rss_before_mb:+.1f} MB "
            f"({(rss_mb - self._rss_before_mb) / tests:+.3f} MB per test, traced).",
            "",
            "Objects the garbage collector tracks, by type, most grown:",
            *(
                f"{count:+8d} {name}"
                for name, count in sorted(types.items(), key=lambda item: -item[1])[
                    :HEAP_DIFF_TYPES
                ]
            ),
            "",
            "Kernels compiled (or loaded from numba's cache) for a new signature meanwhile:",
            *(new_signatures or ["  none"]),
            "",
            "Allocation sites, most grown:",
            "",
        ]
        for stat in grown[:HEAP_DIFF_SITES]:
            lines.append(
                f"{stat.size_diff / 1e3:+10.1f} kB {stat.count_diff:+7d} blocks "
                f"(now {stat.size / 1e3:.1f} kB in {stat.count})"
            )
            lines += [f"    {line}" for line in stat.traceback.format(most_recent_first=True)]
        self.path.write_text("\n".join(lines) + "\n", encoding="utf-8")
        log(f"heap growth from test {self.first} to {self.last} written to {self.path}")
        self._before = None


class Service:
    """One service process: servers, the wait for commands, the tests, the shutdown.

    Args:
        config: the validated configuration (command-line overrides applied).
        record_path: the first test's recording; None = timestamped files in the state
            directory.
        notifier: the service manager's notifier.
        viewer: a Rerun output that outlives the tests, or None.
        log: where one line per event goes (journald reads stderr).
        now: UNIX time source for test ids (injected for tests).
    """

    def __init__(
        self,
        config: Config,
        *,
        record_path: Path | None,
        notifier: ServiceNotifier,
        viewer: RerunViewer | None = None,
        log: TextIO = sys.stderr,
        now: Callable[[], datetime.datetime] = lambda: datetime.datetime.now(datetime.UTC),
    ) -> None:
        self.config = config
        self.record_path = record_path
        self.notifier = notifier
        self.log_stream = log
        self._now = now
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._start_requested = config.service.start == "auto"
        self._testing = False
        self._test_ended = False
        self._stopping = False
        self._gauge_length_mm = config.gauge.length_mm
        self._test_id = ""
        self._hung_call = ""
        self.tests_run = 0
        self._heap_diff = HeapDiff.from_environment()
        self.link = LiveLink(
            config,
            notifier=notifier,
            viewer=viewer,
            on_start=self._on_start,
            on_gauge_length=self._on_gauge_length,
            on_transition=self._on_transition,
        )

    def log(self, text: str) -> None:
        """One line on the service's log."""
        self.log_stream.write(f"extensometer: {text}\n")
        self.log_stream.flush()

    def run(self) -> int:
        """Serve until SIGTERM or SIGINT; returns the exit status (0 after a clean stop; 1
        when a device call hung and no watchdog will restart the service).

        Raises:
            InputError: a server or device that cannot start (names the key); nothing is left
                running.
        """
        signals = (signal.SIGTERM, signal.SIGINT)
        previous = {sig: signal.signal(sig, self._on_signal) for sig in signals}
        try:
            self._start_up()
            self.notifier.ready(self._idle_status())
            self.log(f"ready: {self._idle_status()}")
            while True:
                with self._lock:
                    stopping, start = self._stopping, self._start_requested
                    self._start_requested = False
                    hung = self._hung_call
                    start = start and not hung
                    self._testing = start
                    self._test_ended = False
                if not hung:
                    self.notifier.watchdog()
                elif self.notifier.watchdog_interval_s is None:
                    self.log("exiting: a device call hung and no watchdog restarts the service")
                    return 1
                self.link.modbus.tick()
                if stopping:
                    break
                if start:
                    self._run_one_test()
                    with self._lock:
                        self._testing = False
                    if self._heap_diff is not None:
                        self._heap_diff.after_test(self.tests_run, self.log)
                    release_freed_memory()
                    continue
                self._wake.wait(IDLE_TICK_S)
                self._wake.clear()
            self.notifier.stopping("stopping")
            self.log("stopping")
            return 0
        finally:
            self.link.close()
            for sig, handler in previous.items():
                signal.signal(sig, handler)

    def _start_up(self) -> None:
        self.notifier.status("starting: servers, devices, measurement kernels")
        try:
            check_devices(self.config, simulate=self.config.camera.url.startswith("sim://"))
        except HardwareError as exc:
            raise InputError(f"serve: {exc}") from None
        if self.record_path is None:
            directory = state_directory(self.config)
            try:
                directory.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise InputError(
                    f"[service] state_directory {directory}: cannot create ({exc.strerror})"
                ) from None
        self._check_calibration()
        self._check_watchdog()
        self.link.start()
        warm_up_kernels()

    def _check_calibration(self) -> None:
        """Read `[optics] calibration` once at start-up, so a bad file is named before the
        service is ready (each test reads it again when it starts)."""
        region = self.config.camera.region()
        calibration = calibration_file(
            self.config, (region.width, region.height) if region is not None else None
        )
        if calibration is not None:
            self.log(
                f"calibration {calibration.file} ({calibration.checksum}), read again at "
                "each start command"
            )

    def _check_watchdog(self) -> None:
        """Refuse a frame period of half the watchdog interval or more: a camera outage is
        noticed two frame periods after the last frame, within the interval."""
        interval = self.notifier.watchdog_interval_s
        if interval is None:
            return
        camera = self.config.camera
        key, rate = (
            ("frame_rate_hz", camera.frame_rate_hz)
            if camera.frame_rate_hz
            else ("min_frame_rate_hz", camera.min_frame_rate_hz)
        )
        period = max(1.0 / rate, (camera.exposure_us or 0.0) * 1e-6)
        if interval <= 2 * period:
            raise InputError(
                f"[camera] {key}: a frame period of {period:g} s needs a watchdog interval "
                f"above {2 * period:g} s (WatchdogSec is {interval:g} s)"
            )

    def _idle_status(self) -> str:
        done = f"; {self.tests_run} tests run" if self.tests_run else ""
        return f"idle, waiting for a start command{done}"

    def _on_signal(self, signum: int, _frame: Any) -> None:
        with self._lock:
            self._stopping = True
        self.link.request_stop(f"service stopping ({signal.Signals(signum).name})")
        self._wake.set()

    def _on_start(self) -> bool:
        with self._lock:
            idle = self.link.state in _ENDED
            busy = (self._testing and not self._test_ended) or self._start_requested
            if not idle or busy or self._stopping or self._hung_call:
                return False
            self._start_requested = True
        self._wake.set()
        return True

    def _on_gauge_length(self, length_mm: float) -> bool:
        with self._lock:
            self._gauge_length_mm = length_mm
        return True

    def _on_transition(self, transition: Transition) -> None:
        if transition.target is RunState.RUNNING:
            self.notifier.status(f"running test {self._test_id}")
        with self._lock:
            if transition.target in _ENDED:
                self._test_ended = True
            stopping = self._stopping
        if stopping and transition.target is RunState.RUNNING:
            self.link.request_stop("service stopping")

    def _run_one_test(self) -> None:
        self.tests_run += 1
        stamp = self._now().strftime("%Y%m%dT%H%M%SZ")
        self._test_id = f"test-{stamp}-{self.tests_run:04d}"
        if self.record_path is not None:
            record = numbered(self.record_path, self.tests_run)
        else:
            record = state_directory(self.config) / f"{self._test_id}.mcap"
        files = OutputFiles(
            strain=record.with_suffix(".strain.csv"),
            summary=record.with_suffix(".summary.json"),
            recording=record,
        )
        config = self.config
        with self._lock:
            gauge_length = self._gauge_length_mm
        if gauge_length:
            config = dataclasses.replace(
                config, gauge=dataclasses.replace(config.gauge, length_mm=gauge_length)
            )
        self.log(f"{self._test_id}: starting, recording to {record}")
        self.notifier.status(f"starting test {self._test_id}")
        try:
            if self.record_path is None:
                enforce_retention(record.parent, config.service.max_state_mb, self.log)
            outcome = run_test(
                config,
                simulate=config.camera.url.startswith("sim://"),
                files=files,
                test_id=self._test_id,
                hooks=self._hooks(),
            )
        except (InputError, HardwareError) as error:
            self._not_started(str(error))
            return
        except OSError as error:
            self._not_started(f"{error.filename or ''}: {error.strerror}")
            return
        except Exception as error:  # noqa: BLE001 - the service outlives any one test
            self._not_started(f"{type(error).__name__}: {error}", ended="failed")
            return
        summary = outcome.summary
        ended = f"{summary.exit_status}: {summary.reason}"
        self.log(
            f"{self._test_id}: {ended}; {summary.frames_processed} frames, "
            f"final strain {summary.final_strain}; recording {record}"
        )
        if self.link.hung_call:
            self._give_up(self.link.hung_call)
            return
        self.notifier.status(f"last test {ended}; {self._idle_status()}")

    def _hooks(self) -> RunHooks:
        """The link's hooks, with the test's warnings and device events on the log."""
        hooks = self.link.hooks()

        def device_event(event: DeviceEvent) -> None:
            if event.kind != "waiting":
                self.log(f"{self._test_id}: {event.device} {event.kind}: {event.text}")

        return dataclasses.replace(
            hooks,
            device_listeners=[*hooks.device_listeners, device_event],
            on_warning=lambda text: self.log(f"{self._test_id}: warning: {text}"),
        )

    def _give_up(self, hung_call: str) -> None:
        """A device call hung: no further test in this process, and no more watchdog pings."""
        with self._lock:
            self._hung_call = hung_call
        self.log(f"a device call hangs ({hung_call}): no more tests; the service needs a restart")
        self.notifier.status(f"needs a restart: a device call hangs ({hung_call})")

    def _not_started(self, why: str, ended: str = "not started") -> None:
        """A test that could not run (or failed without a result): logged, said in STATUS=
        and on the Modbus server as a fault."""
        self.log(f"{self._test_id}: {ended}: {why}")
        self.notifier.status(f"last test {ended}: {why}; {self._idle_status()}")
        self.link.modbus.set_exit_status(ExitStatus.FAULT)
        self.link.modbus.set_run_state(RunState.FAULT)
