"""Benchmark of a test's results against the simulated materials' own values.

`extensometer bench results --out DIR [--quick]` runs whole simulated tests with
`appliance.runner` and compares the results they report (`appliance.results`, from the
measured strain, the simulated machine's force and the preset's nominal cross-section) with
the values of the material model behind the simulation (`appliance.sim.metal`,
`appliance.sim.rubber`), which only score here. Writes `DIR/test_results.md` and
`DIR/test_results.json`.

* Steel (S355 model, ISO 6892-1 flat specimen): a two-speed test program, 2 mm/min through
  the elastic range and Rp0.2, then 100 mm/min to 17 % strain, past the maximum force
  (Agt = 15.1 %); seeds 1, 2 and 3 (`--quick`: seed 1). Targets: Rp0.2 within 0.5 %, Rm
  within 0.2 %, E within 1 % of the model's; Ag is shown against the model's, without a
  target. Then seed 1 again to the fracture, for A against the model's permanent elongation
  after fracture (no target; not in `--quick`).
* Rubber (Mooney-Rivlin filled rubber, ISO 37 type 1, 500 mm/min) to the break at 600 %
  (`--quick`: to 350 %, so TS and Eb are not determined): S100, S200, S300, TS and Eb against
  the model's, without a target (the issue's targets name the steel's results only).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from appliance.bench.results import write_report
from appliance.config import Config, config_from_table
from appliance.runner import run_test

NAME = "test_results"
METAL_TO_RM: dict[str, dict[str, Any]] = {
    "sim": {
        "material": "metal",
        "sensor_width_px": 320,
        "speed_change_after_s": 12.0,
        "speed_change_mm_min": 100.0,
    },
    "run": {"speed_mm_min": 2.0, "until_strain": 0.17},
    "camera": {"exposure_us": 500.0, "frame_rate_hz": 20.0},
    "trigger": {"replan_hysteresis": 0.0},
}
"""A quick simulated steel test past Rm: about 40 samples in the modulus's fit range at
2 mm/min and 20 frames/s, the rest at 100 mm/min; a narrow sensor (only the marks' columns are
read)."""
METAL_TARGETS = {"Rp0.2": 0.5, "Rm": 0.2, "E": 1.0}
"""Largest error of each result, % of the model's value."""
METAL_SEEDS = (1, 2, 3)


def metal_model_values(*, fracture: bool = False) -> dict[str, float]:
    """The S355 model's E (GPa), Rp0.2 and Rm (MPa), Ag (%), and with `fracture` A (%)."""
    from appliance.sim.metal import ElasticPlastic

    steel = ElasticPlastic.steel_s355()
    values = {
        "E": steel.youngs_modulus_mpa / 1e3,
        "Rp0.2": steel.proof_stress_mpa,
        "Rm": steel.tensile_strength_mpa,
        "Ag": 100.0 * steel.uniform_elongation,
    }
    return {**values, "A": 100.0 * steel.elongation_after_fracture} if fracture else values


def rubber_model_values() -> dict[str, float]:
    """The filled rubber's S100, S200, S300 and TS (MPa), and Eb (%)."""
    from appliance.sim.rubber import MooneyRivlin

    rubber = MooneyRivlin.filled_rubber()
    values = {f"S{p}": float(rubber.nominal_stress_mpa(1.0 + p / 100)) for p in (100, 200, 300)}
    return {**values, "TS": rubber.peak_stress_mpa, "Eb": 100.0 * rubber.break_strain}


def cases(quick: bool) -> list[tuple[str, Config, dict[str, float]]]:
    """(name, configuration, the model's values) of every test."""
    seeds = METAL_SEEDS[:1] if quick else METAL_SEEDS
    metal = [
        (
            f"steel, seed {seed}",
            config_from_table(
                {**METAL_TO_RM, "sim": {**METAL_TO_RM["sim"], "seed": seed}}, "bench results"
            ),
            metal_model_values(),
        )
        for seed in seeds
    ]
    if not quick:
        to_fracture = {"until_strain": 0.0, "until_break": True}
        metal.append(
            (
                "steel to the fracture, seed 1",
                config_from_table(
                    {**METAL_TO_RM, "run": {**METAL_TO_RM["run"], **to_fracture}}, "bench results"
                ),
                metal_model_values(fracture=True),
            )
        )
    rubber_run = {"until_strain": 3.5} if quick else {"until_break": True}
    rubber = (
        "rubber to the break" if not quick else "rubber to 350 %",
        config_from_table({"sim": {"material": "rubber"}, "run": rubber_run}, "bench results"),
        rubber_model_values(),
    )
    return [*metal, rubber]


