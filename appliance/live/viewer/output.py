"""`RerunViewer`: the run output that streams test after test to Rerun.

`RerunViewer` is a `appliance.run.outputs.RunOutput` that follows test after test and streams
each to Rerun (rerun-sdk 0.41) through the sinks `[rerun]` chooses, in any combination:

    serve   = "HOST:PORT"   a gRPC server remote viewers connect to:
                            `rerun rerun+http://HOST:PORT/proxy`
    connect = URL           push to a viewer (or a `rerun --serve-grpc` proxy) listening at
                            `rerun+http://HOST:PORT/proxy`
    save    = PATH          an .rrd file per test ("{test}" in PATH becomes the test's id)

Every test is a recording of its own (an explicit `rr.RecordingStream`, never the global one),
with application id "extensometer" and the test's id (`RunFacts.facts["test_id"]`) as its
recording id and name. The server is opened by `start()` and closed by `close()`; `begin`
and `end` open and close one test's recording.
"""

from __future__ import annotations

import datetime
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from appliance.config import RerunConfig
from appliance.errors import InputError
from appliance.live.viewer.layout import APPLICATION_ID
from appliance.live.viewer.server import RerunService
from appliance.live.viewer.stream import OneTestStream
from appliance.measure.frame_measurer import StrainSample
from appliance.run.loop import LoopResult
from appliance.run.outputs import RunFacts
from appliance.run.state import ExitStatus

_URL_SCHEMES = ("rerun://", "rerun+http://", "rerun+https://")


def has_sinks(config: RerunConfig) -> bool:
    """Whether `[rerun]` asks for any sink (serve, connect or save): whether to make a viewer."""
    return bool(config.serve or config.connect or config.save)


