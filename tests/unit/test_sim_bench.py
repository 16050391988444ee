"""The simulated bench's error sources, each measured from rendered images or the truth."""

import dataclasses
import math

import numpy as np
import pytest

from appliance.config import Config, parse_config
from appliance.dic.correlation import Correlator
from appliance.errors import InputError
from appliance.optics.camera_model import LensDistortion
from appliance.sim.bench import BENCHES, bench_errors, corner_radius
from appliance.sim.bench_scene import BenchScene
from appliance.sim.deformation import AxialDeformation
from appliance.sim.lens import BenchGeometry
from appliance.sim.scene import SpecimenScene, SpeckleCoat
from appliance.sim.world import PRESETS, SimWorld, ideal_bench
from hal.camera.base import Region

SCALE = 0.05
WIDTH, HEIGHT = 200, 260
HALF_WIDTH = 3.5
COAT = SpeckleCoat(radius_mm=2 * SCALE, seed=7)
FULL = Region(0, 0, WIDTH, HEIGHT)
TABLE_Y = np.linspace(-40.0, 40.0, 81)
DISTANCE_MM = 30.0
SUBSET = 21


def deformation(stretch=1.0, lateral=1.0, shift_mm=0.0, travel_mm=0.0):
    """Uniform stretch about Y = 0 with lateral contraction, then an axial translation; the
    crosshead's end of the table (far out of view) moves `travel_mm` further."""
    spatial = shift_mm + stretch * TABLE_Y
    spatial[0] -= travel_mm
    return AxialDeformation(
        material_y_mm=TABLE_Y,
        spatial_y_mm=spatial,
        lateral_stretch=np.full(TABLE_Y.size, lateral),
        half_width_mm=np.full(TABLE_Y.size, HALF_WIDTH),
    )


def bench(**changes):
    return dataclasses.replace(ideal_bench(), name="test", **changes)


def geometry(errors, seed=0):
    return BenchGeometry(
        errors,
        scale_mm_per_px=SCALE,
        object_distance_mm=DISTANCE_MM,
        sensor_size=(WIDTH, HEIGHT),
        centre_mm=(0.0, 0.0),
        thickness_mm=2.0,
        seed=seed,
    )


def bench_scene(errors, deformation_at=lambda t: deformation(), seed=0):
    return BenchScene(
        deformation_at,
        geometry(errors, seed),
        material_y_range_mm=(-12.0, 12.0),
        half_width_mm=HALF_WIDTH,
        coat=COAT,
    )


def plain_scene(deformation_at=lambda t: deformation()):
    return SpecimenScene(
        deformation_at,
        scale_mm_per_px=SCALE,
        sensor_width=WIDTH,
        sensor_height=HEIGHT,
        material_y_range_mm=(-12.0, 12.0),
        half_width_mm=HALF_WIDTH,
        coat=COAT,
    )


def grid():
    xs, ys = np.meshgrid([70.0, 100.0, 130.0], [40.0, 85.0, 130.0, 175.0, 220.0])
    return np.c_[xs.ravel(), ys.ravel()]


def track(reference, target, points):
    correlator = Correlator(subset=SUBSET, search_radius=12)
    correlator.prepare(reference, points)
    result = correlator.measure(target).refinement
    assert result.ok().all()
    return points + np.c_[result.u, result.v]


def sim_config(**sim):
    config = Config()
    return dataclasses.replace(config, sim=dataclasses.replace(config.sim, **sim))


def test_the_ideal_bench_is_the_plain_scene():
    world = SimWorld.from_config(sim_config(), PRESETS["metal"].optics)
    assert world.bench.is_ideal
    assert type(world.scene) is SpecimenScene
    assert world.lens_camera.telecentric
    assert world.specimen_plane.normal_tilt_deg == 0.0


def test_the_ideal_bench_renders_bit_identically_to_the_plain_scene():
    config = sim_config(sensor_width_px=256, sensor_height_px=512)
    world = SimWorld.from_config(config, PRESETS["rubber"].optics)
    length = world.specimen.overall_length_mm
    plain = SpecimenScene(
        world.machine.deformation_at,
        scale_mm_per_px=PRESETS["rubber"].optics.scale_mm_per_px,
        sensor_width=256,
        sensor_height=512,
        material_y_range_mm=(-0.5 * length, 0.5 * length),
        half_width_mm=0.5 * world.specimen.end_width_mm,
        centre_mm=world.scene.centre_mm,
        coat=SpeckleCoat(radius_mm=PRESETS["rubber"].speckle_radius_mm, seed=config.sim.seed),
    )
    world.machine.start(world.speed_mm_min, 0.0)
    region = Region(0, 0, 256, 512)
    for start_s in (0.0, 2.0):
        image, _ = world.scene.render(start_s, start_s + 0.01, region)
        expected, _ = plain.render(start_s, start_s + 0.01, region)
        assert np.array_equal(image, expected)


def test_a_bench_without_errors_renders_as_the_plain_scene():
    moving = deformation(stretch=1.1, lateral=0.95, shift_mm=-1.0)
    plain, _ = plain_scene(lambda t: moving).render(0.0, 0.0, FULL)
    through, _ = bench_scene(bench(), lambda t: moving).render(0.0, 0.0, FULL)
    np.testing.assert_allclose(through, plain, atol=1e-9)


