"""Measuring in the object plane: the configured camera calibration, and what it says.

`[optics] calibration = "FILE"` names a calibration written by `extensometer calibrate`
(`appliance.optics.calibration_file`). A test then measures gauge lengths in mm on the
specimen plane through the calibration's lens model (`appliance.measure.gauges`); without one
it measures by the nominal scale of the thin-lens optics (`appliance.plan.optics`).

The file's path is taken relative to the directory of the configuration file that names it
(`resolved_calibration_path`, applied by every command that reads a configuration file), so a
configuration and its calibration can be moved together; an absolute path is kept.

Out of plane: a specimen surface that moves by dz along the optical axis after the reference
(slack taken up, the specimen thinning, the grips settling) changes the magnification of an
entocentric (pinhole) lens by Z / (Z - dz), so every length, the gauge length included, reads
longer by the factor 1 + dz / Z: a false strain of dz / Z at a stand-off Z, whatever the
calibration. A telecentric lens has none. `out_of_plane_bound` states it for `plan` and the
summary, with the best ISO 9513 class the bias leaves at 1 % strain. Z is the calibration's:
the distance from the centre of projection to the calibrated plane (along its normal, from the
plane's translation); without a calibration, `[optics] object_distance_mm`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from appliance.config import Config
from appliance.errors import InputError
from appliance.measure.gauges import Calibration
from appliance.optics.calibration_file import CameraCalibration, load_calibration
from appliance.plan.optics import Optics
from appliance.run.iso9513 import best_class

OUT_OF_PLANE_MM = 0.1
"""The out-of-plane motion the plan and the summary state the false strain of, mm."""
STRAIN_FOR_CLASS = 0.01
"""The strain at which the false strain's ISO 9513 class is stated."""


def resolved_calibration_path(config: Config, config_file: Path | None) -> Config:
    """`config` with a relative `[optics] calibration` made relative to the directory of
    `config_file` (the file the configuration was read from; None = the working directory,
    the path is kept as it is)."""
    name = config.optics.calibration
    if not name or config_file is None or Path(name).is_absolute():
        return config
    path = str(Path(config_file).parent / name)
    return dataclasses.replace(config, optics=dataclasses.replace(config.optics, calibration=path))


def configured_calibration(
    config: Config, optics: Optics, sensor_size: tuple[int, int] | None = None
) -> Calibration:
    """What a test measures with: the calibration file of `[optics] calibration`, in the
    object plane; without one, the nominal scale of `optics`.

    Args:
        config: the configuration (its calibration path already resolved).
        optics: the configured (or simulated) thin-lens optics.
        sensor_size: (width, height) px of the images the test will take, when known; a
            calibration made for another size is refused.

    Raises:
        InputError: "[optics] calibration: FILE: why" for a file that is unreadable, foreign,
            altered, or made for another sensor size or region.
    """
    calibration = calibration_file(config, sensor_size)
    if calibration is not None:
        return calibration
    return Calibration.from_optics(optics.pixel_size_um, optics.magnification)


def calibration_file(
    config: Config, sensor_size: tuple[int, int] | None = None
) -> Calibration | None:
    """The object-plane calibration of `[optics] calibration`; None when it names no file.

    Raises:
        InputError: as `configured_calibration`.
    """
    name = config.optics.calibration
    if not name:
        return None
    try:
        camera = load_calibration(Path(name), sensor_size=sensor_size)
    except InputError as exc:
        raise InputError(f"[optics] calibration: {exc}") from None
    return Calibration.object_plane(camera, name)


def image_size(config: Config, sensor_size: tuple[int, int] | None) -> tuple[int, int] | None:
    """(width, height) px of the images a test will take, when known before the camera opens:
    the configured sensor region's, else `sensor_size` (a simulated camera's sensor); None
    for a real camera's full sensor (checked on the reference frame, `check_image_size`)."""
    region = config.camera.region()
    if region is not None:
        return (region.width, region.height)
    if sensor_size is not None:
        return (int(sensor_size[0]), int(sensor_size[1]))
    return None


def check_image_size(calibration: Calibration, width_px: int, height_px: int) -> None:
    """Refuse images of another size than the calibration's sensor (one line naming the file).

    Raises:
        InputError: the calibration was made for another sensor size or region.
    """
    camera = calibration.camera
    if camera is None or camera.camera.sensor_size == (width_px, height_px):
        return
    made = "x".join(str(v) for v in camera.camera.sensor_size)
    raise InputError(
        f"[optics] calibration: {calibration.file}: calibration made for a {made} px sensor, "
        f"the images are {width_px}x{height_px} px (calibrate the camera with the region it "
        "measures with)"
    )


