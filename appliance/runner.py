"""One tensile test from configuration to summary: devices, exposure plan, marks, loop, outputs.

`run_test` is what `extensometer run` and each test of `extensometer serve` do:

1. devices (`appliance.rig`): the simulated world (`--sim`: camera and machine on one
   virtual clock, with a ground truth that only scores) or the camera and machine named by
   the configuration's URLs;
2. exposure (`appliance.plan.exposure.exposure_for`): the configured exposure and frame
   rate, or the planner's: the longest exposure whose motion blur at the test speed stays
   within the blur budget and the frame rate that keeps the marks' frame-to-frame motion
   inside the tracker's search; while the test runs, exposure and trigger spacing follow
   the speed the machine reports (`appliance.plan.pacing`);
3. marks: placed on the reference frame, centred on the specimen's parallel length along its
   axis as detected in that frame (or at the configured centre, `appliance.rig`), at the
   configured gauge length, refused when they do not fit the parallel length; the summary and
   the recording say how the gauge was placed and the gauge length achieved; each axial mark
   a short line of points; lengths are measured in mm on the specimen
   plane through `[optics] calibration` when it names a file (read once, before any device
   opens: a file that is bad or made for another sensor size or region refuses the test),
   else by the nominal scale of the optics (`appliance.run.object_plane`);
4. the loop (`appliance.run.loop`) until the strain limit, the break, or a stop;
5. outputs (`OutputFiles`): the strain file (every sample, with the truth when simulated),
   the summary with the test's results and the report page (`appliance.results`: the
   `[specimen]` table's material and cross-section, or a simulated test's preset), the MCAP
   recording (`appliance.recording.writer`) and the hooks' outputs (a viewer), and the summary
   returned; the hooks get the results as soon as they are computed (`RunHooks.on_results`:
   the Modbus result registers, the viewer).

Before the test its directories must have `[storage] min_free_mb` free, and a reserve is held
beside the strain file (`appliance.run.disk_space`). A full disk during the test (the recording
or the strain file cannot be written) ends it as a fault: the reserve is released, so the
strain file still gets every sample measured and the summary is written.
"""

from __future__ import annotations

import dataclasses
import errno
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from appliance import __version__
from appliance.config import Config
from appliance.errors import InputError
from appliance.measure.automatic_search import SearchChoiceChange
from appliance.measure.edge_width import EdgesNotFound, EdgeWidthGauge, edge_width_gauge
from appliance.measure.frame_measurer import StopCriteria, StrainSample, tracker_and_gauges
from appliance.measure.gauges import (
    Calibration,
    StrainGauges,
    StrainGaugesLayout,
)
from appliance.measure.image_quality import speckle_problem
from appliance.measure.specimen_gauge import (
    IMAGE_CENTRE,
    GaugeCentre,
)
from appliance.measure.tracking import MarkTracker, warm_up_kernels
from appliance.plan.exposure import ExposurePlan, exposure_for
from appliance.plan.pacing import ExposurePacer, Replan
from appliance.plan.trigger_plan import (
    TriggerPlan,
    TriggerReplanner,
    configured_trigger_plan,
    free_running_plan,
)
from appliance.recording.writer import McapRecorder
from appliance.results.report_output import TestReport
from appliance.results.series import cross_section_mm2
from appliance.rig import Rig, painted_marks, rig_for, speckle_marks
from appliance.run.disk_space import DiskReserve, check_free_space
from appliance.run.drops import DropWarning
from appliance.run.loop import DeviceEvent, LoopResult, MeasurementLoop, call_in_control
from appliance.run.object_plane import (
    check_image_size,
    configured_calibration,
    image_size,
    measurement_facts,
)
from appliance.run.outputs import RunFacts, RunHooks, RunOutput
from appliance.run.progress import ProgressLine
from appliance.run.state import ExitStatus, RunStateMachine, Transition
from appliance.run.strain_file import StrainCsvWriter, StrainFileError
from appliance.run.summary import RunOutcome, RunSummary, SampleRecord
from hal.camera.base import Frame, PixelFormat

