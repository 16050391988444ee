"""DIC Challenge 1.0 Sample 14: a 0.1 px chirp in u(x) under 3.5 grey levels of noise.

Truth (`sample14/truth.csv`, published with the images): v = 0, u depends on x only, u = 0 for
x <= 100, then a sinusoid of amplitude 0.1 px whose period shrinks with x: L1 has about 2
periods across the image, L5 about 10.5, the shortest L5 period being about 100 px near the
right edge (half-period 49 px between the last zero crossings at x = 1997 and 2046).

The trap (README): Gauss-Newton on the cubic B-spline of the raw noisy images is biased by the
noise and over-estimates the amplitude by about 30 %; a mild Gaussian pre-filter on both images
(sigma 0.6 to 1.0 px) removes the bias. The test uses sigma = 0.8 px. (The product's IC-GN
does not show that over-estimate here: on the raw images it reads 0.1004 px (L1) and 0.1002 px
(L5) by the least squares below, against 0.0994 and 0.0992 px pre-filtered; the test guards the
recommended pre-filtered configuration.)

Subset size. A first-order subset of side S reports roughly the subset average of u, which for
a sinusoid of period P is the true value times sinc(S / P) = sin(pi S / P) / (pi S / P). With
S = 21 that factor is 0.93 at the shortest L5 period (100 px) and 0.99 at 250 px; weighted by
u^2 over the whole L5 chirp the expected least-squares scale is 0.974, so the attenuation uses
about half of the 5 % budget. S = 31 would use all of it (0.944), while S = 15 halves the
attenuation but raises the random error per point from about 0.022 px to 0.037 px and loses
3 % of the points to non-convergence. S = 21 is the largest subset that leaves room for the
noise, and the same subset is used for L1, whose periods are long enough not to matter.
"""

import numpy as np
import pytest

from appliance.dic.icgn import ICGN
from tests.validation import dic_data

SUBSET = 21
PREFILTER_SIGMA = 0.8
AMPLITUDE = 0.1
TOLERANCE = 0.05
"""Relative tolerance on the recovered amplitude (the README's "within about 5 %")."""

TRUTH_COLUMN = {"L1": 1, "L5": 5}


@pytest.mark.parametrize("level", ["L1", "L5"])
def test_chirp_amplitude_is_recovered_within_5_percent(level, figures):
    """The recovered chirp amplitude is 0.1 px within 5 %, on the pre-filtered images.

    Points: 387 columns x = 105, 110, ..., 2035 (all of the chirp, x > 100) times 11 rows
    y = 44, 94, ..., 544, 4257 in all, each started from a zero guess (|u| <= 0.1 px).
    Amplitude: least-squares scale s minimising sum (u_measured - s u_true)^2 over the converged
    points, u_true read from truth.csv at the subset centre; amplitude = 0.1 s. The least
    squares use every point of the chirp, so the 0.022 px random error per point leaves a
    standard error of about 0.4 % on s, while a peak-to-peak reading would pick up the noise
    extremes (about +10 % here even after averaging the 11 rows).
    """
    reference = dic_data.load_image("sample14", "Sample14_Reference.png")
    target = dic_data.load_image("sample14", f"Sample14_{level}_Amp0.1.png")
    truth = dic_data.load_csv("sample14", "truth.csv", skip_header=1)
    points = dic_data.grid_points(np.arange(105, 2036, 5), np.arange(44, 545, 50))
    icgn = ICGN(subset=SUBSET, prefilter_sigma=PREFILTER_SIGMA)
    icgn.prepare(reference, points)
    result = icgn.compute(target)
    ok = result.ok()
    assert ok.mean() >= 0.98, f"only {ok.sum()} of {ok.size} points converged"
    u_true = np.interp(points[ok, 0], truth[:, 0], truth[:, TRUTH_COLUMN[level]])
    scale = (result.u[ok] @ u_true) / (u_true @ u_true)
    amplitude = AMPLITUDE * scale
    figures.record(f"{level} chirp amplitude, px", amplitude, "0.1 +- 5 %")
    assert abs(amplitude - AMPLITUDE) <= TOLERANCE * AMPLITUDE, (
        f"{level}: recovered amplitude {amplitude:.4f} px, truth {AMPLITUDE} px"
    )
