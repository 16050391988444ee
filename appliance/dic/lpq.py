"""Local phase quantisation (LPQ): blur-insensitive texture codes and their histograms.

LPQ (Ojansivu & Heikkilae 2008, "Blur insensitive texture classification using local phase
quantization"; Heikkilae, Rahtu & Ojansivu 2010) describes the neighbourhood of every pixel by
the signs of the real and imaginary parts of a short-term Fourier transform (STFT) at four low
frequencies. Zhang et al. 2016 ("Image matching based on local phase quantization applied for
measuring the tensile properties of high elongation materials", Math. Probl. Eng., article
5182106) match DIC subsets by comparing 256-bin histograms of these codes with the chi-square
distance, because the codes survive the centrally symmetric motion blur of a fast tensile test.

Conventions
-----------
Images are 2-D arrays indexed ``[row, col] = [y, x]``; pixel centres sit at integers, x points
right and y down. The STFT of an image ``f`` at pixel ``x`` and frequency ``u`` (cycles per pixel)
over the ``M x M`` neighbourhood ``N`` (``M`` odd, ``r = M // 2``) is::

    F(u, x) = sum_{d in [-r, r]^2} w(d) * exp(-2j * pi * u . d) * f(x + d)

with the window ``w`` (uniform by default), evaluated at ``a = 1 / M`` for::

    u1 = (a, 0),  u2 = (0, a),  u3 = (a, a),  u4 = (a, -a)      (components (x, y))

The 1-D even (cosine) kernels are made exactly zero-sum by subtracting the matching multiple of
the window. For the uniform window this changes nothing (a cosine sums to zero over one full
period); for the Gaussian window it removes the leakage of the local mean into the coefficients,
so that codes stay invariant to an intensity offset with either window.

Blur tolerance
--------------
If ``g = h * f`` with a point-spread function ``h`` that is centrally symmetric, its transfer
function ``H`` is real, and in the limit of a window much larger than the blur
``F_g(u) = H(u) F_f(u)``: where ``H(u) > 0`` at all four frequencies the phases, and therefore the
codes, are unchanged. For a centred line (motion) PSF of length ``L`` px along the unit direction
``n = (cos t, sin t)``, ``H(u) = sinc(L u . n)`` with ``sinc(z) = sin(pi z) / (pi z)`` (the
discrete line of ``L`` pixels has ``sin(pi L z) / (L sin(pi z))``, of the same sign for
``|z| < 1``), so the condition is ``L |u_k . n| < 1`` for every ``k``. The largest projection is
``a (|cos t| + |sin t|)`` (reached by ``u1``, ``u3`` and ``u4`` for blur along x, by ``u3`` alone
along the 45-degree diagonal), which gives the nominal tolerance of ``max_invariant_line_blur``::

    L < M / (|cos t| + |sin t|)  =  M along x or y,  M / sqrt(2) ~= 0.71 M along a diagonal

At ``L = M`` the binding coefficients vanish and beyond it ``H < 0`` flips them. A Gaussian PSF
(``H > 0`` everywhere) satisfies the condition at any width; a uniform defocus disc of radius
``R`` while ``R < 3.8317 / (2 pi sqrt(2) a) ~= 0.43 M`` (first zero of ``J1``). The Gaussian window
uses the same four frequencies, so its nominal bounds are the same.

The condition is necessary, not sufficient: the ``M x M`` window truncates the blurred
neighbourhood, and the STFT at ``a`` also collects frequencies up to about ``2a`` where ``H``
is smaller or negative, so agreement decays gradually with ``L / M`` rather than dropping at
``L = M``. Measured fraction of unchanged codes (``M = 7``, uniform window, decorrelated; noise
smoothed by a Gaussian of sigma 2 px; interior pixels; horizontal line blur of ``L`` pixels):
``L = 3``: 81 %, ``L = 5``: 52 %, ``L = 7``: 25 %, ``L = 9``: 11 %, ``L = 15``: 2 % (two unrelated
textures agree on 0.4 %). The Gaussian window gives nearly the same figures (79, 49, 25, 12, 3 %).
A practical rule: most codes survive blur up to about ``M / 2``; larger windows tolerate
proportionally longer blur (``M = 15``: 77 % at ``L = 5``, 59 % at ``L = 7``, 29 % at ``L = 10``
on the same data).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numba import get_num_threads, njit, prange

__all__ = [
    "N_BINS",
    "LPQParams",
    "chi_square",
    "code_histogram",
    "decorrelation_matrix",
    "lpq_codes",
    "lpq_coefficients",
    "lpq_kernels",
    "max_invariant_line_blur",
    "window_for_blur",
]

N_BINS = 256
"""Number of distinct LPQ codes (8 sign bits)."""

_TIE_TOLERANCE = 1e-3
_PERTURBATION = 1e-6
_MIN_BAND_ROWS = 32


@dataclass(frozen=True)
class LPQParams:
    """Parameters of the LPQ code image.

    Attributes:
        window: side ``M`` of the square STFT neighbourhood in px; odd, at least 3. The STFT
            frequency is ``a = 1 / M`` cycles/px, and codes at a pixel depend on the ``M x M``
            block centred on it.
        rho: correlation coefficient of adjacent pixels in the decorrelation model (the
            correlation of two pixels at Euclidean distance ``d`` is ``rho ** d``); in (0, 1).
            0.9 is the value used in the LPQ papers.
        gaussian_window: use a Gaussian window ``exp(-d^2 / (2 sigma^2))`` with
            ``sigma = (M - 1) / 4`` px per axis, truncated to the ``M x M`` block (the
            convention of the reference implementation), instead of the uniform window.
        decorrelate: whiten the eight STFT coefficients under the ``rho ** distance`` model
            before quantisation (as in the LPQ papers); ``False`` quantises the raw
            coefficients.
    """

    window: int = 7
    rho: float = 0.9
    gaussian_window: bool = False
    decorrelate: bool = True

    def __post_init__(self) -> None:
        if isinstance(self.window, bool) or int(self.window) != self.window:
            raise TypeError(f"window must be an integer, got {self.window!r}")
        if self.window < 3 or self.window % 2 == 0:
            raise ValueError(f"window must be odd and >= 3, got {self.window}")
        if not 0.0 < float(self.rho) < 1.0:
            raise ValueError(f"rho must lie in (0, 1), got {self.rho}")

    @property
    def radius(self) -> int:
        """Half-width ``r = M // 2`` of the neighbourhood in px."""
        return self.window // 2

    @property
    def frequency(self) -> float:
        """STFT frequency ``a = 1 / M`` in cycles per px."""
        return 1.0 / self.window