if TYPE_CHECKING:
    from appliance.sim.world import GaugeTruth

TRUTH_COLUMNS = ("truth_strain", "truth_elongation_mm", "strain_error")
FETCH_TIMEOUT_S = 2.0
"""Timeout of a frame fetch (two frame periods when longer): a camera that delivers nothing
for that long is in an outage (`appliance.run.loop`)."""
SIM_FETCH_TIMEOUT_S = 20.0
"""Timeout of a frame fetch in a simulation run as fast as possible: its camera renders each
frame inside the fetch on a virtual clock, which through a bench's lens (`[sim] bench`) on a
busy computer takes seconds; no frame is late there, so only a render that never ends is a
hung call."""
NO_HOOKS = RunHooks()


@dataclass(frozen=True)
class OutputFiles:
    """The files one test writes; None = not written.

    Attributes:
        strain: the strain file (`appliance.run.strain_file`); its directory is created.
        summary: the summary as JSON, written at the end; its directory is created.
        recording: the MCAP recording (must not exist; its directory must).
        report: the report page; left out, it is written beside the summary (`report_page`).
    """

    strain: Path | None = None
    summary: Path | None = None
    recording: Path | None = None
    report: Path | None = None

    @property
    def report_page(self) -> Path | None:
        """Where the report page goes: `report`, else beside the summary (`summary.json` ->
        `report.html`, `NAME.summary.json` -> `NAME.report.html`, `NAME.json` ->
        `NAME.report.html`); None with neither."""
        if self.report is not None or self.summary is None:
            return self.report
        stem = self.summary.name.removesuffix(".json")
        prefix = stem.removesuffix("summary") if stem.endswith("summary") else f"{stem}."
        return self.summary.with_name(f"{prefix}report.html")

    @classmethod
    def in_directory(cls, out_dir: Path | None, recording: Path | None = None) -> OutputFiles:
        """`strain.csv` and `summary.json` in `out_dir` (None: neither), and the recording."""
        if out_dir is None:
            return cls(recording=recording)
        return cls(out_dir / "strain.csv", out_dir / "summary.json", recording)

    def directories(self) -> list[Path]:
        """The directories written to, each once."""
        paths = (self.strain, self.summary, self.recording)
        return list(dict.fromkeys(p.parent for p in paths if p is not None))


NO_FILES = OutputFiles()


