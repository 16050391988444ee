import threading

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.optimize import brentq

from appliance.sim.bar import BarModel, BarPhase
from appliance.sim.crosshead import Crosshead
from appliance.sim.machine import MachineWithSpecimen
from appliance.sim.materials import ElasticPlastic, MooneyRivlin, NeoHookean
from appliance.sim.specimen import Specimen
from hal.clock import SimClock
from hal.machine.sim import MachineModel
from hal.registry import machine_from_url


@pytest.fixture(scope="module")
def rubber_bar():
    return BarModel(Specimen.iso37_type1(), MooneyRivlin.filled_rubber())


@pytest.fixture(scope="module")
def steel_bar():
    return BarModel(Specimen.iso6892_flat(), ElasticPlastic.steel_s355())


def predicted_displacement(piece, material, force_n):
    """Integral of (lambda - 1) over the free length, by adaptive quadrature of the outline."""

    def excess(Y):
        return float(material.stretch_at_stress(force_n / piece.cross_section_mm2(Y))) - 1.0

    half = 0.5 * piece.grip_distance_mm
    edges = [0.0, *[p for p in piece.breakpoints_mm() if p < half], half]
    return 2.0 * sum(
        quad(excess, a, b, epsabs=1e-12, epsrel=1e-12, limit=200)[0]
        for a, b in zip(edges[:-1], edges[1:], strict=True)
    )


# Materials


def test_neo_hookean_and_mooney_rivlin_known_values():
    neo = NeoHookean(shear_modulus_mpa=0.5)
    assert neo.nominal_stress_mpa(2.0) == pytest.approx(0.5 * (2.0 - 0.25))
    assert neo.nominal_stress_mpa(1.0) == 0.0
    assert neo.small_strain_modulus_mpa == pytest.approx(1.5)
    mooney = MooneyRivlin(c10_mpa=0.3, c01_mpa=0.05)
    assert mooney.nominal_stress_mpa(2.0) == pytest.approx(2.0 * 1.75 * (0.3 + 0.025))
    assert mooney.small_strain_modulus_mpa == pytest.approx(6.0 * 0.35)
    stretch = np.linspace(0.5, 8.0, 50)
    np.testing.assert_allclose(
        MooneyRivlin(c10_mpa=0.25, c01_mpa=0.0).nominal_stress_mpa(stretch),
        neo.nominal_stress_mpa(stretch),
        rtol=1e-14,
    )
    slope = (mooney.nominal_stress_mpa(3.0 + 1e-6) - mooney.nominal_stress_mpa(3.0 - 1e-6)) / 2e-6
    assert mooney.stress_slope_mpa(3.0) == pytest.approx(slope, rel=1e-7)


@pytest.mark.parametrize("material", [NeoHookean(0.4), MooneyRivlin.filled_rubber()])
def test_rubber_inverse_round_trip_and_incompressibility(material):
    stretch = np.linspace(0.5, 12.0, 2001)
    back = material.stretch_at_stress(material.nominal_stress_mpa(stretch))
    np.testing.assert_allclose(back, stretch, rtol=1e-12)
    lateral = material.lateral_stretch(stretch)
    np.testing.assert_allclose(stretch * lateral**2, 1.0, rtol=1e-14)
    assert material.break_stretch == pytest.approx(7.0)
    assert material.stretch_at_stress(material.peak_stress_mpa) == pytest.approx(7.0)


def test_rubber_rejects_bad_constants():
    with pytest.raises(ValueError, match="shear_modulus_mpa"):
        NeoHookean(0.0)
    with pytest.raises(ValueError, match="c01_mpa"):
        MooneyRivlin(0.3, -0.1)
    with pytest.raises(ValueError, match="break_strain"):
        MooneyRivlin(0.3, 0.05, break_strain=-1.0)