class RerunViewer:
    """Streams every test to Rerun: a `RunOutput` that never slows the measurement.

    One viewer follows any number of tests in turn (`begin` ... `end`, then the next): each is
    a recording of its own, named by the test id of its facts (`facts.facts["test_id"]`, else
    "test-<UTC time of the reference frame>"). The gRPC server (`[rerun] serve`) is opened by
    `start()` (or by the first `begin`) and stays up across the tests, until `close()`.

        viewer = RerunViewer(config.rerun)
        viewer.start()                      # InputError naming the key if the port is taken
        for each test: viewer.begin(facts); viewer(sample)...; viewer.end(result)
        viewer.close()

    Args:
        config: `[rerun]`: the sinks, the image rate and scale, the queue size. In `save`,
            "{test}" is replaced by the test's recording id (one file per test); without it,
            each test overwrites the file.
        application_id: the Rerun application id.
        service: a gRPC server shared with other viewers; when given, `config.serve` is not
            opened again and `close()` leaves it running.
        close_timeout_s: the longest `end()` waits for the queue to drain and the test's
            stream to flush and close.

    Raises:
        ValueError: no sink at all (see `has_sinks`).
        InputError: a malformed `connect` URL, or a `save` directory that does not exist (one
            line naming the key).

    Attributes (of the test running, or the last one):
        recording_id: its recording id (None before the first `begin`).
        samples_shown: samples logged by the viewer thread.
        samples_dropped: samples dropped because the queue was full (or that came outside
            `begin` ... `end`).
        images_shown: camera images logged (the reference included).
        problem: the first problem met (a sink that failed, a viewer that went away), one
            line; None while all is well.
    """

    def __init__(
        self,
        config: RerunConfig,
        *,
        application_id: str = APPLICATION_ID,
        service: RerunService | None = None,
        close_timeout_s: float = 10.0,
    ) -> None:
        if service is None and not has_sinks(config):
            raise ValueError("[rerun] has no sink: set serve, connect or save")
        if config.connect and not _is_proxy_url(config.connect):
            raise InputError(
                f"[rerun] connect: must be rerun+http://HOST:PORT/proxy, got {config.connect!r}"
            )
        if config.save:
            folder = Path(config.save).parent
            if "{test}" not in str(folder) and not folder.is_dir():
                raise InputError(f"[rerun] save: {config.save}: no such directory {str(folder)!r}")
        self.config = config
        self.application_id = application_id
        self.close_timeout_s = close_timeout_s
        self._service = service
        self._owns_service = service is None and bool(config.serve)
        self._test: OneTestStream | None = None
        self._outside_tests_dropped = 0

    @property
    def service(self) -> RerunService | None:
        """The gRPC server the tests go to (None before `start` or without `serve`)."""
        return self._service

    def start(self) -> None:
        """Open the gRPC server of `[rerun] serve`, if any (idempotent).

        Raises:
            InputError: the address is malformed or not available, naming `[rerun] serve`.
        """
        if self._owns_service and self._service is None:
            self._service = RerunService(
                self.config.serve,
                application_id=self.application_id,
                server_memory_limit=f"{self.config.history_mb:g}MB",
            )

    def close(self) -> None:
        """End a test still open and close the gRPC server this viewer opened (idempotent)."""
        test = self._test
        if test is not None and not test.ended:
            test.close(LoopResult(exit_status=ExitStatus.ABORTED, reason="viewer closed"))
        if self._owns_service and self._service is not None:
            self._service.close()

    def begin(self, facts: RunFacts) -> None:
        """Open the test's recording, log its facts and reference frame, start its thread.

        Raises:
            InputError: the server cannot listen (`[rerun] serve`) or the `save` file cannot
                be created (`[rerun] save`).
        """
        self.start()
        if self._test is not None and not self._test.ended:
            self._test.close(LoopResult(exit_status=ExitStatus.ABORTED, reason="next test began"))
        test_id = str(facts.facts.get("test_id") or "") or _default_recording_id(facts)
        urls = [self._service.local_url] if self._service is not None else []
        if self.config.connect and self.config.connect not in urls:
            urls.append(self.config.connect)
        save = Path(self.config.save.replace("{test}", test_id)) if self.config.save else None
        self._test = OneTestStream(
            self.config, self.application_id, self.close_timeout_s, facts, test_id, urls, save
        )

    def __call__(self, sample: StrainSample) -> None:
        """Queue the sample for the viewer thread and return at once; drop it when full."""
        test = self._test
        if test is None:
            self._outside_tests_dropped += 1
            return
        test.offer(sample)

    def show_results(self, values: Mapping[str, float | int]) -> None:
        """The running test's results, shown when it ends: in `status/result` beside its exit
        status, and the determined ones in its last status document.

        Args:
            values: by name, as the Modbus result registers serve them
                (`appliance.live.result_registers.result_register_values`).
        """
        if self._test is not None:
            self._test.set_results(values)

    def end(self, result: LoopResult) -> None:
        """Drain, log how the test ended, flush and close its stream (at most `close_timeout_s`).

        The gRPC server stays up for the next test. Never raises for a sink that failed or a
        viewer that went away: that is one warning on the `appliance.live.viewer` logger (and
        `problem`).
        """
        if self._test is not None:
            self._test.close(result)

    @property
    def recording_id(self) -> str | None:
        """The recording id of the test running, or of the last one (None before any)."""
        return self._test.recording_id if self._test is not None else None

    @property
    def samples_shown(self) -> int:
        """Samples of the test (running or last) logged by the viewer thread."""
        return self._test.samples_shown if self._test is not None else 0

    @property
    def samples_dropped(self) -> int:
        """Samples dropped on a full queue in the test (running or last), and outside tests."""
        test = self._test
        return self._outside_tests_dropped + (test.samples_dropped if test is not None else 0)

    @property
    def images_shown(self) -> int:
        """Camera images logged in the test (running or last), the reference included."""
        return self._test.images_shown if self._test is not None else 0

    @property
    def problem(self) -> str | None:
        """The first problem of the test (running or last), one line; None while all is well."""
        return self._test.problem if self._test is not None else None

    def stats(self) -> dict[str, Any]:
        """{}: the viewer's counts are shown in the viewer, not added to the summary."""
        return {}


def _default_recording_id(facts: RunFacts) -> str:
    unix_ns = facts.unix_time_ns(facts.reference.timestamp_ns)
    when = datetime.datetime.fromtimestamp(unix_ns / 1e9, tz=datetime.UTC)
    return f"test-{when:%Y%m%dT%H%M%S.%f}Z"


def _is_proxy_url(url: str) -> bool:
    return url.startswith(_URL_SCHEMES) and url.endswith("/proxy")
