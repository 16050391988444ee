"""The output that turns a test into its results and `report.html`.

`TestReport` follows a run or a replay like any output (`appliance.run.outputs.RunOutput`):
it keeps the reference frame and the gauge when the test begins, every sample's strain, force,
validity and losses while it runs, and at the end computes the results under the standard of
the specimen's material (`metals` or `rubber`). Its `stats` give the summary's `results`
object; `write` draws the figures and writes the page (`report_page`).

The material and the original cross-section S0 are run facts (`specimen_material`,
`cross_section_mm2`: the `[specimen]` table's, or a simulated test's preset), so a replay
reports with what the test was run with (a recording older than these facts: the simulated
`material`, and no S0). The truth of a simulated test comes in only as the
`truth` callable of the composition, and only draws the error figure: no result reads it.
"""

from __future__ import annotations

import contextlib
import datetime
import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from appliance.measure.frame_measurer import StrainSample
from appliance.results import plots
from appliance.results.metals import metal_results
from appliance.results.report_page import ReportFigures, report_html
from appliance.results.result import ResultsObject, TestResults
from appliance.results.rubber import rubber_results
from appliance.results.series import SeriesRecorder, TestSeries
from appliance.run.loop import LoopResult
from appliance.run.outputs import RunFacts
from appliance.run.state import ExitStatus
from appliance.run.summary import RunOutcome

REPORT_NAME = "report.html"
STANDARDS = {"metal": metal_results, "rubber": rubber_results}


class TestReport:
    """Results and report of one test; a `RunOutput`.

    Args:
        truth: (true strain, true elongation mm) of the sample just measured, in a simulated
            test (scoring only: it draws the error figure); None otherwise.
    """

    def __init__(self, truth: Callable[[StrainSample], tuple[float, float]] | None = None) -> None:
        self._recorder = SeriesRecorder(truth)
        self._facts: RunFacts | None = None
        self._reference: np.ndarray | None = None
        self.series: TestSeries | None = None
        self.results: TestResults | None = None
        self.no_results_reason: str | None = "the test did not begin"

    def begin(self, facts: RunFacts) -> None:
        """Keep the test's facts and a copy of its reference frame."""
        self._facts = facts
        self._reference = np.array(facts.reference.image, copy=True)

    def __call__(self, sample: StrainSample) -> None:
        """Record one sample."""
        self._recorder.add(sample)

    def end(self, result: LoopResult) -> None:
        """Compute the results of the test as it ended."""
        self.series = self._recorder.series()
        if self._facts is None:
            return
        facts = self._facts.facts
        material = facts.get("specimen_material") or facts.get("material")
        area = facts.get("cross_section_mm2")
        compute = STANDARDS.get(str(material))
        if compute is None:
            self.no_results_reason = "[specimen] material is not configured (metal or rubber)"
            return
        self.no_results_reason = None
        self.results = compute(
            self.series,
            float(area) if isinstance(area, (int, float)) else None,
            broke=result.exit_status is ExitStatus.BREAK,
        )

    def stats(self) -> dict[str, Any]:
        """The summary's `results` object."""
        if self.results is not None:
            return {"results": ResultsObject.of(self.results)}
        return {"results": ResultsObject.none(self.no_results_reason or "")}

    def write(self, path: Path, outcome: RunOutcome) -> None:
        """Draw the figures and write the page to `path` (its directory must exist).

        The summary's `report` then names the page, or says why it could not be written: the
        page only shows what the summary and the strain file hold, so the test's outcome
        stands either way. A page cut short (a full disk) is removed, giving its room back to
        the summary.
        """
        facts = self._facts.facts if self._facts is not None else {}
        devices = self._facts.devices if self._facts is not None else {}
        title = f"Tensile test {facts.get('test_id') or ''}".strip()
        page = report_html(
            title,
            _facts_rows(outcome.as_dict(), devices),
            self.results,
            self.no_results_reason,
            self._figures(),
        )
        try:
            path.write_text(page, encoding="utf-8")
        except OSError as exc:
            outcome.extra["report"] = f"{path}: cannot write ({exc.strerror})"
            _remove_partial(path)
            return
        outcome.extra["report"] = str(path)

    def _figures(self) -> ReportFigures:
        series = self.series
        if series is None or len(series) == 0:
            return ReportFigures()
        area = self.results.cross_section_mm2 if self.results is not None else None
        facts = self._facts
        gauge = None
        if facts is not None and self._reference is not None:
            gauge = plots.gauge_png_uri(
                self._reference, facts.points, facts.layout, facts.gauge_length_mm
            )
        return ReportFigures(
            stress_strain=plots.stress_strain_svg(series, area, self.results)
            if series.has_force
            else None,
            time_series=plots.time_series_svg(series),
            transverse=plots.transverse_svg(series)
            if series.transverse_strain is not None
            else None,
            validity=plots.validity_svg(series),
            truth_error=plots.truth_error_svg(series) if series.has_truth else None,
            gauge=gauge,
        )


def _remove_partial(path: Path) -> None:
    with contextlib.suppress(OSError):
        path.unlink(missing_ok=True)


_FACT_ROWS = (
    ("test_id", "test"),
    ("exit_status", "ended"),
    ("reason", "why"),
    ("specimen_material", "material"),
    ("cross_section_mm2", "original cross-section S0 (mm²)"),
    ("cross_section_source", "cross-section from"),
    ("gauge_length_mm", "gauge length requested (mm)"),
    ("gauge_length_achieved_mm", "gauge length L0 as placed, the strain's reference (mm)"),
    ("gauge_placement", "gauge placement"),
    ("speed_mm_min", "crosshead speed (mm/min)"),
    ("frame_rate_hz", "frame rate (Hz)"),
    ("test_duration_s", "duration (s)"),
    ("frames_processed", "frames measured"),
    ("frames_dropped", "frames dropped"),
    ("invalid_samples", "invalid samples"),
    ("lost_points", "points lost"),
    ("final_strain", "final strain"),
    ("max_abs_strain_error", "largest strain error against the truth (simulated)"),
    ("iso9513_class", "ISO 9513 class against the truth (simulated)"),
    ("recording", "recording replayed"),
    ("max_abs_diff_to_recorded", "largest difference to the recorded strain"),
)


def _facts_rows(summary: dict[str, Any], devices: Mapping[str, str]) -> list[tuple[str, str]]:
    rows = [
        (label, _text(summary[key]))
        for key, label in _FACT_ROWS
        if key in summary and summary[key] is not None
    ]
    rows += [(name, text) for name, text in devices.items() if text]
    created = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
    return [*rows, ("report written", created)]


def _text(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.6g}" if math.isfinite(value) else "-"
    return str(value)