def test_metal_proof_stress_is_rp02_on_the_generated_curve():
    steel = ElasticPlastic.steel_s355()
    modulus = steel.youngs_modulus_mpa

    def offset(strain):
        return steel.nominal_stress_mpa(1.0 + strain) - modulus * (strain - 0.002)

    strain = brentq(offset, 0.0021, 0.05, xtol=1e-14)
    assert steel.nominal_stress_mpa(1.0 + strain) == pytest.approx(355.0, abs=0.1)
    assert steel.nominal_stress_mpa(1.0 + strain) == pytest.approx(355.0, abs=1e-6)
    slope = (steel.nominal_stress_mpa(1.0 + 1e-6) - steel.nominal_stress_mpa(1.0)) / 1e-6
    assert slope == pytest.approx(modulus, rel=1e-5)


def test_metal_force_peaks_at_the_uniform_elongation():
    steel = ElasticPlastic.steel_s355()
    stretch = np.linspace(1.0, 1.4, 400_001)
    stress = steel.nominal_stress_mpa(stretch)
    top = int(np.argmax(stress))
    assert stretch[top] == pytest.approx(steel.stretch_at_peak, abs=2e-6)
    assert stress[top] == pytest.approx(510.0, rel=1e-9)
    assert steel.peak_stress_mpa == pytest.approx(510.0, rel=1e-12)
    assert steel.total_uniform_elongation == pytest.approx(steel.stretch_at_peak - 1.0)
    assert steel.uniform_elongation == pytest.approx(
        steel.total_uniform_elongation - 510.0 / 210_000.0
    )
    assert 0.1 < steel.uniform_elongation < steel.elongation_after_fracture
    assert np.all(np.diff(stress[: top + 1]) > 0)
    assert np.all(np.diff(stress[top + 10 :]) < 0)


def test_metal_inverse_and_lateral_stretch():
    steel = ElasticPlastic.steel_s355()
    stretch = np.linspace(0.999, steel.stretch_at_peak, 5001)[:-1]
    back = steel.stretch_at_stress(steel.nominal_stress_mpa(stretch))
    np.testing.assert_allclose(back, stretch, rtol=1e-9)
    assert np.isnan(steel.stretch_at_stress(511.0))
    small = 1e-5
    assert (1.0 - steel.lateral_stretch(1.0 + small)) / small == pytest.approx(0.3, rel=1e-4)
    plastic_stretch = 1.1
    area = steel.lateral_stretch(plastic_stretch) * steel.thickness_stretch(plastic_stretch)
    sigma = steel.nominal_stress_mpa(plastic_stretch) / area
    volume = plastic_stretch * area
    expected = np.exp(sigma / 210_000.0) * (1.0 - 0.3 * sigma / 210_000.0) ** 2
    assert volume == pytest.approx(expected, rel=1e-12)
    plastic = steel.plastic_strain(plastic_stretch)
    unloaded, lateral = steel.elastic_state(plastic, 0.0)
    assert unloaded == pytest.approx(np.exp(plastic))
    assert lateral == pytest.approx(unloaded ** (-1.8 / 2.8), rel=1e-12)


def test_the_metal_sheet_gives_up_width_and_thickness_by_its_plastic_strain_ratio():
    steel = ElasticPlastic.steel_s355()
    assert steel.plastic_anisotropy == 1.8
    stretch = np.array([1.02, 1.05, 1.1, steel.stretch_at_peak])
    width = np.log(steel.lateral_stretch(stretch))
    thickness = np.log(steel.thickness_stretch(stretch))
    elastic = np.log(
        1.0
        - 0.3
        * steel.nominal_stress_mpa(stretch)
        / (210_000.0 * np.exp(-steel.plastic_strain(stretch)))
    )
    ratio = (width - elastic) / (thickness - elastic)
    np.testing.assert_allclose(ratio, 1.8, rtol=1e-3)
    isotropic = ElasticPlastic(210_000.0, 0.3, 355.0, 510.0, 0.25)
    np.testing.assert_allclose(
        isotropic.nominal_stress_mpa(stretch), steel.nominal_stress_mpa(stretch), rtol=1e-12
    )


