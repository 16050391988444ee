"""The simulated tensile test: one world drives the simulated camera and machine on one clock.

`SimWorld.from_config` builds, for a material preset:

* the specimen and its material (`appliance.sim.specimen`, `appliance.sim.materials`) in a
  bar model (`appliance.sim.bar`) loaded by a crosshead with an acceleration limit
  (`appliance.sim.crosshead`), together the machine (`appliance.sim.machine`);
* the camera's view of it (`appliance.sim.scene`), through the preset's lens and sensor
  (`appliance.plan.optics`), with a field of view that keeps both gauge marks in sight to the
  end of the test;
* the devices, through the backend registry like any other: `sim://camera` and `sim://machine`
  receive the scene, the machine and the shared `SimClock` (fast or real time).

Presets (`PRESETS`):

* rubber: ISO 37 type 1 dumbbell, Mooney-Rivlin rubber breaking at 600 %, 500 mm/min, a
  2 MP camera (1024 x 2048, portrait) with a 14 mm lens at 400 mm (0.152 mm/px: the marks
  travel 276 mm between the start and the break), dense speckle;
* metal: ISO 6892-1 flat specimen, steel, 10 mm/min, the same camera with a 35 mm lens at
  400 mm.

The bench between the specimen and the sensor (`[sim] bench`, `appliance.sim.bench`): ideal
(telecentric, nothing else: the plain `SpecimenScene`), or a lens with distortion and tilt,
out-of-plane moves, flicker, vibration and drift (`appliance.sim.bench_scene.BenchScene`). The
true camera and the specimen plane's pose are `SimWorld.lens_camera` and `specimen_plane`, for
scoring only.

`GaugeTruth` gives the true strain and elongation of gauge marks placed in the reference
image, as the material points they were placed on: their distance in the specimen's plane, mm.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from appliance.config import Config
from appliance.errors import InputError
from appliance.measure.frame_measurer import StrainSample
from appliance.measure.gauges import Gauge
from appliance.optics.camera_model import CameraModel, LensDistortion, PlanePose
from appliance.plan.optics import Optics
from appliance.sim.bar import BarModel
from appliance.sim.bench import BENCHES, BenchErrors, bench_errors
from appliance.sim.bench_scene import BenchScene
from appliance.sim.crosshead import Crosshead
from appliance.sim.lens import BenchGeometry
from appliance.sim.machine import MachineWithSpecimen
from appliance.sim.materials import ElasticPlastic, MooneyRivlin
from appliance.sim.scene import TEXTURE_OVERSAMPLE, PaintedMarks, SpecimenScene, SpeckleCoat
from appliance.sim.specimen import Specimen
from appliance.sim.trigger import SimTriggerController
from hal.camera.base import Frame
from hal.clock import Pace, SimClock
from hal.registry import camera_from_url, machine_from_url

MAX_SENSOR_PIXELS = 8192 * 4096
"""The simulated camera's largest sensor, px (33.6 MP: the largest machine-vision sensors)."""
MAX_TEXTURE_PIXELS = 100e6
"""The largest specimen texture the simulator renders (px; the metal preset's is 5.2e6)."""
MIN_SPECKLE_RADIUS_PX = 0.5
"""The smallest speckle the simulator paints, in pixels of the image (the presets' are 2 px)."""
PAINTED_MARK_SIZE_FRACTION = 1.0 / 6.0
"""Radius of a painted dot (half-width of a painted line), as a fraction of the specimen's
parallel width (1 mm on the rubber preset's 6 mm)."""
MAX_TEST_DURATION_S = 24 * 3600.0
"""The longest simulated test: to its end strain (or the break) at the configured speed."""


