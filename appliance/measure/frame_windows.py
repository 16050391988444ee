"""The pixels the tracker used: windows cut from a frame, and a frame rebuilt from them.

The tracker reads only small windows around its marks (`TrackedFrame.read_regions`). Keeping
those windows of every frame, exactly, is enough to track the test again to the same numbers:
`paste_windows` rebuilds a frame in which every pixel the tracker read holds its recorded
value (the rest is zero and is never read by the same tracking).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from appliance.measure.tracking import ReadRegion


@dataclass(frozen=True)
class ImageWindow:
    """A rectangle of a frame's pixels.

    Attributes:
        x, y: column and row of the window's first pixel in the frame.
        pixels: (height, width) copy of the frame's grey values there (the frame's dtype).
    """

    x: int
    y: int
    pixels: np.ndarray

    @property
    def region(self) -> ReadRegion:
        """Where the window lies in the frame."""
        height, width = self.pixels.shape
        return ReadRegion(self.x, self.y, width, height)


def cut_windows(image: np.ndarray, regions: Iterable[ReadRegion]) -> tuple[ImageWindow, ...]:
    """Copies of `image` inside each of `regions` (which lie inside the image)."""
    return tuple(
        ImageWindow(r.x, r.y, image[r.y : r.y + r.height, r.x : r.x + r.width].copy())
        for r in regions
    )


def paste_windows(
    shape: tuple[int, int], dtype: np.dtype, windows: Iterable[ImageWindow]
) -> np.ndarray:
    """A frame of `shape` and `dtype` holding `windows` (later ones over earlier), zero elsewhere.

    Raises:
        ValueError: a window reaches outside the frame.
    """
    image = np.zeros(shape, dtype=dtype)
    height, width = shape
    for w in windows:
        h, wd = w.pixels.shape
        if w.x < 0 or w.y < 0 or w.x + wd > width or w.y + h > height:
            raise ValueError(
                f"window {wd}x{h} at ({w.x}, {w.y}) reaches outside the {width}x{height} frame"
            )
        image[w.y : w.y + h, w.x : w.x + wd] = w.pixels
    return image


def uncovered(regions: Iterable[ReadRegion], windows: Sequence[ImageWindow]) -> list[ReadRegion]:
    """The regions not wholly inside one of `windows` (what a tracking read but was not kept)."""
    kept = [w.region for w in windows]
    return [r for r in regions if not any(k.contains(r) for k in kept)]