def test_metal_rejects_impossible_properties():
    with pytest.raises(ValueError, match="tensile_strength_mpa"):
        ElasticPlastic(210_000.0, 0.3, 355.0, 300.0, 0.25)
    with pytest.raises(ValueError, match="elongation_after_fracture"):
        ElasticPlastic(210_000.0, 0.3, 355.0, 510.0, 0.05)
    with pytest.raises(ValueError, match="poisson_ratio"):
        ElasticPlastic(210_000.0, 0.5, 355.0, 510.0, 0.25)


# Specimens


def test_iso37_type1_outline():
    piece = Specimen.iso37_type1()
    assert piece.half_width_mm(0.0) == pytest.approx(3.1)
    assert piece.half_width_mm(16.5) == pytest.approx(3.1)
    assert piece.half_width_mm(50.0) == pytest.approx(12.5)
    assert piece.half_width_mm(60.0) == 0.0
    assert piece.shoulder_end_mm == pytest.approx(41.894, abs=1e-3)
    Y = np.linspace(0.0, piece.shoulder_end_mm, 20001)
    width = piece.half_width_mm(Y)
    assert np.all(np.diff(width) >= 0)
    slope = np.diff(width) / np.diff(Y)
    assert np.max(np.abs(np.diff(slope))) < 1e-3
    np.testing.assert_array_equal(piece.half_width_mm(-Y), width)
    assert piece.cross_section_mm2(0.0) == pytest.approx(12.4)
    assert Specimen.iso37_type1a().shoulder_end_mm == pytest.approx(35.4, abs=0.01)


def test_iso6892_flat_outline_has_the_transition_radius():
    piece = Specimen.iso6892_flat()
    assert (piece.parallel_width_mm, piece.gauge_length_mm, piece.parallel_length_mm) == (
        12.5,
        50.0,
        75.0,
    )
    u = 5.0
    expected = 6.25 + 20.0 - np.sqrt(20.0**2 - u**2)
    assert piece.half_width_mm(37.5 + u) == pytest.approx(expected)
    assert piece.half_width_mm(piece.shoulder_end_mm) == pytest.approx(10.0)
    assert Specimen.iso6892_flat(specimen_type=2).parallel_width_mm == 20.0


def test_specimen_validation():
    good = dict(
        overall_length_mm=115.0,
        end_width_mm=25.0,
        parallel_length_mm=33.0,
        parallel_width_mm=6.2,
        transition_radius_mm=25.0,
        outer_radius_mm=14.0,
        thickness_mm=2.0,
        gauge_length_mm=25.0,
        grip_distance_mm=90.0,
    )
    Specimen(**good)
    for key, value, message in [
        ("grip_distance_mm", 70.0, "grip_distance_mm"),
        ("gauge_length_mm", 40.0, "gauge_length_mm"),
        ("end_width_mm", 6.0, "end_width_mm"),
        ("thickness_mm", 0.0, "thickness_mm"),
        ("end_width_mm", 100.0, "radii"),
        ("overall_length_mm", 80.0, "overall_length_mm"),
    ]:
        with pytest.raises(ValueError, match=message):
            Specimen(**{**good, key: value})


# Bar


def test_bar_elongation_integral_equals_the_crosshead_displacement(rubber_bar, steel_bar):
    for bar in (rubber_bar, steel_bar):
        piece = bar.specimen
        half = 0.5 * piece.grip_distance_mm
        for d in (0.3 * bar.peak_crosshead_mm, 0.9 * bar.peak_crosshead_mm):
            state = bar.deformation(d)
            predicted = predicted_displacement(piece, bar.material, state.force_n)
            assert predicted == pytest.approx(d, abs=2e-6)
            y = state.spatial_y([-half, half])
            assert y[0] == pytest.approx(-half - d, abs=1e-9)
            assert y[1] == half
            np.testing.assert_array_equal(
                state.spatial_y([half + 1.0, half + 10.0]), [half + 1.0, half + 10.0]
            )


