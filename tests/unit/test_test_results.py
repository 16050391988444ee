"""Test results on synthetic curves with known values, and the report page."""

import json
import math
import re

import numpy as np
import pytest

from appliance.measure.gauges import Gauge, StrainGaugesLayout
from appliance.results import metals, plots, report_page, rubber
from appliance.results import result as result_module
from appliance.results import series as series_module
from appliance.sim.metal import ElasticPlastic
from appliance.sim.rubber import NeoHookean

AREA_MM2 = 25.0


def curve(strain, stress_mpa, *, area_mm2=AREA_MM2):
    return series_module.TestSeries.of(np.asarray(strain), np.asarray(stress_mpa) * area_mm2)


def steel_curve(end_strain=0.2, step=2e-4, elastic_step=1e-5):
    """The steel's curve sampled finely to 1 % strain (a slow first speed), then by `step`."""
    steel = ElasticPlastic.steel_s355()
    strain = np.concatenate(
        [np.arange(0.0, 0.01, elastic_step), np.arange(0.01, end_strain + step / 2, step)]
    )
    return steel, curve(strain, steel.nominal_stress_mpa(1.0 + strain))


def test_the_steel_curve_gives_the_material_model_values():
    steel, series = steel_curve()
    found = metals.metal_results(series, AREA_MM2, broke=False)
    assert found["E"].value == pytest.approx(210.0, rel=2e-3)
    assert found["Rp0.2"].value == pytest.approx(355.0, rel=2e-4)
    assert found["Rm"].value == pytest.approx(510.0, rel=1e-6)
    assert found["Ag"].value == pytest.approx(100 * steel.uniform_elongation, abs=0.05)
    assert "continuous yielding" in found["ReH"].reason
    assert "continuous yielding" in found["ReL"].reason
    assert found["A"].reason == "the test ended before the fracture"


def test_each_result_names_its_samples_and_how_it_was_taken():
    _, series = steel_curve()
    found = metals.metal_results(series, AREA_MM2, broke=False)
    modulus = found["E"]
    first, last = modulus.samples
    used = series.force_n[first : last + 1] / AREA_MM2
    assert used.min() >= 0.1 * found["Rp0.2"].value * (1 - 1e-9)
    assert used.max() <= 0.5 * found["Rp0.2"].value * (1 + 1e-9)
    assert "10 % to 50 % of Rp0.2" in modulus.basis
    proof = found["Rp0.2"]
    a, b = proof.samples
    assert b == a + 1
    assert series.force_n[a] / AREA_MM2 <= proof.value <= series.force_n[b] / AREA_MM2
    peak = int(np.argmax(series.force_n))
    assert found["Rm"].samples == (peak, peak)


def test_an_upper_yield_point_gives_reh_and_rel_without_the_initial_transient():
    elastic = np.linspace(0.0, 0.0015, 16)
    strain = [*elastic, 0.0017, 0.0019, 0.003, 0.006, 0.009, 0.012]
    stress = [*(200e3 * elastic), 270.0, 283.0, 281.0, 285.0, 280.0, 286.0]
    hardening = np.linspace(0.015, 0.15, 30)
    falling = np.linspace(0.155, 0.2, 10)
    strain += [*hardening, *falling]
    stress += [*(286.0 + 164.0 * np.sqrt((hardening - 0.012) / 0.138)), *np.linspace(449, 400, 10)]
    found = metals.metal_results(curve(strain, stress), AREA_MM2, broke=False)
    assert found["ReH"].value == pytest.approx(300.0)
    assert found["ReH"].samples == (15, 15)
    assert found["ReL"].value == pytest.approx(280.0)
    assert found["ReL"].at_sample == 20
    assert found["ReH"].at_sample == 15
    assert "initial transient" in found["ReL"].basis
    assert found["Rm"].value == pytest.approx(450.0)
    assert found["E"].value == pytest.approx(200.0, rel=1e-9)
    assert "of ReH" in found["E"].basis


