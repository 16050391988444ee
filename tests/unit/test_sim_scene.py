import math

import numpy as np
import pytest

from appliance.dic.bspline import PAD, sample
from appliance.dic.correlation import Correlator
from appliance.sim.deformation import AxialDeformation
from appliance.sim.scene import SpecimenScene, SpeckleCoat
from hal.camera.base import CameraSettings, Region, Scene, TriggerInfo, TriggerMode
from hal.camera.sim import SimCamera
from hal.clock import SimClock

SCALE = 0.05
WIDTH, HEIGHT = 200, 260
HALF_WIDTH = 3.5
COAT = SpeckleCoat(radius_mm=2 * SCALE, seed=7)
FULL = Region(0, 0, WIDTH, HEIGHT)
TABLE_Y = np.linspace(-40.0, 40.0, 81)


def deformation(stretch=1.0, lateral=1.0, shift_mm=0.0, half_width=(HALF_WIDTH, HALF_WIDTH)):
    """Uniform stretch about Y = 0 with lateral contraction, then an axial translation."""
    return AxialDeformation(
        material_y_mm=TABLE_Y,
        spatial_y_mm=shift_mm + stretch * TABLE_Y,
        lateral_stretch=np.full(TABLE_Y.size, lateral),
        half_width_mm=np.linspace(*half_width, TABLE_Y.size),
    )


def make_scene(deformation_at, **kwargs):
    options = dict(
        scale_mm_per_px=SCALE,
        sensor_width=WIDTH,
        sensor_height=HEIGHT,
        material_y_range_mm=(-12.0, 12.0),
        half_width_mm=HALF_WIDTH,
        coat=COAT,
    )
    options.update(kwargs)
    return SpecimenScene(deformation_at, **options)


def grid():
    xs, ys = np.meshgrid([70.0, 100.0, 130.0], [50.0, 90.0, 130.0, 170.0, 210.0])
    return np.c_[xs.ravel(), ys.ravel()]


def track(reference, target, points):
    correlator = Correlator(subset=41, search_radius=12)
    correlator.prepare(reference, points)
    result = correlator.measure(target).refinement
    assert result.ok().all()
    return np.c_[result.u, result.v]


@pytest.fixture(scope="module")
def still():
    return make_scene(lambda t: deformation())


def test_scene_satisfies_the_camera_protocol(still):
    assert isinstance(still, Scene)
    assert (still.sensor_width, still.sensor_height) == (WIDTH, HEIGHT)


def test_undeformed_render_is_the_analytic_coat():
    # A quarter-pixel offset puts every pixel centre half-way between texels (the worst case).
    scene = make_scene(lambda t: deformation(), centre_mm=(0.25 * SCALE, 0.25 * SCALE))
    image, truth = scene.render(0.0, 0.0, FULL)
    assert image.shape == (HEIGHT, WIDTH)
    assert truth["time_samples"] == 1 and truth["time_s"] == 0.0
    cols, rows = np.meshgrid(np.arange(WIDTH), np.arange(HEIGHT))
    x, y = scene.object_of(cols, rows)
    inside = np.abs(x) <= HALF_WIDTH - SCALE / 2
    exact = scene.coat_intensity(x[inside], y[inside])
    assert np.std(exact) > 30.0
    error = image[inside] - exact
    assert np.sqrt(np.mean(error**2)) < 0.02
    assert np.max(np.abs(error)) < 0.1
    assert np.all(image[np.abs(x) >= HALF_WIDTH + SCALE / 2] == scene.background)


def test_pixel_and_object_coordinates_are_inverse(still):
    x, y = still.object_of([0.0, 99.5, 199.0], [0.0, 129.5, 259.0])
    np.testing.assert_allclose(x, [-99.5 * SCALE, 0.0, 99.5 * SCALE])
    np.testing.assert_allclose(y, [-129.5 * SCALE, 0.0, 129.5 * SCALE])
    col, row = still.pixel_of(x, y)
    np.testing.assert_allclose(col, [0.0, 99.5, 199.0])
    np.testing.assert_allclose(row, [0.0, 129.5, 259.0])


def test_rigid_subpixel_translation_is_tracked_to_the_truth():
    axial = make_scene(lambda t: deformation(shift_mm=0.37 * SCALE * t))
    lateral = make_scene(lambda t: deformation(), centre_mm=(-0.23 * SCALE, 0.0))
    reference, _ = axial.render(0.0, 0.0, FULL)
    points = grid()
    material = axial.material_points(points, 0.0)
    for scene, expected in ((axial, (0.0, 0.37)), (lateral, (0.23, 0.0))):
        target, _ = scene.render(1.0, 1.0, FULL)
        truth = scene.image_positions(material, 1.0, 1.0) - points
        np.testing.assert_allclose(truth, np.tile(expected, (len(points), 1)), atol=1e-9)
        np.testing.assert_allclose(track(reference, target, points), truth, atol=0.01)