def test_distortion_and_tilt_put_object_points_where_the_camera_model_projects_them():
    errors = bench(
        entocentric=True,
        distortion=LensDistortion(k1=-0.2, k2=0.05, p1=0.002, p2=-0.001),
        camera_tilt_deg=2.0,
    )
    scene = bench_scene(errors)
    camera, pose = scene.geometry.camera, scene.geometry.pose
    corner = camera.distortion_px([[0.0, 0.0]])[0]
    assert corner > 2.0
    ideal, _ = plain_scene().render(0.0, 0.0, FULL)
    lensed, _ = scene.render(0.0, 0.0, FULL)
    points = grid()
    objects = np.column_stack(plain_scene().object_of(points[:, 0], points[:, 1]))
    expected = camera.project(pose.to_camera(objects))
    assert np.abs(expected - points).max() > 0.5
    found = track(ideal, lensed, points)
    np.testing.assert_allclose(found, expected, atol=0.02)
    truth = scene.image_positions(objects, 0.0, 0.0)
    np.testing.assert_allclose(truth, expected, atol=1e-9)


def test_a_region_renders_as_the_same_part_of_the_full_frame():
    errors = bench(entocentric=True, distortion=LensDistortion(k1=-0.2), camera_tilt_deg=1.0)
    scene = bench_scene(errors)
    full, _ = scene.render(0.0, 0.0, FULL)
    part, _ = scene.render(0.0, 0.0, Region(50, 70, 64, 48))
    np.testing.assert_allclose(part, full[70:118, 50:114], atol=0.01)


def test_out_of_plane_slack_scales_the_image_by_the_distance_ratio():
    slack_mm = 0.3
    errors = bench(entocentric=True, slack_out_of_plane_mm=slack_mm)
    frames = {0.0: deformation(), 1.0: deformation(travel_mm=2.0)}
    scene = bench_scene(errors, lambda t: frames[t])
    reference, _ = scene.render(0.0, 0.0, FULL)
    moved, _ = scene.render(1.0, 1.0, FULL)
    points = np.array([[100.0, 60.0], [100.0, 200.0]])
    found = track(reference, moved, points)
    ratio = np.hypot(*(found[1] - found[0])) / np.hypot(*(points[1] - points[0]))
    assert ratio == pytest.approx(DISTANCE_MM / (DISTANCE_MM + slack_mm), abs=1e-4)


def test_thinning_recedes_the_surface_by_half_the_thickness_lost():
    errors = bench(entocentric=True, thinning_out_of_plane=True)
    geometry_ = geometry(errors)
    thinned = deformation(stretch=1.44, lateral=1.0 / 1.2)
    dz = geometry_.out_of_plane_mm(thinned, np.array([0.0]))[0]
    assert dz == pytest.approx(0.5 * 2.0 * (1.0 - 1.0 / 1.2))
    scene = bench_scene(errors, lambda t: thinned)
    material = np.array([[0.0, -2.0], [0.0, 2.0]])
    image = scene.image_positions(material, 0.0, 0.0)
    imaged_mm = np.hypot(*(image[1] - image[0])) * SCALE
    assert imaged_mm == pytest.approx(4.0 * 1.44 * DISTANCE_MM / (DISTANCE_MM + dz), rel=1e-9)
    np.testing.assert_allclose(scene.material_points(image, 0.0), material, atol=1e-9)


def test_flicker_follows_the_sine_integrated_over_each_exposure():
    percent, mains_hz, exposure_s = 5.0, 50.0, 0.003
    scene = bench_scene(bench(flicker_percent=percent, mains_frequency_hz=mains_hz))
    steady = plain_scene().render(0.0, 0.0, FULL)[0].mean()
    omega = 2 * math.pi * 2 * mains_hz
    for start in np.linspace(0.0, 0.01, 7):
        image, _ = scene.render(start, start + exposure_s, FULL)
        mean = (math.cos(omega * start) - math.cos(omega * (start + exposure_s))) / (
            omega * exposure_s
        )
        assert image.mean() / steady == pytest.approx(1 + 0.01 * percent * mean, rel=1e-9)


def test_vibration_shifts_the_image_by_its_rms():
    rms_px, hz = 0.5, 20.0
    scene = bench_scene(bench(vibration_px_rms=rms_px, vibration_frequency_hz=hz), seed=3)
    times = np.arange(16) / (16 * hz)
    frames = [scene.render(t, t, FULL)[0] for t in times]
    points = np.array([[100.0, 130.0]])
    shifts = np.array([track(frames[0], frame, points)[0] for frame in frames])
    deviation = shifts - shifts.mean(axis=0)
    assert math.sqrt(np.mean(np.sum(deviation**2, axis=1))) == pytest.approx(rms_px, abs=0.01)