def test_elongation_after_fracture_takes_the_elastic_part_off_the_last_strain():
    steel, series = steel_curve(end_strain=0.25)
    broken = series_module.TestSeries.of(
        np.append(series.strain, 0.26),
        np.append(series.force_n, 0.0),
        valid=np.append(series.valid, False),
    )
    found = metals.metal_results(broken, AREA_MM2, broke=True)
    last_stress = series.force_n[-1] / AREA_MM2
    expected = 100 * (series.strain[-1] - last_stress / (found["E"].value * 1e3))
    assert found["A"].value == pytest.approx(expected)
    assert found["A"].samples == (len(series) - 1, len(series) - 1)


def necking_curve(points=5001):
    """E 210 GPa up to a parabolic top R = 510 - 2500 (e - 0.15)^2 MPa: Agt 15 %, Ag 14.757 %."""
    strain = np.linspace(0.0, 0.25, points)
    stress = np.minimum(210e3 * strain, 510.0 - 2500.0 * (strain - 0.15) ** 2)
    return strain, stress, 100 * (0.15 - 510.0 / 210e3)


@pytest.mark.parametrize("seed", range(5))
def test_ag_under_force_noise_is_taken_where_a_fit_of_the_top_peaks(seed):
    strain, stress, true_ag = necking_curve()
    noisy = stress * (1 + np.random.default_rng(seed).normal(0.0, 5e-4, strain.size))
    found = metals.metal_results(curve(strain, noisy), AREA_MM2, broke=True)
    assert found["Ag"].value == pytest.approx(true_ag, abs=0.05)
    assert "cubic least-squares fit" in found["Ag"].basis
    first, last = found["Ag"].samples
    assert noisy[first : last + 1].min() >= 0.99 * noisy.max()
    assert first <= found["Ag"].at_sample <= last


def test_a_sharp_maximum_without_noise_keeps_agt_at_its_sample():
    strain = np.concatenate([np.arange(0.0, 0.01, 1e-5), np.arange(0.01, 0.1701, 1e-3)])
    top = np.where(strain < 0.15, 2500.0, 50000.0) * (strain - 0.15) ** 2
    stress = np.minimum(210e3 * strain, 510.0 - top)
    found = metals.metal_results(curve(strain, stress), AREA_MM2, broke=False)
    assert found["Ag"].value == pytest.approx(100 * (0.15 - 510.0 / 210e3), abs=1e-6)
    assert "the strain of the sample of largest stress" in found["Ag"].basis


def test_a_strain_offset_at_the_start_moves_neither_ag_nor_a_nor_rp02():
    strain, stress, _ = necking_curve()
    plain = metals.metal_results(curve(strain, stress), AREA_MM2, broke=True)
    shifted = metals.metal_results(curve(strain + 0.002, stress), AREA_MM2, broke=True)
    for symbol in ("Ag", "A", "Rp0.2", "E", "Rm"):
        assert shifted[symbol].value == pytest.approx(plain[symbol].value, abs=1e-6), symbol


def test_serrations_during_work_hardening_are_no_yield_point():
    strain = np.linspace(0.0, 0.15, 15001)
    grid = np.linspace(0.0, 400.0, 400001)
    stress = np.interp(strain, grid / 70e3 + 0.002 * (grid / 250.0) ** 12, grid)
    serrated = stress * (1 - np.where(strain > 0.03, 0.015 * ((strain * 200) % 1.0), 0.0))
    found = metals.metal_results(curve(strain, serrated), AREA_MM2, broke=True)
    for symbol in ("ReH", "ReL"):
        assert found[symbol].value is None
        assert found[symbol].reason.startswith("continuous yielding: the first fall")
        assert "serration of work hardening" in found[symbol].reason
    assert found["Rp0.2"].value == pytest.approx(250.0, rel=2e-3)
    assert found["E"].value == pytest.approx(70.0, rel=1e-3)