def test_uniform_stretch_is_tracked_to_the_image_positions():
    scene = make_scene(lambda t: deformation(stretch=1.0 + 0.04 * t, lateral=1.0 - 0.015 * t))
    reference, _ = scene.render(0.0, 0.0, FULL)
    target, _ = scene.render(1.0, 1.0, FULL)
    points = grid()
    truth = scene.image_positions(scene.material_points(points, 0.0), 1.0, 1.0) - points
    assert np.ptp(truth[:, 1]) > 6.0
    np.testing.assert_allclose(track(reference, target, points), truth, atol=0.02)


def test_specimen_edges_are_where_the_lateral_stretch_puts_them():
    shape = deformation(stretch=1.2, lateral=0.9, shift_mm=0.3, half_width=(3.0, 3.6))
    blank = SpeckleCoat(radius_mm=0.1, levels=(200.0 - 1e-6, 200.0 + 1e-6))
    scene = make_scene(lambda t: shape, coat=blank)
    image, _ = scene.render(0.0, 0.0, FULL)
    coverage = (image - scene.background) / (200.0 - scene.background)
    centre = 0.5 * (WIDTH - 1)
    left = centre - coverage[:, : WIDTH // 2].sum(axis=1)
    right = centre + coverage[:, WIDTH // 2 :].sum(axis=1)
    _, y = scene.object_of(0.0, np.arange(HEIGHT))
    Y = shape.material_y(y)
    half_width = shape.lateral_stretch_at(Y) * shape.half_width_at(Y)
    np.testing.assert_allclose(left, scene.pixel_of(-half_width, y)[0], atol=1e-4)
    np.testing.assert_allclose(right, scene.pixel_of(half_width, y)[0], atol=1e-4)
    assert np.ptp(right - left) > 2.0


def test_rows_beyond_the_textured_material_show_the_backdrop():
    scene = make_scene(lambda t: deformation(), centre_mm=(0.0, 10.0))
    image, _ = scene.render(0.0, 0.0, FULL)
    last_textured = math.floor(scene.pixel_of(0.0, 12.0)[1])
    assert np.all(image[last_textured + 1 :] == scene.background)
    assert np.ptp(image[last_textured, 60:140]) > 50.0


@pytest.fixture(scope="module")
def moving():
    speed_px = {"value": 8.0}
    scene = make_scene(lambda t: deformation(shift_mm=speed_px["value"] * SCALE * t))
    return scene, speed_px


def test_exposure_is_the_mean_of_its_time_samples(moving):
    scene, _ = moving
    blurred, truth = scene.render(0.0, 1.0, FULL)
    assert truth["time_samples"] == 32 and truth["time_s"] == 0.5
    times = truth["sample_times_s"]
    np.testing.assert_allclose(times, (np.arange(32) + 0.5) / 32)
    samples = [scene.render(t, t, FULL)[0] for t in times]
    np.testing.assert_allclose(blurred, np.mean(samples, axis=0), atol=1e-12)
    fine = np.mean([scene.render(t, t, FULL)[0] for t in (np.arange(256) + 0.5) / 256], axis=0)
    error = blurred - fine
    assert np.sqrt(np.mean(error**2)) < 0.05
    assert np.max(np.abs(error)) < 0.5
    sharp, _ = scene.render(0.5, 0.5, FULL)
    assert np.std(blurred[:, 60:140]) < 0.8 * np.std(sharp[:, 60:140])


def _exposure_by_definition(scene, start_s, stop_s, region):
    """`SpecimenScene.render` as its kernel defines it: every pixel of every time sample
    evaluated, weighted and added in sample order, in whole-array numpy operations."""
    times, deformations = scene._exposure(start_s, stop_s)
    weight = 1.0 / len(times)
    rows = np.arange(region.y, region.y + region.height, dtype=np.float64)
    cols = np.arange(region.x, region.x + region.width, dtype=np.float64)
    _, row_y = scene.object_of(0.0, rows)
    offset = (cols - 0.5 * (scene.sensor_width - 1))[np.newaxis, :]
    coefficients = scene._coefficients
    tx_max = coefficients.shape[1] - 2 * PAD - 1.0
    ty_max = coefficients.shape[0] - 2 * PAD - 1.0
    size = scene.scale_mm_per_px
    y_min, y_max = scene.material_y_range_mm
    image = np.zeros((region.height, region.width))
    for deformation in deformations:
        Y = deformation.material_y(row_y)
        stretch = deformation.lateral_stretch_at(Y)
        ty = np.clip((Y - scene.texture_origin_mm[1]) / scene.texel_mm, 0.0, ty_max)
        half_width = (deformation.half_width_at(Y) * stretch)[:, np.newaxis]
        x = scene.centre_mm[0] + offset * size
        cover = 0.5 + (half_width - np.abs(x)) * (1.0 / size)
        to_texels = ((1.0 / stretch) * (1.0 / scene.texel_mm))[:, np.newaxis]
        x_origin = scene.texture_origin_mm[0] / scene.texel_mm
        tx = np.clip(x * to_texels - x_origin, 0.0, tx_max)
        coat = sample(coefficients, tx, np.broadcast_to(ty[:, np.newaxis], tx.shape))
        back = scene.background
        value = np.where(cover >= 1.0, coat, back + cover * (coat - back))
        value = np.where(cover <= 0.0, back, value)
        value[~((Y >= y_min) & (Y <= y_max))] = back
        image += weight * value
    return image


def test_the_exposure_is_its_time_samples_summed():
    """The kernel evaluates only the columns near the specimen (the others are the backdrop
    it would have found) and interpolates the coat along texel rows first: the same values
    within rounding."""
    scene = make_scene(
        lambda t: deformation(stretch=1.0 + 0.3 * t, lateral=1.0 - 0.1 * t, shift_mm=2.0 * t),
        material_y_range_mm=(-5.0, 5.0),
    )
    for region in (FULL, Region(13, 21, 150, 97)):
        image, truth = scene.render(0.2, 0.6, region)
        assert truth["time_samples"] > 10
        expected = _exposure_by_definition(scene, 0.2, 0.6, region)
        np.testing.assert_allclose(image, expected, rtol=0.0, atol=1e-10)
        assert np.array_equal(image == scene.background, expected == scene.background)


def test_time_samples_follow_the_speed(moving):
    scene, speed = moving
    counts = {}
    for start, value in enumerate((0.1, 4.0, 8.0, 100.0)):
        speed["value"] = value
        counts[value] = scene.time_samples(10.0 + start, 11.0 + start)
    speed["value"] = 8.0
    assert {v: len(t) for v, t in counts.items()} == {0.1: 1, 4.0: 16, 8.0: 32, 100.0: 64}
    assert scene.time_samples(2.0, 2.0) == [2.0]
    assert scene.render(2.0, 2.0, FULL)[1]["time_samples"] == 1


def test_image_positions_average_over_the_exposure(moving):
    scene, _ = moving
    points = grid()
    material = scene.material_points(points, 0.0)
    np.testing.assert_allclose(scene.image_positions(material, 0.0, 0.0), points, atol=1e-9)
    mid = scene.image_positions(material, 0.5, 0.5)
    np.testing.assert_allclose(scene.image_positions(material, 0.0, 1.0), mid, atol=1e-9)
    np.testing.assert_allclose(mid - points, np.tile([0.0, 4.0], (len(points), 1)), atol=1e-9)


def test_renders_are_deterministic_for_a_seed_and_regions_are_crops(still):
    image, _ = still.render(0.0, 0.0, FULL)
    again, _ = make_scene(lambda t: deformation()).render(0.0, 0.0, FULL)
    np.testing.assert_array_equal(image, again)
    other = make_scene(lambda t: deformation(), coat=SpeckleCoat(radius_mm=2 * SCALE, seed=8))
    assert np.abs(other.render(0.0, 0.0, FULL)[0] - image).max() > 50.0
    crop, _ = still.render(0.0, 0.0, Region(30, 40, 100, 120))
    np.testing.assert_allclose(crop, image[40:160, 30:130], atol=1e-12)


def test_bad_requests_are_refused(still):
    with pytest.raises(ValueError, match="region"):
        still.render(0.0, 0.0, Region(150, 0, 100, 10))
    with pytest.raises(ValueError, match="stop_s"):
        still.render(1.0, 0.5, FULL)
    with pytest.raises(ValueError, match="material_y_range_mm"):
        make_scene(lambda t: deformation(), material_y_range_mm=(5.0, -5.0))
    with pytest.raises(ValueError, match="radius_mm"):
        SpeckleCoat(radius_mm=0.0)


def test_sim_camera_delivers_the_rendered_view(still):
    camera = SimCamera(
        "sim://camera", scene=still, clock=SimClock(), read_noise=0.0, electrons_per_grey=0.0
    )
    camera.open()
    camera.configure(CameraSettings(exposure_us=500.0))
    camera.prepare(TriggerInfo(mode=TriggerMode.INTERNAL, frames=1, rate_hz=10.0))
    camera.arm()
    frame = camera.fetch(timeout_s=1.0)
    expected, _ = still.render(0.0, 500e-6, FULL)
    np.testing.assert_array_equal(frame.image, np.clip(np.rint(expected), 0, 255))
    assert frame.metadata["truth"]["time_samples"] == 1
