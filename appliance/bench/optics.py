"""Benchmark of the optics: camera calibration, measuring in the object plane, ISO 9513 classes.

`extensometer bench optics --out DIR [--quick]` measures, on the simulated benches
(`[sim] bench`, `appliance.sim.bench`), what a camera calibration and the object plane buy, and
writes the report `DIR/optics.md` and its figures `DIR/optics.json`; each case's files (target
views, calibration files, strain.csv, summary.json, verification.json) go under `DIR/optics/`.
Calibrations are made by the product's own calibration (`extensometer calibrate`'s) from
simulated ChArUco views of the same bench's lens, the first view lying in the specimen plane
(`appliance.bench.optics_calibration`); the world's true camera only scores them. Targets:

1. calibration (typical bench, the rubber preset's camera), over seeds, median and worst: RMS
   reprojection <= 0.05 px, scale error at the specimen plane <= 0.02 %, distortion at the
   field corners recovered to <= 0.02 px;
2. rubber (ISO 37 type 1) to break (about 600 %) on the typical bench: by the nominal scale it
   misses class 0.5; calibrated it holds class 0.5 with a relative error <= 0.3 % over readings
   above 1 %, judged with the specimen's out-of-plane moves (the preset) and without them
   (what a calibration can correct); the ideal bench for reference;
3. metal (ISO 6892-1, 10 mm/min) on the typical bench, to `until_strain` (2 %; the break is
   ten minutes further): with a telecentric lens class 0.2, by its nominal scale and by its
   own calibration (`calibrate --telecentric`); with the entocentric lens (by a calibration)
   the class reached, with the specimen's out-of-plane moves (thinning, slack) and without,
   whose difference is their share of the error;
4. `extensometer verify --sim --material metal` on each bench preset: the ISO 9513 class
   reached by the nominal scale, and on the typical bench with a calibration.

`--quick` calibrates twice instead of three times, ends the rubber tests at 50 % and the metal
tests at 0.5 %, and verifies the typical bench only: a look at every path, not the figures.
`--only SECTION` (`calibration`, `rubber`, `metal` or `verify`) measures that section again
into an existing report of the same mode and keeps the rest; the report says which section was
measured when.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from appliance.bench.optics_calibration import Calibrations, calibration_trials
from appliance.bench.optics_report import SECTION_KEYS, report
from appliance.bench.results import command_line, write_report
from appliance.config import Config
from appliance.errors import InputError
from appliance.runner import OutputFiles, run_test

RUBBER_RELATIVE_TARGET = 0.003
"""Calibrated rubber: largest relative error over readings above 1 % strain."""

IN_PLANE = {"thinning_out_of_plane": False, "slack_out_of_plane_mm": 0.0}
"""`[sim]` keys that keep the specimen's surface in its plane (no thinning, no slack)."""

SUMMARY_KEYS = (
    "exit_status",
    "measured_in",
    "frames_processed",
    "final_strain",
    "truth_final_strain",
    "max_abs_strain_error",
    "max_rel_strain_error",
    "max_elongation_error_um",
    "max_elongation_error_um_below_300um",
    "lost_points",
    "lost_points_in_valid_samples",
    "iso9513_class",
)


@dataclasses.dataclass(frozen=True)
class Plan:
    """How much the benchmark runs.

    Attributes:
        calibration_seeds: one calibration per seed (target 1).
        rubber_until_strain: the rubber tests' end (0 = to break).
        metal_until_strain: the metal tests' end.
        verify_benches: the bench presets verified.
        sim: `[sim]` keys set in every simulated world (a smaller sensor for a fast look).
    """

    calibration_seeds: tuple[int, ...]
    rubber_until_strain: float
    metal_until_strain: float
    verify_benches: tuple[str, ...]
    sim: dict[str, Any] = dataclasses.field(default_factory=dict)


FULL = Plan((1, 2, 3), 0.0, 0.02, ("ideal", "typical", "harsh"))
QUICK = Plan((1, 2), 0.5, 0.005, ("typical",))