def test_a_test_stopped_in_the_elastic_range_determines_only_the_modulus():
    strain = np.linspace(0.0, 0.001, 40)
    found = metals.metal_results(curve(strain, 200e3 * strain), AREA_MM2, broke=False)
    assert found["E"].value == pytest.approx(200.0)
    assert "before 0.2 %" in found["Rp0.2"].reason
    assert "maximum was not reached" in found["Rm"].reason
    assert found["Ag"].reason.startswith("Rm: ")
    assert all(found[s].value is None for s in ("Rp0.2", "Rm", "Ag", "A"))


def test_too_few_elastic_samples_leave_the_modulus_not_determined():
    _, series = steel_curve(step=2e-3, elastic_step=2e-3)
    found = metals.metal_results(series, AREA_MM2, broke=False)
    assert found["E"].value is None and "fewer than 5" in found["E"].reason
    assert found["Rp0.2"].value is None and found["Rp0.2"].reason.startswith("E: ")
    assert found["Rm"].value == pytest.approx(510.0, rel=1e-3)


@pytest.mark.parametrize(
    ("force", "area", "reason"),
    [
        (math.nan, AREA_MM2, "no force readings from the machine"),
        (1000.0, None, "no cross-section: [specimen] width_mm and thickness_mm"),
    ],
)
def test_without_force_or_cross_section_nothing_is_a_number(force, area, reason):
    series = series_module.TestSeries.of(np.linspace(0, 0.1, 50), np.full(50, force))
    for found in (
        metals.metal_results(series, area, broke=True),
        rubber.rubber_results(series, area, broke=True),
    ):
        stresses = [r for r in found.results if r.unit == "MPa" or r.symbol in ("E", "Ag", "A")]
        assert stresses and all(r.value is None for r in stresses)
        assert all(r.reason.startswith(reason) for r in stresses)


def neo_hookean_curve(end_strain, step=1e-3):
    material = NeoHookean(shear_modulus_mpa=0.5, break_strain=6.0)
    strain = np.arange(0.0, end_strain + step / 2, step)
    return material, curve(strain, material.nominal_stress_mpa(1.0 + strain))


def test_rubber_to_break_gives_the_material_values():
    material, series = neo_hookean_curve(6.0)
    found = rubber.rubber_results(series, AREA_MM2, broke=True)
    for percent in (100, 200, 300):
        expected = float(material.nominal_stress_mpa(1.0 + percent / 100))
        assert found[f"S{percent}"].value == pytest.approx(expected, rel=1e-6)
        first, last = found[f"S{percent}"].samples
        assert series.strain[first] <= percent / 100 <= series.strain[last]
    assert found["TS"].value == pytest.approx(material.peak_stress_mpa, rel=1e-9)
    assert found["Eb"].value == pytest.approx(600.0)
    assert found["Eb"].samples == (len(series) - 1, len(series) - 1)


def test_rubber_stopped_early_reports_what_it_did_not_reach():
    _, series = neo_hookean_curve(1.5)
    found = rubber.rubber_results(series, AREA_MM2, broke=False)
    assert found["S100"].value is not None
    assert found["S200"].reason == "the test ended at 150 % elongation"
    assert found["S300"].value is None
    assert found["TS"].reason == found["Eb"].reason == "the test ended before the break"


def test_the_summary_object_is_plain_json_and_prints_as_one_line():
    _, series = steel_curve()
    results = metals.metal_results(series, AREA_MM2, broke=False)
    document = result_module.ResultsObject.of(results)
    parsed = json.loads(json.dumps(document))
    assert parsed["standard"] == "ISO 6892-1" and parsed["cross_section_mm2"] == AREA_MM2
    assert parsed["Rp0.2"]["unit"] == "MPa" and parsed["A"]["value"] is None
    assert parsed["A"]["not_determined"] == "the test ended before the fracture"
    line = f"{document}"
    assert line.startswith("ISO 6892-1: E 2") and "A -" in line and "\n" not in line


def test_a_result_is_never_nan():
    with pytest.raises(ValueError, match="Rm"):
        result_module.Result.determined("Rm", "tensile strength", "MPa", math.nan, (1, 1), "")


