"""The devices of one test, and what is known of them before its reference frame is taken.

`rig_for(config, simulate=...)` builds them, not yet opened:

* simulated (`extensometer run --sim`): the simulated world (`appliance.sim.world`) gives the
  camera and the machine on one clock, read in-process or over Modbus TCP
  (`[sim] controller`); the world's ground truth is kept for scoring the result only;
* real: the camera and the machine named by `[camera] url` and `[machine] url` through the
  backend registry (`hal.registry`), the machine polled on its own thread. What the
  simulator would know must then be configured: `[optics]`, `[gauge] length_mm`,
  `[run] speed_mm_min`.

Both place the gauge alike (`gauge_centre_for`): centred on the specimen detected in the
reference frame (`appliance.measure.specimen_gauge`; on the image's centre when the specimen
fills the view), or at `[gauge] centre_x_px`, `centre_y_px` along `[gauge] axis_deg` when
both are configured. The simulated world's own knowledge of where the specimen is never
places it.

`Rig.open` opens and configures them and prepares the triggering; `Rig.close` closes every
device on every path, the trigger microcontroller's link included. `check_devices` runs the
same checks without opening anything (the service does it before it says it is ready).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from appliance.config import Config, register_map_of
from appliance.devices.mcu_trigger import McuTriggerLine, connect_trigger_line
from appliance.devices.polled_machine import PolledMachine
from appliance.devices.trigger_stamping import TriggerStampedCamera
from appliance.errors import InputError
from appliance.measure.gauges import (
    Calibration,
    Gauge,
    StrainGaugesLayout,
    marks_outside,
    place_marks,
)
from appliance.measure.painted_marks import DotSettings, PaintedMarksNotFound, find_dots
from appliance.measure.specimen_detection import NothingStandsOut, SpecimenNotFound
from appliance.measure.specimen_gauge import (
    CONFIGURED,
    IMAGE_CENTRE,
    GaugeCentre,
    detected_gauge_centre,
    marks_beyond_parallel_length,
)
from appliance.plan.exposure import ExposurePlan
from appliance.plan.optics import Optics, configured_optics
from appliance.plan.pacing import TriggerTimer
from appliance.plan.trigger_plan import TriggerPlan, configured_trigger_plan
from hal.camera.base import Camera, CameraSettings, Frame, PixelFormat, TriggerInfo, TriggerMode
from hal.clock import Pace
from hal.machine.base import TestingMachine
from hal.registry import camera_from_url, machine_from_url

if TYPE_CHECKING:
    from appliance.sim.world import SimWorld


@dataclass
class Rig:
    """The devices of a test and what is known of them before the reference is taken.

    Attributes:
        camera: the camera (after `open`, wrapped to stamp frames with their triggers' times
            where a real camera is triggered by the microcontroller).
        machine: the testing machine, or None (strain only).
        optics: the configured optics (or the simulated preset's).
        speed_mm_min: the test speed.
        gauge_length_mm: the gauge length asked for, mm.
        gauge_centre: the centre and axis of the marks on the reference frame, and how they
            were found (`gauge_centre_for`).
        commands: whether the appliance starts and stops the crosshead.
        block_when_full: the loop waits for room instead of dropping frames (a simulation
            running as fast as possible, whose clock moves only when a frame is fetched).
        world: the simulated world (simulated tests only; its truth only scores).
        mcu_line: the real trigger microcontroller, once connected (kept after `close`, so
            its counts can be read).
    """

    camera: Camera
    machine: TestingMachine | None
    optics: Optics
    speed_mm_min: float
    gauge_length_mm: float
    gauge_centre: Callable[[Frame], GaugeCentre]
    commands: bool
    block_when_full: bool
    world: SimWorld | None = None
    mcu_line: McuTriggerLine | None = None

    def open(self, config: Config, plan: ExposurePlan) -> tuple[CameraSettings, TriggerPlan | None]:
        """Open and configure the devices for `plan` and prepare the triggering: the camera
        free-running at the planned rate, or on external edges from the trigger
        microcontroller, configured and armed here. Returns the camera settings in force and
        the trigger plan (None for a free-running camera). The caller closes the rig also
        when this raises.

        Raises:
            InputError: a trigger that cannot be planned or reached (names the key).
            HardwareError: a device that cannot be opened or configured.
        """
        self.camera.open()
        if self.machine is not None:
            self.machine.open()
        in_force = self.camera.configure(
            CameraSettings(
                exposure_us=plan.exposure_s * 1e6,
                gain_db=config.camera.gain_db,
                region=config.camera.region(),
                pixel_format=PixelFormat(config.camera.pixel_format),
            )
        )
        return in_force, self._prepare_triggers(config, plan)

    def _prepare_triggers(self, config: Config, plan: ExposurePlan) -> TriggerPlan | None:
        camera = self.camera
        if config.trigger.source == "internal":
            camera.prepare(
                TriggerInfo(mode=TriggerMode.INTERNAL, rate_hz=1.0 / plan.frame_period_s)
            )
            return None
        if config.trigger.url:
            world = self.world
            self.mcu_line = connect_trigger_line(
                config.trigger.url,
                None if world is None else lambda host_ns: world.clock.at_wall_s(host_ns * 1e-9),
            )
            if world is not None:
                world.camera.wire_trigger_input(self.mcu_line)
        try:
            triggers = configured_trigger_plan(config.trigger, plan, self.trigger_tick_hz())
        except ValueError as exc:
            raise InputError(f"[trigger] pulse_width_us: {exc}") from None
        camera.prepare(TriggerInfo(mode=TriggerMode.EXTERNAL))
        if self.world is None:
            assert self.mcu_line is not None
            self.camera = TriggerStampedCamera(camera, self.mcu_line, triggers)
            return triggers
        if self.mcu_line is not None:
            self.mcu_line.start(triggers)
            return triggers
        self.world.trigger.configure(triggers)
        self.world.trigger.arm(self.world.clock.now_s())
        return triggers

    def trigger_timer(self) -> TriggerTimer:
        """What times the triggers: the real microcontroller or the simulated one."""
        if self.mcu_line is not None:
            return self.mcu_line
        assert self.world is not None, "a real camera is triggered through [trigger] url"
        return self.world.trigger

    def trigger_tick_hz(self) -> float:
        """Tick rate of the trigger microcontroller in use (real or simulated)."""
        if self.mcu_line is not None:
            return float(self.mcu_line.link.firmware.tick_hz)
        return float(self.trigger_timer().tick_hz)

    def close(self) -> None:
        """Close the camera, the trigger microcontroller's link and the machine; idempotent."""
        self.camera.close()
        if self.mcu_line is not None:
            self.mcu_line.release()
        if self.machine is not None:
            self.machine.close()


def rig_for(config: Config, *, simulate: bool) -> Rig:
    """The devices of a test, not yet opened; see the module docstring.

    Raises:
        InputError: naming the key at fault.
        HardwareError: a backend refusing its URL.
    """
    return _simulated_rig(config) if simulate else _hardware_rig(config)


def check_devices(config: Config, *, simulate: bool) -> None:
    """Check, without opening anything, that the configured devices can run a test: the URLs
    name known backends with valid options, and what a real test needs is configured.

    Raises:
        InputError: naming the key at fault.
        HardwareError: a backend refusing its URL.
    """
    rig_for(config, simulate=simulate)


def _simulated_rig(config: Config) -> Rig:
    from appliance.sim.world import PRESETS, SimWorld

    if not config.machine.url.startswith("sim://"):
        raise InputError(
            f"[machine] url: {config.machine.url or 'empty'}: the simulated test needs the "
            "simulated machine (sim://machine)"
        )
    optics = configured_optics(config, PRESETS[config.sim.material].optics)
    world = SimWorld.from_config(config, optics)
    gauge_centre = gauge_centre_for(config)
    _check_trigger_url(config, simulate=True)
    machine: TestingMachine = world.controller
    if config.sim.controller == "modbus-tcp":
        from appliance.sim.controller_server import ModbusServedMachine

        machine = ModbusServedMachine(world.controller, poll_rate_hz=config.machine.poll_rate_hz)
    return Rig(
        camera=world.camera,
        machine=machine,
        optics=optics,
        speed_mm_min=world.speed_mm_min,
        gauge_length_mm=config.gauge.length_mm or world.gauge_length_mm,
        gauge_centre=gauge_centre,
        commands=True,
        block_when_full=world.pace is Pace.FAST,
        world=world,
    )


def _hardware_rig(config: Config) -> Rig:
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
    gauge_centre = gauge_centre_for(config)
    return Rig(
        camera=camera,
        machine=machine,
        optics=optics,
        speed_mm_min=speed,
        gauge_length_mm=config.gauge.length_mm,
        gauge_centre=gauge_centre,
        commands=machine is not None and config.machine.accepts_commands,
        block_when_full=False,
    )


def gauge_centre_for(config: Config) -> Callable[[Frame], GaugeCentre]:
    """Where the gauge of a test goes on its reference frame: `gauge_centre_in` the frame's
    image, a refusal naming the reference frame.

    Raises:
        InputError: as `gauge_centre_in`.
    """
    place = gauge_centre_in(config, "reference frame")
    return lambda reference: place(reference.image)


def gauge_centre_in(config: Config, source: str) -> Callable[[np.ndarray], GaugeCentre]:
    """Where the gauge goes on an image (the reference frame of a test, or an image
    `extensometer detect` is shown): at `[gauge] centre_x_px`, `centre_y_px` along
    `[gauge] axis_deg` when both are set (nothing is detected), else centred on the parallel
    length of the specimen detected in the image, along its axis. An image in which nothing
    stands out from the background (a speckle from edge to edge: a specimen that fills the
    view) centres the gauge on the image along `[gauge] axis_deg`; a test's speckle check
    then refuses a frame that holds nothing to track.

    Raises:
        InputError: only one of the centre's keys is set (here); from the returned function,
            an image in which no single specimen can be measured, naming `source` and what
            was seen.
    """
    g = config.gauge
    if (g.centre_x_px is None) != (g.centre_y_px is None):
        raise InputError(
            "[gauge] centre_x_px, centre_y_px: set both (a configured centre) or neither "
            "(the gauge is centred on the specimen found in the reference frame)"
        )
    if g.centre_x_px is not None and g.centre_y_px is not None:
        configured = GaugeCentre((g.centre_x_px, g.centre_y_px), g.axis_deg, CONFIGURED)
        return lambda reference: configured

    def detected(image: np.ndarray) -> GaugeCentre:
        try:
            return detected_gauge_centre(image)
        except NothingStandsOut:
            height, width = image.shape[:2]
            return GaugeCentre(((width - 1) / 2, (height - 1) / 2), g.axis_deg, IMAGE_CENTRE)
        except SpecimenNotFound as exc:
            raise InputError(
                f"{source}: {exc} (or set [gauge] centre_x_px and centre_y_px)"
            ) from None

    return detected


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


def speckle_marks(
    config: Config,
    centre: GaugeCentre,
    gauge_length_mm: float,
    calibration: Calibration,
    shape: tuple[int, ...],
) -> tuple[np.ndarray, StrainGaugesLayout]:
    """The speckle marks a test places about `centre`: `[gauge]`'s points per mark, spacing and
    transverse width, `gauge_length_mm` apart along the gauge's axis, checked against an image
    of `shape` and against the detected parallel length when there is one.

    Raises:
        InputError: marks that cannot be placed, beyond the image or beyond the parallel
            length, naming `[gauge] length_mm`.
    """
    g = config.gauge
    try:
        points, layout = place_marks(
            centre.centre_px,
            gauge_length_mm,
            calibration,
            axis_deg=centre.axis_deg,
            mark_width_px=g.mark_spacing_px * (g.points_per_mark - 1),
            points_per_mark=g.points_per_mark,
            transverse_width_mm=g.transverse_width_mm or None,
            along_axis=True,
        )
    except ValueError as exc:
        raise InputError(f"[gauge] length_mm: {exc}") from None
    outside = marks_outside(points, shape, config.tracking.min_subset_px)
    if outside is not None:
        raise InputError(f"[gauge] length_mm: {outside}: shorten the gauge or move its centre")
    if centre.detection is not None:
        beyond = marks_beyond_parallel_length(points, centre.detection)
        if beyond is not None:
            raise InputError(f"[gauge] length_mm: {beyond}")
    return points, layout


def painted_marks(
    image: np.ndarray, config: Config, source: str = "reference frame"
) -> tuple[np.ndarray, StrainGaugesLayout, GaugeCentre]:
    """The gauge between the two painted dots or lines of a reference image (`[gauge] marks`
    "dots" or "lines"): their positions, one point per mark, and the centre and axis they
    define. `source` names the image in a refusal.

    Raises:
        InputError: not exactly two marks (naming what was seen), or a transverse gauge asked.
    """
    kind = config.gauge.marks
    if config.gauge.transverse_width_mm:
        raise InputError(
            f'[gauge] transverse_width_mm: no transverse gauge with [gauge] marks = "{kind}"'
        )
    try:
        first, second = find_dots(image, DotSettings(kind=kind))
    except PaintedMarksNotFound as exc:
        raise InputError(f'{source}: {exc} ([gauge] marks = "{kind}")') from None
    points = np.array([first.centre_px, second.centre_px])
    dx, dy = points[1] - points[0]
    axis_deg = float(np.degrees(np.arctan2(dy, dx)))
    centre = GaugeCentre(tuple(points.mean(axis=0)), axis_deg, f"painted {kind}")
    return points, StrainGaugesLayout(Gauge((0,), (1,)), None), centre
