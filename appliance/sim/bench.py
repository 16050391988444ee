"""The simulated bench's error sources: the `[sim] bench` presets and the keys that override them.

A bench is what stands between the specimen and the sensor besides the thin-lens optics: the
kind of lens and its distortion, the camera's tilt, the specimen surface's moves along the
optical axis (thinning, slack take-up), the lighting's flicker, the camera's vibration and its
warm-up drift. Three presets (`BENCHES`):

* ``ideal``: the world the simulator had before it knew of any of them (telecentric, no
  distortion, no tilt, nothing else): its images are bit-identical to it.
* ``typical``: a careful lab: an entocentric lens at the optics' object distance with about
  1 % barrel distortion in the image corners, 0.5 deg tilt, the surface receding as the
  specimen thins and 0.1 mm of slack take-up over the first millimetre of crosshead travel,
  1.5 % flicker at twice the mains frequency, 0.05 px RMS vibration, 0.005 % warm-up drift
  (a warmed-up camera's remainder).
* ``harsh``: a poor bench: 2 % distortion, 2 deg tilt, 0.3 mm slack, 5 % flicker, 0.2 px
  vibration, 0.05 % drift.

Distortion is given in the presets as the radial distortion at the image corners; the
coefficients follow from the lens: with r_c the corner's normalised radius (half the sensor
diagonal over the focal length in pixels), ``k1 = D / (r_c^2 - r_c^4 / 4)``, ``k2 = -k1 / 4``
(so that ``k1 r_c^2 + k2 r_c^4 = D``), and small decentring ``p1 = 0.05 D / r_c``,
``p2 = -0.03 D / r_c``. Every `[sim]` key that is set replaces the preset's value.

Coefficients are in the normalised units of a pinhole at the object distance whatever the
lens: a telecentric lens with the same coefficients displaces every pixel as much (see
`appliance.sim.lens`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from appliance.config import SimConfig
from appliance.optics.camera_model import LensDistortion


@dataclass(frozen=True)
class BenchPreset:
    """One row of the bench table.

    Attributes:
        lens: "telecentric" or "entocentric".
        corner_distortion_percent: radial distortion at the image corners, % of the radius
            (negative = barrel).
        camera_tilt_deg: tilt of the camera's axis from the specimen's normal, deg.
        thinning_out_of_plane: the surface recedes as the specimen thins.
        slack_out_of_plane_mm: out-of-plane move while the slack is taken up, mm (positive
            = away from the camera).
        flicker_percent: peak illumination flicker at twice the mains frequency, %.
        vibration_px_rms: RMS image shift from camera vibration, px.
        vibration_frequency_hz: its frequency, Hz.
        warm_up_drift_percent: image scale drift over the warm-up, %.
        warm_up_time_constant_s: the warm-up's time constant, s.
    """

    lens: str
    corner_distortion_percent: float
    camera_tilt_deg: float
    thinning_out_of_plane: bool
    slack_out_of_plane_mm: float
    flicker_percent: float
    vibration_px_rms: float
    vibration_frequency_hz: float
    warm_up_drift_percent: float
    warm_up_time_constant_s: float


BENCHES: dict[str, BenchPreset] = {
    "ideal": BenchPreset("telecentric", 0.0, 0.0, False, 0.0, 0.0, 0.0, 17.0, 0.0, 600.0),
    "typical": BenchPreset("entocentric", -1.0, 0.5, True, 0.1, 1.5, 0.05, 17.0, 0.005, 600.0),
    "harsh": BenchPreset("entocentric", -2.0, 2.0, True, 0.3, 5.0, 0.2, 23.0, 0.05, 900.0),
}
"""The `[sim] bench` presets."""

SLACK_TRAVEL_MM = 1.0
"""Crosshead travel over which the slack is taken up, mm."""


@dataclass(frozen=True)
class BenchErrors:
    """The error sources of one simulated bench, resolved from a preset and the `[sim]` keys.

    Attributes:
        name: the preset's name.
        entocentric: a pinhole lens (perspective) rather than a telecentric one.
        distortion: Brown-Conrady coefficients in normalised pinhole units.
        camera_tilt_deg: tilt of the camera's axis from the specimen's normal, deg (about the
            image's x axis: the perspective runs along the specimen).
        thinning_out_of_plane: the surface recedes by half the thickness change.
        slack_out_of_plane_mm: the surface's move over the slack take-up, mm.
        flicker_percent: peak flicker, %.
        mains_frequency_hz: mains frequency, Hz (the flicker is at twice it).
        vibration_px_rms: RMS image shift, px.
        vibration_frequency_hz: its frequency, Hz.
        warm_up_drift_percent: image scale drift over the warm-up, %.
        warm_up_time_constant_s: the warm-up's time constant, s.
    """

    name: str
    entocentric: bool
    distortion: LensDistortion
    camera_tilt_deg: float
    thinning_out_of_plane: bool
    slack_out_of_plane_mm: float
    flicker_percent: float
    mains_frequency_hz: float
    vibration_px_rms: float
    vibration_frequency_hz: float
    warm_up_drift_percent: float
    warm_up_time_constant_s: float

    @property
    def is_ideal(self) -> bool:
        """True when nothing differs from the telecentric, distortion-free world."""
        return (
            not self.entocentric
            and self.distortion.is_zero
            and self.camera_tilt_deg == 0.0
            and self.slack_out_of_plane_mm == 0.0
            and self.flicker_percent == 0.0
            and self.vibration_px_rms == 0.0
            and self.warm_up_drift_percent == 0.0
        )

    @property
    def needs_remap(self) -> bool:
        """True when the sensor image is not an affine view of the object plane."""
        return not self.distortion.is_zero or self.camera_tilt_deg != 0.0


def corner_radius(sensor_size: tuple[int, int], focal_px: float) -> float:
    """Normalised radius of the image corners: half the sensor diagonal over the focal
    length, both px."""
    width, height = sensor_size
    return 0.5 * math.hypot(width - 1, height - 1) / focal_px


def distortion_for_corner(corner_fraction: float, corner_radius_norm: float) -> LensDistortion:
    """Coefficients giving radial distortion `corner_fraction` (of the radius) at normalised
    radius `corner_radius_norm` (see the module docstring)."""
    if corner_fraction == 0.0:
        return LensDistortion()
    r2 = corner_radius_norm**2
    k1 = corner_fraction / (r2 - 0.25 * r2 * r2)
    return LensDistortion(
        k1=k1,
        k2=-0.25 * k1,
        p1=0.05 * corner_fraction / corner_radius_norm,
        p2=-0.03 * corner_fraction / corner_radius_norm,
    )


def bench_errors(sim: SimConfig, sensor_size: tuple[int, int], focal_px: float) -> BenchErrors:
    """The bench of a `[sim]` table: its preset, each key that is set replacing the preset's.

    Args:
        sim: the `[sim]` table.
        sensor_size: (width, height), px.
        focal_px: focal length of the pinhole equivalent of the optics, px (object distance
            over the object-plane scale).
    """
    preset = BENCHES[sim.bench]

    def pick(key: str, default: object) -> object:
        value = getattr(sim, key)
        return default if value is None else value

    fallback = distortion_for_corner(
        preset.corner_distortion_percent / 100.0, corner_radius(sensor_size, focal_px)
    )
    distortion = LensDistortion(
        k1=float(pick("lens_k1", fallback.k1)),
        k2=float(pick("lens_k2", fallback.k2)),
        p1=float(pick("lens_p1", fallback.p1)),
        p2=float(pick("lens_p2", fallback.p2)),
    )
    return BenchErrors(
        name=sim.bench,
        entocentric=pick("lens", preset.lens) == "entocentric",
        distortion=distortion,
        camera_tilt_deg=float(pick("camera_tilt_deg", preset.camera_tilt_deg)),
        thinning_out_of_plane=bool(pick("thinning_out_of_plane", preset.thinning_out_of_plane)),
        slack_out_of_plane_mm=float(pick("slack_out_of_plane_mm", preset.slack_out_of_plane_mm)),
        flicker_percent=float(pick("flicker_percent", preset.flicker_percent)),
        mains_frequency_hz=float(sim.mains_frequency_hz),
        vibration_px_rms=float(pick("vibration_px_rms", preset.vibration_px_rms)),
        vibration_frequency_hz=float(pick("vibration_frequency_hz", preset.vibration_frequency_hz)),
        warm_up_drift_percent=float(pick("warm_up_drift_percent", preset.warm_up_drift_percent)),
        warm_up_time_constant_s=float(
            pick("warm_up_time_constant_s", preset.warm_up_time_constant_s)
        ),
    )