def run_test(
    config: Config,
    *,
    simulate: bool,
    files: OutputFiles = NO_FILES,
    progress: TextIO | None = None,
    hooks: RunHooks = NO_HOOKS,
    test_id: str = "",
) -> RunOutcome:
    """Run one test as configured; see the module docstring.

    Args:
        config: the validated configuration.
        simulate: use the simulated world (ground truth in the outputs).
        files: the strain file, summary and recording to write; none by default.
        progress: a terminal stream for the progress line; None = quiet.
        hooks: what follows and drives the test from outside (Modbus registers, a viewer,
            the watchdog, the service's run-state listener); none by default.
        test_id: names the test in the recording and the viewer.

    Raises:
        InputError: a configuration that cannot run (named key), a recording file or output
            directory that cannot be created, or a disk without the room a test needs.
        HardwareError: a device that cannot be opened or configured.
    """
    alive = [hooks.on_alive] if hooks.on_alive is not None else []
    rig = call_in_control(lambda: rig_for(config, simulate=simulate), alive)
    sensor = rig.world.camera.sensor_size if rig.world is not None else None
    calibration = configured_calibration(config, rig.optics, image_size(config, sensor))
    plan = exposure_for(config, rig.optics, rig.speed_mm_min)
    call_in_control(warm_up_kernels, alive)
    line = ProgressLine(progress) if progress is not None else None
    samples = _SampleLog()
    reserve = _prepare_directories(files, config)
    recorder = None
    if files.recording is not None:
        try:
            recorder = McapRecorder(
                files.recording,
                config.record,
                truth=samples.latest_truth if simulate else None,
                trigger_mode=config.trigger.source,
            )
        except BaseException:
            _release(reserve)
            raise
    writer = None
    faults = _LateFaults()
    try:
        in_force, triggers = call_in_control(lambda: rig.open(config, plan), alive)
        pacer = _exposure_pacer(config, rig, in_force.exposure_us, recorder, line)
        if files.strain is not None:
            writer = _strain_file(
                files.strain,
                samples if simulate else None,
                faults.disk_full(reserve, files.strain, recorder),
                config.transverse.stations,
            )
    except BaseException:
        if recorder is not None:
            recorder.close()
        _release(reserve)
        call_in_control(rig.close, alive)
        raise
    report = TestReport(truth=samples.latest_truth if simulate else None)
    outputs: list[RunOutput] = [
        *([recorder] if recorder is not None else []),
        report,
        *hooks.outputs,
    ]
    known_before = _run_facts(config, rig, plan, calibration, in_force.exposure_us, triggers)
    facts = {"test_id": test_id, "simulated": simulate, **known_before}
    warn = _warning_listener(recorder, hooks)
    reference = _Reference(config, rig, calibration, samples, outputs, facts, warn)
    reference.note = _note_listener(recorder, line)
    drops = DropWarning(1.0 / plan.frame_period_s, warn)
    loop = MeasurementLoop(
        rig.camera,
        rig.machine,
        reference.place_marks,
        sinks=[
            samples,
            *([writer] if writer else []),
            *outputs,
            drops,
            *([line] if line else []),
        ],
        immediate_sinks=hooks.immediate_sinks,
        state=RunStateMachine(on_transition=_transition_listener(recorder, hooks)),
        block_when_full=rig.block_when_full,
        start_speed_mm_min=rig.speed_mm_min if rig.commands else None,
        fetch_timeout_s=max(
            SIM_FETCH_TIMEOUT_S if rig.block_when_full else FETCH_TIMEOUT_S,
            2 * plan.frame_period_s,
        ),
        camera_outage_timeout_s=0.0 if simulate else config.camera.outage_timeout_s,
        device_listeners=_device_listeners(recorder, hooks, line),
        liveness_listeners=alive,
        machine_listeners=[pacer.follow] if pacer is not None else [],
    )
    faults.loop = loop
    if hooks.on_loop is not None:
        hooks.on_loop(loop)
    try:
        result = loop.run(
            StopCriteria(
                until_strain=config.run.until_strain or None, until_break=config.run.until_break
            )
        )
    except BaseException:
        if recorder is not None:
            recorder.close()
        raise
    finally:
        if writer is not None:
            writer.close()
        if line is not None:
            line.close()
        call_in_control(rig.close, alive)
    call_in_control(lambda: _end_outputs(outputs, result, report, hooks.on_results), alive)
    _release(reserve)
    extra = {**known_before, **_run_counts(result, samples, reference, loop, rig, pacer)}
    if writer is not None:
        extra["strain_file_rows"] = writer.rows
    for output in outputs:
        extra.update(output.stats())
    outcome = RunOutcome(
        RunSummary.from_run(result, samples.records),
        extra,
        writer.path if writer is not None else None,
    )
    page = files.report_page
    if page is not None:
        call_in_control(lambda: report.write(page, outcome), alive)
    if files.summary is not None:
        call_in_control(lambda: _write_summary(outcome, files.summary), alive)
    return outcome


def _prepare_directories(files: OutputFiles, config: Config) -> DiskReserve | None:
    """Create the output directories, check their free space and hold the reserve beside the
    strain file (None when there is no strain file or summary)."""
    for path in (files.strain, files.summary):
        if path is not None:
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise InputError(f"{path.parent}: cannot create ({exc.strerror})") from None
    check_free_space(files.directories(), config.storage.min_free_mb)
    kept = files.strain or files.summary
    return DiskReserve(kept.parent, config.storage.reserve_mb) if kept is not None else None


def _release(reserve: DiskReserve | None) -> None:
    if reserve is not None:
        reserve.release()