def test_every_loaded_state_closes_the_grip_distance_to_the_solver_tolerance(rubber_bar, steel_bar):
    """Through loading and necking, the solved stretch puts the moving clamp edge where the
    crosshead is (equation 1), within the Illinois tolerance of 1e-12 of the grip distance."""
    for bar in (rubber_bar, steel_bar):
        half = 0.5 * bar.specimen.grip_distance_mm
        for d in np.linspace(1e-3, 0.999 * bar.breaking_crosshead_mm, 41):
            edge = bar.deformation(float(d)).spatial_y([-half])[0]
            assert abs(edge + half + d) <= 4e-12 * bar.specimen.grip_distance_mm + 1e-12


def test_bar_stretch_profile_and_force(rubber_bar, steel_bar):
    for bar in (rubber_bar, steel_bar):
        piece = bar.specimen
        state = bar.deformation(0.7 * bar.peak_crosshead_mm)
        Y = bar.material_y_mm
        parallel = np.abs(Y) <= 0.5 * piece.parallel_length_mm
        stretch = state.stretch
        assert np.ptp(stretch[parallel]) == 0.0
        parallel_stretch = stretch[parallel][0]
        assert state.force_n == pytest.approx(
            piece.parallel_area_mm2 * bar.material.nominal_stress_mpa(parallel_stretch), rel=1e-12
        )
        shoulder = (np.abs(Y) > 0.5 * piece.parallel_length_mm) & (
            np.abs(Y) < piece.shoulder_end_mm
        )
        assert np.all(stretch[shoulder] < parallel_stretch)
        fixed_side = Y >= 0.5 * piece.parallel_length_mm
        assert np.all(np.diff(stretch[fixed_side]) <= 0)
        tabs = np.abs(Y) >= piece.shoulder_end_mm
        assert np.all(stretch[tabs] <= stretch[shoulder].min())
        lateral = state.deformation.lateral_stretch
        assert np.all(lateral[parallel] == lateral[parallel][0])
        assert lateral[parallel][0] < lateral[tabs].min()


def test_material_point_velocity_runs_from_the_moving_to_the_fixed_clamp(rubber_bar, steel_bar):
    for bar in (rubber_bar, steel_bar):
        half = 0.5 * bar.specimen.grip_distance_mm
        Y = np.linspace(-half, half, 401)
        d = 0.5 * bar.peak_crosshead_mm
        step = 1e-4 * bar.peak_crosshead_mm
        velocity = (
            bar.deformation(d + step).spatial_y(Y) - bar.deformation(d - step).spatial_y(Y)
        ) / (2 * step)
        assert velocity[0] == pytest.approx(-1.0, abs=1e-6)
        assert velocity[-1] == 0.0
        assert np.all(np.diff(velocity) >= -1e-9)


def test_bar_grid_converges(rubber_bar):
    piece, rubber = rubber_bar.specimen, rubber_bar.material
    predicted = predicted_displacement(
        piece, rubber, piece.parallel_area_mm2 * rubber.peak_stress_mpa
    )
    coarse = BarModel(piece, rubber, axial_points=501)
    assert abs(coarse.breaking_crosshead_mm - predicted) < 1e-5
    assert abs(rubber_bar.breaking_crosshead_mm - predicted) < 1e-7


def test_rubber_reaches_600_percent_at_the_predicted_displacement(rubber_bar):
    piece, rubber = rubber_bar.specimen, rubber_bar.material
    break_force = piece.parallel_area_mm2 * rubber.peak_stress_mpa
    predicted = predicted_displacement(piece, rubber, break_force)
    assert rubber_bar.breaking_crosshead_mm == pytest.approx(predicted, rel=1e-9)
    low, high = piece.gauge_marks_mm
    at_break = rubber_bar.deformation(rubber_bar.breaking_crosshead_mm)
    assert at_break.phase is BarPhase.LOADING
    assert at_break.gauge_strain(low, high) == pytest.approx(6.0, rel=1e-12)
    assert at_break.force_n == pytest.approx(break_force, rel=1e-12)
    end = rubber_bar.crosshead_for_gauge_strain(low, high, 6.0)
    assert end == pytest.approx(rubber_bar.breaking_crosshead_mm, rel=1e-9)
    half_way = rubber_bar.crosshead_for_gauge_strain(low, high, 3.0)
    assert rubber_bar.gauge_strain(low, high, half_way) == pytest.approx(3.0, rel=1e-9)


