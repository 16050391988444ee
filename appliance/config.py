"""Appliance configuration: one TOML file, validated completely at load.

Every key carries its unit in its name (`exposure_us`, `speed_mm_min`), unknown keys are
rejected, and every error is one line naming the file, the table and the key:
`run.toml: [camera] exposure_us: must be > 0, got -5`. Missing keys take the defaults below,
so an empty file is a valid configuration of the simulated test.

The schema is the dataclasses of this module, a table per section and a field per key, and
`appliance.measure.tracking.TrackerSettings`, which is the `[tracking]` table (the tracker's
settings are defined once, where the tracker lives). A field's `metadata` may give `minimum`,
`maximum` (inclusive), `choices` and `odd`; a field with `configurable` False is not a key.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import types
import typing
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from appliance.errors import InputError, read_user_text
from appliance.measure.tracking import TrackerSettings
from hal.camera.base import Region
from hal.errors import HardwareConfigError

if TYPE_CHECKING:
    from hal.machine.register_map import RegisterMap


def _range(minimum: float | None = None, maximum: float | None = None, **extra: Any) -> dict:
    return {"minimum": minimum, "maximum": maximum, **extra}


@dataclass(frozen=True)
class CameraConfig:
    """[camera]: which camera and how it acquires.

    `exposure_us` and `frame_rate_hz` left out are chosen by the exposure planner
    (`appliance.plan.exposure`) from the test speed and the optics: the longest exposure within
    `blur_budget_px` of motion blur (between `min_exposure_us` and `max_exposure_us`) and a
    frame rate that keeps the frame-to-frame motion of the marks inside the tracker's search,
    and no lower than `min_frame_rate_hz` (the rate the controller receives strain at), unless
    the exposure does not allow it.

    `url` names the camera (`sim://camera`, `aravis://192.168.10.2`, `v4l2:///dev/video0`).
    The sensor region `region_*_px` is given whole or not at all (left out = the full sensor).
    A camera that goes away during a test is waited for up to `outage_timeout_s` while its
    backend reconnects (strain is flagged not valid meanwhile); 0 = the first loss faults.
    """

    url: str = field(default="sim://camera", metadata={"device_url": True})
    exposure_us: float | None = field(default=None, metadata=_range(1.0, 1e7))
    gain_db: float = field(default=0.0, metadata=_range(0.0, 48.0))
    pixel_format: str = field(default="Mono8", metadata={"choices": ("Mono8", "Mono12", "Mono16")})
    region_x_px: int | None = field(default=None, metadata=_range(0, 65535))
    region_y_px: int | None = field(default=None, metadata=_range(0, 65535))
    region_width_px: int | None = field(default=None, metadata=_range(16, 65535))
    region_height_px: int | None = field(default=None, metadata=_range(16, 65535))
    outage_timeout_s: float = field(default=30.0, metadata=_range(0.0, 3600.0))
    frame_rate_hz: float | None = field(default=None, metadata=_range(0.1, 10000.0))
    min_frame_rate_hz: float = field(default=20.0, metadata=_range(0.1, 10000.0))
    blur_budget_px: float = field(default=1.0, metadata=_range(0.0, 100.0))
    min_exposure_us: float = field(default=100.0, metadata=_range(1.0, 1e6))
    max_exposure_us: float = field(default=20000.0, metadata=_range(1.0, 1e6))

    def region(self) -> Region | None:
        """The sensor region of `region_*_px`; None = the full sensor."""
        if self.region_width_px is None or self.region_height_px is None:
            return None
        return Region(
            self.region_x_px or 0,
            self.region_y_px or 0,
            self.region_width_px,
            self.region_height_px,
        )


@dataclass(frozen=True)
class MachineConfig:
    """[machine]: the testing machine's controller.

    `url` names it (`sim://machine`, `modbus-tcp://192.168.10.5:502?unit=1`,
    `modbus-rtu:///dev/ttyUSB0?baud=115200&parity=E`); empty = no controller (strain is
    measured, force and crosshead are missing). A real controller is polled at `poll_rate_hz`
    on its own thread. With `accepts_commands` the appliance starts the crosshead at the test
    speed and stops it at the end; without, it only reads. `[machine.registers]` is the
    controller's register map (`hal.machine.register_map`): `preset` and one table per
    quantity overriding the preset's entry key by key; left out, the generic controller's
    map.
    """

    url: str = field(default="sim://machine", metadata={"device_url": True})
    accepts_commands: bool = True
    poll_rate_hz: float = field(default=100.0, metadata=_range(1.0, 1000.0))
    registers: dict = field(default_factory=dict, metadata={"table": True})


@dataclass(frozen=True)
class TriggerConfig:
    """[trigger]: what starts each exposure.

    `source`: `internal` = the camera free-runs at the planned frame rate; `period` = the
    trigger microcontroller fires the camera at the planned period in its clock ticks;
    `encoder` = it fires every N counts of the crosshead encoder, N the planned
    frame-to-frame travel (`appliance.plan.trigger_plan`). The simulated test has a simulated
    microcontroller on the simulated machine's encoder (`encoder_counts_per_mm`).
    `pulse_width_us` is the trigger pulse's width. `url` names the real microcontroller's
    serial port (a device path or pyserial URL); empty = the simulated one (simulated test
    only). A real camera on its output is triggered on its trigger line (EXTERNAL) and its
    frames are matched to the TRIGGER events and stamped with their times
    (`appliance.devices.trigger_stamping`); in a real-time simulated test it times the simulated
    camera (`appliance.devices.mcu_trigger`).

    While the test runs, exposure and trigger spacing follow the crosshead speed the
    controller reports (`appliance.plan.pacing`): a speed more than `replan_hysteresis`
    (relative) above the one planned for is re-planned at once, one below it after
    `replan_slow_down_s` of slower readings; 0 = keep the plan of the test speed.
    """

    source: str = field(default="internal", metadata={"choices": ("internal", "period", "encoder")})
    replan_hysteresis: float = field(default=0.1, metadata=_range(0.0, 10.0))
    replan_slow_down_s: float = field(default=2.0, metadata=_range(0.0, 3600.0))
    pulse_width_us: float = field(default=60.0, metadata=_range(50.0, 100000.0))
    url: str = ""
    encoder_counts_per_mm: float = field(default=1000.0, metadata=_range(1.0, 1e7))


@dataclass(frozen=True)
class OpticsConfig:
    """[optics]: lens and sensor, for calibration and exposure planning.

    Left out, the simulated test takes its material preset's camera; a real camera needs all
    three.
    """

    focal_length_mm: float | None = field(default=None, metadata=_range(1.0, 1000.0))
    object_distance_mm: float | None = field(default=None, metadata=_range(1.0, 1e5))
    pixel_size_um: float | None = field(default=None, metadata=_range(0.5, 100.0))
    calibration: str = ""


@dataclass(frozen=True)
class GaugeConfig:
    """[gauge]: where the marks are and how long the gauge is.

    Marks are placed centred on the specimen: each axial mark is a line of `points_per_mark`
    points `mark_spacing_px` apart along the axis. `length_mm` left out takes the simulated
    specimen's gauge length; `transverse_width_mm` = 0 means no transverse gauge. The marks
    are centred on (`centre_x_px`, `centre_y_px`) of the reference image along a loading axis
    `axis_deg` degrees from the image's +x towards +y (90 = vertical specimen) when both are
    given; left out, on the parallel length of the specimen detected in the reference image,
    along its axis (`appliance.rig`). `marks = "dots"` (or `"lines"`) measures between two
    dots (lines across the specimen) painted on it instead of the speckle
    (`appliance.measure.painted_marks`): found in the reference image, they are the gauge, and
    `length_mm`, the centre and the points are not used.
    """

    length_mm: float | None = field(default=None, metadata=_range(0.1, 10000.0))
    points_per_mark: int = field(default=3, metadata=_range(1, 50))
    mark_spacing_px: float = field(default=8.0, metadata=_range(0.0, 1000.0))
    transverse_width_mm: float = field(default=0.0, metadata=_range(0.0, 1000.0))
    centre_x_px: float | None = field(default=None, metadata=_range(0.0, 65535.0))
    centre_y_px: float | None = field(default=None, metadata=_range(0.0, 65535.0))
    axis_deg: float = field(default=90.0, metadata=_range(-180.0, 180.0))
    marks: str = field(default="speckle", metadata={"choices": ("speckle", "dots", "lines")})


@dataclass(frozen=True)
class RunConfig:
    """[run]: test speed and when the test ends.

    `speed_mm_min` left out takes the simulated material's standard speed (a real machine needs
    it, for the exposure plan and the start command); `until_strain` = 0 means no strain
    limit.
    """

    speed_mm_min: float | None = field(default=None, metadata=_range(0.001, 10000.0))
    until_strain: float = field(default=0.0, metadata=_range(0.0, 100.0))
    until_break: bool = True


@dataclass(frozen=True)
class TransverseConfig:
    """[transverse]: the specimen's width from its edges, at stations between the axial marks.

    `stations` = N measures the width in every frame at N stations along the gauge (at the
    fractions 1/(N+1) ... N/(N+1) of the distance between the marks), each kept and their mean,
    and from it the transverse strain, Poisson's ratio and, for a metal, the plastic strain
    ratio r; 0 = no width measured.
    """

    stations: int = field(default=0, metadata=_range(0, 32))


@dataclass(frozen=True)
class SimConfig:
    """[sim]: the simulated world (used by sim:// devices only).

    `camera_hang_after_s` > 0 makes the simulated camera hang that long after the start of a
    test, as a hung driver would (fault injection for the watchdog); 0 = never.
    `speed_change_after_s` > 0 makes the simulated controller change the crosshead speed to
    `speed_change_mm_min` that long after the start, as a two-speed test program does (the
    appliance re-plans exposure and triggers from the speed it reads); 0 = one speed.
    `controller = "modbus-tcp"` serves the simulated machine on a Modbus TCP server on
    127.0.0.1 (a free port, the generic register map) and reads it through the appliance's
    Modbus client and poller, as a real controller is read (`appliance.sim.controller_server`);
    `direct` reads it in-process.
    `bench` sets the simulated bench's error sources together (`appliance.sim.bench`): `ideal`
    (telecentric, nothing else), `typical` (a careful lab) or `harsh`; each of the keys from
    `lens` on that is set (not None) replaces the bench's value. Distortion coefficients are
    OpenCV's, in the normalised units of a pinhole at the object distance whatever the lens.
    """

    material: str = field(default="rubber", metadata={"choices": ("rubber", "metal")})
    seed: int = field(default=1, metadata=_range(0, 2**31 - 1))
    realtime: bool = False
    sensor_width_px: int | None = field(default=None, metadata=_range(64, 8192))
    sensor_height_px: int | None = field(default=None, metadata=_range(64, 8192))
    read_noise_grey: float = field(default=0.5, metadata=_range(0.0, 50.0))
    electrons_per_grey: float = field(default=40.0, metadata=_range(0.0, 1e6))
    camera_hang_after_s: float = field(default=0.0, metadata=_range(0.0, 1e6))
    controller: str = field(default="direct", metadata={"choices": ("direct", "modbus-tcp")})
    speed_change_after_s: float = field(default=0.0, metadata=_range(0.0, 1e6))
    speed_change_mm_min: float = field(default=0.0, metadata=_range(0.0, 10000.0))
    bench: str = field(default="ideal", metadata={"choices": ("ideal", "typical", "harsh")})
    lens: str | None = field(default=None, metadata={"choices": ("telecentric", "entocentric")})
    lens_k1: float | None = field(default=None, metadata=_range(-1.0, 1.0))
    lens_k2: float | None = field(default=None, metadata=_range(-1.0, 1.0))
    lens_p1: float | None = field(default=None, metadata=_range(-0.05, 0.05))
    lens_p2: float | None = field(default=None, metadata=_range(-0.05, 0.05))
    camera_tilt_deg: float | None = field(default=None, metadata=_range(0.0, 10.0))
    thinning_out_of_plane: bool | None = None
    slack_out_of_plane_mm: float | None = field(default=None, metadata=_range(-5.0, 5.0))
    flicker_percent: float | None = field(default=None, metadata=_range(0.0, 20.0))
    mains_frequency_hz: float = field(default=50.0, metadata=_range(45.0, 65.0))
    vibration_px_rms: float | None = field(default=None, metadata=_range(0.0, 5.0))
    vibration_frequency_hz: float | None = field(default=None, metadata=_range(0.1, 1000.0))
    warm_up_drift_percent: float | None = field(default=None, metadata=_range(-1.0, 1.0))
    warm_up_time_constant_s: float | None = field(default=None, metadata=_range(1.0, 1e5))
    painted_marks: str = field(default="none", metadata={"choices": ("none", "dots", "lines")})


@dataclass(frozen=True)
class SpecimenConfig:
    """[specimen]: what the test's results (`appliance.results`) need of the specimen.

    `material` names the standard the results follow: `metal` (ISO 6892-1: modulus, Rp0.2,
    ReH/ReL, Rm, Ag, A) or `rubber` (ISO 37: TS, Eb, stresses at 100/200/300 %); left out, a
    simulated test takes its `[sim] material` and a real one gives no results. The original
    cross-section S0 is `width_mm` x `thickness_mm` (a flat specimen or a dumbbell) or the
    circle of `diameter_mm` (a round one); left out, a simulated test takes its preset
    specimen's nominal dimensions (its test specification) and a real one gives no stresses.
    """

    material: str | None = field(default=None, metadata={"choices": ("metal", "rubber")})
    width_mm: float | None = field(default=None, metadata=_range(0.001, 10000.0))
    thickness_mm: float | None = field(default=None, metadata=_range(0.001, 10000.0))
    diameter_mm: float | None = field(default=None, metadata=_range(0.001, 10000.0))

    def __post_init__(self) -> None:
        flat = (self.width_mm is not None, self.thickness_mm is not None)
        if self.diameter_mm is not None and any(flat):
            raise ValueError("diameter_mm: give either diameter_mm or width_mm and thickness_mm")
        if flat[0] != flat[1]:
            missing = "thickness_mm" if flat[0] else "width_mm"
            raise ValueError(f"{missing}: missing (width_mm and thickness_mm go together)")


@dataclass(frozen=True)
class RecordConfig:
    """[record]: the MCAP recording of every test (`appliance.recording.writer`).

    `path` empty: `run` records only with `--record`, `serve` writes a timestamped file per
    test into the service's state directory. The tracker's windows of every frame are always
    recorded (they make the replay exact); full frames at `full_frame_rate_hz` (0 = only the
    reference). Records wait at most `flush_interval_s` in memory: a chunk is closed and the
    file flushed (and synced with `fsync`) at least that often, which bounds what a crash can
    lose. When the disk falls behind by `backlog_mb`, full frames are recorded at a lower rate
    (the degradation is recorded and reported); every other record is always written.
    """

    path: str = ""
    full_frame_rate_hz: float = field(default=2.0, metadata=_range(0.0, 1000.0))
    flush_interval_s: float = field(default=1.0, metadata=_range(0.01, 60.0))
    chunk_size_kb: int = field(default=4096, metadata=_range(16, 262144))
    fsync: bool = True
    backlog_mb: float = field(default=64.0, metadata=_range(1.0, 16384.0))


@dataclass(frozen=True)
class StorageConfig:
    """[storage]: room on disk for a test's files (`appliance.run.disk_space`).

    A test does not start while a directory it writes to (the output directory of `run`, the
    recording's, the service's state directory) has less than `min_free_mb` free. While it
    runs, `reserve_mb` is held beside its strain file and released when the disk is full, so
    that the test ends as a fault with every sample measured in the strain file and its
    summary written; 0 = no reserve.
    """

    min_free_mb: float = field(default=1000.0, metadata=_range(0.0, 1e9))
    reserve_mb: float = field(default=4.0, metadata=_range(0.0, 1e6))


@dataclass(frozen=True)
class ModbusConfig:
    """[modbus]: the strain server for the machine controller (`appliance.live.modbus_server`).

    `tcp` is "HOST:PORT" to listen on (empty = no TCP server; bind 127.0.0.1 unless the
    controller is on another host), `rtu_device` a serial device for Modbus RTU (empty = no
    RTU server); both may run at once with one register map. Floats are 32-bit in `big`
    word order (ABCD: high word first) or `little` (CDAB). `allow_write_from` lists the
    client IP addresses whose writes are accepted (empty = any client; RTU has no address
    and is allowed whenever the list is empty). At most `max_connections` TCP connections
    are open at once (a new one beyond it drops the oldest idle one), and a TCP connection
    that sends no complete request for `idle_timeout_s` is closed.
    """

    tcp: str = field(default="", metadata={"address": True})
    rtu_device: str = ""
    rtu_baud: int = field(default=115200, metadata=_range(300, 4000000))
    rtu_parity: str = field(default="N", metadata={"choices": ("N", "E", "O")})
    rtu_stop_bits: int = field(default=1, metadata=_range(1, 2))
    unit_id: int = field(default=1, metadata=_range(1, 247))
    word_order: str = field(default="big", metadata={"choices": ("big", "little")})
    allow_write_from: tuple[str, ...] = ()
    max_connections: int = field(default=16, metadata=_range(1, 1024))
    idle_timeout_s: float = field(default=60.0, metadata=_range(0.1, 86400.0))


@dataclass(frozen=True)
class RerunConfig:
    """[rerun]: live monitoring in a Rerun viewer (`appliance.live.viewer`).

    Any of three sinks: `serve` = "HOST:PORT" of a gRPC server remote viewers connect to (HOST
    an IP address: no name is looked up), `connect` = the URL of a viewer to push to
    (`rerun+http://HOST:PORT/proxy`), `save` = an .rrd file (`{test}` in the path becomes the
    test id, one file per test; without it each test replaces the file). Images go at
    `image_rate_hz`, scaled by `image_scale`; the viewer has a queue of `queue_size` samples
    and drops (and counts) what does not fit, so it never slows the measurement. The server
    keeps at most `history_mb` of what it relayed, for viewers that connect late (the oldest
    goes first; each test's facts stay): the service's memory for the viewer is bounded by it.
    """

    serve: str = field(default="", metadata={"address": True})
    connect: str = ""
    save: str = ""
    image_rate_hz: float = field(default=2.0, metadata=_range(0.0, 1000.0))
    image_scale: float = field(default=0.5, metadata=_range(0.05, 1.0))
    queue_size: int = field(default=64, metadata=_range(1, 100000))
    history_mb: float = field(default=64.0, metadata=_range(1.0, 65536.0))


@dataclass(frozen=True)
class ServiceConfig:
    """[service]: `extensometer serve`, the appliance as a long-running service.

    Every test's files (recording, strain file, summary) go to `state_directory` (systemd's
    $STATE_DIRECTORY wins when set). `start`: `command` waits for the controller's start
    command (Modbus), `auto` also starts one test as soon as the service is up. Before each
    test the oldest tests' files in the state directory are deleted while all of them together
    exceed `max_state_mb` (`appliance.recording.retention`); 0 = keep everything.
    """

    state_directory: str = "/var/lib/extensometer"
    start: str = field(default="command", metadata={"choices": ("command", "auto")})
    max_state_mb: float = field(default=20000.0, metadata=_range(0.0, 1e9))


@dataclass(frozen=True)
class Config:
    """The whole configuration."""

    camera: CameraConfig = field(default_factory=CameraConfig)
    machine: MachineConfig = field(default_factory=MachineConfig)
    trigger: TriggerConfig = field(default_factory=TriggerConfig)
    optics: OpticsConfig = field(default_factory=OpticsConfig)
    tracking: TrackerSettings = field(default_factory=TrackerSettings)
    gauge: GaugeConfig = field(default_factory=GaugeConfig)
    run: RunConfig = field(default_factory=RunConfig)
    specimen: SpecimenConfig = field(default_factory=SpecimenConfig)
    transverse: TransverseConfig = field(default_factory=TransverseConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    record: RecordConfig = field(default_factory=RecordConfig)
    storage: StorageConfig = field(default_factory=StorageConfig)
    modbus: ModbusConfig = field(default_factory=ModbusConfig)
    rerun: RerunConfig = field(default_factory=RerunConfig)
    service: ServiceConfig = field(default_factory=ServiceConfig)


def parse_address(text: str, where: str) -> tuple[str, int]:
    """Split "HOST:PORT" (IPv6 as "[::1]:PORT"); raises InputError naming `where`."""
    host, sep, port = text.rpartition(":")
    host = host.removeprefix("[").removesuffix("]")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise InputError(f"{where}: must be HOST:PORT with a port in 1..65535, got {text!r}")
    return host, int(port)


def _check_value(value: Any, kind: Any, meta: dict, where: str) -> Any:
    if meta.get("table"):
        if not isinstance(value, dict):
            raise InputError(f"{where}: must be a table")
        return value
    if typing.get_origin(kind) is tuple:
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise InputError(f"{where}: must be a list of strings, got {value!r}")
        return tuple(value)
    if kind is bool:
        if not isinstance(value, bool):
            raise InputError(f"{where}: must be true or false, got {value!r}")
        return value
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise InputError(f"{where}: must be an integer, got {value!r}")
    elif kind is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise InputError(f"{where}: must be a number, got {value!r}")
        value = float(value)
        if not math.isfinite(value):
            raise InputError(f"{where}: must be finite, got {value!r}")
    elif kind is str:
        if not isinstance(value, str):
            raise InputError(f"{where}: must be a string, got {value!r}")
    choices = meta.get("choices")
    if choices is not None and value not in choices:
        raise InputError(f"{where}: must be one of {', '.join(choices)}, got {value!r}")
    minimum, maximum = meta.get("minimum"), meta.get("maximum")
    if minimum is not None and value < minimum:
        raise InputError(f"{where}: must be >= {minimum:g}, got {value!r}")
    if maximum is not None and value > maximum:
        raise InputError(f"{where}: must be <= {maximum:g}, got {value!r}")
    if meta.get("odd") and value % 2 == 0:
        raise InputError(f"{where}: must be odd, got {value!r}")
    if meta.get("address") and value:
        parse_address(value, where)
    if meta.get("device_url") and value.startswith("sim://") and ("?" in value or "#" in value):
        raise InputError(
            f"{where}: {value!r}: a simulated device takes no options in its URL "
            "(the simulated world is set in [sim])"
        )
    return value


def _build(cls: type, table: dict, source: str, section: str | None) -> Any:
    fields = _keys_of(cls)
    values = {}
    for key, value in table.items():
        where = f"{source}: [{section}] {key}" if section else f"{source}: [{key}]"
        if key not in fields:
            known = ", ".join(fields)
            label = f"{source}: [{section}]" if section else source
            raise InputError(f"{label}: unknown key {key!r} (known: {known})")
        values[key] = _field_value(cls, fields[key], value, where, source)
    if section is not None:
        _check_relations(section, fields, values, source)
    try:
        return cls(**values)
    except ValueError as exc:
        raise InputError(f"{source}: [{section}]: {exc}") from None


def _keys_of(cls: type) -> dict[str, dataclasses.Field]:
    """The keys of a table class: its configurable fields by name."""
    return {f.name: f for f in dataclasses.fields(cls) if f.metadata.get("configurable", True)}


def _field_value(cls: type, f: dataclasses.Field, value: Any, where: str, source: str) -> Any:
    """`value` checked for field `f` of table class `cls`; errors start with `where`."""
    kind = typing.get_type_hints(cls)[f.name]
    if dataclasses.is_dataclass(kind):
        if not isinstance(value, dict):
            raise InputError(f"{where}: must be a table")
        return _build(kind, value, source, f.name)
    if isinstance(kind, types.UnionType):
        kind = next(k for k in typing.get_args(kind) if k is not type(None))
    return _check_value(value, kind, dict(f.metadata), where)


@dataclass(frozen=True)
class Override:
    """One configuration key set from outside a file, a command-line option say.

    Attributes:
        option: how the user spelled it (`--speed-mm-min`): errors name it.
        table, key: the key it sets (`run`, `speed_mm_min`).
        value: the value, checked as the file's would be.
    """

    option: str
    table: str
    key: str
    value: Any


def with_overrides(config: Config, overrides: Sequence[Override]) -> Config:
    """`config` with the overrides' keys set: each value checked as in a file, the error
    naming its option (`--modbus-tcp: must be HOST:PORT ...`); then the whole configuration
    checked again (a relation between keys names both keys).

    Raises:
        InputError: one line naming the option or the keys at fault.
    """
    tables = config_to_table(config)
    for override in overrides:
        cls = type(getattr(config, override.table))
        f = _keys_of(cls)[override.key]
        value = _field_value(cls, f, override.value, override.option, override.option)
        tables = merge_tables(tables, {override.table: {override.key: value}})
    return config_from_table(tables, "command line")


def parse_config(text: str, source: str = "<config>") -> Config:
    """Validate a configuration given as TOML text; `source` names it in errors."""
    try:
        table = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{source}: invalid TOML: {exc}") from None
    return config_from_table(table, source)


_RELATIONS = (
    ("tracking", "min_subset_px", "subset_px"),
    ("tracking", "search_radius_px", "reacquire_radius_px"),
    ("tracking", "min_zncc", "update_zncc"),
    ("camera", "min_exposure_us", "max_exposure_us"),
    ("storage", "reserve_mb", "min_free_mb"),
)
"""(table, key, other key): the value of key may not exceed that of the other key."""


def _check_relations(
    section: str, fields: dict[str, dataclasses.Field], values: dict[str, Any], source: str
) -> None:
    for table, key, upper in _RELATIONS:
        if table != section:
            continue
        value = values.get(key, fields[key].default)
        limit = values.get(upper, fields[upper].default)
        if value > limit:
            raise InputError(
                f"{source}: [{section}] {key}: must be <= {upper} ({limit:g}), got {value:g}"
            )


def config_to_table(config: Config) -> dict[str, dict[str, Any]]:
    """The configuration as nested plain tables (keys left out where the value is "not set"),
    which `config_from_table` turns back into the same configuration."""

    def table(value: Any) -> Any:
        if dataclasses.is_dataclass(value):
            return {
                f.name: table(getattr(value, f.name))
                for f in dataclasses.fields(value)
                if getattr(value, f.name) is not None and f.metadata.get("configurable", True)
            }
        if isinstance(value, tuple):
            return list(value)
        return value

    return table(config)


def config_from_table(table: dict[str, Any], source: str = "<config>") -> Config:
    """Validate a configuration given as nested tables (as TOML or JSON would give them)."""
    if not isinstance(table, dict):
        raise InputError(f"{source}: a configuration must be a table")
    config = _build(Config, table, source, None)
    _check_region(config, source)
    if config.machine.registers:
        register_map_of(config, source)
    return config


def _check_region(config: Config, source: str) -> None:
    c = config.camera
    keys = ("region_x_px", "region_y_px", "region_width_px", "region_height_px")
    given = [getattr(c, k) is not None for k in keys]
    if any(given) and not all(given):
        missing = keys[given.index(False)]
        raise InputError(f"{source}: [camera] {missing}: required with the other region keys")


def register_map_of(config: Config, source: str = "<config>") -> RegisterMap:
    """The controller register map of `[machine.registers]`; the generic controller's
    (`hal.machine.register_map.GENERIC_CONTROLLER`) when the table is left out.

    Raises InputError naming the file, the register table and the key.
    """
    from hal.machine.register_map import GENERIC_CONTROLLER, RegisterMap

    if not config.machine.registers:
        return GENERIC_CONTROLLER
    try:
        return RegisterMap.from_table(config.machine.registers, f"{source}: [machine.registers]")
    except HardwareConfigError as exc:
        raise InputError(str(exc)) from None


def merge_tables(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    """`base` with every key of `override` replaced, table by table."""
    merged = dict(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = merge_tables(merged[key], value)
        else:
            merged[key] = value
    return merged


def read_config_table(path: str | Path) -> dict[str, Any]:
    """The tables of a TOML file, unvalidated. Raises InputError naming the file."""
    path = Path(path)
    try:
        return tomllib.loads(read_user_text(path, "configuration file"))
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{path}: invalid TOML: {exc}") from None


def load_config(path: str | Path) -> Config:
    """Read and validate a configuration file. Raises InputError naming file and key."""
    path = Path(path)
    return parse_config(read_user_text(path, "configuration file"), str(path))