class _LateFaults:
    """Faults noticed outside the loop's threads after it was built: a full disk."""

    def __init__(self) -> None:
        self.loop: MeasurementLoop | None = None

    def disk_full(
        self, reserve: DiskReserve | None, path: Path, recorder: McapRecorder | None
    ) -> Callable[[], bool]:
        """The strain file's `on_no_space`: end the test as a fault, stop the recording (so it
        takes none of the room given back) and release the reserve; True when the reserve
        gave room back."""

        def no_space() -> bool:
            error = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
            if self.loop is not None:
                self.loop.request_fault("strain file", error)
            if recorder is not None:
                recorder.abandon(f"{path}: {error.strerror}")
            return reserve is not None and reserve.release()

        return no_space


def _write_summary(outcome: RunOutcome, path: Path) -> None:
    """Write the summary; a summary that cannot be written turns the test into a fault, said
    in the summary returned (which the caller prints or logs)."""
    try:
        path.write_text(outcome.to_json() + "\n")
    except OSError as exc:
        summary = outcome.summary
        outcome.summary = dataclasses.replace(
            summary,
            exit_status=ExitStatus.FAULT,
            reason=(
                f"{path}: cannot write the summary ({exc.strerror}); "
                f"the test ended {summary.exit_status}: {summary.reason}"
            ),
        )
        return
    outcome.summary_path = path


class _SampleLog:
    """Every sample's record for the summary, with the truth of a simulated test (which only
    scores: nothing measured reads it)."""

    def __init__(self) -> None:
        self.records: list[SampleRecord] = []
        self.truth: GaugeTruth | None = None
        self.last_time_s = 0.0
        self.max_blur_px: float | None = None

    def __call__(self, sample: StrainSample) -> None:
        truth = self.truth
        self.records.append(
            SampleRecord.of(sample, *truth.at(sample)) if truth else SampleRecord.of(sample)
        )
        self.last_time_s = sample.time_s
        if sample.data_valid and truth is not None:
            self.max_blur_px = max(self.max_blur_px or 0.0, truth.blur_px(sample))

    def latest_truth(self, sample: StrainSample) -> tuple[float, float]:
        """(true strain, true elongation mm) of the sample just recorded."""
        latest = self.records[-1]
        return latest.truth_strain, latest.truth_elongation_mm

    def truth_columns(self, sample: StrainSample) -> dict[str, float]:
        """The strain file's truth columns of the sample just recorded."""
        latest = self.records[-1]
        return {
            "truth_strain": latest.truth_strain,
            "truth_elongation_mm": latest.truth_elongation_mm,
            "strain_error": latest.strain - latest.truth_strain,
        }


