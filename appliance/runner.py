"""One tensile test from configuration to summary: devices, exposure plan, marks, loop, outputs.

`run_test` is what `extensometer run` does:

1. devices: the simulated world (`--sim`: camera and machine on one virtual clock, with ground
   truth) or the camera and machine named by the configuration's URLs;
2. exposure: the configured exposure and frame rate, or the planner's (`appliance.plan.exposure`):
   the longest exposure whose motion blur at the test speed stays within the blur budget and
   the frame rate that keeps the marks' frame-to-frame motion inside the tracker's search;
3. marks: placed on the reference image, centred on the specimen, at the configured gauge
   length; each axial mark a short line of points;
4. the loop (`appliance.run.loop`) until the strain limit, the break, or an interrupt;
5. outputs: `strain.csv` (every sample, with the truth when simulated) and `summary.json`
   in the output directory, the MCAP recording (`appliance.recording.writer`) and any other output
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
from appliance.config import Config, register_map_of
from appliance.devices.polled_machine import PolledMachine
from appliance.errors import InputError
from appliance.measure.frame_measurer import StopCriteria, StrainSample
from appliance.measure.gauges import Calibration, StrainGauges, StrainGaugesLayout, place_marks
from appliance.measure.tracking import MarkTracker
from appliance.plan.exposure import ExposurePlan, motion_blur_length, plan_exposure
from appliance.plan.optics import Optics
from appliance.plan.pacing import ExposurePacer, Replan
from appliance.plan.trigger_plan import TriggerPlan, TriggerReplanner, plan_triggers
from appliance.recording.writer import McapRecorder
from appliance.run.loop import DeviceEvent, MeasurementLoop
from appliance.run.outputs import RunFacts, RunOutput
from appliance.run.state import ExitStatus, RunStateMachine, Transition
from appliance.run.strain_file import StrainCsvWriter
from appliance.run.summary import RunSummary, SampleRecord
from hal.camera.base import (
    Camera,
    CameraSettings,
    Frame,
    PixelFormat,
    Region,
    TriggerInfo,
    TriggerMode,
)
from hal.clock import Pace
from hal.machine.base import TestingMachine
from hal.registry import camera_from_url, machine_from_url

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


def configured_optics(config: Config, fallback: Optics | None) -> Optics:
    """The [optics] of a configuration; `fallback` (a simulated preset's) when the table
    gives none of its keys. Raises InputError naming a missing or bad key."""
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
    tracker = MarkTracker(image, points, marks_of(layout), config.tracking)
    gauges = StrainGauges(layout.axial, points, calibration, layout.transverse)
    return tracker, gauges


@dataclass
class _Rig:
    """The devices of a test and what is known of them before the reference is taken."""

    camera: Camera
    machine: TestingMachine | None
    optics: Optics
    speed_mm_min: float
    gauge_length_mm: float
    centre_px: Callable[[Frame], tuple[float, float]]
    commands: bool
    block_when_full: bool
    world: Any = None
    mcu_line: Any = None


def _sim_rig(config: Config) -> _Rig:
    from appliance.sim.world import PRESETS, SimWorld

    if not config.machine.url.startswith("sim://"):
        raise InputError(
            f"[machine] url: {config.machine.url or 'empty'}: the simulated test needs the "
            "simulated machine (sim://machine)"
        )
    optics = configured_optics(config, PRESETS[config.sim.material].optics)
    world = SimWorld.from_config(config, optics)
    g = config.gauge
    centre = (
        (g.centre_x_px, g.centre_y_px)
        if g.centre_x_px is not None and g.centre_y_px is not None
        else world.specimen_centre_px
    )
    _check_trigger_url(config, simulate=True)
    machine: TestingMachine = world.controller
    if config.sim.controller == "modbus-tcp":
        from appliance.sim.controller_server import ModbusServedMachine

        machine = ModbusServedMachine(world.controller, poll_rate_hz=config.machine.poll_rate_hz)
    return _Rig(
        camera=world.camera,
        machine=machine,
        optics=optics,
        speed_mm_min=world.speed_mm_min,
        gauge_length_mm=config.gauge.length_mm or world.gauge_length_mm,
        centre_px=lambda reference: centre,
        commands=True,
        block_when_full=world.pace is Pace.FAST,
        world=world,
    )


def _close_devices(rig: _Rig) -> None:
    """Close the camera, the trigger microcontroller's link and the controller of a test."""
    rig.camera.close()
    _release_trigger_mcu(rig)
    if rig.machine is not None:
        rig.machine.close()


def _release_trigger_mcu(rig: _Rig) -> None:
    """Disarm and close the real trigger microcontroller's link, if the test has one."""
    line = rig.mcu_line
    if line is None:
        return
    from firmware_bridge.link import FirmwareError

    try:
        line.stop()
    except FirmwareError:
        pass
    line.link.close()
    rig.mcu_line = None


def _check_trigger_url(config: Config, *, simulate: bool) -> None:
    """Refuse a `[trigger] url` that does not go with [trigger] source (a real camera needs
    one for period and encoder triggering) or, in a simulated test, with [sim] realtime."""
    trigger = config.trigger
    if trigger.url and trigger.source == "internal":
        raise InputError("[trigger] url: set, but [trigger] source is internal")
    if not trigger.url and trigger.source != "internal" and not simulate:
        raise InputError(
            f"[trigger] url: required with a real camera and [trigger] source "
            f"{trigger.source!r} (the trigger microcontroller's serial port)"
        )
    if trigger.url and simulate and not config.sim.realtime:
        raise InputError("[trigger] url: the microcontroller runs in real time: set [sim] realtime")


def _connect_trigger_mcu(config: Config, world: Any) -> Any:
    """The real trigger microcontroller at `[trigger] url`, wired to the simulated camera of
    `world` (None: a real camera on its output)."""
    from appliance.devices.mcu_trigger import McuTriggerLine
    from firmware_bridge.link import FirmwareError, McuLink

    try:
        link = McuLink(config.trigger.url)
        try:
            link.connect()
        except BaseException:
            link.close()
            raise
    except FirmwareError as exc:
        raise InputError(f"[trigger] url: {config.trigger.url}: {exc}") from None
    if world is None:
        return McuTriggerLine(link)
    line = McuTriggerLine(link, lambda host_ns: world.clock.at_wall_s(host_ns * 1e-9))
    world.camera.wire_trigger_input(line)
    return line


def _hardware_rig(config: Config) -> _Rig:
    """The configured camera and controller; every fact the simulator would know must be
    configured (optics, gauge length, test speed)."""
    for key, url in (("[camera] url", config.camera.url), ("[machine] url", config.machine.url)):
        if url.startswith("sim://"):
            raise InputError(f"{key}: {url} is simulated: run with --sim, or name a real device")
    _check_trigger_url(config, simulate=False)
    camera = camera_from_url(config.camera.url)
    optics = configured_optics(config, None)
    if config.gauge.length_mm is None:
        raise InputError("[gauge] length_mm: required with a real specimen")
    speed = config.run.speed_mm_min
    if speed is None:
        raise InputError("[run] speed_mm_min: required with a real machine (exposure plan)")
    machine: TestingMachine | None = None
    if config.machine.url:
        controller = machine_from_url(
            config.machine.url,
            register_map=register_map_of(config, "[machine.registers]"),
            accepts_commands=config.machine.accepts_commands,
        )
        machine = PolledMachine(controller, rate_hz=config.machine.poll_rate_hz)
    g = config.gauge

    def centre(reference: Frame) -> tuple[float, float]:
        height, width = reference.image.shape[:2]
        x = g.centre_x_px if g.centre_x_px is not None else (width - 1) / 2
        y = g.centre_y_px if g.centre_y_px is not None else (height - 1) / 2
        return float(x), float(y)

    return _Rig(
        camera=camera,
        machine=machine,
        optics=optics,
        speed_mm_min=speed,
        gauge_length_mm=config.gauge.length_mm,
        centre_px=centre,
        commands=machine is not None and config.machine.accepts_commands,
        block_when_full=False,
    )


def _prepare_triggers(
    config: Config, rig: _Rig, plan: ExposurePlan, camera: Camera
) -> TriggerPlan | None:
    """Prepare the camera's triggering: free-running at the planned rate, or external edges
    from the trigger microcontroller, configured and armed here; the trigger plan or None."""
    source = config.trigger.source
    if source == "internal":
        camera.prepare(TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=1.0 / plan.frame_period_s))
        return None
    if config.trigger.url:
        rig.mcu_line = _connect_trigger_mcu(config, rig.world)
    try:
        triggers = _trigger_plan(config, plan, _trigger_tick_hz(rig))
    except ValueError as exc:
        raise InputError(f"[trigger] pulse_width_us: {exc}") from None
    camera.prepare(TriggerInfo(mode=TriggerMode.EXTERNAL))
    if rig.world is None:
        from appliance.devices.trigger_stamping import TriggerStampedCamera

        rig.camera = TriggerStampedCamera(camera, rig.mcu_line, triggers)
        return triggers
    if rig.mcu_line is not None:
        rig.mcu_line.start(triggers)
        return triggers
    controller = rig.world.trigger
    controller.configure(triggers)
    controller.arm(rig.world.clock.now_s())
    return triggers