def test_warm_up_drift_scales_the_image():
    percent, tau_s = 1.0, 10.0
    scene = bench_scene(bench(warm_up_drift_percent=percent, warm_up_time_constant_s=tau_s))
    reference, _ = scene.render(0.0, 0.0, FULL)
    warm, _ = scene.render(30.0, 30.0, FULL)
    points = np.array([[100.0, 60.0], [100.0, 200.0]])
    found = track(reference, warm, points)
    ratio = np.hypot(*(found[1] - found[0])) / np.hypot(*(points[1] - points[0]))
    assert ratio == pytest.approx(1 + 0.01 * percent * (1 - math.exp(-3.0)), abs=1e-4)


def test_the_truth_in_pixels_is_where_the_camera_sees_the_material():
    errors = bench(
        entocentric=True,
        distortion=LensDistortion(k1=-0.2, p1=0.001),
        camera_tilt_deg=1.0,
        thinning_out_of_plane=True,
        slack_out_of_plane_mm=0.2,
        vibration_px_rms=0.3,
        warm_up_drift_percent=0.5,
        warm_up_time_constant_s=2.0,
    )
    frames = {0.0: deformation(), 1.0: deformation(stretch=1.05, lateral=0.976, travel_mm=1.5)}
    scene = bench_scene(errors, lambda t: frames[t])
    reference, _ = scene.render(0.0, 0.0, FULL)
    later, _ = scene.render(1.0, 1.0, FULL)
    points = grid()[3:12]
    material = scene.material_points(points, 0.0)
    np.testing.assert_allclose(scene.image_positions(material, 0.0, 0.0), points, atol=1e-9)
    found = track(reference, later, points)
    np.testing.assert_allclose(found, scene.image_positions(material, 1.0, 1.0), atol=0.05)


def test_the_presets_keys_override_them():
    typical = bench_errors(sim_config(bench="typical").sim, (1024, 2048), 2638.0)
    assert typical.entocentric and typical.thinning_out_of_plane
    assert typical.flicker_percent == BENCHES["typical"].flicker_percent
    r = corner_radius((1024, 2048), 2638.0)
    d = typical.distortion
    assert d.k1 * r**2 + d.k2 * r**4 == pytest.approx(-0.01)
    changed = bench_errors(
        sim_config(bench="typical", lens="telecentric", lens_k1=0.02, flicker_percent=0.0).sim,
        (1024, 2048),
        2638.0,
    )
    assert not changed.entocentric
    assert changed.distortion.k1 == 0.02 and changed.distortion.k2 == d.k2
    assert changed.flicker_percent == 0.0
    assert changed.vibration_px_rms == typical.vibration_px_rms
    ideal = bench_errors(sim_config(flicker_percent=2.0).sim, (1024, 2048), 2638.0)
    assert not ideal.is_ideal and ideal.flicker_percent == 2.0


def test_a_telecentric_lens_displaces_pixels_as_the_pinhole_with_the_same_coefficients():
    distortion = LensDistortion(k1=-0.2, k2=0.05, p1=0.002, p2=-0.001)
    pinhole = geometry(bench(entocentric=True, distortion=distortion)).camera
    telecentric = geometry(bench(distortion=distortion)).camera
    corners = np.array([[0.0, 0.0], [WIDTH - 1.0, HEIGHT - 1.0], [10.0, 200.0]])
    np.testing.assert_allclose(
        telecentric.distortion_px(corners), pinhole.distortion_px(corners), rtol=1e-9
    )


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("bench", '"awful"'),
        ("lens", '"fisheye"'),
        ("lens_k1", "2.0"),
        ("lens_p2", "0.1"),
        ("camera_tilt_deg", "11"),
        ("slack_out_of_plane_mm", "-6"),
        ("flicker_percent", "25"),
        ("mains_frequency_hz", "70"),
        ("vibration_px_rms", "-0.1"),
        ("warm_up_time_constant_s", "0"),
    ],
)
def test_out_of_range_keys_are_refused_in_one_line(key, value):
    with pytest.raises(InputError) as error:
        parse_config(f"[sim]\n{key} = {value}\n", "bench.toml")
    message = str(error.value)
    assert "\n" not in message and key in message and "bench.toml" in message


def test_a_lens_that_folds_over_within_the_image_is_refused_in_one_line():
    config = sim_config(bench="typical", lens_k1=-1.0, lens_k2=-1.0)
    with pytest.raises(InputError) as error:
        SimWorld.from_config(
            config, dataclasses.replace(PRESETS["rubber"].optics, focal_length_mm=4.0)
        )
    assert "\n" not in str(error.value) and "lens_k1" in str(error.value)


def test_vibration_blurs_an_exposure_where_the_truth_averages_it():
    scene = bench_scene(bench(vibration_px_rms=0.5, vibration_frequency_hz=20.0), seed=3)
    assert len(scene.time_samples(0.0, 0.01)) == 4
    reference, _ = scene.render(0.0, 0.0, FULL)
    blurred, _ = scene.render(0.0, 0.01, FULL)
    points = np.array([[100.0, 90.0], [100.0, 170.0]])
    material = scene.material_points(points, 0.0)
    found = track(reference, blurred, scene.image_positions(material, 0.0, 0.0))
    np.testing.assert_allclose(found, scene.image_positions(material, 0.0, 0.01), atol=0.02)
