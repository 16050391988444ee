"""The files of an ISO 9513 verification: `verification.json` and `report.html`.

`verification.json` is `Verification.to_document()` with the run's facts (software version,
the calibration file's checksum, the command, the time). `report.html` is one self-contained
page: the outcome and every finding, the facts, two plots embedded as SVG (the bias error
against the calibrator's elongation with the class limits drawn, absolute in um and relative
in %, each series in its own marker) and the table of every calibration point.
"""

from __future__ import annotations

import html
import io
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from appliance.errors import InputError
from appliance.run.iso9513 import CLASSES
from appliance.run.verification import Verification

JSON_NAME = "verification.json"
HTML_NAME = "report.html"
_CLASS_COLOURS = {"0.2": "#1b7837", "0.5": "#2166ac", "1": "#b2182b", "2": "#7f7f7f"}


def write_verification(
    verification: Verification, out_dir: Path, facts: dict[str, Any]
) -> tuple[Path, Path]:
    """Write `verification.json` and `report.html` into `out_dir` (created).

    Args:
        verification: the graded verification.
        out_dir: the output directory.
        facts: the run's facts, first in the document (`software_version`,
            `calibration_checksum`, `command`, `created_utc`, ...).

    Returns:
        (the JSON path, the HTML path).

    Raises:
        InputError: the directory or a file cannot be written.
    """
    document = {**facts, **verification.to_document()}
    json_path, html_path = out_dir / JSON_NAME, out_dir / HTML_NAME
    page = report_html(verification, facts)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(document, indent=2) + "\n")
        html_path.write_text(page)
    except OSError as exc:
        raise InputError(f"{exc.filename or out_dir}: cannot write ({exc.strerror})") from None
    return json_path, html_path


def report_html(verification: Verification, facts: dict[str, Any]) -> str:
    """The report as one HTML page with its plots inline."""
    v = verification
    outcome = (
        f"meets class {html.escape(v.requested.name)}"
        if v.met
        else f"does not meet class {html.escape(v.requested.name)}"
    )
    achieved = v.achieved if v.achieved is not None else "none"
    rows = [
        ("requested class", v.requested.name),
        ("class reached", achieved),
        *[
            (
                f"{name.replace('_', ' ')} class",
                (c.best_class or "none") if c.assessed else "not assessed",
            )
            for name, c in v.criteria.items()
        ],
        ("resolution", _um(v.resolution_um)),
        ("standard deviation at rest", _um(v.rest_std_um)),
        ("gauge length measured", _mm(v.gauge_length_mm)),
        ("gauge length nominal", _mm(v.data.nominal_gauge_length_mm)),
        ("gauge length error", _percent(v.gauge_length_error_percent)),
    ]
    worst = v.worst_bias
    if worst is not None:
        rows.append(("worst bias", worst.describe_bias()))
    rows += [
        (key.replace("_", " "), "none" if value is None else str(value))
        for key, value in facts.items()
    ]
    findings = "".join(f"<li>{html.escape(line)}</li>" for line in v.findings)
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        "<title>ISO 9513 verification</title>",
        "<style>body{font-family:sans-serif;max-width:60em;margin:2em auto}"
        "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:2px 8px;"
        "text-align:right}td:first-child,th:first-child{text-align:left}"
        ".fail{color:#b2182b}.pass{color:#1b7837}</style></head><body>",
        "<h1>ISO 9513 verification</h1>",
        f'<p class="{"pass" if v.met else "fail"}"><strong>The extensometer {outcome}'
        f"</strong> (class reached: {html.escape(achieved)}).</p>",
        f"<ul>{findings}</ul>" if findings else "",
        "<h2>Summary</h2>",
        _table(("", ""), rows, header=False),
        "<h2>Bias error</h2>",
        f'<figure id="bias-absolute">{_plot(v, relative=False)}</figure>',
        f'<figure id="bias-relative">{_plot(v, relative=True)}</figure>',
        "<h2>Calibration points</h2>",
        _points_table(v),
        "<h2>Class limits (ISO 9513:2012, Table 2)</h2>",
        _table(
            ("class", "bias %", "bias um", "resolution %", "resolution um", "gauge length %"),
            [
                (
                    c.name,
                    f"{100 * c.relative:g}",
                    f"{c.absolute_um:g}",
                    f"{100 * c.resolution_relative:g}",
                    f"{c.resolution_um:g}",
                    f"{100 * c.gauge_length_relative:g}",
                )
                for c in CLASSES
            ],
        ),
        "</body></html>",
    ]
    return "\n".join(part for part in parts if part) + "\n"