def simulated(plan: Plan, material: str, bench: str, **tables: dict[str, Any]) -> Config:
    """A simulated test's configuration: `material` on `bench` with `plan`'s `[sim]` keys,
    and `tables`' keys set (table name -> {key: value})."""
    config = Config()
    config = dataclasses.replace(
        config,
        sim=dataclasses.replace(config.sim, material=material, bench=bench, **plan.sim),
    )
    for name, values in tables.items():
        config = dataclasses.replace(
            config, **{name: dataclasses.replace(getattr(config, name), **values)}
        )
    return config


def calibrated(config: Config, calibration: Path) -> Config:
    """`config` measuring in the object plane of `calibration`."""
    return dataclasses.replace(
        config, optics=dataclasses.replace(config.optics, calibration=str(calibration.resolve()))
    )


def run_case(name: str, config: Config, folder: Path) -> dict[str, Any]:
    """One whole simulated test; its summary's figures and wall time."""
    started = time.perf_counter()
    try:
        outcome = run_test(config, simulate=True, files=OutputFiles.in_directory(folder))
    except Exception as exc:  # a case that fails is reported, the others still run
        print(f"{name}: failed: {exc}", flush=True)
        return {"case": name, "error": str(exc), "wall_s": time.perf_counter() - started}
    summary = json.loads(outcome.to_json())
    figures = {key: summary.get(key) for key in SUMMARY_KEYS}
    figures["case"] = name
    figures["wall_s"] = time.perf_counter() - started
    print(
        f"{name}: class {figures['iso9513_class']}, relative error "
        f"{_percent(figures['max_rel_strain_error'])} ({figures['wall_s']:.0f} s)",
        flush=True,
    )
    return figures


def rubber_cases(out: Path, plan: Plan, calibrations: Calibrations) -> dict[str, Any]:
    """Target 2: the rubber test on the ideal bench, and on the typical bench by the nominal
    scale and by a calibration of its lens, with the specimen's out-of-plane moves (the bench
    as its preset sets it) and without them (what a calibration can correct)."""
    run = {"until_strain": plan.rubber_until_strain, "until_break": True}
    typical = simulated(plan, "rubber", "typical", run=run)
    in_plane = simulated(plan, "rubber", "typical", run=run, sim=IN_PLANE)
    calibration, made = calibrations.get("rubber", "typical")
    cases = [
        run_case("ideal bench", simulated(plan, "rubber", "ideal", run=run), out / "rubber-ideal"),
        run_case("typical bench, nominal scale", typical, out / "rubber-typical"),
        run_case(
            "typical bench, calibrated",
            calibrated(typical, calibration),
            out / "rubber-typical-calibrated",
        ),
        run_case(
            "typical bench, calibrated, specimen in its plane",
            calibrated(in_plane, calibration),
            out / "rubber-typical-calibrated-in-plane",
        ),
    ]
    nominal = cases[1]
    verdicts = {
        f"nominal scale misses class 0.5 (largest relative error "
        f"{_percent(nominal.get('max_rel_strain_error'))} against 0.5 %)": _verdict(
            "error" not in nominal and nominal["iso9513_class"] not in ("0.2", "0.5")
        )
    }
    for fitted in cases[2:]:
        relative = fitted.get("max_rel_strain_error")
        verdicts[f"{fitted['case']}: holds class 0.5"] = _verdict(
            fitted.get("iso9513_class") in ("0.2", "0.5")
        )
        verdicts[f"{fitted['case']}: relative error <= 0.3 % ({_percent(relative)})"] = _verdict(
            relative is not None and relative <= RUBBER_RELATIVE_TARGET
        )
    return {
        "until_strain": plan.rubber_until_strain or "break",
        "calibration": made,
        "cases": cases,
        "verdicts": verdicts,
    }


