"""`report.html`: one self-contained page a person reads after a test.

In order: how the test ended and its facts, the results table (each result's value, the
samples it was taken from and how, or why it was not determined), the stress-strain curve,
strain and force over time, the gauge on the reference frame, the data-valid and lost-frame
history and, for a simulated test, the error against the simulated truth. Every figure is
inline (SVG, or a PNG `data:` URI); the page loads nothing from a file or the network.
"""

from __future__ import annotations

import html
from collections.abc import Sequence
from dataclasses import dataclass

from appliance.results.result import TestResults

STYLE = (
    "body{font-family:sans-serif;max-width:64em;margin:2em auto;color:#222}"
    "table{border-collapse:collapse;margin:0.5em 0}"
    "td,th{border:1px solid #ccc;padding:2px 8px;text-align:left;vertical-align:top}"
    "td.number{text-align:right;white-space:nowrap}.missing{color:#b2182b}"
    "figure{margin:1em 0}img{max-width:100%}"
)


@dataclass(frozen=True)
class ReportFigures:
    """The page's figures as embeddable text (`appliance.results.plots`); None = left out.

    Attributes:
        stress_strain, time_series, transverse, validity, truth_error: inline SVG.
        gauge: the reference frame with the gauge, a `data:` URI.
    """

    stress_strain: str | None = None
    time_series: str | None = None
    transverse: str | None = None
    validity: str | None = None
    truth_error: str | None = None
    gauge: str | None = None


def report_html(
    title: str,
    facts: Sequence[tuple[str, str]],
    results: TestResults | None,
    no_results_reason: str | None,
    figures: ReportFigures,
) -> str:
    """The report page.

    Args:
        title: the page's heading (the test's name).
        facts: (what, value) rows of the test's facts, in order.
        results: the test's results; None when there are none.
        no_results_reason: why there are none (shown instead of the table).
        figures: the figures to embed.
    """
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{html.escape(title)}</title>",
        f"<style>{STYLE}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        "<h2>The test</h2>",
        _rows_table(facts),
        "<h2>Results</h2>",
        _results_table(results)
        if results is not None
        else f'<p class="missing">No results: {html.escape(no_results_reason or "")}</p>',
    ]
    sections = (
        ("Stress-strain curve", "stress-strain", figures.stress_strain),
        ("Strain and force over time", "time-series", figures.time_series),
        ("Transverse strain against axial strain", "transverse", figures.transverse),
        ("Data valid and lost frames", "validity", figures.validity),
        ("Error against the simulated truth (scoring only)", "truth-error", figures.truth_error),
    )
    for heading, anchor, svg in sections[:3]:
        if svg is not None:
            parts += [f"<h2>{heading}</h2>", f'<figure id="{anchor}">{svg}</figure>']
    if figures.gauge is not None:
        parts += [
            "<h2>The gauge on the reference frame</h2>",
            f'<figure id="gauge"><img alt="reference frame with the gauge marks" '
            f'src="{figures.gauge}"></figure>',
        ]
    for heading, anchor, svg in sections[3:]:
        if svg is not None:
            parts += [f"<h2>{heading}</h2>", f'<figure id="{anchor}">{svg}</figure>']
    parts.append("</body></html>")
    return "\n".join(parts) + "\n"


def _rows_table(rows: Sequence[tuple[str, str]]) -> str:
    body = "".join(
        f"<tr><th>{html.escape(what)}</th><td>{html.escape(value)}</td></tr>"
        for what, value in rows
    )
    return f"<table>{body}</table>"


def _results_table(results: TestResults) -> str:
    area = (
        f"{results.cross_section_mm2:.5g} mm²"
        if results.cross_section_mm2 is not None
        else "not configured"
    )
    head = (
        "<tr><th>result</th><th>name</th><th>value</th><th>samples</th>"
        "<th>how it was taken</th></tr>"
    )
    rows = []
    for r in results.results:
        if r.is_determined:
            samples = (
                f"{r.samples[0]}" if r.samples[0] == r.samples[1] else "{} to {}".format(*r.samples)
            )
            cells = (
                f'<td class="number">{html.escape(r.text())}</td>'
                f'<td class="number">{samples}</td><td>{html.escape(r.basis)}</td>'
            )
        else:
            cells = (
                '<td class="missing">not determined</td><td></td>'
                f'<td class="missing">{html.escape(r.reason or "")}</td>'
            )
        rows.append(
            f'<tr id="result-{html.escape(r.symbol)}"><th>{html.escape(r.symbol)}</th>'
            f"<td>{html.escape(r.name)}</td>{cells}</tr>"
        )
    caption = f"{html.escape(results.standard)}; original cross-section S0 {area}"
    return f'<p>{caption}</p><table id="results">{head}{"".join(rows)}</table>'