class _Reference:
    """What happens on the reference frame: the marks are placed, the tracker and gauges
    built, and the outputs begin with the test's facts."""

    def __init__(
        self,
        config: Config,
        rig: Rig,
        calibration: Calibration,
        samples: _SampleLog,
        outputs: list[RunOutput],
        facts: dict[str, Any],
        warn: Callable[[str], None],
    ) -> None:
        self.config = config
        self.rig = rig
        self.calibration = calibration
        self.samples = samples
        self.outputs = outputs
        self.facts = facts
        self.warn = warn
        self.points_placed = 0
        self.placement: dict[str, Any] = {}
        self.note: Callable[[str], None] = lambda text: None
        self.search_choices: list[dict[str, Any]] = []

    def place_marks(
        self, reference: Frame
    ) -> tuple[MarkTracker, StrainGauges, EdgeWidthGauge | None]:
        """The loop's set-up: marks on the reference frame, tracker and gauges on them, and
        the width gauge between the axial marks when `[transverse] stations` asks for one."""
        arrived_unix_ns = time.time_ns()
        config, rig = self.config, self.rig
        g = config.gauge
        check_image_size(self.calibration, reference.image.shape[1], reference.image.shape[0])
        if g.marks in ("dots", "lines"):
            points, layout, centre = painted_marks(reference.image, config)
        else:
            points, layout, centre = self._placed_marks(reference)
        if rig.world is not None:
            self.samples.truth = rig.world.gauge_truth(points, layout.axial, reference)
        self.points_placed = len(points)
        tracker, gauges = tracker_and_gauges(
            config.tracking, reference.image, points, layout, self.calibration, g.marks
        )
        widths = _width_gauge(reference.image, points, layout, self.calibration, config, centre)
        self.placement = {**centre.facts(), "gauge_length_achieved_mm": gauges.gauge_length_mm}
        if widths is not None:
            self.placement["width_stations"] = widths.count
            self.placement["reference_widths_mm"] = list(widths.reference_widths_mm)
        self.facts.update(self.placement)
        exposure_end_ns = reference.timestamp_ns + int(round(reference.exposure_us * 1e3))
        run_facts = RunFacts(
            config=config,
            reference=reference,
            points=points,
            marks=layout.marks,
            layout=layout,
            calibration=self.calibration,
            gauge_length_mm=gauges.gauge_length_mm,
            epoch_offset_ns=arrived_unix_ns - exposure_end_ns,
            devices={
                "camera": rig.camera.url,
                "machine": rig.machine.url if rig.machine is not None else "",
                "software": f"extensometer {__version__}",
            },
            facts=self.facts,
        )
        for output in self.outputs:
            output.begin(run_facts)
        if centre.placement == IMAGE_CENTRE:
            self.warn(
                "nothing stands out from the background of the reference frame: the gauge is "
                f"centred on the image along [gauge] axis_deg = {centre.axis_deg:g}; set "
                "[gauge] centre_x_px and centre_y_px if the specimen is elsewhere"
            )
        if isinstance(tracker, MarkTracker):
            tracker.follow_search_choices(self._search_choice)
        return tracker, gauges, widths

    def _search_choice(self, change: SearchChoiceChange) -> None:
        """An automatic search choice of the tracker: logged, and kept for the summary."""
        self.search_choices.append(change.to_json())
        self.note(change.describe())

    def _placed_marks(self, reference: Frame) -> tuple[np.ndarray, StrainGaugesLayout, GaugeCentre]:
        """Speckle marks placed on the gauge centre of the reference frame, checked."""
        config, rig = self.config, self.rig
        centre = rig.gauge_centre(reference)
        points, layout = speckle_marks(
            config, centre, rig.gauge_length_mm, self.calibration, reference.image.shape
        )
        _check_speckle(reference.image, points, layout.marks, config)
        return points, layout, centre


def _width_gauge(
    image: np.ndarray,
    points: np.ndarray,
    layout: StrainGaugesLayout,
    calibration: Calibration,
    config: Config,
    centre: GaugeCentre,
) -> EdgeWidthGauge | None:
    """The width gauge between the axial marks (`[transverse] stations`); None when none.

    Raises:
        InputError: no station's edges are found in the reference frame.
    """
    count = config.transverse.stations
    if count == 0:
        return None
    first, second = (
        points[list(mark)].mean(axis=0) for mark in (layout.axial.first, layout.axial.second)
    )
    try:
        return edge_width_gauge(image, first, second, calibration, count, centre.detection)
    except (EdgesNotFound, ValueError) as exc:
        raise InputError(f"[transverse] stations: reference frame: {exc}") from None


def _check_speckle(
    image: np.ndarray, points: np.ndarray, marks: tuple[tuple[int, ...], ...], config: Config
) -> None:
    """Refuse a reference in which a mark's subset holds no speckle the correlation can track
    (`appliance.measure.image_quality`): a test on it would only measure invalid samples."""
    full_scale = PixelFormat(config.camera.pixel_format).max_value
    half = config.tracking.subset_px // 2
    height, width = image.shape[:2]
    for number, mark in enumerate(marks, start=1):
        for x, y in points[list(mark)]:
            col, row = round(x), round(y)
            window = image[
                max(row - half, 0) : min(row + half + 1, height),
                max(col - half, 0) : min(col + half + 1, width),
            ]
            problem = speckle_problem(window, full_scale)
            if problem is not None:
                raise InputError(
                    f"reference frame: mark {number} at ({x:.0f}, {y:.0f}) px cannot be "
                    f"tracked: {problem}"
                )


