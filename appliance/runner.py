"""One tensile test from configuration to summary: devices, exposure plan, marks, loop, outputs.

`run_test` is what `extensometer run` does:

1. devices: the simulated world (`--sim`: camera and frame on one virtual clock, with ground
   truth) or the camera and frame named by the configuration's URLs;
2. exposure: the configured exposure and frame rate, or the planner's (`appliance.planner`):
   the longest exposure whose motion blur at the test speed stays within the blur budget and
   the frame rate that keeps the marks' frame-to-frame motion inside the tracker's search;
3. marks: placed on the reference image, centred on the specimen, at the configured gauge
   length; each axial mark a short line of points;
4. the loop (`appliance.loop`) until the strain limit, the break, or an interrupt;
5. outputs: `strain.csv` (every sample, with the truth when simulated) and `summary.json`
   in the output directory, the MCAP recording (`appliance.recorder`) and any other output
   given (a viewer), and the summary returned.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from appliance import __version__
from appliance.config import Config
from appliance.errors import InputError
from appliance.gauges import Calibration, StrainGauges, StrainGaugesLayout, place_marks
from appliance.loop import MeasurementLoop
from appliance.measurement import StopCriteria, StrainSample
from appliance.optics import Optics
from appliance.outputs import RunFacts, RunOutput
from appliance.planner import ExposurePlan, motion_blur_length, plan_exposure
from appliance.recorder import McapRecorder
from appliance.run_state import RunStateMachine, Transition
from appliance.strain_file import StrainCsvWriter
from appliance.summary import RunSummary, SampleRecord
from appliance.tracking import MarkTracker, TrackerSettings
from hal.camera.base import CameraSettings, PixelFormat, TriggerInfo, TriggerMode
from hal.clock import Pace

TRUTH_COLUMNS = ("true_engineering_strain", "true_elongation_mm", "strain_error")


@dataclass
class RunOutcome:
    """What a run produced.

    Attributes:
        summary: the figures of the run (with `extra` merged in `as_dict`).
        extra: run facts beyond the summary: exposure plan, gauge length, duration.
        csv_path, summary_path: files written (None without an output directory).
    """

    summary: RunSummary
    extra: dict[str, Any] = field(default_factory=dict)
    csv_path: Path | None = None
    summary_path: Path | None = None

    def as_dict(self) -> dict[str, Any]:
        """Summary and facts as one dictionary."""
        return {**self.summary.as_dict(), **self.extra}

    def to_json(self) -> str:
        """Summary and facts as JSON (NaN and infinities as null)."""
        return json.dumps(_json_ready(self.as_dict()), indent=2)


def _optics(config: Config, fallback: Optics | None) -> Optics:
    o = config.optics
    given = (o.focal_length_mm, o.object_distance_mm, o.pixel_size_um)
    if all(v is None for v in given) and fallback is not None:
        return fallback
    missing = [
        k
        for k, v in zip(
            ("focal_length_mm", "object_distance_mm", "pixel_size_um"), given, strict=True
        )
        if v is None
    ]
    if missing:
        raise InputError(f"[optics] {missing[0]}: required (the camera's optics must be known)")
    try:
        return Optics(*given)
    except ValueError as exc:
        raise InputError(f"[optics]: {exc}") from None


def exposure_for(config: Config, optics: Optics, speed_mm_min: float) -> ExposurePlan:
    """The exposure plan for a test speed; configured exposure and rate take precedence."""
    camera = config.camera
    plan = plan_exposure(
        optics,
        speed_mm_min,
        blur_budget_px=camera.blur_budget_px,
        capture_range_px=float(config.tracking.search_radius_px),
        min_exposure_s=camera.min_exposure_us * 1e-6,
        max_exposure_s=camera.max_exposure_us * 1e-6,
    )
    exposure_s = plan.exposure_s if camera.exposure_us is None else camera.exposure_us * 1e-6
    if camera.frame_rate_hz is None:
        period_s = max(min(plan.frame_period_s, 1.0 / camera.min_frame_rate_hz), exposure_s)
    else:
        period_s = 1.0 / camera.frame_rate_hz
    if exposure_s > period_s:
        raise InputError(
            f"[camera] exposure_us: {exposure_s * 1e6:g} exceeds the frame period "
            f"{period_s * 1e6:g} us"
        )
    blur = motion_blur_length(optics, speed_mm_min, exposure_s)
    motion = motion_blur_length(optics, speed_mm_min, period_s).px
    return dataclasses.replace(
        plan,
        exposure_s=exposure_s,
        frame_period_s=period_s,
        blur_um=blur.um,
        blur_px=blur.px,
        motion_per_frame_px=motion,
        budget_met=bool(blur.px <= camera.blur_budget_px),
    )


class _Progress:
    """One self-rewriting status line on a terminal."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream

    def __call__(self, sample: StrainSample) -> None:
        r = sample.reading
        machine = sample.machine
        force = f" force {machine.force_n:9.1f} N" if machine is not None else ""
        flag = "valid" if sample.data_valid else "INVALID"
        self.stream.write(
            f"\r  t {sample.time_s:7.2f} s  frame {sample.index:6d}  strain "
            f"{r.engineering_strain * 100:9.3f} %{force}  {flag}"
        )
        self.stream.flush()

    def close(self) -> None:
        self.stream.write("\n")
        self.stream.flush()