def test_the_report_page_is_self_contained_and_holds_the_results_table():
    steel, series = steel_curve()
    results = metals.metal_results(series, AREA_MM2, broke=False)
    image = np.random.default_rng(1).integers(0, 255, (400, 200), dtype=np.uint8)
    points = np.array([[100.0, 100.0], [100.0, 300.0]])
    layout = StrainGaugesLayout(Gauge((0,), (1,)), None)
    figures = report_page.ReportFigures(
        stress_strain=plots.stress_strain_svg(series, AREA_MM2, results),
        time_series=plots.time_series_svg(series),
        validity=plots.validity_svg(series),
        truth_error=None,
        gauge=plots.gauge_png_uri(image, points, layout, 50.0),
    )
    page = report_page.report_html(
        "Tensile test t1", [("ended", "completed")], results, None, figures
    )
    assert not re.search(r"https?:", page, re.IGNORECASE)
    assert not re.search(r"""(src|href)=["'](?!data:|#)""", page)
    table = page[
        page.index('<table id="results">') : page.index("</table>", page.index('id="results"'))
    ]
    for symbol in ("E", "Rp0.2", "ReH", "ReL", "Rm", "Ag", "A"):
        assert f'id="result-{symbol}"' in table
    assert "355" in table and "not determined" in table
    assert page.count("<svg") == 3 and "data:image/png;base64," in page


def test_the_page_shows_the_transverse_strain_where_the_test_measured_one():
    strain = np.linspace(0.0, 0.05, 51)
    series = series_module.TestSeries.of(strain, 1000.0 * strain, transverse_strain=-0.3 * strain)
    figures = report_page.ReportFigures(
        time_series=plots.time_series_svg(series), transverse=plots.transverse_svg(series)
    )
    page = report_page.report_html("Tensile test", [], None, "none", figures)
    assert page.index('id="time-series"') < page.index('id="transverse"')
    assert "Transverse strain (given)" in page
    without = report_page.report_html("Tensile test", [], None, "none", report_page.ReportFigures())
    assert 'id="transverse"' not in without


def test_a_page_without_results_says_why():
    page = report_page.report_html(
        "Tensile test",
        [],
        None,
        "[specimen] material is not configured",
        report_page.ReportFigures(),
    )
    assert "No results: [specimen] material is not configured" in page


@pytest.mark.parametrize(
    ("summary", "page"),
    [
        ("out/summary.json", "out/report.html"),
        ("state/test-1.summary.json", "state/test-1.report.html"),
        ("out/first.json", "out/first.report.html"),
    ],
)
def test_the_report_page_goes_beside_the_summary(summary, page):
    from pathlib import Path

    from appliance.runner import OutputFiles

    assert OutputFiles(summary=Path(summary)).report_page == Path(page)
    assert OutputFiles(summary=Path(summary), report=Path("x.html")).report_page == Path("x.html")
    assert OutputFiles().report_page is None


def test_the_cross_section_of_a_specimen_table():
    from appliance.config import config_from_table

    def area(**keys):
        return series_module.cross_section_mm2(config_from_table({"specimen": keys}, "t").specimen)

    assert area(width_mm=12.5, thickness_mm=2.0) == 25.0
    assert area(diameter_mm=10.0) == pytest.approx(78.5398, rel=1e-6)
    assert area(material="metal") is None


@pytest.mark.parametrize(
    ("keys", "message"),
    [
        ({"width_mm": 3.0, "diameter_mm": 5.0}, "diameter_mm: give either diameter_mm or"),
        ({"thickness_mm": 2.0}, "width_mm: missing (width_mm and thickness_mm go together)"),
        ({"material": "wood"}, "[specimen] material: must be one of metal, rubber"),
    ],
)
def test_a_bad_specimen_table_is_refused_naming_the_key(keys, message):
    from appliance.config import config_from_table
    from appliance.errors import InputError

    with pytest.raises(InputError, match=re.escape(message)):
        config_from_table({"specimen": keys}, "site.toml")
