"""The optics benchmark's report: its figures (`appliance.bench.optics`) as Markdown tables."""

from __future__ import annotations

from typing import Any

from appliance.bench.optics_calibration import TARGETS

SECTION_KEYS = ("calibration", "rubber", "metal", "verify")
"""The report's sections, as the figures name them."""


def report(figures: dict[str, Any]) -> str:
    """The report's body: one section per target, each figure with its target and verdict."""
    mode = "quick (fewer calibrations, shortened tests)" if figures["mode"] == "quick" else "full"
    latest = {r["section"]: r for r in figures.get("remeasured", [])}
    remeasured = ""
    if latest:
        remeasured = (
            " Sections measured again (the latest of each): "
            + "; ".join(
                f"{r['section']} on {r['measured_utc']} ({r['wall_s']:.0f} s, `{r['command']}`)"
                for r in sorted(latest.values(), key=lambda r: r["measured_utc"])
            )
            + (
                f"; the others as first measured on {figures['first_measured_utc']}."
                if len(latest) < len(SECTION_KEYS)
                else "."
            )
        )
    first = "first measured" if latest else "measured"
    parts = [
        f"Mode: {mode}; {first} in {figures['wall_s']:.0f} s.{remeasured} Errors are against the "
        "simulated world's ground truth (the specimen plane's material points); every "
        "calibration is made by the product's calibration from simulated ChArUco views of the "
        "bench's lens, "
        "the first lying in the specimen plane. Each case's files are under `optics/`.",
        _failed(figures["calibration"], "1. Calibration from simulated target views")
        or _calibration(figures["calibration"]),
        _failed(figures["rubber"], "2. Rubber") or _rubber(figures["rubber"]),
        _failed(figures["metal"], "3. Metal") or _metal(figures["metal"]),
        _failed(figures["verify"], "4. ISO 9513 verification") or _verify(figures["verify"]),
    ]
    return "\n\n".join(parts) + "\n"


def _failed(section: Any, title: str) -> str:
    if isinstance(section, dict) and "error" in section:
        return f"## {title}\n\nfailed: {section['error']}"
    return ""


def _calibration(section: dict[str, Any]) -> str:
    seeds = ", ".join(str(t["seed"]) for t in section["trials"])
    rows = [
        "## 1. Calibration from simulated target views",
        "",
        f"Typical bench ({section['true_corner_distortion_px']:.2f} px of distortion at the "
        f"image corners), the {section['camera']}'s camera; {section['views']} views of a "
        f"{section['target']}; seeds {seeds}.",
        "",
        "| figure | median | worst | target | verdict |",
        "|---|---|---|---|---|",
    ]
    names = {
        "rms_reprojection_px": ("RMS reprojection, px", TARGETS["rms_reprojection_px"]),
        "scale_error_percent": (
            "scale error at the specimen plane, %",
            TARGETS["scale_error_percent"],
        ),
        "corner_distortion_error_px": (
            "distortion at the field corners, error, px",
            TARGETS["corner_distortion_px"],
        ),
        "corner_length_error_px": ("centre-to-corner length on the plane, error, px", None),
    }
    for key, (label, target) in names.items():
        row = section["figures"][key]
        limit = "-" if target is None else f"<= {target:g}"
        rows.append(
            f"| {label} | {_cell(row['median'])} | {_cell(row['worst'])} | {limit} | "
            f"{row['verdict']} |"
        )
    return "\n".join(rows)


def _run_table(cases: list[dict[str, Any]]) -> list[str]:
    rows = [
        "| figure | " + " | ".join(c["case"] for c in cases) + " |",
        "|---" * (len(cases) + 1) + "|",
    ]
    keys = ["error"] if any("error" in c for c in cases) else []
    for key in (
        *keys,
        "measured_in",
        "iso9513_class",
        "max_rel_strain_error",
        "max_abs_strain_error",
        "max_elongation_error_um_below_300um",
        "final_strain",
        "truth_final_strain",
        "lost_points_in_valid_samples",
        "lost_points",
        "exit_status",
        "frames_processed",
        "wall_s",
    ):
        rows.append(f"| {key} | " + " | ".join(_cell(c.get(key)) for c in cases) + " |")
    return rows


def _verdicts(verdicts: dict[str, str]) -> list[str]:
    return ["", *(f"- {target}: {verdict}" for target, verdict in verdicts.items())]


def _made(calibration: dict[str, Any]) -> str:
    return (
        f"calibration (seed {calibration['seed']}, {calibration['target']}): RMS "
        f"{calibration['rms_reprojection_px']:.4f} px, scale error "
        f"{calibration['scale_error_percent']:+.4f} %"
    )


def _rubber(section: dict[str, Any]) -> str:
    end = section["until_strain"]
    end_text = "to break" if end == "break" else f"to {100 * end:g} % strain"
    rows = [
        "## 2. Rubber, ISO 37 type 1, 500 mm/min",
        "",
        f"`run --sim`, {end_text}; the typical bench as its preset sets it (thinning and slack "
        f"included); {_made(section['calibration'])}. Relative error over readings above 1 %.",
        "",
        *_run_table(section["cases"]),
        *_verdicts(section["verdicts"]),
    ]
    return "\n".join(rows)


def _metal(section: dict[str, Any]) -> str:
    share = section["out_of_plane_share"]
    share_text = "-" if share is None else f"{100 * share:.0f} %"
    rows = [
        "## 3. Metal, ISO 6892-1 flat, 10 mm/min, typical bench",
        "",
        f"`run --sim` to `[run] until_strain = {section['until_strain']:g}` (not to break); "
        f"entocentric lens: {_made(section['calibration'])}; telecentric lens "
        f"(`calibrate --telecentric`): {_made(section['telecentric_calibration'])}. "
        "The specimen's out-of-plane moves (thinning, slack) "
        f"make {share_text} of the calibrated entocentric run's largest strain error (1 - the "
        "error without them / the error with them).",
        "",
        *_run_table(section["cases"]),
        *_verdicts(section["verdicts"]),
    ]
    return "\n".join(rows)


def _verify(rows_in: list[dict[str, Any]]) -> str:
    rows = [
        "## 4. ISO 9513 verification on each bench",
        "",
        "`extensometer verify --sim --material metal --bench B` (seed 1); calibrated: with "
        "`[optics] calibration` naming a calibration of that bench's lens.",
        "",
        "| bench | optics | class reached | bias / resolution / gauge length class | worst bias, "
        "um (at um) | resolution, um | gauge length error, % | wall, s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in rows_in:
        if row.get("error"):
            rows.append(f"| {row['bench']} | {row['optics']} | failed: {row['error']} | | | | | |")
            continue
        classes = " / ".join(str(c) for c in row["classes"].values())
        rows.append(
            f"| {row['bench']} | {row['optics']} | {row['achieved_class']} | {classes} | "
            f"{_cell(row['worst_bias_um'])} ({_cell(row['worst_bias_at_um'])}) | "
            f"{_cell(row['resolution_um'])} | {_cell(row['gauge_length_error_percent'])} | "
            f"{row['wall_s']:.0f} |"
        )
    return "\n".join(rows)


def _cell(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return "-" if value is None else str(value)