@dataclass(frozen=True)
class SimPreset:
    """A simulated test setup.

    Attributes:
        specimen: builds the specimen.
        material: builds the material.
        speed_mm_min: standard test speed.
        optics: lens and sensor pixel.
        sensor_size: (width, height) px.
        speckle_radius_mm: speckle radius of the coat.
        transverse_width_mm: spacing of the transverse marks (0 = none).
    """

    specimen: Callable[[], Specimen]
    material: Callable[[], object]
    speed_mm_min: float
    optics: Optics
    sensor_size: tuple[int, int]
    speckle_radius_mm: float
    transverse_width_mm: float


PRESETS: dict[str, SimPreset] = {
    "rubber": SimPreset(
        specimen=Specimen.iso37_type1,
        material=MooneyRivlin.filled_rubber,
        speed_mm_min=500.0,
        optics=Optics(focal_length_mm=14.0, object_distance_mm=400.0, pixel_size_um=5.5),
        sensor_size=(1024, 2048),
        speckle_radius_mm=0.3,
        transverse_width_mm=0.0,
    ),
    "metal": SimPreset(
        specimen=Specimen.iso6892_flat,
        material=ElasticPlastic.steel_s355,
        speed_mm_min=10.0,
        optics=Optics(focal_length_mm=35.0, object_distance_mm=400.0, pixel_size_um=5.5),
        sensor_size=(1024, 2048),
        speckle_radius_mm=0.12,
        transverse_width_mm=8.0,
    ),
}