@dataclass(frozen=True)
class OutOfPlaneBound:
    """The false strain an out-of-plane motion causes at the camera's stand-off.

    Attributes:
        motion_mm: the out-of-plane motion dz, mm.
        stand_off_mm: Z, mm; None for a telecentric lens.
        stand_off_from: where Z comes from ("calibration", "[optics] object_distance_mm",
            or "telecentric lens").
        false_strain: dz / Z (0 for a telecentric lens).
        iso9513_class_at_1_percent: the best ISO 9513 class whose bias limits the false
            strain leaves at 1 % strain over the gauge length (None: no class).
    """

    motion_mm: float
    stand_off_mm: float | None
    stand_off_from: str
    false_strain: float
    iso9513_class_at_1_percent: str | None

    def facts(self) -> dict[str, Any]:
        """The bound as summary facts."""
        return {
            "out_of_plane_motion_mm": self.motion_mm,
            "out_of_plane_false_strain": self.false_strain,
            "out_of_plane_stand_off_mm": self.stand_off_mm,
            "out_of_plane_stand_off_from": self.stand_off_from,
            "out_of_plane_iso9513_class_at_1_percent": self.iso9513_class_at_1_percent,
        }

    def describe(self) -> str:
        """One line: the false strain, where Z comes from, and the class it allows."""
        if self.stand_off_mm is None:
            return f"{self.motion_mm:g} mm out of plane: no false strain (telecentric lens)"
        allowed = self.iso9513_class_at_1_percent or "none"
        return (
            f"{self.motion_mm:g} mm out of plane: false strain {self.false_strain:.3g} "
            f"(dz / Z, Z = {self.stand_off_mm:.1f} mm from {self.stand_off_from}); "
            f"ISO 9513 class at 1 % strain: {allowed}"
        )


def stand_off(
    calibration: CameraCalibration | None, object_distance_mm: float
) -> tuple[float | None, str]:
    """(Z mm, where it comes from): the calibrated plane's distance from the centre of
    projection along its normal; without a calibration the thin-lens object distance; None
    for a telecentric lens."""
    if calibration is None:
        return object_distance_mm, "[optics] object_distance_mm"
    if calibration.camera.telecentric:
        return None, "telecentric lens"
    normal = calibration.plane.rotation[:, 2]
    return abs(float(np.dot(normal, calibration.plane.translation))), "calibration"


def out_of_plane_bound(
    calibration: Calibration,
    object_distance_mm: float,
    gauge_length_mm: float,
    motion_mm: float = OUT_OF_PLANE_MM,
    *,
    object_distance_from: str = "[optics] object_distance_mm",
) -> OutOfPlaneBound:
    """The false strain `motion_mm` out of plane causes, and the ISO 9513 class its bias
    leaves at 1 % strain over `gauge_length_mm` (the measured elongation reads
    (1 + e)(1 + dz / Z) - 1 of L0 for a true strain e); `object_distance_mm` is the thin-lens
    stand-off, used without a calibration (`object_distance_from` names where it was given)."""
    z, source = stand_off(calibration.camera, object_distance_mm)
    if calibration.camera is None:
        source = object_distance_from
    false_strain = 0.0 if z is None else motion_mm / z
    true_um = STRAIN_FOR_CLASS * gauge_length_mm * 1e3
    measured_um = ((1 + STRAIN_FOR_CLASS) * (1 + false_strain) - 1) * gauge_length_mm * 1e3
    allowed = best_class([measured_um], [true_um]) if math.isfinite(measured_um) else None
    return OutOfPlaneBound(motion_mm, z, source, false_strain, allowed)


def measurement_facts(
    calibration: Calibration, optics: Optics, gauge_length_mm: float
) -> dict[str, Any]:
    """A test's facts of how it measures: `calibration_facts`, the thin-lens scale when
    measured in the object plane (`nominal_scale_mm_per_px`), the thin-lens stand-off
    (`object_distance_mm`) and the out-of-plane bound over `gauge_length_mm`."""
    nominal = {"nominal_scale_mm_per_px": optics.scale_mm_per_px}
    return {
        **calibration_facts(calibration),
        **(nominal if calibration.in_object_plane else {}),
        "object_distance_mm": optics.object_distance_mm,
        **out_of_plane_bound(calibration, optics.object_distance_mm, gauge_length_mm).facts(),
    }


def calibration_facts(calibration: Calibration) -> dict[str, Any]:
    """What the summary and the recording say of the calibration: its file, its checksum,
    and whether the test was measured in the object plane or by nominal scale."""
    return {
        "measured_in": "object plane" if calibration.in_object_plane else "nominal scale",
        "calibration_file": calibration.file or None,
        "calibration_checksum": calibration.checksum or None,
    }