def _trigger_plan(config: Config, exposure: ExposurePlan, tick_hz: float) -> TriggerPlan:
    """The trigger plan of an exposure plan for `[trigger]` (period or encoder source).
    Raises ValueError when the pulse does not fit."""
    encoder = config.trigger.source == "encoder"
    return plan_triggers(
        exposure,
        tick_hz=tick_hz,
        counts_per_mm=config.trigger.encoder_counts_per_mm if encoder else None,
        pulse_width_us=config.trigger.pulse_width_us,
    )


def _trigger_tick_hz(rig: _Rig) -> float:
    """Tick rate of the trigger microcontroller in use (real or simulated)."""
    if rig.mcu_line is not None:
        return float(rig.mcu_line.link.firmware.tick_hz)
    return float(rig.world.trigger.tick_hz)


def _exposure_pacer(
    config: Config,
    rig: _Rig,
    camera: Camera,
    exposure_us: float,
    recorder: McapRecorder | None,
    progress: TextIO | None,
) -> ExposurePacer | None:
    """The pacing of exposure and triggers by the controller's speed; None when it is off
    (`[trigger] replan_hysteresis = 0`) or there is no controller to read the speed from."""
    if not config.trigger.replan_hysteresis or rig.machine is None:
        return None
    source = config.trigger.source
    timer = None
    if source != "internal":
        timer = rig.mcu_line if rig.mcu_line is not None else rig.world.trigger
        tick_hz = _trigger_tick_hz(rig)

    def make_plan(speed_mm_min: float) -> TriggerPlan:
        try:
            exposure = exposure_for(config, rig.optics, speed_mm_min)
        except InputError as exc:
            raise ValueError(str(exc)) from None
        if source == "internal":
            return TriggerPlan(
                "internal",
                speed_mm_min,
                exposure.exposure_s * 1e6,
                0,
                0,
                0,
                exposure.frame_period_s,
                speed_mm_min / 60.0 * exposure.frame_period_s,
            )
        return _trigger_plan(config, exposure, tick_hz)

    def tell(replan: Replan) -> None:
        if recorder is not None:
            recorder.log("WARNING" if replan.error else "INFO", replan.describe())
        if progress is not None:
            progress.write(f"\n  {replan.describe()}\n")
            progress.flush()

    return ExposurePacer(
        make_plan,
        TriggerReplanner(
            rig.speed_mm_min,
            hysteresis=config.trigger.replan_hysteresis,
            slow_down_after_s=config.trigger.replan_slow_down_s,
        ),
        camera,
        timer,
        exposure_us=exposure_us,
        on_replan=tell,
    )