def test_broken_specimen_carries_no_force_and_opens_a_gap(rubber_bar, steel_bar):
    for bar in (rubber_bar, steel_bar):
        half = 0.5 * bar.specimen.grip_distance_mm
        d = bar.breaking_crosshead_mm + 5.0
        state = bar.deformation(d)
        assert state.broken and state.force_n == 0.0
        shape = state.deformation
        assert shape.spatial_y(-half) == pytest.approx(-half - d)
        assert shape.spatial_y(half) == half
        crack = bar.fracture_position_mm
        below, above = shape.spatial_y([crack - 1e-3, crack + 1e-3])
        assert above - below > 5.0
        assert shape.lateral_stretch_at(crack) < 1e-5
        assert np.all(np.diff(shape.spatial_y_mm) > 0)
    relaxed = rubber_bar.deformation(rubber_bar.breaking_crosshead_mm + 1.0)
    np.testing.assert_allclose(relaxed.stretch, 1.0, rtol=1e-12)


def test_metal_necking_localises_and_the_force_falls(steel_bar):
    bar, steel = steel_bar, steel_bar.material
    assert bar.peak_force_n == pytest.approx(510.0 * bar.specimen.parallel_area_mm2, rel=1e-9)
    displacements = np.linspace(0.0, bar.breaking_crosshead_mm, 60)[1:]
    forces = np.array([bar.force_n(d) for d in displacements])
    top = int(np.argmax(forces))
    assert displacements[top] == pytest.approx(bar.peak_crosshead_mm, abs=0.5)
    assert np.all(np.diff(forces[top + 1 :]) < 0)
    assert bar.breaking_force_n < 0.95 * bar.peak_force_n
    state = bar.deformation(0.5 * (bar.peak_crosshead_mm + bar.breaking_crosshead_mm))
    assert state.phase is BarPhase.NECKING
    Y = bar.material_y_mm
    centre = int(np.argmax(state.stretch))
    assert Y[centre] == pytest.approx(bar.fracture_position_mm, abs=0.1)
    assert state.stretch[centre] > steel.stretch_at_peak + 0.05
    far = np.abs(Y - bar.fracture_position_mm) > 3 * bar.neck_width_mm
    parallel = np.abs(Y) <= 0.5 * bar.specimen.parallel_length_mm
    assert np.all(state.stretch[far & parallel] < steel.stretch_at_peak)
    low, high = bar.specimen.gauge_marks_mm
    before = bar.deformation(bar.peak_crosshead_mm).gauge_strain(low, high)
    assert state.gauge_strain(low, high) > before
    assert state.gauge_strain(low, -20.0) < bar.deformation(bar.peak_crosshead_mm).gauge_strain(
        low, -20.0
    )
    broken = bar.deformation(bar.breaking_crosshead_mm + 1.0)
    permanent = broken.gauge_strain(low, high) * bar.specimen.gauge_length_mm
    gap = np.diff(broken.spatial_y(bar.fracture_position_mm + np.array([-1e-6, 1e-6])))[0]
    elongation = (permanent - gap) / bar.specimen.gauge_length_mm
    assert elongation == pytest.approx(steel.elongation_after_fracture, abs=1e-4)