def compare(results: dict[str, Any], model: dict[str, float]) -> list[dict[str, Any]]:
    """Each result the model gives a value for: measured, model, error in %, the target (%
    or None) and whether it was met (None without a target)."""
    rows = []
    for symbol, expected in model.items():
        measured = results.get(symbol, {}).get("value")
        error = None if measured is None else 100.0 * (measured / expected - 1.0)
        target = METAL_TARGETS.get(symbol) if results.get("standard") == "ISO 6892-1" else None
        met = None if target is None else error is not None and abs(error) <= target
        rows.append(
            {
                "result": symbol,
                "unit": results.get(symbol, {}).get("unit"),
                "measured": measured,
                "model": expected,
                "error_percent": error,
                "target_percent": target,
                "met": met,
                "not_determined": results.get(symbol, {}).get("not_determined"),
                "samples": results.get(symbol, {}).get("samples"),
            }
        )
    return rows


def run_results_benchmark(out: Path, *, quick: bool = False) -> int:
    """Run every case, print and write the report; returns 0 (measured, met or not)."""
    figures: dict[str, Any] = {"quick": quick, "cases": []}
    sections = []
    for name, config, model in cases(quick):
        print(f"{name} ...", flush=True)
        outcome = run_test(config, simulate=True, test_id=f"bench {NAME}: {name}")
        summary = outcome.as_dict()
        rows = compare(summary["results"], model)
        figures["cases"].append(
            {
                "name": name,
                "exit_status": summary["exit_status"],
                "reason": summary["reason"],
                "frames_processed": summary["frames_processed"],
                "max_rel_strain_error": summary["max_rel_strain_error"],
                "results": dict(summary["results"]),
                "comparison": rows,
            }
        )
        section = _section(name, summary, rows)
        print(section, flush=True)
        sections.append(section)
    body = "\n".join([_INTRODUCTION, *sections])
    path = write_report(out, NAME, "Test results against the simulated materials", figures, body)
    print(f"report: {path}")
    return 0


_INTRODUCTION = """\
Each simulated test reports its results from the measured strain, the machine's force and the
preset specimen's nominal cross-section; the material model behind the simulation gives the
values they are scored against (the model's Rp0.2 and Rm are those of its engineering curve,
E its elastic modulus). Targets: Rp0.2, Rm and E of the steel within 0.5 %, 0.2 % and 1 %.
"""


def _section(name: str, summary: dict[str, Any], rows: list[dict[str, Any]]) -> str:
    lines = [
        f"## {name}",
        "",
        f"Ended {summary['exit_status']} ({summary['reason']}), "
        f"{summary['frames_processed']} frames; largest relative strain error "
        f"{_number(summary['max_rel_strain_error'], 100, '%')}.",
        "",
        "| result | measured | model | error | target | met | samples |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        unit = row["unit"] or ""
        measured = (
            f"{row['measured']:.5g} {unit}"
            if row["measured"] is not None
            else f"not determined: {row['not_determined']}"
        )
        target = f"{row['target_percent']:g} %" if row["target_percent"] is not None else "-"
        met = {True: "yes", False: "**no**", None: "-"}[row["met"]]
        samples = "-" if row["samples"] is None else "{} to {}".format(*row["samples"])
        lines.append(
            f"| {row['result']} | {measured} | {row['model']:.5g} {unit} | "
            f"{_number(row['error_percent'], 1, '%', signed=True)} | {target} | {met} | "
            f"{samples} |"
        )
    return "\n".join(lines) + "\n"


def _number(value: float | None, scale: float, unit: str, *, signed: bool = False) -> str:
    if value is None:
        return "-"
    return f"{value * scale:{'+' if signed else ''}.3f} {unit}"
