"""Band-limited analytic texture: exact grey values anywhere, so any mapping has exact truth."""

import numpy as np


class CosineTexture:
    """Sum of random plane cosines with wavelengths between 5 and 20 px."""

    def __init__(self, seed: int, terms: int = 60) -> None:
        rng = np.random.default_rng(seed)
        wavelength = rng.uniform(5.0, 20.0, terms)
        angle = rng.uniform(0, np.pi, terms)
        self.kx = np.cos(angle) / wavelength
        self.ky = np.sin(angle) / wavelength
        self.phase = rng.uniform(0, 2 * np.pi, terms)
        self.amplitude = rng.uniform(0.5, 1.0, terms) * 100.0 / np.sqrt(terms)

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        out = np.full(np.shape(x), 128.0)
        for kx, ky, ph, a in zip(self.kx, self.ky, self.phase, self.amplitude, strict=True):
            out += a * np.cos(2 * np.pi * (kx * x + ky * y) + ph)
        return out

    def image(self, height: int, width: int, inverse=None) -> np.ndarray:
        """Render pixels (row r, col c) as texture(inverse(c, r)); identity when inverse is None."""
        y, x = np.mgrid[0:height, 0:width].astype(np.float64)
        if inverse is not None:
            x, y = inverse(x, y)
        return self(x, y)
