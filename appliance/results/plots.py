"""The report's figures, drawn with matplotlib (Agg) and returned as text to embed in a page.

Plots are inline SVG (`<svg ...>`); the gauge on the reference frame is a PNG as a `data:` URI
(an image in SVG would be as large and slower to draw). Nothing refers to a file or a network
resource.
"""

from __future__ import annotations

import base64
import io

import numpy as np

from appliance.measure.gauges import StrainGaugesLayout
from appliance.results.result import TestResults
from appliance.results.series import TestSeries

WIDTH_IN = 8.0
HEIGHT_IN = 4.0
GAUGE_MARGIN_PX = 120
GAUGE_MARGIN_FRACTION = 0.3
GAUGE_FIGURE_IN = 6.0
GAUGE_DPI = 80


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


SVG_METADATA = {"Creator": None, "Date": None, "Format": None, "Type": None}
SVG_NAMESPACES = (
    ' xmlns:xlink="http://www.w3.org/1999/xlink"',
    ' xmlns="http://www.w3.org/2000/svg"',
)


def _svg(figure) -> str:
    """The figure as an `<svg>` element for an HTML page: no metadata block, and no namespace
    declarations (HTML knows the SVG and xlink names), so the page names no web address."""
    buffer = io.StringIO()
    figure.tight_layout()
    figure.savefig(buffer, format="svg", metadata=SVG_METADATA)
    _pyplot().close(figure)
    text = buffer.getvalue()
    text = text[text.index("<svg") :]
    for declaration in SVG_NAMESPACES:
        text = text.replace(declaration, "", 1)
    return text


def stress_strain_svg(
    series: TestSeries, cross_section_mm2: float | None, results: TestResults | None
) -> str:
    """Stress (force without a cross-section) against strain in %, valid samples only, with
    the stress results marked at the strain of the sample each lies at (`Result.at_sample`)."""
    plt = _pyplot()
    figure, axes = plt.subplots(figsize=(WIDTH_IN, HEIGHT_IN))
    keep = series.valid & np.isfinite(series.force_n)
    strain = 100.0 * series.strain[keep]
    if cross_section_mm2 is not None:
        load, label = series.force_n[keep] / cross_section_mm2, "stress R = F / S0 (MPa)"
    else:
        load, label = series.force_n[keep], "force F (N)"
    axes.plot(strain, load, lw=1.0, color="#2166ac")
    if results is not None and cross_section_mm2 is not None:
        for result in results.results:
            if result.unit != "MPa" or result.value is None or result.at_sample is None:
                continue
            position = np.flatnonzero(series.index[keep] == result.at_sample)
            if position.size:
                axes.plot(strain[position[0]], result.value, "o", mfc="none", color="#b2182b")
                axes.annotate(
                    result.symbol,
                    (strain[position[0]], result.value),
                    textcoords="offset points",
                    xytext=(6, -12),
                    fontsize=8,
                )
    axes.set_xlabel("engineering strain e (%)")
    axes.set_ylabel(label)
    axes.set_title("Stress-strain curve" if cross_section_mm2 else "Force-strain curve")
    axes.grid(alpha=0.3)
    return _svg(figure)


def time_series_svg(series: TestSeries) -> str:
    """Strain and force against time, on two axes."""
    plt = _pyplot()
    figure, strain_axes = plt.subplots(figsize=(WIDTH_IN, HEIGHT_IN))
    shown = np.where(series.valid, 100.0 * series.strain, np.nan)
    strain_axes.plot(series.time_s, shown, color="#2166ac", lw=1.0, label="strain")
    strain_axes.set_xlabel("time since the reference frame (s)")
    strain_axes.set_ylabel("engineering strain (%)", color="#2166ac")
    force_axes = strain_axes.twinx()
    force_axes.plot(series.time_s, series.force_n, color="#b2182b", lw=1.0, label="force")
    force_axes.set_ylabel("force (N)", color="#b2182b")
    strain_axes.set_title("Strain and force over time")
    strain_axes.grid(alpha=0.3)
    return _svg(figure)


def transverse_svg(series: TestSeries) -> str:
    """Transverse against axial engineering strain over the valid samples of a test that
    measured a transverse strain (`series.transverse_strain` not None), with where it came
    from in the title."""
    plt = _pyplot()
    figure, axes = plt.subplots(figsize=(WIDTH_IN, HEIGHT_IN))
    transverse = series.transverse_strain
    shown = series.valid & np.isfinite(transverse)
    axes.plot(100.0 * series.strain[shown], 100.0 * transverse[shown], color="#5e3c99", lw=1.0)
    axes.set_xlabel("axial engineering strain (%)")
    axes.set_ylabel("transverse engineering strain (%)")
    source = f" ({series.transverse_source})" if series.transverse_source else ""
    axes.set_title(f"Transverse strain{source}")
    axes.grid(alpha=0.3)
    return _svg(figure)