@functools.lru_cache(maxsize=32)
def _window_kernels(params: LPQParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """1-D window ``w``, zero-sum even kernel ``c`` and odd kernel ``s`` (each of length M).

    ``w(x) exp(-2j pi a x) = c(x) + 1j s(x)`` up to the zero-sum correction of ``c``.
    """
    r = params.radius
    x = np.arange(-r, r + 1, dtype=np.float64)
    if params.gaussian_window:
        sigma = (params.window - 1) / 4.0
        w = np.exp(-0.5 * (x / sigma) ** 2)
    else:
        w = np.ones_like(x)
    w /= w.sum()
    phase = 2.0 * np.pi * params.frequency * x
    c = w * np.cos(phase)
    c -= (c.sum() / w.sum()) * w
    s = -w * np.sin(phase)
    for arr in (w, c, s):
        arr.setflags(write=False)
    return w, c, s


def lpq_kernels(params: LPQParams = LPQParams()) -> np.ndarray:
    """The eight real 2-D STFT kernels, as correlation kernels.

    Args:
        params: LPQ parameters.

    Returns:
        float64 array ``(8, M, M)`` indexed ``[k, dy + r, dx + r]``. Coefficient ``k`` at pixel
        ``(x, y)`` is ``sum_d kernels[k, dy + r, dx + r] * f(y + dy, x + dx)``. The order is
        ``Re F(u1), Im F(u1), Re F(u2), Im F(u2), Re F(u3), Im F(u3), Re F(u4), Im F(u4)``
        with the frequencies of the module docstring.
    """
    w, c, s = _window_kernels(params)
    outer = np.outer
    return np.stack(
        [
            outer(w, c),
            outer(w, s),
            outer(c, w),
            outer(s, w),
            outer(c, c) - outer(s, s),
            outer(c, s) + outer(s, c),
            outer(c, c) + outer(s, s),
            outer(c, s) - outer(s, c),
        ]
    )


@functools.lru_cache(maxsize=32)
def _decorrelation_matrix_cached(params: LPQParams) -> np.ndarray:
    m = params.window
    r = params.radius
    kernels = lpq_kernels(params).reshape(8, m * m)
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    pos = np.stack([xx.ravel(), yy.ravel()], axis=1).astype(np.float64)
    dist = np.sqrt(((pos[:, None, :] - pos[None, :, :]) ** 2).sum(axis=-1))
    scale = 1.0 + _PERTURBATION * np.arange(1, 9)
    covariance = (kernels * scale[:, None]) @ (params.rho**dist) @ (kernels * scale[:, None]).T
    rows: list[tuple[float, np.ndarray]] = []
    for parity in (0, 1):
        idx = np.arange(parity, 8, 2)
        _, sv, vt = np.linalg.svd(covariance[np.ix_(idx, idx)])
        for value, vec in zip(sv, vt, strict=True):
            full = np.zeros(8)
            full[idx] = vec
            rows.append((float(value), full))
    rows.sort(key=lambda item: -item[0])
    out = np.array([row for _, row in rows])
    for row in out:
        mags = np.abs(row)
        lead = int(np.flatnonzero(mags >= mags.max() * (1.0 - _TIE_TOLERANCE))[0])
        if row[lead] < 0:
            row *= -1.0
    out.setflags(write=False)
    return out


def decorrelation_matrix(params: LPQParams = LPQParams()) -> np.ndarray:
    """Orthogonal matrix that decorrelates the eight STFT coefficients.

    The coefficient vector ``f`` (order of ``lpq_kernels``) of a neighbourhood whose pixels have
    unit variance and correlation ``rho ** distance`` has covariance ``D = K C K^T``. Real parts
    (even kernels) and imaginary parts (odd kernels) are exactly uncorrelated under this
    centrally symmetric model, so the two 4 x 4 blocks of ``A D A`` are decomposed separately by
    SVD. ``A = diag(1 + k * 1e-6)``, ``k = 1..8``, is a deterministic perturbation that selects a
    basis inside the eigenspaces that the model's rotational symmetry makes repeated. The rows
    (right singular vectors, zero outside their block) are ordered by decreasing singular value,
    so ``V f`` has (nearly) diagonal covariance with decreasing variances. Each row's sign is
    fixed so that its largest-magnitude entry is positive; among entries within 0.1 % of the
    largest magnitude the first (lowest index) decides. The codes therefore do not depend on
    the LAPACK build.

    Args:
        params: LPQ parameters (``decorrelate`` is ignored here).

    Returns:
        Read-only float64 array ``V`` of shape ``(8, 8)``: row ``j`` gives the weights of
        decorrelated component ``j`` on the raw coefficients. Rows mix either only real parts
        (even columns) or only imaginary parts (odd columns).
    """
    return _decorrelation_matrix_cached(params)


@njit(cache=True)
def _row_pass(row, w, c, s, out_w, out_c, out_s):
    """Valid 1-D correlation of ``row`` with the even ``w``, ``c`` and the odd ``s``."""
    r = w.shape[0] // 2
    n = out_w.shape[0]
    w0 = w[r]
    c0 = c[r]
    mid = row[r : r + n]
    for j in range(n):
        out_w[j] = w0 * mid[j]
        out_c[j] = c0 * mid[j]
        out_s[j] = 0.0
    for t in range(1, r + 1):
        wt = w[r + t]
        ct = c[r + t]
        st = s[r + t]
        right = row[r + t : r + t + n]
        left = row[r - t : r - t + n]
        for j in range(n):
            p = right[j] + left[j]
            q = right[j] - left[j]
            out_w[j] += wt * p
            out_c[j] += ct * p
            out_s[j] += st * q


@njit(cache=True)
def _stft_band(
    img,
    w,
    c,
    s,
    mix_re,
    mix_im,
    bits_re,
    bits_im,
    chan_re,
    chan_im,
    coeffs,
    store,
    codes,
    first,
    stop,
):
    """Output rows ``first:stop`` of the valid-mode LPQ transform of ``img``.

    Rows are streamed through a ring buffer of ``M`` horizontally filtered rows. The eight
    separable products ``P`` (y kernel, x kernel) are ``P0 = (w, c), P1 = (w, s), P2 = (c, w),
    P3 = (s, w), P4 = (c, c), P5 = (s, s), P6 = (c, s), P7 = (s, c)``; real-part channels mix
    ``(P0, P2, P4, P5)`` with the rows of ``mix_re``, imaginary-part channels ``(P1, P3, P6, P7)``
    with ``mix_im``. Channel ``chan_re[q]`` adds the bit value ``bits_re[q]`` (a float holding
    ``2**chan_re[q]``) where positive (likewise ``_im``).
    """
    m = w.shape[0]
    r = m // 2
    n = img.shape[1] - m + 1
    ring = np.empty((3, m, n))
    prod = np.empty((8, n))
    packed = np.empty(n)
    w0 = w[r]
    c0 = c[r]
    for i in range(first, stop + m - 1):
        slot = i % m
        _row_pass(img[i], w, c, s, ring[0, slot], ring[1, slot], ring[2, slot])
        if i < first + m - 1:
            continue
        oi = i - m + 1
        centre = (oi + r) % m
        hw = ring[0, centre]
        hc = ring[1, centre]
        hs = ring[2, centre]
        p0 = prod[0]
        p1 = prod[1]
        p2 = prod[2]
        p3 = prod[3]
        p4 = prod[4]
        p5 = prod[5]
        p6 = prod[6]
        p7 = prod[7]
        for j in range(n):
            p0[j] = w0 * hc[j]
            p1[j] = w0 * hs[j]
            p2[j] = c0 * hw[j]
            p3[j] = 0.0
            p4[j] = c0 * hc[j]
            p5[j] = 0.0
            p6[j] = c0 * hs[j]
            p7[j] = 0.0
        for t in range(1, r + 1):
            wt = w[r + t]
            ct = c[r + t]
            st = s[r + t]
            up = (oi + r - t) % m
            down = (oi + r + t) % m
            uw = ring[0, up]
            uc = ring[1, up]
            us = ring[2, up]
            dw = ring[0, down]
            dc = ring[1, down]
            ds = ring[2, down]
            for j in range(n):
                pc = dc[j] + uc[j]
                ps = ds[j] + us[j]
                p0[j] += wt * pc
                p1[j] += wt * ps
                p2[j] += ct * (dw[j] + uw[j])
                p3[j] += st * (dw[j] - uw[j])
                p4[j] += ct * pc
                p5[j] += st * (ds[j] - us[j])
                p6[j] += ct * ps
                p7[j] += st * (dc[j] - uc[j])
        out = codes[oi]
        a00, a01, a02, a03 = mix_re[0, 0], mix_re[0, 1], mix_re[0, 2], mix_re[0, 3]
        a10, a11, a12, a13 = mix_re[1, 0], mix_re[1, 1], mix_re[1, 2], mix_re[1, 3]
        a20, a21, a22, a23 = mix_re[2, 0], mix_re[2, 1], mix_re[2, 2], mix_re[2, 3]
        a30, a31, a32, a33 = mix_re[3, 0], mix_re[3, 1], mix_re[3, 2], mix_re[3, 3]
        b00, b01, b02, b03 = mix_im[0, 0], mix_im[0, 1], mix_im[0, 2], mix_im[0, 3]
        b10, b11, b12, b13 = mix_im[1, 0], mix_im[1, 1], mix_im[1, 2], mix_im[1, 3]
        b20, b21, b22, b23 = mix_im[2, 0], mix_im[2, 1], mix_im[2, 2], mix_im[2, 3]
        b30, b31, b32, b33 = mix_im[3, 0], mix_im[3, 1], mix_im[3, 2], mix_im[3, 3]
        g0, g1, g2, g3 = bits_re[0], bits_re[1], bits_re[2], bits_re[3]
        h0, h1, h2, h3 = bits_im[0], bits_im[1], bits_im[2], bits_im[3]
        for j in range(n):
            e0 = p0[j]
            e1 = p2[j]
            e2 = p4[j]
            e3 = p5[j]
            o0 = p1[j]
            o1 = p3[j]
            o2 = p6[j]
            o3 = p7[j]
            packed[j] = (
                (g0 if a00 * e0 + a01 * e1 + a02 * e2 + a03 * e3 > 0.0 else 0.0)
                + (g1 if a10 * e0 + a11 * e1 + a12 * e2 + a13 * e3 > 0.0 else 0.0)
                + (g2 if a20 * e0 + a21 * e1 + a22 * e2 + a23 * e3 > 0.0 else 0.0)
                + (g3 if a30 * e0 + a31 * e1 + a32 * e2 + a33 * e3 > 0.0 else 0.0)
                + (h0 if b00 * o0 + b01 * o1 + b02 * o2 + b03 * o3 > 0.0 else 0.0)
                + (h1 if b10 * o0 + b11 * o1 + b12 * o2 + b13 * o3 > 0.0 else 0.0)
                + (h2 if b20 * o0 + b21 * o1 + b22 * o2 + b23 * o3 > 0.0 else 0.0)
                + (h3 if b30 * o0 + b31 * o1 + b32 * o2 + b33 * o3 > 0.0 else 0.0)
            )
        for j in range(n):
            out[j] = np.uint8(packed[j])
        if store:
            for j in range(n):
                for q in range(4):
                    coeffs[oi, j, chan_re[q]] = (
                        mix_re[q, 0] * p0[j]
                        + mix_re[q, 1] * p2[j]
                        + mix_re[q, 2] * p4[j]
                        + mix_re[q, 3] * p5[j]
                    )
                    coeffs[oi, j, chan_im[q]] = (
                        mix_im[q, 0] * p1[j]
                        + mix_im[q, 1] * p3[j]
                        + mix_im[q, 2] * p6[j]
                        + mix_im[q, 3] * p7[j]
                    )


@njit(cache=True, parallel=True)
def _stft_signs(
    img, w, c, s, mix_re, mix_im, bits_re, bits_im, chan_re, chan_im, coeffs, store, codes, n_bands
):
    """Valid-mode LPQ transform of ``img`` into ``codes`` (and ``coeffs`` if ``store``).

    Output rows are split into ``n_bands`` bands processed in parallel.
    """
    rows = codes.shape[0]
    for band in prange(n_bands):
        first = band * rows // n_bands
        stop = (band + 1) * rows // n_bands
        if stop > first:
            _stft_band(
                img,
                w,
                c,
                s,
                mix_re,
                mix_im,
                bits_re,
                bits_im,
                chan_re,
                chan_im,
                coeffs,
                store,
                codes,
                first,
                stop,
            )


@functools.lru_cache(maxsize=32)
def _mixing(params: LPQParams) -> tuple[np.ndarray, ...]:
    """Mixing of the separable products into output channels, split by parity.

    Raw coefficients from the products of ``_stft_band``: ``Re u1 = P0, Im u1 = P1,
    Re u2 = P2, Im u2 = P3, Re u3 = P4 - P5, Im u3 = P6 + P7, Re u4 = P4 + P5, Im u4 = P6 - P7``.
    Returns ``mix_re, mix_im`` (4 x 4 weights on ``(P0, P2, P4, P5)`` and ``(P1, P3, P6, P7)``),
    the bit values and the channel indices of their rows.
    """
    raw_on_products = np.array(
        [
            [1, 0, 0, 0],
            [1, 0, 0, 0],
            [0, 1, 0, 0],
            [0, 1, 0, 0],
            [0, 0, 1, -1],
            [0, 0, 1, 1],
            [0, 0, 1, 1],
            [0, 0, 1, -1],
        ],
        dtype=np.float64,
    )
    vt = decorrelation_matrix(params) if params.decorrelate else np.eye(8)
    mixes: tuple[list[np.ndarray], list[np.ndarray]] = ([], [])
    chans: tuple[list[int], list[int]] = ([], [])
    for k, row in enumerate(vt):
        par = int(np.flatnonzero(row)[0] % 2)
        mixes[par].append(row[par::2] @ raw_on_products[par::2])
        chans[par].append(k)
    out = []
    for par in (0, 1):
        chan = np.array(chans[par], dtype=np.int64)
        out.extend([np.array(mixes[par]), (1 << chan).astype(np.float64), chan])
    mix_re, bits_re, chan_re, mix_im, bits_im, chan_im = out
    for arr in out:
        arr.setflags(write=False)
    return mix_re, mix_im, bits_re, bits_im, chan_re, chan_im


def _prepare(image: np.ndarray, params: LPQParams, border: str) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"image must be 2-D, got shape {img.shape}")
    if border not in ("reflect", "valid"):
        raise ValueError(f"border must be 'reflect' or 'valid', got {border!r}")
    r = params.radius
    img = img.astype(np.float64, copy=False)
    if border == "reflect":
        if min(img.shape) <= r:
            raise ValueError(f"image {img.shape} too small for window {params.window}")
        return cv2.copyMakeBorder(img, r, r, r, r, cv2.BORDER_REFLECT_101)
    if min(img.shape) < params.window:
        raise ValueError(f"image {img.shape} smaller than window {params.window}")
    return np.ascontiguousarray(img)