def test_unloading_follows_the_elastic_path(rubber_bar, steel_bar):
    d = 0.6 * rubber_bar.peak_crosshead_mm
    back = rubber_bar.deformation(d, max_crosshead_mm=0.9 * rubber_bar.peak_crosshead_mm)
    assert back.phase is BarPhase.UNLOADING
    assert back.force_n == pytest.approx(rubber_bar.force_n(d), rel=1e-12)
    peak = steel_bar.peak_crosshead_mm
    loaded = steel_bar.deformation(peak)
    unloaded = steel_bar.deformation(peak - 0.01, max_crosshead_mm=peak)
    assert unloaded.phase is BarPhase.UNLOADING
    assert 0.0 < unloaded.force_n < loaded.force_n
    np.testing.assert_allclose(unloaded.plastic_strain, loaded.plastic_strain)
    slack = steel_bar.deformation(1.0, max_crosshead_mm=peak)
    assert slack.phase is BarPhase.SLACK and slack.force_n == 0.0
    assert slack.spatial_y(-0.5 * steel_bar.specimen.grip_distance_mm) == pytest.approx(-61.0)


def test_bar_is_deterministic():
    first = BarModel(Specimen.iso6892_flat(), ElasticPlastic.steel_s355())
    second = BarModel(Specimen.iso6892_flat(), ElasticPlastic.steel_s355())
    d = 0.5 * (first.peak_crosshead_mm + first.breaking_crosshead_mm)
    a, b = first.deformation(d), second.deformation(d)
    assert a.force_n == b.force_n
    np.testing.assert_array_equal(a.deformation.spatial_y_mm, b.deformation.spatial_y_mm)
    np.testing.assert_array_equal(a.deformation.lateral_stretch, b.deformation.lateral_stretch)


def test_bar_rejects_a_fracture_outside_the_parallel_section():
    with pytest.raises(ValueError, match="fracture_position_mm"):
        BarModel(Specimen.iso6892_flat(), ElasticPlastic.steel_s355(), fracture_position_mm=30.0)


# Crosshead


def test_crosshead_ramps_obey_the_acceleration_limit():
    crosshead = Crosshead(max_acceleration_mm_s2=20.0)
    crosshead.start(600.0, 1.0)
    t = np.linspace(0.0, 3.0, 30001)
    speed = crosshead.speed_mm_min(t) / 60.0
    assert np.max(np.abs(np.diff(speed) / np.diff(t))) <= 20.0 * (1 + 1e-9)
    assert speed[t < 1.0].max() == 0.0
    assert np.all(speed[t >= 1.5] == 10.0)
    assert crosshead.position_mm(1.5) == pytest.approx(0.5 * 20.0 * 0.5**2)
    assert crosshead.position_mm(2.5) == pytest.approx(2.5 + 10.0)
    assert crosshead.running(2.0)


def test_crosshead_stop_and_continuity():
    crosshead = Crosshead(max_acceleration_mm_s2=50.0)
    crosshead.start(300.0, 0.0)
    crosshead.stop(2.0)
    plan = crosshead.plan
    x_at_stop = crosshead.position_mm(2.0)
    assert crosshead.position_mm(5.0) == pytest.approx(x_at_stop + 5.0**2 / (2 * 50.0))
    assert crosshead.speed_mm_min(2.1) == pytest.approx(300.0 - 60.0 * 50.0 * 0.1)
    assert crosshead.speed_mm_min(5.0) == 0.0
    assert not crosshead.running(5.0)
    joins = plan.start_s
    np.testing.assert_allclose(
        crosshead.position_mm(joins - 1e-9), crosshead.position_mm(joins + 1e-9), atol=1e-7
    )
    with pytest.raises(ValueError, match="precedes"):
        crosshead.start(100.0, 1.0)