def tracker_settings(config: Config) -> TrackerSettings:
    """The tracker's settings of a configuration's [tracking] table."""
    t = config.tracking
    return TrackerSettings(
        subset_px=t.subset_px,
        min_subset_px=t.min_subset_px,
        search=t.search,
        search_radius_px=t.search_radius_px,
        reacquire_search=t.reacquire_search,
        reacquire_radius_px=t.reacquire_radius_px,
        prefilter_sigma_px=t.prefilter_sigma_px,
        min_zncc=t.min_zncc,
        update_zncc=t.update_zncc,
        update_deformation=t.update_deformation,
    )


def marks_of(layout: StrainGaugesLayout) -> tuple[tuple[int, ...], ...]:
    """The tracker's marks of a gauge layout: the axial marks, then the transverse ones."""
    marks = [layout.axial.first, layout.axial.second]
    if layout.transverse is not None:
        marks += [layout.transverse.first, layout.transverse.second]
    return tuple(tuple(m) for m in marks)


def build_measurement(
    config: Config,
    reference: np.ndarray,
    points: np.ndarray,
    layout: StrainGaugesLayout,
    calibration: Calibration,
) -> tuple[MarkTracker, StrainGauges]:
    """The tracker and gauges of a test, on its reference image and placed points."""
    image = np.asarray(reference, dtype=np.float64)
    tracker = MarkTracker(image, points, marks_of(layout), tracker_settings(config))
    gauges = StrainGauges(layout.axial, points, calibration, layout.transverse)
    return tracker, gauges