def check_devices(config: Config, *, simulate: bool) -> None:
    """Check, without opening anything, that the configured devices can run a test: the URLs
    name known backends with valid options, and what a real test needs is configured.

    Raises:
        InputError: naming the key at fault.
        HardwareError: a backend refusing its URL.
    """
    if simulate:
        _sim_rig(config)
    else:
        _hardware_rig(config)


def camera_region(config: Config) -> Region | None:
    """The sensor region of [camera] region_*_px; None = the full sensor."""
    c = config.camera
    if c.region_width_px is None:
        return None
    return Region(c.region_x_px or 0, c.region_y_px or 0, c.region_width_px, c.region_height_px)


def _check_marks_inside(points: np.ndarray, shape: tuple[int, ...], subset_px: int) -> None:
    """Refuse marks on which not even the smallest subset fits in the image (a gauge length
    too long for the field of view, or a centre off the image)."""
    height, width = shape[:2]
    half = subset_px // 2
    x, y = points[:, 0], points[:, 1]
    if (
        x.min() < half
        or y.min() < half
        or x.max() > width - 1 - half
        or y.max() > height - 1 - half
    ):
        raise InputError(
            f"[gauge] length_mm: the marks span x {x.min():.0f}..{x.max():.0f}, "
            f"y {y.min():.0f}..{y.max():.0f} px, outside the {width}x{height} image less half "
            f"the smallest subset ({half} px): shorten the gauge or move its centre"
        )


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
    device_listeners: Sequence[Callable[[DeviceEvent], None]] = (),
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
        device_listeners: called with every `appliance.run.loop.DeviceEvent` (a camera or
            controller lost or back), on the acquisition thread.
        test_id: names the test in the recording and the viewer.

    Raises:
        InputError: a configuration that cannot run (named key), or a recording file that
            cannot be created.
        HardwareError: a device that cannot be opened or configured.
    """
    rig = _sim_rig(config) if simulate else _hardware_rig(config)
    optics, speed = rig.optics, rig.speed_mm_min
    plan = exposure_for(config, optics, speed)
    calibration = Calibration.from_optics(optics.pixel_size_um, optics.magnification)
    gauge_length_mm = rig.gauge_length_mm
    records: list[SampleRecord] = []
    recorder = None
    if record_path is not None:
        recorder = McapRecorder(
            record_path,
            config.record,
            truth=(
                (lambda sample: (records[-1].true_strain, records[-1].true_elongation_mm))
                if simulate
                else None
            ),
            trigger_mode=config.trigger.source,
        )
    every_output: list[RunOutput] = ([recorder] if recorder is not None else []) + list(outputs)
    listeners = [on_transition] if on_transition is not None else []
    if recorder is not None:
        listeners.insert(0, lambda t: recorder.log("INFO", _transition_text(t)))

    def transition(record: Transition) -> None:
        for listener in listeners:
            listener(record)

    state = RunStateMachine(on_transition=transition)
    camera, machine = rig.camera, rig.machine
    try:
        camera.open()
        if machine is not None:
            machine.open()
        in_force = camera.configure(
            CameraSettings(
                exposure_us=plan.exposure_s * 1e6,
                gain_db=config.camera.gain_db,
                region=camera_region(config),
                pixel_format=PixelFormat(config.camera.pixel_format),
            )
        )
        triggers = _prepare_triggers(config, rig, plan, camera)
        camera, mcu_line = rig.camera, rig.mcu_line
        pacer = _exposure_pacer(config, rig, camera, in_force.exposure_us, recorder, progress)
    except BaseException:
        if recorder is not None:
            recorder.close()
        _close_devices(rig)
        raise

    extra = {
        **({"material": config.sim.material} if simulate else {}),
        "speed_mm_min": speed,
        "gauge_length_mm": gauge_length_mm,
        "scale_mm_per_px": calibration.scale_mm_per_px,
        "exposure_us": in_force.exposure_us,
        "frame_rate_hz": 1.0 / plan.frame_period_s,
        "blur_px_at_crosshead_speed": plan.blur_px,
        "blur_budget_met": bool(plan.budget_met),
        "trigger_source": config.trigger.source,
        "machine_url": machine.url if machine is not None else "",
    }
    if triggers is not None:
        extra["trigger_period_ticks"] = triggers.period_ticks
        extra["trigger_encoder_divisor"] = triggers.encoder_divisor
        extra["frame_period_s"] = triggers.frame_period_s
    state_of_run: dict[str, Any] = {}

    def setup(reference):
        g = config.gauge
        transverse = g.transverse_width_mm or None
        points, layout = place_marks(
            rig.centre_px(reference),
            gauge_length_mm,
            calibration,
            axis_deg=g.axis_deg,
            mark_width_px=g.mark_spacing_px * (g.points_per_mark - 1),
            points_per_mark=g.points_per_mark,
            transverse_width_mm=transverse,
            along_axis=True,
        )
        _check_marks_inside(points, reference.image.shape, config.tracking.min_subset_px)
        if rig.world is not None:
            state_of_run["truth"] = rig.world.gauge_truth(points, layout.axial, reference)
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
                "machine": machine.url if machine is not None else "",
                "software": f"extensometer {__version__}",
            },
            facts={"test_id": test_id, "simulated": simulate, **extra},
        )
        for output in every_output:
            output.begin(facts)
        return tracker, gauges

    def record(sample: StrainSample) -> None:
        truth = state_of_run.get("truth")
        records.append(
            SampleRecord.of(sample, *truth.at(sample)) if truth else SampleRecord.of(sample)
        )
        state_of_run["last_time_s"] = sample.time_s
        if sample.data_valid and truth is not None:
            blur = truth.blur_px(sample)
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
            writer = (
                StrainCsvWriter(csv_path, TRUTH_COLUMNS, truth_columns)
                if simulate
                else StrainCsvWriter(csv_path)
            )
            sinks.append(writer)
    except BaseException:
        if recorder is not None:
            recorder.close()
        _close_devices(rig)
        raise
    sinks.extend(every_output)
    bar = _Progress(progress) if progress is not None else None
    if bar is not None:
        sinks.append(bar)
    until_strain = config.run.until_strain or None
    device_events: list[Callable[[DeviceEvent], None]] = list(device_listeners)
    if recorder is not None:
        device_events.insert(0, _device_logger(recorder))
    if progress is not None:
        device_events.append(_device_printer(progress))
    loop = MeasurementLoop(
        camera,
        machine,
        setup,
        sinks=sinks,
        immediate_sinks=immediate_sinks,
        state=state,
        block_when_full=rig.block_when_full,
        start_speed_mm_min=speed if rig.commands else None,
        camera_outage_timeout_s=0.0 if simulate else config.camera.outage_timeout_s,
        device_listeners=device_events,
        machine_listeners=[pacer.follow] if pacer is not None else [],
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
        _close_devices(rig)
    for output in every_output:
        try:
            output.end(result)
        except Exception as exc:  # noqa: BLE001 - one failing output must not hide the others
            output_errors.append(f"{type(exc).__name__}: {exc}")
    if output_errors and result.exit_status.ended_normally:
        result.exit_status = ExitStatus.FAULT
        result.reason = f"outputs: {output_errors[0]}"
    summary = RunSummary.from_run(result, records)
    extra.update(
        {
            "max_blur_px_at_marks": state_of_run.get("max_blur_px"),
            "test_duration_s": state_of_run.get("last_time_s", 0.0),
            "points": int(len(state_of_run.get("points", []))),
            "run_states": [t.target.value for t in loop.state.history],
            "camera_outages": result.camera_outages,
            "camera_outage_s": result.camera_outage_s,
            "controller_outages": result.controller_outages,
            "frames_without_controller": result.samples_without_controller,
        }
    )
    statistics = getattr(camera, "statistics", None)
    if callable(statistics):
        extra["camera_statistics"] = statistics()
    if pacer is not None:
        extra["replans"] = [dataclasses.asdict(replan) for replan in pacer.replans]
        extra["replan_failures"] = pacer.failures
    if mcu_line is not None and rig.world is not None:
        extra["mcu_triggers"] = len(mcu_line.events)
        extra["mcu_triggers_without_time"] = mcu_line.unstamped
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


def _device_logger(recorder: McapRecorder) -> Callable[[DeviceEvent], None]:
    def log(event: DeviceEvent) -> None:
        if event.kind != "waiting":
            level = "INFO" if event.available else "WARNING"
            recorder.log(level, f"{event.device} {event.kind}: {event.url}: {event.text}")

    return log


def _device_printer(stream: TextIO) -> Callable[[DeviceEvent], None]:
    def show(event: DeviceEvent) -> None:
        if event.kind != "waiting":
            stream.write(f"\n  {event.device} {event.kind}: {event.text}\n")
            stream.flush()

    return show


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