def _run_facts(
    config: Config,
    rig: Rig,
    plan: ExposurePlan,
    calibration: Calibration,
    exposure_us: float,
    triggers: TriggerPlan | None,
) -> dict[str, Any]:
    """The facts of a test known before its reference frame (recorded, and in the summary)."""
    facts: dict[str, Any] = {
        **({"material": config.sim.material} if rig.world is not None else {}),
        "speed_mm_min": rig.speed_mm_min,
        "gauge_length_mm": rig.gauge_length_mm,
        **_specimen_facts(config, rig),
        "scale_mm_per_px": calibration.scale_mm_per_px,
        **measurement_facts(calibration, rig.optics, rig.gauge_length_mm),
        "exposure_us": exposure_us,
        "frame_rate_hz": 1.0 / plan.frame_period_s,
        "blur_px_at_crosshead_speed": plan.blur_px,
        "blur_budget_met": bool(plan.budget_met),
        "trigger_source": config.trigger.source,
        "machine_url": rig.machine.url if rig.machine is not None else "",
    }
    if triggers is not None:
        facts["trigger_period_ticks"] = triggers.period_ticks
        facts["trigger_encoder_divisor"] = triggers.encoder_divisor
        facts["frame_period_s"] = triggers.frame_period_s
    return facts


def _specimen_facts(config: Config, rig: Rig) -> dict[str, Any]:
    """The specimen's material and original cross-section S0, for the results: the
    `[specimen]` table's, else a simulated test's preset (its nominal dimensions are the
    test's specification, not the simulated truth)."""
    specimen = config.specimen
    material = specimen.material or (config.sim.material if rig.world is not None else None)
    area = cross_section_mm2(specimen)
    source = "[specimen]" if area is not None else None
    if area is None and rig.world is not None:
        from appliance.sim.world import PRESETS

        nominal = PRESETS[config.sim.material].specimen()
        area, source = nominal.parallel_area_mm2, f"{nominal.name}, nominal dimensions"
    return {
        "specimen_material": material,
        "cross_section_mm2": area,
        "cross_section_source": source,
    }


def _run_counts(
    result: LoopResult,
    samples: _SampleLog,
    reference: _Reference,
    loop: MeasurementLoop,
    rig: Rig,
    pacer: ExposurePacer | None,
) -> dict[str, Any]:
    """What the run counted besides the summary's figures."""
    counts: dict[str, Any] = {
        "max_blur_px_at_marks": samples.max_blur_px,
        "test_duration_s": samples.last_time_s,
        "points": reference.points_placed,
        **reference.placement,
        "run_states": [t.target.value for t in loop.state.history],
        "camera_outages": result.camera_outages,
        "camera_outage_s": result.camera_outage_s,
        "controller_outages": result.controller_outages,
        "frames_without_controller": result.samples_without_controller,
    }
    if result.hung_call:
        counts["hung_call"] = result.hung_call
    if reference.search_choices:
        counts["search_choices"] = reference.search_choices
    statistics = rig.camera.statistics()
    if statistics:
        counts["camera_statistics"] = statistics
    if pacer is not None:
        counts["replans"] = [dataclasses.asdict(replan) for replan in pacer.replans]
        counts["replan_failures"] = pacer.failures
    if rig.mcu_line is not None and rig.world is not None:
        counts["mcu_triggers"] = len(rig.mcu_line.events)
        counts["mcu_triggers_without_time"] = rig.mcu_line.unstamped
    return counts


def _end_outputs(
    outputs: list[RunOutput],
    result: LoopResult,
    report: TestReport | None = None,
    on_results: Callable[[Mapping[str, Any]], None] | None = None,
) -> None:
    """End every output; a failing one turns a normal end into a fault, without hiding the
    others. Once `report` has ended, its results object goes to `on_results`, before the
    outputs after it (the hooks': Modbus registers, a viewer) end."""
    errors: list[str] = []
    for output in outputs:
        try:
            output.end(result)
            if output is report and on_results is not None:
                on_results(report.stats()["results"])
        except Exception as exc:  # noqa: BLE001 - one failing output must not hide the others
            errors.append(f"{type(exc).__name__}: {exc}")
    if errors and result.exit_status.ended_normally:
        result.exit_status = ExitStatus.FAULT
        result.reason = f"outputs: {errors[0]}"