def run_test(
    config: Config,
    *,
    simulate: bool,
    out_dir: Path | None = None,
    progress: TextIO | None = None,
    record_path: Path | None = None,
    outputs: Sequence[RunOutput] = (),
    immediate_sinks: Sequence[Callable[[StrainSample], None]] = (),
    on_transition: Callable[[Transition], None] | None = None,
    on_loop: Callable[[MeasurementLoop], None] | None = None,
    test_id: str = "",
) -> RunOutcome:
    """Run one test as configured; see the module docstring.

    Args:
        config: the validated configuration.
        simulate: use the simulated world (ground truth in the outputs).
        out_dir: where to write strain.csv and summary.json (created); None = nowhere.
        progress: a terminal stream for the progress line; None = quiet.
        record_path: the MCAP recording to write (must not exist); None = no recording.
        outputs: further outputs following the test (a viewer, for instance).
        immediate_sinks: called on the tracking thread with every sample (Modbus registers,
            watchdog).
        on_transition: called at every change of the run state.
        on_loop: called with the measurement loop before it runs (to stop or zero it from
            another thread).
        test_id: names the test in the recording and the viewer.

    Raises:
        InputError: a configuration that cannot run (named key), or a recording file that
            cannot be created.
        HardwareError: a device that cannot be opened or configured.
    """
    if not simulate:
        raise InputError(
            "run: only the simulated devices are available in this version (use --sim)"
        )
    from appliance.sim.world import PRESETS, SimWorld

    optics = _optics(config, PRESETS[config.sim.material].optics)
    world = SimWorld.from_config(config, optics)
    speed = world.speed_mm_min
    plan = exposure_for(config, optics, speed)
    calibration = Calibration.from_optics(optics.pixel_size_um, optics.magnification)
    gauge_length_mm = config.gauge.length_mm or world.gauge_length_mm
    records: list[SampleRecord] = []
    recorder = None
    if record_path is not None:
        recorder = McapRecorder(
            record_path,
            config.record,
            truth=lambda sample: (records[-1].true_strain, records[-1].true_elongation_mm),
        )
    every_output: list[RunOutput] = ([recorder] if recorder is not None else []) + list(outputs)
    listeners = [on_transition] if on_transition is not None else []
    if recorder is not None:
        listeners.insert(0, lambda t: recorder.log("INFO", _transition_text(t)))

    def transition(record: Transition) -> None:
        for listener in listeners:
            listener(record)

    state = RunStateMachine(on_transition=transition)
    camera, frame = world.camera, world.frame
    try:
        camera.open()
        frame.open()
        pixel_format = (
            PixelFormat.MONO8 if config.camera.pixel_format == "Mono8" else PixelFormat.MONO12
        )
        camera.configure(
            CameraSettings(
                exposure_us=plan.exposure_s * 1e6,
                gain_db=config.camera.gain_db,
                pixel_format=pixel_format,
            )
        )
        camera.prepare(TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=1.0 / plan.frame_period_s))
    except BaseException:
        if recorder is not None:
            recorder.close()
        raise

    extra = {
        "material": config.sim.material,
        "speed_mm_min": speed,
        "gauge_length_mm": gauge_length_mm,
        "scale_mm_per_px": calibration.scale_mm_per_px,
        "exposure_us": plan.exposure_s * 1e6,
        "frame_rate_hz": 1.0 / plan.frame_period_s,
        "blur_px_at_crosshead_speed": plan.blur_px,
        "blur_budget_met": bool(plan.budget_met),
    }
    state_of_run: dict[str, Any] = {}

    def setup(reference):
        g = config.gauge
        transverse = g.transverse_width_mm or None
        points, layout = place_marks(
            world.specimen_centre_px,
            gauge_length_mm,
            calibration,
            mark_width_px=g.mark_spacing_px * (g.points_per_mark - 1),
            points_per_mark=g.points_per_mark,
            transverse_width_mm=transverse,
            along_axis=True,
        )
        state_of_run["truth"] = world.gauge_truth(points, layout.axial, reference)
        state_of_run["points"] = points
        tracker, gauges = build_measurement(config, reference.image, points, layout, calibration)
        exposure_end_ns = reference.timestamp_ns + int(round(reference.exposure_us * 1e3))
        facts = RunFacts(
            config=config,
            reference=reference,
            points=points,
            marks=marks_of(layout),
            layout=layout,
            calibration=calibration,
            gauge_length_mm=gauges.gauge_length_mm,
            epoch_offset_ns=time.time_ns() - exposure_end_ns,
            devices={
                "camera": camera.url,
                "frame": frame.url,
                "software": f"extensometer {__version__}",
            },
            facts={"test_id": test_id, "simulated": True, **extra},
        )
        for output in every_output:
            output.begin(facts)
        return tracker, gauges

    def record(sample: StrainSample) -> None:
        records.append(SampleRecord.of(sample, *state_of_run["truth"].at(sample)))
        state_of_run["last_time_s"] = sample.time_s
        if sample.data_valid:
            blur = state_of_run["truth"].blur_px(sample)
            state_of_run["max_blur_px"] = max(state_of_run.get("max_blur_px", 0.0), blur)

    def truth_columns(sample: StrainSample) -> dict[str, float]:
        measured = records[-1]
        return {
            "true_engineering_strain": measured.true_strain,
            "true_elongation_mm": measured.true_elongation_mm,
            "strain_error": measured.strain - measured.true_strain,
        }

    sinks: list[Callable[[StrainSample], None]] = [record]
    writer = None
    csv_path = summary_path = None
    try:
        if out_dir is not None:
            out_dir.mkdir(parents=True, exist_ok=True)
            csv_path = out_dir / "strain.csv"
            writer = StrainCsvWriter(csv_path, TRUTH_COLUMNS, truth_columns)
            sinks.append(writer)
    except BaseException:
        if recorder is not None:
            recorder.close()
        camera.close()
        frame.close()
        raise
    sinks.extend(every_output)
    bar = _Progress(progress) if progress is not None else None
    if bar is not None:
        sinks.append(bar)
    until_strain = config.run.until_strain or None
    loop = MeasurementLoop(
        camera,
        frame,
        setup,
        sinks=sinks,
        immediate_sinks=immediate_sinks,
        state=state,
        block_when_full=world.pace is Pace.FAST,
        start_speed_mm_min=speed,
    )
    if on_loop is not None:
        on_loop(loop)
    output_errors: list[str] = []
    try:
        result = loop.run(
            StopCriteria(until_strain=until_strain, until_break=config.run.until_break)
        )
    finally:
        if writer is not None:
            writer.close()
        if bar is not None:
            bar.close()
        camera.close()
        frame.close()
    for output in every_output:
        try:
            output.end(result)
        except Exception as exc:  # noqa: BLE001 - one failing output must not hide the others
            output_errors.append(f"{type(exc).__name__}: {exc}")
    if output_errors and result.exit_status in ("completed", "break"):
        result.exit_status = "fault"
        result.reason = f"outputs: {output_errors[0]}"
    summary = RunSummary.from_run(result, records)
    extra.update(
        {
            "max_blur_px_at_marks": state_of_run.get("max_blur_px"),
            "test_duration_s": state_of_run.get("last_time_s", 0.0),
            "points": int(len(state_of_run.get("points", []))),
            "run_states": [t.target.value for t in loop.state.history],
        }
    )
    for output in every_output:
        stats = getattr(output, "stats", None)
        if callable(stats):
            extra.update(stats())
    outcome = RunOutcome(summary, extra, csv_path)
    if out_dir is not None:
        summary_path = out_dir / "summary.json"
        summary_path.write_text(outcome.to_json() + "\n")
        outcome.summary_path = summary_path
    return outcome


def _transition_text(transition: Transition) -> str:
    reason = f": {transition.reason}" if transition.reason else ""
    return f"run state {transition.source.value} -> {transition.target.value}{reason}"


def _json_ready(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _json_ready(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_json_ready(v) for v in value]
    return value


def print_summary(outcome: RunOutcome, stream: TextIO = sys.stdout) -> None:
    """The summary as aligned human-readable lines."""
    for key, value in outcome.as_dict().items():
        if isinstance(value, float):
            value = f"{value:.6g}"
        stream.write(f"{key:38s} {value}\n")
