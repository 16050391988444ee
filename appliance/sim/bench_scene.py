"""What the simulated camera sees through a real bench: lens, out-of-plane moves, flicker,
vibration and warm-up drift (`appliance.sim.lens` for the geometry).

`BenchScene` is a `SpecimenScene` whose sensor looks through a `BenchGeometry`. A frame is
rendered in two steps:

1. the ideal grid (an undistorted pinhole view square to the specimen, at the optics' scale),
   over the bounding box of the ideal-grid points the sensor region sees plus a margin, time
   sample by time sample with that sample's out-of-plane magnification (row by row: thinning
   follows the local strain), vibration shift and drift. The renderer is the plain scene's,
   separable by rows and columns;
2. when the lens distorts or the camera is tilted, a fixed remap (float32 maps) from the ideal
   grid to the sensor region by cubic B-spline interpolation (`appliance.dic.bspline`); then
   the flicker's factor.

The remap is a B-spline rather than OpenCV's bicubic `cv2.remap`: on the 2 px speckle of the
presets the bicubic kernel's phase-dependent bias moved imaged points by up to 0.04 px (a
simulator artefact a correlator reads as displacement), the B-spline's by under 0.01 px.

The truth follows the same path: `image_positions` maps material points to the ideal grid at
every time sample and through the lens to the sensor, and averages; `object_positions` gives
the exposure-averaged object-plane points, mm, that the true strain is measured between.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

import numba
import numpy as np
import numpy.typing as npt

from appliance.dic.bspline import PAD, interpolate, spline_coefficients
from appliance.sim.deformation import AxialDeformation
from appliance.sim.lens import BenchGeometry
from appliance.sim.scene import SpecimenScene, integrate_exposure
from hal.camera.base import Region

FloatArray = npt.NDArray[np.float64]

REMAP_MARGIN_PX = 10
"""Ideal-grid pixels rendered beyond those the remap reads: the spline reaches 2, and the
prefilter's boundary effect decays by 0.27 a pixel (to 1e-5 of the contrast at 10), so that
a region renders as the same part of the full frame."""


@numba.njit(parallel=True, cache=True)
def _remap(
    coefficients: np.ndarray, map_x: np.ndarray, map_y: np.ndarray, u0: float, v0: float
) -> FloatArray:
    """The image whose pixel (r, c) is the spline at (map_x[r, c] - u0, map_y[r, c] - v0)."""
    rows, cols = map_x.shape
    x_max = coefficients.shape[1] - 2 * PAD - 1.0
    y_max = coefficients.shape[0] - 2 * PAD - 1.0
    out = np.empty((rows, cols), np.float64)
    for r in numba.prange(rows):
        for c in range(cols):
            x = min(max(map_x[r, c] - u0, 0.0), x_max)
            y = min(max(map_y[r, c] - v0, 0.0), y_max)
            out[r, c] = interpolate(coefficients, x, y)
    return out


class BenchScene(SpecimenScene):
    """A `SpecimenScene` seen through a bench's lens and per-frame errors.

    Args:
        deformation_at: as for `SpecimenScene`.
        geometry: the bench; its scale, sensor size and centre are the scene's.
        **scene: the other arguments of `SpecimenScene` (not the scale, sensor size or
            centre).

    `object_of` and `pixel_of` stay the ideal grid's mapping at rest (the optics' scale);
    `sensor_positions`, `image_positions` and `material_points` go through the bench.
    """

    def __init__(
        self,
        deformation_at: Callable[[float], AxialDeformation],
        geometry: BenchGeometry,
        **scene: Any,
    ) -> None:
        width, height = geometry.sensor_size
        super().__init__(
            deformation_at,
            scale_mm_per_px=geometry.scale_mm_per_px,
            sensor_width=width,
            sensor_height=height,
            centre_mm=geometry.centre_mm,
            **scene,
        )
        self.geometry = geometry

    def render(
        self, start_s: float, stop_s: float, region: Region
    ) -> tuple[FloatArray, Mapping[str, Any]]:
        """As `SpecimenScene.render`, through the bench (see the module docstring)."""
        if region.x + region.width > self.sensor_width:
            raise ValueError(f"region {region} exceeds the sensor width {self.sensor_width}")
        if region.y + region.height > self.sensor_height:
            raise ValueError(f"region {region} exceeds the sensor height {self.sensor_height}")
        times, deformations = self._exposure(start_s, stop_s)
        geometry = self.geometry
        remap = geometry.errors.needs_remap
        if remap:
            map_x, map_y = geometry.maps()
            window = np.s_[region.y : region.y + region.height, region.x : region.x + region.width]
            map_x, map_y = map_x[window], map_y[window]
            u0 = math.floor(float(map_x.min())) - REMAP_MARGIN_PX
            v0 = math.floor(float(map_y.min())) - REMAP_MARGIN_PX
            u1 = math.ceil(float(map_x.max())) + REMAP_MARGIN_PX
            v1 = math.ceil(float(map_y.max())) + REMAP_MARGIN_PX
        else:
            u0, v0 = region.x, region.y
            u1, v1 = region.x + region.width - 1, region.y + region.height - 1
        cols = np.arange(u0, u1 + 1, dtype=np.float64)
        rows = np.arange(v0, v1 + 1, dtype=np.float64)
        weight = 1.0 / len(times)
        x_origin_texels = self.texture_origin_mm[0] / self.texel_mm
        y_min, y_max = self.material_y_range_mm
        cx = geometry.principal_point_px[0]
        samples = len(times)
        row_ty = np.empty((samples, rows.size))
        row_inv_stretch = np.empty((samples, rows.size))
        row_half_width = np.empty((samples, rows.size))
        row_textured = np.empty((samples, rows.size), np.bool_)
        row_pixel = np.empty((samples, rows.size))
        col_offset = np.empty((samples, cols.size))
        for s, (t, deformation) in enumerate(zip(times, deformations, strict=True)):
            row_y, row_pixel[s] = geometry.object_rows(deformation, t, rows)
            Y = deformation.material_y(row_y)
            stretch = deformation.lateral_stretch_at(Y)
            row_ty[s] = (Y - self.texture_origin_mm[1]) / self.texel_mm
            row_inv_stretch[s] = 1.0 / stretch
            row_half_width[s] = deformation.half_width_at(Y) * stretch
            row_textured[s] = (Y >= y_min) & (Y <= y_max)
            col_offset[s] = cols - cx - geometry.vibration_px(t)[0]
        ideal = np.empty((rows.size, cols.size), np.float64)
        integrate_exposure(
            ideal,
            weight,
            self._coefficients,
            row_ty,
            row_inv_stretch,
            row_half_width,
            row_textured,
            row_pixel,
            col_offset,
            geometry.centre_mm[0],
            x_origin_texels,
            1.0 / self.texel_mm,
            self.background,
        )
        if remap:
            coefficients = np.ascontiguousarray(spline_coefficients(ideal), np.float32)
            image = _remap(
                coefficients,
                np.ascontiguousarray(map_x),
                np.ascontiguousarray(map_y),
                float(u0),
                float(v0),
            )
        else:
            image = ideal
        flicker = geometry.flicker_factor(start_s, stop_s)
        if flicker != 1.0:
            image *= flicker
        truth = {
            "time_s": 0.5 * (start_s + stop_s),
            "start_s": float(start_s),
            "stop_s": float(stop_s),
            "time_samples": len(times),
            "sample_times_s": tuple(times),
        }
        return image, truth

    def _exposure(
        self, start_s: float, stop_s: float
    ) -> tuple[list[float], list[AxialDeformation]]:
        """The plain scene's time samples, more where the vibration moves the image further
        than `max_sample_step_px` between them (its blur is integrated too)."""
        times, deformations = super()._exposure(start_s, stop_s)
        errors = self.geometry.errors
        peak_speed_px_s = (
            2.0 * math.pi * errors.vibration_frequency_hz * errors.vibration_px_rms * math.sqrt(2)
        )
        motion_px = peak_speed_px_s * (float(stop_s) - float(start_s))
        count = min(self.max_time_samples, math.ceil(motion_px / self.max_sample_step_px - 1e-9))
        if count <= len(times):
            return times, deformations
        step = (float(stop_s) - float(start_s)) / count
        times = [float(start_s) + (i + 0.5) * step for i in range(count)]
        deformations = [self._deformation_at(t) for t in times]
        self._remember_exposure(float(start_s), float(stop_s), times, deformations)
        return times, deformations

    def object_positions(
        self, material_points_mm: npt.ArrayLike, start_s: float, stop_s: float
    ) -> FloatArray:
        """Exposure-averaged object-plane positions (x, y) (n, 2), mm, of material points."""
        points = np.asarray(material_points_mm, np.float64).reshape(-1, 2)
        _, deformations = self._exposure(start_s, stop_s)
        total = np.zeros_like(points)
        for deformation in deformations:
            total += np.column_stack(deformation.forward(points[:, 0], points[:, 1]))
        return total / len(deformations)

    def sensor_positions(
        self, material_points_mm: npt.ArrayLike, deformation: AxialDeformation, t_s: float
    ) -> FloatArray:
        """Sensor positions (n, 2), px, of material points in shape `deformation` at t_s."""
        points = np.asarray(material_points_mm, np.float64).reshape(-1, 2)
        objects = np.column_stack(deformation.forward(points[:, 0], points[:, 1]))
        ideal = self.geometry.ideal_points(deformation, t_s, objects, points[:, 1])
        return self.geometry.sensor_of_ideal(ideal)

    def image_positions(
        self, material_points_mm: npt.ArrayLike, start_s: float, stop_s: float
    ) -> FloatArray:
        """Exposure-averaged sensor positions (n, 2), px, of material points, through the
        bench at every time sample (see `SpecimenScene.image_positions`)."""
        points = np.asarray(material_points_mm, np.float64).reshape(-1, 2)
        times, deformations = self._exposure(start_s, stop_s)
        total = np.zeros_like(points)
        for t, deformation in zip(times, deformations, strict=True):
            total += self.sensor_positions(points, deformation, t)
        return total / len(deformations)

    def material_points(self, image_points_px: npt.ArrayLike, t_s: float) -> FloatArray:
        """Material points (n, 2), mm, seen at sensor positions (n, 2), px, at one instant."""
        deformation = self._deformation_at(t_s)
        ideal = self.geometry.ideal_of_sensor(image_points_px)
        objects = self.geometry.object_points(deformation, t_s, ideal)
        X, Y = deformation.inverse(objects[:, 0], objects[:, 1])
        return np.column_stack([X, Y])