def validity_svg(series: TestSeries) -> str:
    """The data-valid flag, the points lost per frame and the frames dropped so far."""
    plt = _pyplot()
    from matplotlib.ticker import MaxNLocator

    figure, (valid_axes, lost_axes) = plt.subplots(2, 1, figsize=(WIDTH_IN, HEIGHT_IN), sharex=True)
    valid_axes.step(series.time_s, series.valid.astype(int), where="post", color="#1b7837")
    valid_axes.set_ylim(-0.1, 1.1)
    valid_axes.set_yticks([0, 1], ["invalid", "valid"])
    valid_axes.set_title("Data valid, points lost and frames dropped")
    lost_axes.step(series.time_s, series.points_lost, where="post", label="points lost in frame")
    lost_axes.step(
        series.time_s, series.frames_dropped, where="post", label="frames dropped so far"
    )
    lost_axes.set_xlabel("time since the reference frame (s)")
    lost_axes.set_ylabel("count")
    lost_axes.yaxis.set_major_locator(MaxNLocator(integer=True))
    lost_axes.set_ylim(bottom=-0.5, top=max(1.5, lost_axes.get_ylim()[1]))
    lost_axes.legend(fontsize=8, loc="upper left")
    for axes in (valid_axes, lost_axes):
        axes.grid(alpha=0.3)
    return _svg(figure)


def truth_error_svg(series: TestSeries) -> str:
    """Measured minus true strain against the true strain (a simulated test), with the ISO
    9513 class 0.5 relative limit for scale."""
    plt = _pyplot()
    figure, axes = plt.subplots(figsize=(WIDTH_IN, HEIGHT_IN))
    keep = series.valid & np.isfinite(series.truth_strain)
    truth = series.truth_strain[keep]
    axes.plot(100.0 * truth, 100.0 * (series.strain[keep] - truth), lw=1.0, color="#2166ac")
    limit = 0.5 * np.abs(truth)
    axes.plot(100.0 * truth, limit, ls="--", lw=0.8, color="#7f7f7f", label="0.5 % of reading")
    axes.plot(100.0 * truth, -limit, ls="--", lw=0.8, color="#7f7f7f")
    axes.axhline(0.0, color="black", lw=0.5)
    axes.set_xlabel("true engineering strain (%)")
    axes.set_ylabel("measured - true strain (% strain)")
    axes.set_title("Error against the simulated truth")
    axes.legend(fontsize=8, loc="upper left")
    axes.grid(alpha=0.3)
    return _svg(figure)


def gauge_png_uri(
    image: np.ndarray, points: np.ndarray, layout: StrainGaugesLayout, gauge_length_mm: float
) -> str:
    """The reference frame around the gauge, with the tracked points and the gauge drawn, as
    a `data:image/png;base64,...` URI."""
    plt = _pyplot()
    grey = image if image.ndim == 2 else image.mean(axis=2)
    centre = points.mean(axis=0)
    half = 0.5 * np.ptp(points, axis=0) + max(
        GAUGE_MARGIN_PX, GAUGE_MARGIN_FRACTION * np.ptp(points)
    )
    half = np.maximum(half, 0.5 * half[::-1])
    low_x, low_y = np.floor(centre - half).astype(int)
    high_x, high_y = np.ceil(centre + half).astype(int)
    low_x, low_y = max(low_x, 0), max(low_y, 0)
    high_x, high_y = min(high_x, grey.shape[1]), min(high_y, grey.shape[0])
    crop = grey[low_y:high_y, low_x:high_x].astype(np.float64)
    dark, bright = np.percentile(crop, [0.5, 99.5]) if crop.size else (0.0, 1.0)
    height, width = crop.shape
    aspect = width / max(height, 1)
    size_in = (
        GAUGE_FIGURE_IN * min(aspect, 1.0) + 1.0,
        GAUGE_FIGURE_IN * min(1.0 / aspect, 1.0) + 0.8,
    )
    figure, axes = plt.subplots(figsize=size_in)
    axes.imshow(
        crop,
        cmap="gray",
        vmin=dark,
        vmax=max(bright, dark + 1e-9),
        extent=(low_x - 0.5, high_x - 0.5, high_y - 0.5, low_y - 0.5),
    )
    axes.plot(points[:, 0], points[:, 1], "+", color="#ffbf00", ms=6)
    centres = [
        points[list(mark)].mean(axis=0) for mark in (layout.axial.first, layout.axial.second)
    ]
    (x0, y0), (x1, y1) = centres
    axes.plot([x0, x1], [y0, y1], color="#e41a1c", lw=1.2)
    axes.set_title(f"gauge length L0 = {gauge_length_mm:.4g} mm", fontsize=10)
    if layout.transverse is not None:
        (tx0, ty0), (tx1, ty1) = (
            points[list(mark)].mean(axis=0)
            for mark in (layout.transverse.first, layout.transverse.second)
        )
        axes.plot([tx0, tx1], [ty0, ty1], color="#377eb8", lw=1.2)
    axes.set_xlabel("x (px)")
    axes.set_ylabel("y (px)")
    buffer = io.BytesIO()
    figure.tight_layout()
    figure.savefig(buffer, format="png", dpi=GAUGE_DPI)
    plt.close(figure)
    return "data:image/png;base64," + base64.b64encode(buffer.getvalue()).decode("ascii")
