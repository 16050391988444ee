"""A speckle coat under uniaxial stretch along the image's vertical axis, rendered analytically.

The coat (`appliance.dic.synthetic.dense_speckle`, speckle radius 2.5 px, 0.25 speckles per
square pixel) is rendered once at twice the sensor's resolution. At engineering strain e the
specimen is stretched about the centre row ``cy = (height - 1) / 2``: the material point at
reference row Y is seen at row ``cy + (Y - cy) * (1 + e)``, columns unchanged. A frame samples
the coat at the inverse-mapped positions (OpenCV bicubic remap: point samples, no noise, no
blur). The GigE Vision cameras of the system tests and of `extensometer bench gige` draw
their frames with it (`appliance.sim.gige_camera`).
"""

from __future__ import annotations

import cv2
import numpy as np

OVERSAMPLE = 2
SPECKLE_RADIUS_PX = 2.5
SPECKLE_DENSITY = 0.25
"""Speckles per square pixel at camera scale (`dense_speckle`'s default)."""


class StretchedSpecimen:
    """The speckle coat and the stretch: renders the sensor region at a given strain.

    Args:
        width, height: sensor size, px.
        seed: seed of the speckle pattern.
    """

    def __init__(self, width: int, height: int, seed: int) -> None:
        from appliance.dic import synthetic

        fine_width, fine_height = OVERSAMPLE * width, OVERSAMPLE * height
        pattern = synthetic.dense_speckle(
            fine_width,
            fine_height,
            seed=seed,
            radius=OVERSAMPLE * SPECKLE_RADIUS_PX,
            density=SPECKLE_DENSITY / OVERSAMPLE**2,
        )
        self.coat = synthetic.render(pattern, fine_height, fine_width).astype(np.float32)
        self.width = width
        self.height = height
        self.centre_y = (height - 1) / 2.0

    def render(self, x: int, y: int, width: int, height: int, strain: float) -> np.ndarray:
        """Grey values (8-bit scale, float32) of the region at `strain`.

        Sensor pixel (X, Y) shows reference point (X, cy + (Y - cy) / (1 + strain)); a camera
        pixel centre c lies at OVERSAMPLE * c + (OVERSAMPLE - 1) / 2 on the fine coat.
        """
        half = (OVERSAMPLE - 1) / 2.0
        columns = OVERSAMPLE * np.arange(x, x + width, dtype=np.float32) + half
        rows = np.arange(y, y + height, dtype=np.float64)
        reference_rows = self.centre_y + (rows - self.centre_y) / (1.0 + strain)
        fine_rows = (OVERSAMPLE * reference_rows + half).astype(np.float32)
        map_x = np.broadcast_to(columns[None, :], (height, width))
        map_y = np.broadcast_to(fine_rows[:, None], (height, width))
        return cv2.remap(
            self.coat,
            np.ascontiguousarray(map_x),
            np.ascontiguousarray(map_y),
            cv2.INTER_CUBIC,
            borderMode=cv2.BORDER_REFLECT,
        )