def _um(value: float | None) -> str:
    return "not assessed" if value is None else f"{value:.4g} um"


def _mm(value: float | None) -> str:
    return "not measured" if value is None else f"{value:.5g} mm"


def _percent(value: float | None) -> str:
    return "not assessed" if value is None else f"{value:+.4f} %"


def _table(columns: tuple[str, ...], rows: list[tuple[str, ...]], *, header: bool = True) -> str:
    head = "<tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in columns) + "</tr>"
    body = "".join(
        "<tr>" + "".join(f"<td>{html.escape(str(cell))}</td>" for cell in row) + "</tr>"
        for row in rows
    )
    return f"<table>{head if header else ''}{body}</table>"


def _points_table(v: Verification) -> str:
    rows = []
    for p in v.data.points:
        limit = float(v.requested.limit_um(np.array([p.calibrator_um]))[0])
        relative = p.relative_bias_percent
        rows.append(
            (
                p.series,
                v.data.direction_of(p.series),
                f"{p.calibrator_um:g}",
                f"{p.reading_um:.3f}",
                f"{p.bias_um:+.3f}",
                "" if relative is None else f"{relative:+.3f}",
                f"{limit:.3g}",
                "yes" if math.isfinite(p.bias_um) and abs(p.bias_um) <= limit else "no",
            )
        )
    return _table(
        (
            "series",
            "direction",
            "calibrator um",
            "reading um",
            "bias um",
            "bias %",
            f"class {v.requested.name} limit um",
            "within",
        ),
        rows,
    )


def _plot(v: Verification, *, relative: bool) -> str:
    """The bias error of every point against the calibrator's elongation, with the class
    limits, as inline SVG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    points = v.data.points
    elongations = np.array([p.calibrator_um for p in points])
    top = float(elongations.max()) if elongations.size else 1.0
    grid = np.linspace(0.0, max(top, 1e-9) * 1.05, 400)
    figure, axes = plt.subplots(figsize=(8, 4.2))
    for c in CLASSES:
        limit = c.limit_um(grid)
        values = 100 * limit / np.maximum(grid, 1e-12) if relative else limit
        if relative:
            keep = grid > 0
            grid_shown, values = grid[keep], values[keep]
        else:
            grid_shown = grid
        colour = _CLASS_COLOURS[c.name]
        width = 2.0 if c.name == v.requested.name else 0.8
        axes.plot(grid_shown, values, color=colour, lw=width, label=f"class {c.name}")
        axes.plot(grid_shown, -values, color=colour, lw=width)
    markers = "osD^v<>"
    for index, name in enumerate(v.data.series_names()):
        mine = [p for p in points if p.series == name]
        if relative:
            mine = [p for p in mine if p.relative_bias_percent is not None]
            y = [p.relative_bias_percent for p in mine]
        else:
            y = [p.bias_um for p in mine]
        axes.plot(
            [p.calibrator_um for p in mine],
            y,
            markers[index % len(markers)],
            ls="-",
            lw=0.6,
            mfc="none",
            label=f"series {name} ({v.data.direction_of(name)})",
        )
    worst = [abs(p.relative_bias_percent or 0.0) if relative else abs(p.bias_um) for p in points]
    shown = max((w for w in worst if math.isfinite(w)), default=0.0)
    if relative:
        span = 100 * v.requested.relative * 4
    else:
        span = float(v.requested.limit_um(np.array([top]))[0])
    bound = max(1.6 * span, 1.2 * shown)
    axes.set_ylim(-bound, bound)
    axes.axhline(0.0, color="black", lw=0.5)
    axes.set_xlabel("calibrator elongation l_t (um)")
    axes.set_ylabel("relative bias q (%)" if relative else "bias l_i - l_t (um)")
    axes.set_title(
        "Relative bias error and class limits" if relative else "Bias error and class limits"
    )
    axes.legend(fontsize=8, loc="upper right", ncol=2)
    axes.grid(alpha=0.3)
    figure.tight_layout()
    buffer = io.StringIO()
    figure.savefig(buffer, format="svg")
    plt.close(figure)
    svg = buffer.getvalue()
    return svg[svg.index("<svg") :]
