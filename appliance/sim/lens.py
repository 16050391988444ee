"""The simulated bench's geometry and light: where each sensor pixel looks, frame by frame.

Two steps take an object-plane point (x, y), mm, to the sensor (see `BenchScene`):

1. The *ideal grid*: the image a distortion-free pinhole camera facing the specimen square on
   at the object distance Z would take, at the optics' scale s (mm/px) with the object point
   `centre_mm` on its principal point (cx, cy):

       u = cx + v_x(t) + (x - x_c) d(t) / (s g),    v = cy + v_y(t) + (y - y_c) d(t) / (s g)

   g = 1 + dz / Z is the magnification change of a surface dz further from the lens (dz > 0
   away from the camera; g = 1 for a telecentric lens), d(t) the warm-up drift of the image
   scale, (v_x, v_y) the vibration's image shift. All three change from frame to frame; the
   out-of-plane move dz also along the specimen (thinning follows the local strain).
2. The *lens*: a fixed map from the ideal grid to the sensor through the true camera
   (`camera`: the pinhole or telecentric model with Brown-Conrady distortion) looking at the
   specimen plane at rest (`pose`: tilted by `camera_tilt_deg` about the image's x axis, the
   plane point `centre_mm` on the optical axis at distance Z). The ideal-grid point (u, v) is
   the plane point (x_c + (u - cx) s, y_c + (v - cy) s).

Treating dz as a scale of the ideal grid about the principal point is exact for a plane square
to the axis; for a tilted one it differs by dz Y sin(tilt) / Z^2 relatively (4e-6 for 0.5 mm,
100 mm and 0.5 deg).

Light: flicker multiplies the exposure-integrated intensity by
``1 + a * mean(sin(2 pi 2 f_mains t))`` over the exposure, the mean taken exactly; it beats with
the frame rate.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import numpy.typing as npt
from scipy.interpolate import RectBivariateSpline

from appliance.optics.camera_model import CameraModel, LensDistortion, PlanePose, PlaneProjection
from appliance.sim.bench import SLACK_TRAVEL_MM, BenchErrors
from appliance.sim.deformation import AxialDeformation

FloatArray = npt.NDArray[np.float64]

_OUT_OF_PLANE_ITERATIONS = 4
MAP_NODE_STEP_PX = 16
"""Spacing of the nodes at which the lens is traced exactly for the remap, px."""


class BenchGeometry:
    """The bench between a specimen and the sensor: lens, pose, and the per-frame changes.

    Args:
        errors: the bench's error sources.
        scale_mm_per_px: object-plane scale of the optics at rest, mm/px.
        object_distance_mm: distance from the lens to the specimen surface at rest, Z, mm.
        sensor_size: (width, height), px.
        centre_mm: object-plane point on the optical axis, mm.
        thickness_mm: the specimen's undeformed thickness, mm.
        seed: seed of the vibration's phases.

    Attributes:
        errors, scale_mm_per_px, object_distance_mm, sensor_size, centre_mm, thickness_mm: as
            given.
        camera: the true camera model (pinhole focal length Z / s px, or telecentric 1 / s
            px per mm; principal point at the sensor centre; the distortion converted to
            millimetres for a telecentric lens).
        pose: the specimen plane's pose at rest.
        projection: `camera` and `pose` together.
    """

    def __init__(
        self,
        errors: BenchErrors,
        *,
        scale_mm_per_px: float,
        object_distance_mm: float,
        sensor_size: tuple[int, int],
        centre_mm: tuple[float, float],
        thickness_mm: float,
        seed: int = 0,
    ) -> None:
        self.errors = errors
        self.scale_mm_per_px = float(scale_mm_per_px)
        self.object_distance_mm = float(object_distance_mm)
        self.sensor_size = (int(sensor_size[0]), int(sensor_size[1]))
        self.centre_mm = (float(centre_mm[0]), float(centre_mm[1]))
        self.thickness_mm = float(thickness_mm)
        width, height = self.sensor_size
        z = self.object_distance_mm
        d = errors.distortion
        if errors.entocentric:
            self.camera = CameraModel.ideal(width, height, z / self.scale_mm_per_px, distortion=d)
        else:
            self.camera = CameraModel.ideal(
                width,
                height,
                1.0 / self.scale_mm_per_px,
                distortion=LensDistortion(
                    d.k1 / z**2, d.k2 / z**4, d.p1 / z, d.p2 / z, d.k3 / z**6
                ),
                telecentric=True,
            )
        tilt = math.radians(errors.camera_tilt_deg)
        rotation, _ = cv2.Rodrigues(np.array([tilt, 0.0, 0.0]))
        origin = np.array([0.0, 0.0, z]) - rotation @ np.array([*self.centre_mm, 0.0])
        self.pose = PlanePose(
            (tilt, 0.0, 0.0), (float(origin[0]), float(origin[1]), float(origin[2]))
        )
        self.projection = PlaneProjection(self.camera, self.pose)
        phases = np.random.default_rng(seed).uniform(0.0, 2.0 * math.pi, 2)
        self._vibration_phases = (float(phases[0]), float(phases[1]))
        self._maps: tuple[np.ndarray, np.ndarray] | None = None

    def check_field(self) -> None:
        """Check that the lens maps the sensor's field one to one.

        Raises:
            ValueError: the radial distortion folds over within the image corners, or a
                border pixel has no ray (the distortion cannot be inverted there).
        """
        d = self.errors.distortion
        width, height = self.sensor_size
        corner = 0.5 * math.hypot(width - 1, height - 1) * self.scale_mm_per_px
        r2 = np.linspace(0.0, 1.1 * corner / self.object_distance_mm, 256) ** 2
        if np.any(1.0 + r2 * (3.0 * d.k1 + r2 * (5.0 * d.k2 + 7.0 * r2 * d.k3)) <= 0.0):
            raise ValueError("the lens distortion folds over within the image")
        if self.errors.needs_remap:
            steps = np.linspace(0.0, 1.0, 65)
            border = np.concatenate(
                [
                    np.column_stack([steps * (width - 1), np.zeros_like(steps)]),
                    np.column_stack([steps * (width - 1), np.full_like(steps, height - 1)]),
                    np.column_stack([np.zeros_like(steps), steps * (height - 1)]),
                    np.column_stack([np.full_like(steps, width - 1), steps * (height - 1)]),
                ]
            )
            self.ideal_of_sensor(border)

    @property
    def principal_point_px(self) -> tuple[float, float]:
        """(cx, cy), px."""
        return self.camera.cx_px, self.camera.cy_px

    def out_of_plane_mm(self, deformation: AxialDeformation, Y_mm: npt.ArrayLike) -> FloatArray:
        """Move dz of the surface of material sections Y along the optical axis, mm (positive
        away from the camera): the slack taken up by the crosshead's travel, plus half the
        thickness lost (the thickness follows the lateral stretch)."""
        Y = np.asarray(Y_mm, np.float64)
        dz = np.full(Y.shape, self.slack_mm(deformation))
        if self.errors.thinning_out_of_plane:
            dz = dz + 0.5 * self.thickness_mm * (1.0 - deformation.lateral_stretch_at(Y))
        return dz

    def slack_mm(self, deformation: AxialDeformation) -> float:
        """Out-of-plane move of the slack take-up, mm: a smooth (half-cosine) ramp over the
        first `SLACK_TRAVEL_MM` of crosshead travel (the moving grip's displacement)."""
        slack = self.errors.slack_out_of_plane_mm
        if slack == 0.0:
            return 0.0
        travel = float(deformation.material_y_mm[0] - deformation.spatial_y_mm[0])
        fraction = min(max(travel / SLACK_TRAVEL_MM, 0.0), 1.0)
        return slack * 0.5 * (1.0 - math.cos(math.pi * fraction))

    def magnification_change(
        self, deformation: AxialDeformation, Y_mm: npt.ArrayLike
    ) -> FloatArray:
        """g = 1 + dz / Z of material sections Y (1 for a telecentric lens)."""
        Y = np.asarray(Y_mm, np.float64)
        if not self.errors.entocentric:
            return np.ones(Y.shape)
        return 1.0 + self.out_of_plane_mm(deformation, Y) / self.object_distance_mm

    def drift(self, t_s: float) -> float:
        """Image scale factor d(t) of the warm-up: 1 + drift (1 - exp(-t / tau))."""
        e = self.errors
        if e.warm_up_drift_percent == 0.0:
            return 1.0
        return 1.0 + 0.01 * e.warm_up_drift_percent * -math.expm1(-t_s / e.warm_up_time_constant_s)

    def vibration_px(self, t_s: float) -> tuple[float, float]:
        """Image shift of the vibration at t_s, px: a sine on each axis, amplitude the RMS
        (so that the RMS of the shift's length is `vibration_px_rms`), seeded phases."""
        amplitude = self.errors.vibration_px_rms
        if amplitude == 0.0:
            return 0.0, 0.0
        angle = 2.0 * math.pi * self.errors.vibration_frequency_hz * t_s
        px, py = self._vibration_phases
        return amplitude * math.sin(angle + px), amplitude * math.sin(angle + py)

    def flicker_factor(self, start_s: float, stop_s: float) -> float:
        """Factor on the intensity integrated over the exposure [start_s, stop_s]."""
        amplitude = 0.01 * self.errors.flicker_percent
        if amplitude == 0.0:
            return 1.0
        omega = 2.0 * math.pi * 2.0 * self.errors.mains_frequency_hz
        if stop_s <= start_s:
            return 1.0 + amplitude * math.sin(omega * start_s)
        mean = (math.cos(omega * start_s) - math.cos(omega * stop_s)) / (omega * (stop_s - start_s))
        return 1.0 + amplitude * mean

    def object_rows(
        self, deformation: AxialDeformation, t_s: float, rows: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """Object y, mm, seen by ideal-grid rows at t_s, and the object-plane size of an
        ideal-grid pixel on each row, mm (s g / d)."""
        cy = self.camera.cy_px
        y_c = self.centre_mm[1]
        base = (rows - cy - self.vibration_px(t_s)[1]) * self.scale_mm_per_px / self.drift(t_s)
        y = y_c + base
        g = np.ones_like(y)
        if self.errors.entocentric:
            for _ in range(_OUT_OF_PLANE_ITERATIONS):
                g = self.magnification_change(deformation, deformation.material_y(y))
                y = y_c + base * g
        return y, g * self.scale_mm_per_px / self.drift(t_s)

    def object_points(
        self, deformation: AxialDeformation, t_s: float, ideal_px: FloatArray
    ) -> FloatArray:
        """Object points (x, y), mm, seen by ideal-grid points (n, 2) at t_s."""
        y, size = self.object_rows(deformation, t_s, ideal_px[:, 1])
        x = (
            self.centre_mm[0]
            + (ideal_px[:, 0] - self.camera.cx_px - self.vibration_px(t_s)[0]) * size
        )
        return np.column_stack([x, y])

    def ideal_points(
        self, deformation: AxialDeformation, t_s: float, object_mm: FloatArray, Y_mm: FloatArray
    ) -> FloatArray:
        """Ideal-grid points (n, 2) seeing object points (x, y) (n, 2), mm, of material
        sections Y (n,), at t_s."""
        scale = self.drift(t_s) / (
            self.scale_mm_per_px * self.magnification_change(deformation, Y_mm)
        )
        vx, vy = self.vibration_px(t_s)
        cx, cy = self.principal_point_px
        return np.column_stack(
            [
                cx + vx + (object_mm[:, 0] - self.centre_mm[0]) * scale,
                cy + vy + (object_mm[:, 1] - self.centre_mm[1]) * scale,
            ]
        )

    def sensor_of_ideal(self, ideal_px: FloatArray) -> FloatArray:
        """Sensor positions (n, 2), px, of ideal-grid points (n, 2) (through the lens)."""
        if not self.errors.needs_remap:
            return np.array(ideal_px, np.float64)
        return self.projection.to_pixels(self._plane_of_ideal(ideal_px))

    def ideal_of_sensor(self, sensor_px: npt.ArrayLike) -> FloatArray:
        """Ideal-grid points (n, 2) seen by sensor positions (n, 2), px."""
        points = np.asarray(sensor_px, np.float64).reshape(-1, 2)
        if not self.errors.needs_remap:
            return points.copy()
        plane = self.projection.to_plane_mm(points)
        cx, cy = self.principal_point_px
        s = self.scale_mm_per_px
        return np.column_stack(
            [cx + (plane[:, 0] - self.centre_mm[0]) / s, cy + (plane[:, 1] - self.centre_mm[1]) / s]
        )

    def _plane_of_ideal(self, ideal_px: FloatArray) -> FloatArray:
        cx, cy = self.principal_point_px
        s = self.scale_mm_per_px
        return np.column_stack(
            [
                self.centre_mm[0] + (ideal_px[:, 0] - cx) * s,
                self.centre_mm[1] + (ideal_px[:, 1] - cy) * s,
            ]
        )

    def maps(self) -> tuple[np.ndarray, np.ndarray]:
        """The remap from the sensor to the ideal grid: float32 (height, width) arrays of the
        ideal-grid column and row each sensor pixel sees (computed once).

        The lens is traced exactly on a grid of nodes every `MAP_NODE_STEP_PX` pixels and the
        map interpolated between them by bicubic splines (the map is a smooth low-order
        function: the interpolation is exact to about 1e-6 px, far below the float32 maps'
        rounding of 1e-4 px).
        """
        if self._maps is None:
            width, height = self.sensor_size
            cols = np.arange(width, dtype=np.float64)
            rows = np.arange(height, dtype=np.float64)
            node_cols = _nodes(width)
            node_rows = _nodes(height)
            grid_cols, grid_rows = np.meshgrid(node_cols, node_rows)
            ideal = self.ideal_of_sensor(np.column_stack([grid_cols.ravel(), grid_rows.ravel()]))
            maps = []
            for axis in (0, 1):
                values = ideal[:, axis].reshape(node_rows.size, node_cols.size)
                spline = RectBivariateSpline(node_rows, node_cols, values, kx=3, ky=3)
                maps.append(np.ascontiguousarray(spline(rows, cols), np.float32))
            self._maps = (maps[0], maps[1])
        return self._maps


def _nodes(count: int) -> FloatArray:
    """Node positions over 0 ... count - 1, every `MAP_NODE_STEP_PX` and the last."""
    nodes = np.arange(0.0, count - 1, MAP_NODE_STEP_PX)
    return np.append(nodes, float(count - 1)) if nodes.size >= 3 else np.linspace(0, count - 1, 4)