class SimWorld:
    """Specimen, machine, scene, clock and the two simulated devices of one test.

    Args:
        preset: the setup.
        optics: lens and sensor (the preset's unless given).
        sensor_size: (width, height) px (the preset's unless given).
        speed_mm_min: test speed (the preset's unless given).
        end_strain: engineering strain of the gauge at which the test is expected to end
            (frames the view); None = the material's break.
        pace: FAST or REAL_TIME.
        seed: seed of the speckle coat and of the camera noise.
        read_noise, electrons_per_grey: camera noise (see `hal.camera.sim.SimCamera`).
        camera_hang_after_s: how long after it is first armed the camera hangs (simulation
            time; fault injection, see `hal.camera.sim.SimCamera`); None = never.
        encoder_counts_per_mm: the crosshead encoder's resolution.
        speed_changes: the simulated controller's speed program after the start: (seconds
            after the start, mm/min), in increasing time.
        bench: the bench's error sources (`appliance.sim.bench`); None = the ideal bench.
        painted_marks: "none", or "dots" / "lines" painted over the speckle at the ends of the
            specimen's gauge length (`appliance.sim.scene.PaintedMarks`, white paint, radius
            or half-width `PAINTED_MARK_SIZE_FRACTION` of the parallel width).

    Attributes:
        bench: the bench's error sources in force.
        geometry: the bench's geometry (`appliance.sim.lens.BenchGeometry`).
        scene: the camera's view (a `BenchScene` unless the bench is ideal).

    The camera's trigger input is wired to `trigger`, the simulated trigger microcontroller
    (`appliance.sim.trigger`), which the test configures and arms for EXTERNAL triggering.
    """

    def __init__(
        self,
        preset: SimPreset,
        *,
        optics: Optics | None = None,
        sensor_size: tuple[int, int] | None = None,
        speed_mm_min: float | None = None,
        end_strain: float | None = None,
        pace: Pace = Pace.FAST,
        seed: int = 1,
        read_noise: float = 0.5,
        electrons_per_grey: float = 40.0,
        camera_hang_after_s: float | None = None,
        encoder_counts_per_mm: float = 1000.0,
        speed_changes: tuple[tuple[float, float], ...] = (),
        bench: BenchErrors | None = None,
        painted_marks: str = "none",
    ) -> None:
        self.preset = preset
        self.specimen = preset.specimen()
        self.material = preset.material()
        self.optics = optics or preset.optics
        self.speed_mm_min = speed_mm_min or preset.speed_mm_min
        self.pace = pace
        self.clock = SimClock(pace)
        self.bar = BarModel(self.specimen, self.material)
        self.machine = MachineWithSpecimen(
            self.bar,
            Crosshead(),
            encoder_counts_per_mm=encoder_counts_per_mm,
            speed_changes=speed_changes,
        )
        self.trigger = SimTriggerController(self.machine)
        width, height = sensor_size or preset.sensor_size
        scale = self.optics.scale_mm_per_px
        half_gauge = 0.5 * self.specimen.gauge_length_mm
        end_d = self.bar.crosshead_for_gauge_strain(
            -half_gauge, half_gauge, end_strain if end_strain else self.material.break_strain
        )
        self.end_crosshead_mm = float(end_d)
        end = self.bar.deformation(end_d).deformation
        top = float(end.spatial_y(-half_gauge))
        bottom = half_gauge
        margin = 0.025 * height * scale
        centre_y = 0.5 * (top + bottom)
        if bottom - top + 2 * margin > height * scale:
            centre_y = bottom + margin - 0.5 * height * scale
        length = self.specimen.overall_length_mm
        self.bench = bench or ideal_bench()
        self.geometry = BenchGeometry(
            self.bench,
            scale_mm_per_px=scale,
            object_distance_mm=self.optics.object_distance_mm,
            sensor_size=(width, height),
            centre_mm=(0.0, centre_y),
            thickness_mm=self.specimen.thickness_mm,
            seed=seed,
        )
        view = {
            "material_y_range_mm": (-0.5 * length, 0.5 * length),
            "half_width_mm": 0.5 * self.specimen.end_width_mm,
            "coat": SpeckleCoat(radius_mm=preset.speckle_radius_mm, seed=seed),
            "marks": None
            if painted_marks == "none"
            else PaintedMarks(
                painted_marks,  # type: ignore[arg-type]
                (-half_gauge, half_gauge),
                PAINTED_MARK_SIZE_FRACTION * self.specimen.parallel_width_mm,
            ),
        }
        self.scene: SpecimenScene
        if self.bench.is_ideal:
            self.scene = SpecimenScene(
                self.machine.deformation_at,
                scale_mm_per_px=scale,
                sensor_width=width,
                sensor_height=height,
                centre_mm=(0.0, centre_y),
                **view,
            )
        else:
            self.scene = BenchScene(self.machine.deformation_at, self.geometry, **view)
            if self.bench.needs_remap:
                self.geometry.maps()
        self.camera = camera_from_url(
            "sim://camera",
            scene=self.scene,
            clock=self.clock,
            seed=seed,
            read_noise=read_noise,
            electrons_per_grey=electrons_per_grey,
            hang_after_s=camera_hang_after_s,
            trigger_line=self.trigger,
        )
        self.controller = machine_from_url("sim://machine", machine=self.machine, clock=self.clock)

    @classmethod
    def from_config(cls, config: Config, optics: Optics) -> SimWorld:
        """The world of a configuration's [sim] table and the related keys, seen through
        `optics` (the configured ones, or the preset's)."""
        preset = PRESETS[config.sim.material]
        width = config.sim.sensor_width_px or preset.sensor_size[0]
        height = config.sim.sensor_height_px or preset.sensor_size[1]
        if width * height > MAX_SENSOR_PIXELS:
            raise InputError(
                f"[sim] sensor_width_px x sensor_height_px: {width} x {height} px is "
                f"{width * height / 1e6:.1f} MP, more than the simulated camera's "
                f"{MAX_SENSOR_PIXELS / 1e6:.1f} MP"
            )
        specimen = preset.specimen()
        speckle_px = preset.speckle_radius_mm / optics.scale_mm_per_px
        if speckle_px < MIN_SPECKLE_RADIUS_PX:
            raise InputError(
                f"[optics]: at {optics.scale_mm_per_px:.3g} mm/px the simulated speckle "
                f"(radius {preset.speckle_radius_mm:g} mm) is {speckle_px:.2g} px; the simulator "
                f"paints speckles of at least {MIN_SPECKLE_RADIUS_PX:g} px (a finer scale: a "
                "longer focal length, a shorter object distance or smaller pixels)"
            )
        texel_mm = optics.scale_mm_per_px / TEXTURE_OVERSAMPLE
        texture_pixels = (specimen.overall_length_mm / texel_mm) * (
            specimen.end_width_mm / texel_mm
        )
        if texture_pixels > MAX_TEXTURE_PIXELS:
            raise InputError(
                f"[optics]: at {optics.scale_mm_per_px:.3g} mm/px the simulated specimen "
                f"({specimen.overall_length_mm:g} x {specimen.end_width_mm:g} mm) needs a "
                f"texture of {texture_pixels / 1e6:.3g} MP; the simulator renders at most "
                f"{MAX_TEXTURE_PIXELS / 1e6:.0f} MP (a coarser scale: a shorter focal length, "
                "a longer object distance or larger pixels)"
            )
        bench = bench_errors(
            config.sim, (width, height), optics.object_distance_mm / optics.scale_mm_per_px
        )
        try:
            BenchGeometry(
                bench,
                scale_mm_per_px=optics.scale_mm_per_px,
                object_distance_mm=optics.object_distance_mm,
                sensor_size=(width, height),
                centre_mm=(0.0, 0.0),
                thickness_mm=specimen.thickness_mm,
            ).check_field()
        except ValueError as exc:
            raise InputError(
                f"[sim] lens_k1, lens_k2, lens_p1, lens_p2: {exc} of {width} x {height} px "
                f"at {optics.scale_mm_per_px:.3g} mm/px and {optics.object_distance_mm:g} mm "
                "(smaller coefficients)"
            ) from None
        world = cls(
            preset,
            optics=optics,
            sensor_size=(width, height),
            speed_mm_min=config.run.speed_mm_min,
            end_strain=config.run.until_strain or None,
            pace=Pace.REAL_TIME if config.sim.realtime else Pace.FAST,
            seed=config.sim.seed,
            read_noise=config.sim.read_noise_grey,
            electrons_per_grey=config.sim.electrons_per_grey,
            camera_hang_after_s=config.sim.camera_hang_after_s or None,
            encoder_counts_per_mm=config.trigger.encoder_counts_per_mm,
            speed_changes=(
                ((config.sim.speed_change_after_s, config.sim.speed_change_mm_min),)
                if config.sim.speed_change_after_s
                else ()
            ),
            bench=bench,
            painted_marks=config.sim.painted_marks,
        )
        duration_s = world.planned_duration_s
        if duration_s > MAX_TEST_DURATION_S:
            end = (
                f"to [run] until_strain {config.run.until_strain:g}"
                if config.run.until_strain
                else f"to the break ({world.material.break_strain:g})"
            )
            raise InputError(
                f"[run] speed_mm_min: at {world.speed_mm_min:g} mm/min the simulated test "
                f"{end} would last {duration_s / 3600:.0f} h; the simulator runs tests of at "
                f"most {MAX_TEST_DURATION_S / 3600:.0f} h (raise the speed or lower the end "
                "strain)"
            )
        return world

    @property
    def planned_duration_s(self) -> float:
        """Time from the start to the end strain (or the break) at the test speed, s."""
        return self.end_crosshead_mm / (self.speed_mm_min / 60.0)

    @property
    def gauge_length_mm(self) -> float:
        """The specimen's standard gauge length, mm."""
        return self.specimen.gauge_length_mm

    @property
    def lens_camera(self) -> CameraModel:
        """The true camera the world renders with (for scoring: nothing that measures reads
        it): a pinhole or telecentric model with the bench's distortion."""
        return self.geometry.camera

    @property
    def specimen_plane(self) -> PlanePose:
        """The specimen surface's true pose at rest in `lens_camera`'s frame (plane X, Y are
        the object-plane x, y of `appliance.sim.deformation`, mm)."""
        return self.geometry.pose

    @property
    def specimen_centre_px(self) -> tuple[float, float]:
        """Pixel (x, y) of the undeformed specimen's centre (for scoring only: a test places
        its gauge on the specimen it detects in the reference frame)."""
        scene = self.scene
        if isinstance(scene, BenchScene):
            x, y = scene.sensor_positions(np.zeros((1, 2)), self.machine.deformation_at(0.0), 0.0)[
                0
            ]
        else:
            x, y = scene.pixel_of(0.0, 0.0)
        return float(x), float(y)

    def gauge_truth(self, points_px: np.ndarray, axial: Gauge, reference: Frame) -> GaugeTruth:
        """Truth for gauge points placed at `points_px` in the reference frame."""
        truth = reference.metadata["truth"]
        material = self.scene.material_points(points_px, truth["time_s"])
        return GaugeTruth(
            self.scene,
            material,
            axial,
            self.optics.scale_mm_per_px,
            points_px,
            reference_time_s=truth["time_s"],
        )


