"""A simulated precision calibrator for verifying the extensometer (ISO 9513).

Two speckled blocks (`block_mm` square) lie in the specimen plane, their centres the nominal
gauge length apart along the loading axis (the image's rows): the upper one fixed, the lower
one carried by the calibrator's micrometer. Across each block's centre runs a dark line
`line_mm` wide on a light, unspeckled strip, the target the gauge length is measured on. The
calibrator is set to an elongation and reports it (its reading, what the lab writes down as
l_t); the block really moves by `displacement_um`, which differs from the reading by the
calibrator's own error:

    displacement = reading / (1 + scale_error) + offset_error_um

so a calibrator whose scale reads 0.4 % long (`scale_error` = 0.004) makes a perfect
extensometer look 0.4 % short (relative bias about -0.4 %). Both errors are 0 by default.

The blocks are seen through the simulated bench (`appliance.sim.lens.BenchGeometry`, the
`[sim] bench` preset and keys): its camera model and the plane's pose at rest (the lens's
distortion, an entocentric lens's perspective, the camera's tilt) and, frame by frame, as
the bench moves the ideal image (`appliance.sim.lens`): the warm-up drift of the image
scale, the vibration's image shift and the light's flicker, at the frame's time (frames
`frame_interval_s` apart from the first, the camera switched on with the first). A
calibrator is rigid: the bench's out-of-plane moves of a specimen do not apply.

Each frame is rendered through the camera (`appliance.sim.target.render_plane`, exact rays)
from a texture of the plane, built anew for each position of the moving block from the
analytic speckle pattern (`appliance.dic.synthetic`), so every displacement is exact to the
texture's interpolation; then the camera adds shot and read noise and quantises to 8 bits, as
the simulated camera does. The truth (`displacement_um`) only scores: the extensometer
measures the frames.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from appliance.dic.synthetic import (
    SpecklePattern,
    add_gaussian_noise,
    add_poisson_noise,
    dense_speckle,
    fourier_shift,
    quantize,
)
from appliance.optics.camera_model import CameraModel
from appliance.sim.bench import BenchErrors
from appliance.sim.lens import BenchGeometry
from appliance.sim.target import render_plane

FloatArray = npt.NDArray[np.float64]

TEXELS_PER_PX = 2
"""Texture texels per pixel of the image, each way."""
LINE_GREY = 15.0
"""Grey level of the dark line across each block (8-bit scale)."""
QUIET_GREY = 215.0
"""Grey level of the unspeckled strip the line lies on (8-bit scale)."""


class SimCalibrator:
    """Two speckled blocks, one moved by a calibrator, seen by a simulated camera.

    Args:
        gauge_length_mm: distance between the blocks' centres (their lines) at zero, mm.
        bench: the bench the camera sees the blocks through (`calibrator_bench`); plane point
            (0, 0), midway between the blocks, on its optical axis, plane Y along the loading
            axis.
        speckle_radius_mm: the coat's speckle radius, mm.
        block_mm: side of each square block, mm.
        line_mm: width of the dark line across each block's centre, mm.
        quiet_mm: width of the light, unspeckled strip on each side of the line, mm (as a
            printed target's quiet zone: the line's edges stand out of the speckle).
        travel_mm: the largest displacement the texture has room for, mm.
        scale_error: the calibrator's relative scale error (its reading over the true
            displacement, less one).
        offset_error_um: the calibrator's zero offset, um (added to the true displacement).
        seed: the speckle patterns' and the camera noise's seed.
        read_noise: read noise, grey levels (standard deviation).
        electrons_per_grey: conversion gain for the shot noise; 0 = no shot noise.
        background: grey level around the blocks.
        frame_interval_s: time between frames, s (for the bench's drift, vibration, flicker).
        exposure_s: each frame's exposure, s (for the flicker).
    """

    def __init__(
        self,
        *,
        gauge_length_mm: float,
        bench: BenchGeometry,
        speckle_radius_mm: float,
        block_mm: float = 10.0,
        line_mm: float = 0.3,
        quiet_mm: float = 0.4,
        travel_mm: float = 5.0,
        scale_error: float = 0.0,
        offset_error_um: float = 0.0,
        seed: int = 1,
        read_noise: float = 0.5,
        electrons_per_grey: float = 40.0,
        background: float = 20.0,
        frame_interval_s: float = 5.0,
        exposure_s: float = 0.002,
    ) -> None:
        if not gauge_length_mm > block_mm:
            raise ValueError(
                f"gauge_length_mm ({gauge_length_mm}) must exceed block_mm ({block_mm})"
            )
        if not scale_error > -1.0:
            raise ValueError(f"scale_error must be > -1, got {scale_error}")
        self.gauge_length_mm = float(gauge_length_mm)
        self.bench = bench
        self.camera = camera = bench.camera
        self.pose = pose = bench.pose
        self.frame_interval_s = float(frame_interval_s)
        self.exposure_s = float(exposure_s)
        self.block_mm = float(block_mm)
        self.line_mm = float(line_mm)
        self.quiet_mm = float(quiet_mm)
        self.travel_mm = float(travel_mm)
        self.scale_error = float(scale_error)
        self.offset_error_um = float(offset_error_um)
        self.read_noise = float(read_noise)
        self.electrons_per_grey = float(electrons_per_grey)
        self.background = float(background)
        self.seed = int(seed)
        scale = 1.0 / camera.fx_px if camera.telecentric else pose.translation[2] / camera.fx_px
        self.texel_mm = scale / TEXELS_PER_PX
        pad = 4.0 * scale
        half = 0.5 * self.block_mm + pad
        top = -0.5 * self.gauge_length_mm - half
        bottom = 0.5 * self.gauge_length_mm + half + max(self.travel_mm, 0.0)
        columns = int(math.ceil(2 * half / self.texel_mm)) + 1
        rows = int(math.ceil((bottom - top) / self.texel_mm)) + 1
        self.origin_mm = (-half, top)
        self._x = self.origin_mm[0] + np.arange(columns) * self.texel_mm
        self._y = self.origin_mm[1] + np.arange(rows) * self.texel_mm
        radius = speckle_radius_mm / self.texel_mm
        self._base = np.full((rows, columns), self.background)
        self._paint(self._base, self._coat(seed, radius), -0.5 * self.gauge_length_mm)
        self._moving_coat = self._coat(seed + 1, radius)
        self._crop, self._crop_camera = self._view_of_texture(rows, columns)
        self.reading_um = 0.0
        self._frames = 0

    def displacement_um(self, reading_um: float) -> float:
        """The true displacement of the moving block when the calibrator reads `reading_um`."""
        return reading_um / (1.0 + self.scale_error) + self.offset_error_um

    def move_to(self, reading_um: float) -> None:
        """Set the calibrator so that it reads `reading_um` (um)."""
        displacement_mm = self.displacement_um(reading_um) * 1e-3
        if not -self.block_mm < displacement_mm <= self.travel_mm:
            raise ValueError(
                f"{reading_um:g} um is beyond the calibrator's travel ({self.travel_mm:g} mm)"
            )
        self.reading_um = float(reading_um)

    def grab(self) -> np.ndarray:
        """One 8-bit frame of the blocks at the calibrator's current position.

        Only the part of the sensor that sees the blocks' plane region is rendered and
        noisy; the rest of the frame is the backdrop's flat grey.
        """
        texture = self._base.copy()
        centre = 0.5 * self.gauge_length_mm + self.displacement_um(self.reading_um) * 1e-3
        self._paint(texture, self._moving_coat, centre)
        bench = self.bench
        t_s = self._frames * self.frame_interval_s
        drift = bench.drift(t_s)
        shift_x, shift_y = bench.vibration_px(t_s)
        scale = bench.scale_mm_per_px
        origin = (
            drift * self.origin_mm[0] + shift_x * scale,
            drift * self.origin_mm[1] + shift_y * scale,
        )
        view = render_plane(
            texture, drift * self.texel_mm, origin, self.pose, self._crop_camera, self.background
        )
        view = view * bench.flicker_factor(t_s, t_s + self.exposure_s)
        seed = self.seed * 1_000_003 + self._frames
        self._frames += 1
        if self.electrons_per_grey > 0:
            view = add_poisson_noise(view, self.electrons_per_grey, seed=seed)
        view = add_gaussian_noise(view, self.read_noise, seed=seed + 1)
        frame = np.full((self.camera.height_px, self.camera.width_px), self.background)
        x0, y0 = self._crop
        frame[y0 : y0 + view.shape[0], x0 : x0 + view.shape[1]] = view
        return quantize(frame, 8)

    def _coat(self, seed: int, radius: float) -> FloatArray:
        """A block's speckle coat on the texel grid, centred, with a margin of 4 texels
        (room for a sub-texel shift)."""
        side = int(math.ceil(self.block_mm / self.texel_mm)) + 8
        pattern: SpecklePattern = dense_speckle(side, side, seed=seed, radius=radius, margin=0.0)
        ys, xs = np.mgrid[0:side, 0:side].astype(np.float64)
        return pattern.intensity(xs, ys)

    def _paint(self, texture: FloatArray, coat: FloatArray, centre_y_mm: float) -> None:
        """Paint a block centred at plane (x of the texture's middle column, `centre_y_mm`)
        with the speckle `coat` (centred on it; shifted by the sub-texel part of the position
        by the Fourier shift theorem, exact for the band-limited speckle), its line across the
        centre and its outline blended by the texel's coverage, onto `texture`."""
        half = 0.5 * self.block_mm
        side = coat.shape[0]
        position = (centre_y_mm - self.origin_mm[1]) / self.texel_mm
        whole = math.floor(position)
        fraction = position - whole
        if fraction:
            coat = fourier_shift(coat, 0.0, fraction)
        row0 = whole - side // 2
        col0 = (texture.shape[1] - 1) // 2 - side // 2
        y = self._y[row0 : row0 + side] - centre_y_mm
        x = self._x[col0 : col0 + side] - self._x[col0 + side // 2]
        strip = 0.5 * self.line_mm + self.quiet_mm
        quiet = np.clip(0.5 + (strip - np.abs(y)) / self.texel_mm, 0.0, 1.0)
        line = np.clip(0.5 + (0.5 * self.line_mm - np.abs(y)) / self.texel_mm, 0.0, 1.0)
        painted = coat + quiet[:, np.newaxis] * (QUIET_GREY - coat)
        painted = painted + line[:, np.newaxis] * (LINE_GREY - painted)
        cover_x = np.clip(0.5 + (half - np.abs(x)) / self.texel_mm, 0.0, 1.0)
        cover_y = np.clip(0.5 + (half - np.abs(y)) / self.texel_mm, 0.0, 1.0)
        cover = cover_y[:, np.newaxis] * cover_x[np.newaxis, :]
        window = texture[row0 : row0 + side, col0 : col0 + side]
        texture[row0 : row0 + side, col0 : col0 + side] = window + cover * (painted - window)

    def _view_of_texture(self, rows: int, columns: int) -> tuple[tuple[int, int], CameraModel]:
        """The sensor region (x0, y0) that sees the texture's extent (its outline sampled
        densely, so a distorting lens's curved edges are inside), and the camera cropped to
        it (the same lens, the principal point moved)."""
        camera = self.camera
        x = self.origin_mm[0] + np.linspace(0.0, columns - 1, 64) * self.texel_mm
        y = self.origin_mm[1] + np.linspace(0.0, rows - 1, 256) * self.texel_mm
        outline = np.concatenate(
            [
                np.column_stack([x, np.full_like(x, y[0])]),
                np.column_stack([x, np.full_like(x, y[-1])]),
                np.column_stack([np.full_like(y, x[0]), y]),
                np.column_stack([np.full_like(y, x[-1]), y]),
            ]
        )
        pixels = camera.project(self.pose.to_camera(outline))
        margin = 4
        x0 = max(int(math.floor(pixels[:, 0].min())) - margin, 0)
        y0 = max(int(math.floor(pixels[:, 1].min())) - margin, 0)
        x1 = min(int(math.ceil(pixels[:, 0].max())) + margin, camera.width_px - 1)
        y1 = min(int(math.ceil(pixels[:, 1].max())) + margin, camera.height_px - 1)
        if x1 < x0 or y1 < y0:
            raise ValueError("the calibrator's blocks are outside the camera's view")
        cropped = CameraModel(
            x1 - x0 + 1,
            y1 - y0 + 1,
            camera.fx_px,
            camera.fy_px,
            camera.cx_px - x0,
            camera.cy_px - y0,
            camera.distortion,
            camera.telecentric,
        )
        return (x0, y0), cropped


def calibrator_bench(
    errors: BenchErrors,
    *,
    scale_mm_per_px: float,
    object_distance_mm: float,
    sensor_size: tuple[int, int],
    seed: int = 0,
) -> BenchGeometry:
    """The bench a calibrator is seen through: `errors` (a `[sim] bench`) at the optics'
    scale and object distance, plane point (0, 0) on the optical axis."""
    return BenchGeometry(
        errors,
        scale_mm_per_px=scale_mm_per_px,
        object_distance_mm=object_distance_mm,
        sensor_size=sensor_size,
        centre_mm=(0.0, 0.0),
        thickness_mm=0.0,
        seed=seed,
    )
