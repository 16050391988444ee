"""Centred linear motion blur: the point-spread function of a specimen moving during exposure.

A point that moves at constant velocity during the exposure paints a line segment; the blur is
centred on the mid-exposure position, so it spreads the image without moving it. The same
kernel serves two purposes: rendering blurred test images, and blurring a reference image to
match targets whose blur is known from the crosshead speed and the exposure time (so that a
sharp reference is never correlated with a blurred target, which biases ZNSSD matching).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


def _keys_cubic(t: FloatArray) -> FloatArray:
    """Keys' cubic convolution kernel (a = -1/2), support ``|t| < 2``."""
    t = np.abs(t)
    near = (1.5 * t - 2.5) * t * t + 1.0
    far = ((-0.5 * t + 2.5) * t - 4.0) * t + 2.0
    return np.where(t < 1.0, near, np.where(t < 2.0, far, 0.0))


_GAUSS_NODES, _GAUSS_WEIGHTS = np.polynomial.legendre.leggauss(4)


def line_psf(length: float, angle_deg: float) -> FloatArray:
    """Point-spread function of linear motion: a centred, anti-aliased line segment.

    The continuous PSF is a uniform line density along the segment of length ``L = length``
    px centred on the origin, with direction ``(cos(angle), sin(angle))`` in image
    coordinates (angle from +x towards +y, i.e. clockwise on screen since y points down).
    It is rasterised with Keys' cubic convolution kernel ``c`` (a = -1/2, the kernel of
    bicubic interpolation):

        ``k[r, c] = (1 / L) * integral_{-L/2}^{L/2} c(c - s cos(angle)) c(r - s sin(angle)) ds``

    integrated exactly (4-point Gauss-Legendre between the kernel's knots). This is the blur
    of the image interpolated bicubically between pixels, so it is anti-aliased for any
    length and angle; because Keys' kernel reproduces quadratics, the kernel's first moments
    are 0 and its second moments are exactly the segment's: ``L**2 / 12`` along the motion
    and 0 across it. Like bicubic interpolation it has small negative side lobes (under 8 %
    of its largest element).

    The kernel has odd sizes with the origin at its centre element, it sums to 1 and it is
    point-symmetric (``k == k[::-1, ::-1]``), so correlation and convolution with it agree and
    the blur does not move the content.

    Args:
        length: Segment length, px (>= 0); 0 gives the identity kernel ``[[1.0]]``.
        angle_deg: Direction of motion, degrees.

    Returns:
        float64 kernel of shape ``(2 hr + 1, 2 hc + 1)``, trimmed to its non-zero support.
    """
    if not (length >= 0.0 and math.isfinite(length)):
        raise ValueError("length must be finite and non-negative")
    if length == 0.0:
        return np.ones((1, 1))
    theta = math.radians(angle_deg)
    dx, dy = math.cos(theta), math.sin(theta)
    half = int(math.ceil(0.5 * length)) + 2
    # Integrate over the normalised arc parameter q = s / L in [-1/2, 1/2].
    breaks = [np.array([-0.5, 0.5])]
    for d in (dx, dy):
        if abs(d * length) > 1e-15:
            knots = np.arange(-half, half + 1) / (d * length)
            breaks.append(knots[(knots > -0.5) & (knots < 0.5)])
    b = np.unique(np.concatenate(breaks))
    mid = 0.5 * (b[1:] + b[:-1])
    hw = 0.5 * (b[1:] - b[:-1])
    q = (mid[:, None] + hw[:, None] * _GAUSS_NODES[None, :]).reshape(-1)
    w = (hw[:, None] * _GAUSS_WEIGHTS[None, :]).reshape(-1)
    x, y = q * (length * dx), q * (length * dy)
    ix, iy = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    k = np.zeros((2 * half + 1, 2 * half + 1))
    for ox in range(-1, 3):
        wx = w * _keys_cubic(x - (ix + ox))
        for oy in range(-1, 3):
            np.add.at(k, (iy + oy + half, ix + ox + half), wx * _keys_cubic(y - (iy + oy)))
    k = 0.5 * (k + k[::-1, ::-1])
    k[np.abs(k) < 1e-14 * np.abs(k).max()] = 0.0
    k /= k.sum()
    hr = int(np.abs(np.flatnonzero(k.any(axis=1)) - half).max())
    hc = int(np.abs(np.flatnonzero(k.any(axis=0)) - half).max())
    return np.ascontiguousarray(k[half - hr : half + hr + 1, half - hc : half + hc + 1])


def motion_blur(image: npt.ArrayLike, length: float, angle_deg: float) -> FloatArray:
    """Blur an image by linear motion of ``length`` px in direction ``angle_deg``.

    Filters with ``line_psf(length, angle_deg)`` using ``cv2.filter2D`` with reflected
    borders (``cv2.BORDER_REFLECT``: the edge pixel is repeated, ``cba|abcd``). The blur is
    centred: it does not move the content, it spreads it by ``+-length / 2``.

    Args:
        image: 2-D array, any real dtype.
        length: Blur length, px (>= 0; 0 returns an unchanged float64 copy).
        angle_deg: Direction of motion, degrees (see ``line_psf``).

    Returns:
        float64 image of the same shape.
    """
    img = np.asarray(image, np.float64)
    if img.ndim != 2:
        raise ValueError("image must be 2-D")
    kernel = line_psf(length, angle_deg)
    if kernel.shape == (1, 1):
        return img.copy()
    return cv2.filter2D(img, cv2.CV_64F, kernel, borderType=cv2.BORDER_REFLECT)