def ideal_bench() -> BenchErrors:
    """The ideal bench: telecentric, distortion-free, nothing else."""
    preset = BENCHES["ideal"]
    return BenchErrors(
        name="ideal",
        entocentric=False,
        distortion=LensDistortion(),
        camera_tilt_deg=0.0,
        thinning_out_of_plane=False,
        slack_out_of_plane_mm=0.0,
        flicker_percent=0.0,
        mains_frequency_hz=50.0,
        vibration_px_rms=0.0,
        vibration_frequency_hz=preset.vibration_frequency_hz,
        warm_up_drift_percent=0.0,
        warm_up_time_constant_s=preset.warm_up_time_constant_s,
    )


class GaugeTruth:
    """True engineering strain and elongation of an axial gauge, frame by frame.

    The gauge's points are material points (where they were placed in the reference image).
    The true gauge length is the distance between the marks' exposure-averaged object-plane
    positions, mm (the specimen's own elongation, whatever the bench); the image positions,
    px, are where the camera sees those points through the bench (the blur). On the ideal
    bench the object plane is the image at a fixed scale, and the length is taken from the
    image positions exactly as the measured one is from the tracked positions.
    """

    def __init__(
        self,
        scene: SpecimenScene,
        material_points_mm: np.ndarray,
        axial: Gauge,
        scale_mm_per_px: float,
        reference_points_px: np.ndarray,
        reference_time_s: float = 0.0,
    ) -> None:
        self.scene = scene
        self.material_points_mm = material_points_mm
        self.axial = axial
        self.scale = scale_mm_per_px
        self.l0_px = axial.length_px(reference_points_px)
        self.l0_mm = self.l0_px * scale_mm_per_px
        if isinstance(scene, BenchScene):
            t_s = reference_time_s
            self.l0_mm = axial.length_px(scene.object_positions(material_points_mm, t_s, t_s))

    def blur_px(self, sample: StrainSample) -> float:
        """Largest distance a gauge point travelled during the frame's exposure, px."""
        start = sample.timestamp_ns * 1e-9
        stop = start + sample.exposure_us * 1e-6
        first = self.scene.image_positions(self.material_points_mm, start, start)
        last = self.scene.image_positions(self.material_points_mm, stop, stop)
        return float(np.hypot(*(last - first).T).max())

    def at(self, sample: StrainSample) -> tuple[float, float]:
        """(true engineering strain, true elongation mm) for the frame of `sample`."""
        start = sample.timestamp_ns * 1e-9
        stop = start + sample.exposure_us * 1e-6
        scene = self.scene
        if isinstance(scene, BenchScene):
            length = self.axial.length_px(
                scene.object_positions(self.material_points_mm, start, stop)
            )
            return (length - self.l0_mm) / self.l0_mm, length - self.l0_mm
        positions = scene.image_positions(self.material_points_mm, start, stop)
        length = self.axial.length_px(positions)
        return (length - self.l0_px) / self.l0_px, (length - self.l0_px) * self.scale