def metal_cases(out: Path, plan: Plan, calibrations: Calibrations) -> dict[str, Any]:
    """Target 3: the metal test on the typical bench through a telecentric lens, and through
    its entocentric lens (calibrated) with and without the specimen's out-of-plane moves."""
    run = {"until_strain": plan.metal_until_strain, "until_break": False}
    entocentric = simulated(plan, "metal", "typical", run=run)
    calibration, made = calibrations.get("metal", "typical")
    telecentric_calibration, telecentric_made = calibrations.get("metal", "typical", "telecentric")
    telecentric = simulated(plan, "metal", "typical", run=run, sim={"lens": "telecentric"})
    in_plane = simulated(plan, "metal", "typical", run=run, sim=IN_PLANE)
    cases = [
        run_case("telecentric lens", telecentric, out / "metal-telecentric"),
        run_case("entocentric lens, nominal scale", entocentric, out / "metal-entocentric"),
        run_case(
            "entocentric lens, calibrated",
            calibrated(entocentric, calibration),
            out / "metal-entocentric-calibrated",
        ),
        run_case(
            "entocentric lens, calibrated, specimen in its plane",
            calibrated(in_plane, calibration),
            out / "metal-entocentric-calibrated-in-plane",
        ),
        run_case(
            "telecentric lens, calibrated",
            calibrated(telecentric, telecentric_calibration),
            out / "metal-telecentric-calibrated",
        ),
    ]
    moving, still = cases[2], cases[3]
    share = None
    if moving.get("max_abs_strain_error") and still.get("max_abs_strain_error") is not None:
        share = 1.0 - still["max_abs_strain_error"] / moving["max_abs_strain_error"]
    return {
        "until_strain": plan.metal_until_strain,
        "calibration": made,
        "telecentric_calibration": telecentric_made,
        "cases": cases,
        "out_of_plane_share": share,
        "verdicts": {
            "telecentric lens: class 0.2": _verdict(cases[0].get("iso9513_class") == "0.2"),
            "telecentric lens, calibrated: class 0.2": _verdict(
                cases[4].get("iso9513_class") == "0.2"
            ),
        },
    }


def verify_cases(out: Path, plan: Plan, calibrations: Calibrations) -> list[dict[str, Any]]:
    """Target 4: `extensometer verify --sim --material metal` on each bench preset by the
    nominal scale, and on the typical bench with a calibration of its lens."""
    rows = []
    for bench in plan.verify_benches:
        settings = [("nominal scale", None)]
        if bench == "typical":
            calibration, _ = calibrations.get("metal", bench)
            settings.append(("calibrated", calibration))
        for how, calibration in settings:
            folder = out / f"verify-{bench}-{how.replace(' ', '-')}"
            measured = _verify(folder, bench, calibration, plan.sim)
            rows.append({"bench": bench, "optics": how, **measured})
            print(
                f"verify, {bench} bench, {how}: class {rows[-1]['achieved_class']} "
                f"({rows[-1]['wall_s']:.0f} s)",
                flush=True,
            )
    return rows


def _verify(
    folder: Path, bench: str, calibration: Path | None, sim: dict[str, Any]
) -> dict[str, Any]:
    folder.mkdir(parents=True, exist_ok=True)
    command = [
        sys.executable,
        "-m",
        "appliance.cli",
        "verify",
        "--sim",
        "--material",
        "metal",
        "--bench",
        bench,
        "--out",
        str(folder),
    ]
    lines = [f"{key} = {json.dumps(value)}" for key, value in sim.items()]
    if calibration is not None:
        lines = [
            f"[optics]\ncalibration = {json.dumps(str(calibration.resolve()))}",
            "[sim]",
            *lines,
        ]
    elif lines:
        lines = ["[sim]", *lines]
    if lines:
        config = folder / "verify.toml"
        config.write_text("\n".join(lines) + "\n", encoding="utf-8")
        command += ["--config", str(config)]
    started = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    wall_s = time.perf_counter() - started
    if done.returncode not in (0, 1):
        return {"achieved_class": None, "error": done.stderr.strip()[-300:], "wall_s": wall_s}
    document = json.loads((folder / "verification.json").read_text(encoding="utf-8"))
    worst = document.get("worst_bias") or {}
    return {
        "achieved_class": document["achieved_class"],
        "classes": {name: c["best_class"] for name, c in document["criteria"].items()},
        "worst_bias_um": worst.get("bias_um"),
        "worst_bias_at_um": worst.get("calibrator_um"),
        "resolution_um": document["resolution_um"],
        "gauge_length_error_percent": document["gauge_length_error_percent"],
        "wall_s": wall_s,
    }


