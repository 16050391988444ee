"""Gauges measured in the object plane through a camera calibration's plane projection."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from appliance.config import Config, parse_config
from appliance.errors import InputError
from appliance.measure.gauges import Calibration, Gauge, StrainGauges, place_marks
from appliance.optics.calibration_file import CameraCalibration, save_calibration
from appliance.optics.camera_model import (
    CameraModel,
    LensDistortion,
    PlanePose,
    PlaneProjection,
)
from appliance.plan.optics import Optics
from appliance.recording.calibration_record import (
    calibration_metadata,
    recorded_calibration,
    recorded_nominal_scale,
)
from appliance.run.object_plane import (
    calibration_facts,
    check_image_size,
    configured_calibration,
    out_of_plane_bound,
    resolved_calibration_path,
)
from appliance.run.outputs import RunFacts

WIDTH, HEIGHT = 1024, 2048
SCALE = 0.05
LENS = LensDistortion(k1=-0.25, k2=0.08, p1=0.001, p2=-0.0015, k3=0.0)


def facing_pinhole(distance_mm=300.0, distortion=None) -> PlaneProjection:
    """A pinhole camera square to the plane, SCALE mm/px at the plane."""
    camera = CameraModel.ideal(WIDTH, HEIGHT, distance_mm / SCALE, distortion=distortion)
    return PlaneProjection(camera, PlanePose.facing(distance_mm))


def tilted_distorted() -> PlaneProjection:
    camera = CameraModel.ideal(WIDTH, HEIGHT, 6000.0, distortion=LENS)
    return PlaneProjection(camera, PlanePose((0.06, -0.1, 0.02), (-4.0, -8.0, 300.0)))


def stretch(points, centre, axial, lateral):
    out = np.asarray(points, dtype=float).copy()
    out[:, 1] = centre[1] + axial * (out[:, 1] - centre[1])
    out[:, 0] = centre[0] + lateral * (out[:, 0] - centre[0])
    return out


def true_marks_mm() -> tuple[np.ndarray, Gauge, Gauge]:
    """Plane points (mm) of two axial marks of three points and a transverse pair."""
    points = np.array(
        [[-0.4, -10.0], [0.0, -10.0], [0.4, -10.0], [-0.4, 10.0], [0.0, 10.0], [0.4, 10.0]]
        + [[-3.0, 0.0], [3.0, 0.0]]
    )
    return points, Gauge((0, 1, 2), (3, 4, 5)), Gauge((6,), (7,))


@pytest.mark.parametrize("telecentric", [False, True])
def test_an_ideal_facing_calibration_measures_as_the_nominal_scale(telecentric):
    if telecentric:
        camera = CameraModel.ideal(WIDTH, HEIGHT, 1.0 / SCALE, telecentric=True)
        projection = PlaneProjection(camera, PlanePose.facing(300.0))
    else:
        projection = facing_pinhole()
    nominal = Calibration(SCALE)
    plane = Calibration(SCALE, projection)
    centre = (512.0, 1000.0)
    points, layout = place_marks(centre, 40.0, nominal, transverse_width_mm=8.0)
    placed, placed_layout = place_marks(centre, 40.0, plane, transverse_width_mm=8.0)
    np.testing.assert_allclose(placed, points, atol=1e-9)
    assert placed_layout == layout
    by_scale = StrainGauges(layout.axial, points, nominal, layout.transverse)
    in_plane = StrainGauges(layout.axial, points, plane, layout.transverse)
    assert in_plane.gauge_length_mm == pytest.approx(by_scale.gauge_length_mm, rel=1e-12)
    for lam in (1.0, 1.001, 1.3, 3.0):
        moved = stretch(points, centre, lam, lam**-0.5)
        a, b = by_scale.read(moved), in_plane.read(moved)
        assert b.engineering_strain == pytest.approx(a.engineering_strain, rel=1e-9, abs=1e-14)
        assert b.elongation_mm == pytest.approx(a.elongation_mm, rel=1e-9, abs=1e-12)
        assert b.gauge_length_mm == pytest.approx(a.gauge_length_mm, rel=1e-12)
        assert b.transverse_strain == pytest.approx(a.transverse_strain, rel=1e-9, abs=1e-14)
        assert b.axial_px == a.axial_px


def test_a_distorting_tilted_camera_measures_the_true_millimetres():
    projection = tilted_distorted()
    truth, axial, transverse = true_marks_mm()
    pixels = projection.to_pixels(truth)
    gauges = StrainGauges(axial, pixels, Calibration(SCALE, projection), transverse)
    assert gauges.gauge_length_mm == pytest.approx(20.0, abs=1e-9)
    nominal = StrainGauges(axial, pixels, Calibration(projection.scale_mm_per_px((512, 1024))))
    assert abs(nominal.gauge_length_mm - 20.0) > 0.05
    for lam in (1.01, 1.5, 4.0):
        moved_mm = stretch(truth, (0.0, 0.0), lam, lam**-0.5)
        reading = gauges.read(projection.to_pixels(moved_mm))
        assert reading.engineering_strain == pytest.approx(lam - 1.0, abs=1e-10)
        assert reading.gauge_length_mm == pytest.approx(20.0 * lam, abs=1e-9)
        assert reading.elongation_mm == pytest.approx(20.0 * (lam - 1.0), abs=1e-9)
        assert reading.transverse_strain == pytest.approx(lam**-0.5 - 1.0, abs=1e-10)


def test_a_mark_is_the_mean_of_its_points_plane_positions():
    projection = tilted_distorted()
    truth, axial, _ = true_marks_mm()
    pixels = projection.to_pixels(truth)
    expected = float(np.hypot(*(truth[3:6].mean(axis=0) - truth[0:3].mean(axis=0))))
    assert axial.length_mm(pixels, projection) == pytest.approx(expected, abs=1e-10)
    valid = np.array([True, False, False, True, True, True, True, True])
    expected = float(np.hypot(*(truth[3:6].mean(axis=0) - truth[0])))
    assert axial.length_mm(pixels, projection, valid) == pytest.approx(expected, abs=1e-10)
    valid[0] = False
    assert math.isnan(axial.length_mm(pixels, projection, valid))
    gauges = StrainGauges(axial, pixels, Calibration(SCALE, projection))
    reading = gauges.read(pixels, valid)
    assert math.isnan(reading.engineering_strain) and math.isnan(reading.gauge_length_mm)
    nan_points = pixels.copy()
    nan_points[0] = np.nan
    assert math.isnan(axial.length_mm(nan_points, projection))


def test_zeroing_in_the_plane_makes_the_current_lengths_l0():
    projection = tilted_distorted()
    truth, axial, _ = true_marks_mm()
    gauges = StrainGauges(axial, projection.to_pixels(truth), Calibration(SCALE, projection))
    moved = projection.to_pixels(stretch(truth, (0.0, 0.0), 1.2, 1.0))
    gauges.rezero(moved)
    assert gauges.gauge_length_mm == pytest.approx(24.0, abs=1e-9)
    assert gauges.read(moved).engineering_strain == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("along_axis", [False, True])
def test_marks_are_placed_l0_apart_on_the_plane(along_axis):
    projection = tilted_distorted()
    calibration = Calibration(SCALE, projection)
    points, layout = place_marks(
        (500.0, 1100.0),
        30.0,
        calibration,
        axis_deg=80.0,
        mark_width_px=16.0,
        points_per_mark=3,
        transverse_width_mm=6.0,
        along_axis=along_axis,
    )
    plane = projection.to_plane_mm(points)
    assert np.hypot(*(plane[4] - plane[1])) == pytest.approx(30.0, abs=1e-9)
    assert np.hypot(*(plane[7] - plane[6])) == pytest.approx(6.0, abs=1e-9)
    centre = projection.to_plane_mm(np.array([[500.0, 1100.0]]))[0]
    np.testing.assert_allclose((plane[1] + plane[4]) / 2, centre, atol=1e-9)
    np.testing.assert_allclose((plane[6] + plane[7]) / 2, centre, atol=1e-9)
    assert np.dot(plane[4] - plane[1], plane[7] - plane[6]) == pytest.approx(0.0, abs=1e-9)
    assert np.hypot(*(points[1] - points[0])) == pytest.approx(8.0, abs=1e-9)
    gauges = StrainGauges(layout.axial, points, calibration, layout.transverse)
    assert gauges.gauge_length_mm == pytest.approx(30.0, rel=1e-4)


def test_marks_off_the_plane_are_refused():
    camera = CameraModel.ideal(WIDTH, HEIGHT, 6000.0)
    steep = PlaneProjection(camera, PlanePose((1.45, 0.0, 0.0), (0.0, 0.0, 300.0)))
    with pytest.raises(ValueError, match="outside the camera's view|cannot be mapped"):
        place_marks((512.0, 1024.0), 5000.0, Calibration(SCALE, steep))


def _save(tmp_path: Path, name="lens.cal.json", size=(WIDTH, HEIGHT)) -> CameraCalibration:
    camera = CameraModel.ideal(*size, 6000.0, distortion=LENS)
    calibration = CameraCalibration(
        camera, PlanePose((0.0, 0.0, 0.0), (0.0, 0.0, 300.0)), 0.05, view_errors_px=(0.1,)
    )
    save_calibration(calibration, tmp_path / name)
    return calibration


def test_the_configured_calibration_is_read_relative_to_the_configuration(tmp_path):
    saved = _save(tmp_path)
    config_file = tmp_path / "run.toml"
    config = parse_config('[optics]\ncalibration = "lens.cal.json"\n', str(config_file))
    resolved = resolved_calibration_path(config, config_file)
    assert resolved.optics.calibration == str(tmp_path / "lens.cal.json")
    assert resolved_calibration_path(config, None) is config
    absolute = parse_config(f'[optics]\ncalibration = "{tmp_path / "lens.cal.json"}"\n')
    assert resolved_calibration_path(absolute, Path("/elsewhere/run.toml")) is absolute
    optics = Optics(14.0, 400.0, 5.5)
    calibration = configured_calibration(resolved, optics, (WIDTH, HEIGHT))
    assert calibration.in_object_plane and calibration.checksum == saved.checksum
    assert calibration.file == str(tmp_path / "lens.cal.json")
    assert calibration_facts(calibration) == {
        "measured_in": "object plane",
        "calibration_file": str(tmp_path / "lens.cal.json"),
        "calibration_checksum": saved.checksum,
    }
    nominal = configured_calibration(Config(), optics)
    assert not nominal.in_object_plane
    assert nominal.scale_mm_per_px == optics.scale_mm_per_px
    assert calibration_facts(nominal)["measured_in"] == "nominal scale"


def test_a_calibration_for_another_size_or_a_bad_file_is_refused_in_one_line(tmp_path):
    _save(tmp_path)
    config = parse_config(f'[optics]\ncalibration = "{tmp_path / "lens.cal.json"}"\n')
    optics = Optics(14.0, 400.0, 5.5)
    with pytest.raises(InputError, match=r"^\[optics\] calibration: .*1024x2048 px sensor"):
        configured_calibration(config, optics, (512, 1024))
    calibration = configured_calibration(config, optics)
    with pytest.raises(InputError, match="the images are 1024x1000 px"):
        check_image_size(calibration, 1024, 1000)
    check_image_size(calibration, WIDTH, HEIGHT)
    missing = parse_config(f'[optics]\ncalibration = "{tmp_path / "none.json"}"\n')
    with pytest.raises(InputError, match=r"^\[optics\] calibration: .*no such calibration"):
        configured_calibration(missing, optics)
    document = json.loads((tmp_path / "lens.cal.json").read_text())
    document["scale_mm_per_px"] = 0.06
    (tmp_path / "lens.cal.json").write_text(json.dumps(document))
    with pytest.raises(InputError, match="checksum mismatch"):
        configured_calibration(config, optics)


def test_out_of_plane_motion_gives_dz_over_z_and_the_class_it_allows(tmp_path):
    optics = Optics(14.0, 400.0, 5.5)
    nominal = Calibration(optics.scale_mm_per_px)
    bound = out_of_plane_bound(nominal, optics.object_distance_mm, 50.0, 0.1)
    assert bound.false_strain == pytest.approx(0.1 / 400.0)
    assert bound.stand_off_from == "[optics] object_distance_mm"
    assert bound.iso9513_class_at_1_percent is None
    assert out_of_plane_bound(nominal, 400.0, 50.0, 0.005).iso9513_class_at_1_percent == "0.2"
    assert out_of_plane_bound(nominal, 400.0, 50.0, 0.03).iso9513_class_at_1_percent == "1"
    assert "dz / Z" in bound.describe() and "400.0 mm" in bound.describe()
    pose = PlanePose((0.3, 0.0, 0.0), (10.0, -20.0, 250.0))
    camera = CameraCalibration(CameraModel.ideal(WIDTH, HEIGHT, 5000.0), pose, 0.05)
    calibrated = out_of_plane_bound(Calibration.object_plane(camera), 400.0, 50.0, 0.1)
    normal = pose.rotation[:, 2]
    assert calibrated.stand_off_mm == pytest.approx(abs(normal @ pose.translation))
    assert calibrated.stand_off_from == "calibration"
    assert calibrated.false_strain == pytest.approx(0.1 / calibrated.stand_off_mm)
    telecentric = CameraCalibration(
        CameraModel.ideal(WIDTH, HEIGHT, 20.0, telecentric=True), pose, 0.05
    )
    flat = out_of_plane_bound(Calibration.object_plane(telecentric), 400.0, 50.0, 0.1)
    assert flat.false_strain == 0.0 and flat.stand_off_mm is None
    assert flat.iso9513_class_at_1_percent == "0.2"
    assert "telecentric" in flat.describe()


def test_the_false_strain_is_what_a_moved_plane_reads(tmp_path):
    distance = 300.0
    projection = facing_pinhole(distance)
    truth, axial, _ = true_marks_mm()
    gauges = StrainGauges(axial, projection.to_pixels(truth), Calibration(SCALE, projection))
    closer = PlaneProjection(projection.camera, PlanePose.facing(distance - 0.1))
    reading = gauges.read(closer.to_pixels(truth))
    bound = out_of_plane_bound(Calibration(SCALE, projection), distance, 20.0, 0.1)
    assert reading.engineering_strain == pytest.approx(0.1 / (distance - 0.1), rel=1e-9)
    assert bound.false_strain == pytest.approx(reading.engineering_strain, rel=1e-3)


def test_the_recorded_calibration_is_the_whole_document(tmp_path):
    saved = _save(tmp_path)
    calibration = Calibration.object_plane(saved, "lens.cal.json")
    facts = RunFacts(
        config=Config(),
        reference=None,
        points=np.zeros((2, 2)),
        marks=((0,), (1,)),
        layout=None,
        calibration=calibration,
        gauge_length_mm=25.0,
        epoch_offset_ns=0,
        facts={"nominal_scale_mm_per_px": 0.15},
    )
    record = calibration_metadata(facts)
    assert all(isinstance(v, str) for v in record.values())
    assert record["measured_in"] == "object plane" and record["checksum"] == saved.checksum
    assert json.loads(record["document"])["checksum"] == saved.checksum
    again = recorded_calibration(record, "test.mcap")
    assert again.checksum == saved.checksum and again.file == "lens.cal.json"
    assert again.camera == saved
    assert recorded_nominal_scale(record) == 0.15
    altered = dict(record, document=record["document"].replace('"views": 1', '"views": 2'))
    with pytest.raises(InputError, match="test.mcap .recorded calibration.: .*checksum"):
        recorded_calibration(altered, "test.mcap")
    nominal = calibration_metadata(
        RunFacts(Config(), None, np.zeros((2, 2)), (), None, Calibration(0.1), 25.0, 0)
    )
    assert nominal["measured_in"] == "nominal scale" and nominal["document"] == ""
    assert recorded_calibration(nominal, "x") == Calibration(0.1)
    assert recorded_calibration({"scale_mm_per_px": "0.1", "gauge_length_mm": "2"}, "x") == (
        Calibration(0.1)
    )
