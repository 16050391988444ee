"""Reading grey images from files: 8/16-bit TIFF, PNG and BMP, including palette images."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from appliance.errors import InputError


def read_grey(path: str | Path) -> np.ndarray:
    """Read an image file as a 2-D array of grey values.

    Grey images come back in their own dtype (uint8, uint16, or float for floating-point
    TIFF). Palette images (8-bit palette TIFF, BMP, PNG) are read through their palette: a
    grey palette gives its grey values; a colour palette or colour image is converted to
    luminance (ITU-R BT.601 weights, as OpenCV's BGR2GRAY), the usual reading of a colour
    camera frame for correlation. An alpha channel is ignored.

    Raises:
        InputError: the file is missing or is not a readable image.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such image file")
    data = np.fromfile(path, dtype=np.uint8)
    try:
        image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    except cv2.error as exc:
        reason = (exc.err or str(exc)).strip()
        raise InputError(f"{path}: not a readable image (OpenCV refused it: {reason})") from None
    if image is None:
        raise InputError(f"{path}: not a readable image (TIFF, PNG or BMP expected)")
    if image.ndim == 3:
        colour = image[..., :3]
        if colour.shape[2] == 1:
            image = colour[..., 0]
        elif np.array_equal(colour[..., 0], colour[..., 1]) and np.array_equal(
            colour[..., 0], colour[..., 2]
        ):
            image = colour[..., 0]
        else:
            image = cv2.cvtColor(np.ascontiguousarray(colour), cv2.COLOR_BGR2GRAY)
    if image.ndim != 2:
        raise InputError(f"{path}: unsupported image layout {image.shape}")
    return np.ascontiguousarray(image)