def _strain_file(
    path: Path,
    samples: _SampleLog | None,
    on_no_space: Callable[[], bool],
    width_stations: int = 0,
) -> StrainCsvWriter:
    """The strain file, with the width's columns when it is measured and the truth columns
    of a simulated test."""
    try:
        if samples is None:
            return StrainCsvWriter(path, on_no_space=on_no_space, width_stations=width_stations)
        return StrainCsvWriter(
            path,
            TRUTH_COLUMNS,
            samples.truth_columns,
            on_no_space=on_no_space,
            width_stations=width_stations,
        )
    except StrainFileError as exc:
        raise InputError(str(exc)) from None
    except OSError as exc:
        raise InputError(f"{path}: cannot create the strain file ({exc.strerror})") from None


def _exposure_pacer(
    config: Config,
    rig: Rig,
    exposure_us: float,
    recorder: McapRecorder | None,
    line: ProgressLine | None,
) -> ExposurePacer | None:
    """The pacing of exposure and triggers by the machine's speed; None when it is off
    (`[trigger] replan_hysteresis = 0`) or there is no machine to read the speed from."""
    if not config.trigger.replan_hysteresis or rig.machine is None:
        return None
    free_running = config.trigger.source == "internal"
    tick_hz = 0.0 if free_running else rig.trigger_tick_hz()

    def make_plan(speed_mm_min: float) -> TriggerPlan:
        try:
            exposure = exposure_for(config, rig.optics, speed_mm_min)
        except InputError as exc:
            raise ValueError(str(exc)) from None
        if free_running:
            return free_running_plan(exposure)
        return configured_trigger_plan(config.trigger, exposure, tick_hz)

    def tell(replan: Replan) -> None:
        if recorder is not None:
            recorder.log("WARNING" if replan.error else "INFO", replan.describe())
        if line is not None:
            line.note(replan.describe())

    return ExposurePacer(
        make_plan,
        TriggerReplanner(
            rig.speed_mm_min,
            hysteresis=config.trigger.replan_hysteresis,
            slow_down_after_s=config.trigger.replan_slow_down_s,
        ),
        rig.camera,
        None if free_running else rig.trigger_timer(),
        exposure_us=exposure_us,
        on_replan=tell,
    )


def _transition_listener(
    recorder: McapRecorder | None, hooks: RunHooks
) -> Callable[[Transition], None]:
    """Every run-state change to the recording's log, then to the hooks' listener."""

    def transition(record: Transition) -> None:
        if recorder is not None:
            recorder.log_transition(record)
        if hooks.on_transition is not None:
            hooks.on_transition(record)

    return transition


def _note_listener(
    recorder: McapRecorder | None, line: ProgressLine | None
) -> Callable[[str], None]:
    """A line about the test (not a warning) to the recording's log and the progress line."""

    def note(text: str) -> None:
        if recorder is not None:
            recorder.log("INFO", text)
        if line is not None:
            line.note(text)

    return note


def _warning_listener(recorder: McapRecorder | None, hooks: RunHooks) -> Callable[[str], None]:
    """A warning about the test to the recording's log, then to the hooks' listener."""

    def warn(text: str) -> None:
        if recorder is not None:
            recorder.log("WARNING", text)
        if hooks.on_warning is not None:
            hooks.on_warning(text)

    return warn


def _device_listeners(
    recorder: McapRecorder | None, hooks: RunHooks, line: ProgressLine | None
) -> list[Callable[[DeviceEvent], None]]:
    """Who hears of a device lost or back: the recording, the hooks, the progress line."""
    listeners: list[Callable[[DeviceEvent], None]] = list(hooks.device_listeners)
    if recorder is not None:
        listeners.insert(0, recorder.log_device_event)
    if line is not None:
        listeners.append(line.device_event)
    return listeners