def _run(
    image: np.ndarray, params: LPQParams, border: str, store: bool
) -> tuple[np.ndarray, np.ndarray]:
    img = _prepare(image, params, border)
    w, c, s = _window_kernels(params)
    m = params.window
    shape = (img.shape[0] - m + 1, img.shape[1] - m + 1)
    codes = np.empty(shape, dtype=np.uint8)
    coeffs = np.empty(shape + (8,) if store else (0, 0, 8))
    n_bands = max(1, min(get_num_threads(), shape[0] // _MIN_BAND_ROWS))
    if n_bands == 1:
        _stft_band(img, w, c, s, *_mixing(params), coeffs, store, codes, 0, shape[0])
    else:
        _stft_signs(img, w, c, s, *_mixing(params), coeffs, store, codes, n_bands)
    return coeffs, codes


def lpq_coefficients(
    image: np.ndarray,
    params: LPQParams = LPQParams(),
    *,
    border: Literal["reflect", "valid"] = "reflect",
) -> np.ndarray:
    """Per-pixel STFT coefficients, decorrelated when ``params.decorrelate`` is set.

    Computed with separable 1-D correlations (3 passes along x, 8 along y) over the whole input;
    ``lpq_codes`` runs the same arithmetic, so its bits are exactly the signs of these values.

    Args:
        image: 2-D array ``(H, W)`` of intensities (any real dtype).
        params: LPQ parameters.
        border: ``"reflect"`` returns ``(H, W)`` values, those within ``r = M // 2`` px of an
            edge computed on the image extended by reflection without repeating the edge pixel
            (OpenCV ``BORDER_REFLECT_101``); ``"valid"`` returns only the ``(H - 2r, W - 2r)``
            pixels whose neighbourhood lies inside the image (output ``[i, j]`` is input pixel
            ``[i + r, j + r]``).

    Returns:
        float64 array ``(H', W', 8)``. Without decorrelation channel ``k`` is coefficient ``k``
        of ``lpq_kernels``; with it, channel ``j`` is ``(decorrelation_matrix(params) @ f)[j]``.
    """
    return _run(image, params, border, True)[0]


def lpq_codes(
    image: np.ndarray,
    params: LPQParams = LPQParams(),
    *,
    border: Literal["reflect", "valid"] = "reflect",
) -> np.ndarray:
    """LPQ code image: 8 sign bits of the (decorrelated) STFT coefficients per pixel.

    Bit ``k`` (value ``2**k``) is 1 where channel ``k`` of ``lpq_coefficients`` is strictly
    positive. Without decorrelation the bits are, from bit 0 (least significant) to bit 7:
    ``Re F(u1), Im F(u1), Re F(u2), Im F(u2), Re F(u3), Im F(u3), Re F(u4), Im F(u4)`` with
    ``u1 = (a, 0), u2 = (0, a), u3 = (a, a), u4 = (a, -a)`` in (x, y) and ``a = 1 / M``.
    With decorrelation (default) bit ``k`` is the sign of decorrelated component ``k``, i.e. of
    row ``k`` of ``decorrelation_matrix(params)`` (decreasing variance) applied to that vector.

    Codes are invariant to ``image -> alpha * image + beta`` for ``alpha > 0`` (exactly up to
    floating-point rounding of coefficients that are numerically zero, which happens on the
    reflected border rows and columns and on flat patches), and insensitive to centrally
    symmetric blur as described in the module docstring.

    Args:
        image: 2-D array ``(H, W)``.
        params: LPQ parameters.
        border: see ``lpq_coefficients``. With ``"reflect"`` the codes of pixels at least
            ``M // 2`` px from every edge depend only on the image (they equal the
            ``"valid"`` codes); the others depend on its reflection.

    Returns:
        uint8 array ``(H, W)`` (``"reflect"``) or ``(H - 2r, W - 2r)`` (``"valid"``).
    """
    return _run(image, params, border, False)[1]


def code_histogram(codes: np.ndarray) -> np.ndarray:
    """256-bin histogram (counts) of an array of LPQ codes, e.g. one subset of a code image.

    Args:
        codes: uint8 array of any shape (typically the ``S x S`` block of a subset).

    Returns:
        float64 array ``(256,)``; entry ``b`` counts the codes equal to ``b``.
    """
    arr = np.asarray(codes)
    if arr.dtype != np.uint8:
        raise TypeError(f"codes must be uint8, got {arr.dtype}")
    return np.bincount(arr.ravel(), minlength=N_BINS).astype(np.float64)


def chi_square(
    h1: np.ndarray,
    h2: np.ndarray,
    weights: np.ndarray | None = None,
) -> np.ndarray | float:
    """Chi-square distance between histograms.

    ``chi2 = sum_b w_b (h1_b - h2_b)**2 / (h1_b + h2_b)``, skipping bins where
    ``h1_b + h2_b == 0`` (Zhang et al. 2016, Eq. 20; the LPQ papers use the same measure).
    Symmetric, zero for identical histograms, and for non-negative histograms normalised to
    sum 1 it lies in ``[0, 2]`` when all ``w_b = 1`` (2 for disjoint supports).

    Args:
        h1, h2: non-negative histograms, shape ``(..., B)`` (broadcast against each other).
        weights: optional non-negative bin weights ``(B,)``; default all 1.

    Returns:
        float for 1-D inputs, else float64 array of the broadcast leading shape.
    """
    a = np.asarray(h1, dtype=np.float64)
    b = np.asarray(h2, dtype=np.float64)
    num = (a - b) ** 2
    den = a + b
    if weights is not None:
        num = num * np.asarray(weights, dtype=np.float64)
    terms = np.divide(
        num, den, out=np.zeros(np.broadcast_shapes(num.shape, den.shape)), where=den != 0
    )
    total = terms.sum(axis=-1)
    return float(total) if np.ndim(total) == 0 else total


def max_invariant_line_blur(params: LPQParams = LPQParams(), angle_deg: float = 0.0) -> float:
    """Length bound ``L < M / (|cos t| + |sin t|)`` of a tolerated centred line blur, in px.

    A centred line PSF shorter than this bound (direction ``t`` from the x axis) has a positive
    transfer function at all four LPQ frequencies, so it leaves the ideal (untruncated) STFT
    phases unchanged; see the module docstring. The bound is exclusive.

    Args:
        params: LPQ parameters (only ``window`` matters).
        angle_deg: blur direction in degrees from the x axis (y down).

    Returns:
        ``M`` for blur along x or y, ``M / sqrt(2)`` along a diagonal.
    """
    t = math.radians(angle_deg)
    return params.window / (abs(math.cos(t)) + abs(math.sin(t)))


WINDOW_PER_BLUR = 3.0
"""LPQ window per px of line blur, along an axis, of `window_for_blur`'s rule."""


def window_for_blur(length_px: float, angle_deg: float = 0.0, *, subset: int | None = None) -> int:
    """LPQ window ``M`` the integer search uses for a known centred line blur.

    The nominal invariance bound (``max_invariant_line_blur``) asks only for
    ``L < M / (|cos t| + |sin t|)``, but the ``M x M`` window truncates the blurred
    neighbourhood and the STFT leaks frequencies up to about ``2 / M``, so codes survive only
    to about ``L = M / 2`` and the search needs more. Measured on 8-bit speckle with noise of
    sigma 2 grey levels, a 25.6 px translation, 41 px subsets, 81 points (the benchmark's
    Gaussian speckle; integer successes within 1 px for M = 1, 1.5, 2, 2.5, 3 L): L = 4 px:
    5, 14, 27, 46, 60 %; L = 8 px: 31, 60, 73, 84, 95 %; L = 12 px: 59, 84, 96, 100, 100 %;
    L = 15 px: 69, 98, 100, 100, 100 % (M capped at 41). The benchmark's dense speckle is
    kinder (81 to 100 % from M = L on), the sparse one sets the rule: three times
    the blur along an axis, and the nominal bound's factor ``|cos t| + |sin t|`` off-axis:

        ``M = 3 L (|cos t| + |sin t|)``, rounded up to odd, at least 7 (the default window
        without blur) and at most ``subset``.

    Args:
        length_px: blur length ``L``, px (>= 0; 0 gives the default 7).
        angle_deg: blur direction, degrees from +x towards +y.
        subset: the subset side, px (odd); the window never exceeds it. None = no cap.

    Returns:
        The odd window side ``M``, px.
    """
    if not length_px >= 0.0:
        raise ValueError(f"blur length must be >= 0, got {length_px}")
    t = math.radians(angle_deg)
    wanted = WINDOW_PER_BLUR * length_px * (abs(math.cos(t)) + abs(math.sin(t)))
    window = max(LPQParams().window, math.ceil(wanted - 1e-9))
    window += 1 - window % 2
    if subset is not None:
        cap = int(subset) if int(subset) % 2 else int(subset) - 1
        window = min(window, max(cap, 3))
    return window