def calibration_cases(out: Path, plan: Plan, calibrations: Calibrations) -> dict[str, Any]:
    """Target 1: the typical bench's lens calibrated once per seed of `plan`."""
    return calibration_trials(
        out / "calibration-trials", list(plan.calibration_seeds), calibrations, plan.sim
    )


SECTIONS = SECTION_KEYS
"""The sections `--only` can measure again on their own."""


def run_optics_benchmark(
    out: Path, *, quick: bool = False, plan: Plan | None = None, only: str | None = None
) -> int:
    """Run every target's cases, print the report, write `out/optics.md` and
    `out/optics.json` (each case's files under `out/optics/`); exit status 0. `plan` (else
    `QUICK` or `FULL`) says how much is run. `only` (one of `SECTIONS`) measures that section
    again and keeps the others from `out/optics.json`, whose `remeasured` then says which
    section was measured when and by which command.

    Raises:
        InputError: `only` without an earlier `out/optics.json` of the same mode.
    """
    plan = plan or (QUICK if quick else FULL)
    mode = "quick" if quick or plan is not FULL else "full"
    earlier = _earlier_figures(out, mode) if only else None
    cases_dir = out / "optics"
    calibrations = Calibrations(cases_dir / "calibrations", plan.sim)
    started = time.perf_counter()
    if earlier is not None and only is not None:
        figures = dict(earlier["figures"])
        figures[only] = _section(MEASURES[only], cases_dir, plan, calibrations)
        figures["remeasured"] = [
            *figures.get("remeasured", []),
            {
                "section": only,
                "measured_utc": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
                "command": command_line(),
                "wall_s": time.perf_counter() - started,
            },
        ]
        figures["first_measured_utc"] = figures.get("first_measured_utc", earlier["measured_utc"])
    else:
        trials = calibration_cases(cases_dir, plan, calibrations)
        figures = {
            "mode": mode,
            "calibration": trials,
            **{
                name: _section(MEASURES[name], cases_dir, plan, calibrations)
                for name in SECTIONS[1:]
            },
        }
        figures["wall_s"] = time.perf_counter() - started
    (cases_dir / "figures.json").write_text(json.dumps(figures, indent=1) + "\n", encoding="utf-8")
    body = report(figures)
    write_report(out, "optics", "Optics: camera calibration, object plane, ISO 9513", figures, body)
    print(body)
    return 0


def _earlier_figures(out: Path, mode: str) -> dict[str, Any]:
    path = out / "optics.json"
    try:
        document = json.loads(path.read_text(encoding="utf-8"))
        figures = document["figures"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{path}: no earlier optics report to complete ({exc})") from None
    if figures.get("mode") != mode:
        raise InputError(f"{path}: its mode is {figures.get('mode')!r}, this run's {mode!r}")
    return document


def _section(measure: Any, out: Path, plan: Plan, calibrations: Calibrations) -> Any:
    try:
        return measure(out, plan, calibrations)
    except Exception as exc:  # a section that fails is reported, the others still run
        print(f"{measure.__name__}: failed: {exc}", flush=True)
        return {"error": str(exc)}


MEASURES = {
    "calibration": calibration_cases,
    "rubber": rubber_cases,
    "metal": metal_cases,
    "verify": verify_cases,
}


def _verdict(met: bool) -> str:
    return "met" if met else "missed"


def _percent(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.3f} %"