def test_crosshead_returns_to_start_without_overshoot():
    crosshead = Crosshead(max_acceleration_mm_s2=10.0)
    crosshead.start(600.0, 0.0)
    crosshead.return_to_start(1200.0, 5.0)
    t = np.linspace(5.0, 20.0, 150001)
    x = crosshead.position_mm(t)
    speed = crosshead.speed_mm_min(t) / 60.0
    assert x.min() >= -1e-9
    assert np.abs(speed).max() <= 20.0 + 1e-9
    assert np.max(np.abs(np.diff(speed) / np.diff(t))) <= 10.0 * (1 + 1e-9)
    assert crosshead.position_mm(30.0) == 0.0
    assert not crosshead.running(30.0)
    assert crosshead.plan.max_position_mm_until(30.0) == pytest.approx(x.max(), abs=1e-6)
    short = Crosshead(max_acceleration_mm_s2=10.0)
    short.start(-60.0, 0.0)
    short.return_to_start(6000.0, 1.0)
    assert short.position_mm(100.0) == 0.0
    assert np.all(short.position_mm(np.linspace(1.0, 10.0, 9001)) <= 1e-12)


def test_crosshead_first_time_at_a_position():
    crosshead = Crosshead(max_acceleration_mm_s2=30.0)
    crosshead.start(120.0, 0.5)
    plan = crosshead.plan
    t = plan.first_time_at_or_beyond(10.0)
    assert crosshead.position_mm(t) == pytest.approx(10.0, abs=1e-12)
    early = plan.first_time_at_or_beyond(0.01)
    assert crosshead.position_mm(early) == pytest.approx(0.01, abs=1e-12)
    crosshead.stop(1.0)
    assert crosshead.plan.first_time_at_or_beyond(10.0) is None


# Machine


def test_machine_state_follows_crosshead_and_bar(rubber_bar):
    machine = MachineWithSpecimen(rubber_bar, Crosshead(max_acceleration_mm_s2=100.0))
    assert isinstance(machine, MachineModel)
    machine.start(500.0, 0.0)
    state = machine.state(10.0)
    assert state.timestamp_ns == 10_000_000_000
    assert state.speed_mm_min == pytest.approx(500.0)
    assert state.running
    assert state.crosshead_mm == pytest.approx(500.0 / 60.0 * 10.0 - 0.5 * (500 / 60) ** 2 / 100)
    assert state.encoder_counts == round(state.crosshead_mm * 1000.0)
    assert state.force_n == pytest.approx(rubber_bar.force_n(state.crosshead_mm), rel=1e-12)
    shape = machine.deformation_at(10.0)
    np.testing.assert_array_equal(
        shape.spatial_y_mm, rubber_bar.deformation(state.crosshead_mm).deformation.spatial_y_mm
    )
    broken_at = machine.broken_at
    assert machine.crosshead.position_mm(broken_at) == pytest.approx(
        rubber_bar.breaking_crosshead_mm, abs=1e-9
    )
    assert machine.state(broken_at - 1e-3).force_n > 50.0
    assert machine.state(broken_at + 1e-3).force_n == 0.0
    assert machine.is_broken(broken_at + 1e-3)
    machine.stop(broken_at + 1.0)
    machine.return_to_start(1000.0, broken_at + 3.0)
    assert machine.broken_at == broken_at
    assert machine.state(broken_at + 100.0).force_n == 0.0
    assert machine.state(broken_at + 100.0).crosshead_mm == 0.0


def test_machine_behind_the_sim_controller_and_threads(steel_bar):
    clock = SimClock()
    machine = MachineWithSpecimen(steel_bar, encoder_counts_per_mm=None)
    controller = machine_from_url("sim://machine", machine=machine, clock=clock)
    controller.open()
    controller.start(10.0)
    errors = []

    def read():
        try:
            for k in range(100):
                machine.deformation_at(0.01 * k)
                machine.state(0.01 * k)
        except Exception as error:
            errors.append(error)

    readers = [threading.Thread(target=read) for _ in range(3)]
    for reader in readers:
        reader.start()
    for k in range(1, 20):
        machine.start(10.0 + k, 0.05 * k)
    for reader in readers:
        reader.join()
    assert not errors
    clock.wait_until(60.0)
    state = controller.read_state()
    assert state.encoder_counts is None
    assert state.timestamp_ns == 60_000_000_000
    assert state.force_n == pytest.approx(steel_bar.force_n(state.crosshead_mm), rel=1e-12)
