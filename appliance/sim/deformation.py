"""The deformed shape of a simulated specimen at one instant, as tabulated functions.

Frames of reference (object plane, millimetres):

* material coordinates (X, Y): a point's position in the undeformed specimen, origin at the
  specimen's centre, Y along the loading axis, X across it;
* spatial coordinates (x, y): where that point is now, in the same axes, fixed to the test
  machine (the fixed grip does not move).

In the image, x runs along the columns and y along the rows (downwards). The moving crosshead
grip is on the -Y side (the top of the image) and moves towards -y; the fixed grip is on the
+Y side.

The specimen deforms cross-section by cross-section (a one-dimensional bar model): the section
at material Y moves axially to y(Y) and contracts laterally about the axis by lambda_t(Y), so

    x = lambda_t(Y) * X,        y = y(Y).

y(Y) is strictly increasing. Beyond the tabulated range the specimen is held rigidly by the
grips: it translates with the nearest end of the table.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class AxialDeformation:
    """Specimen shape at one instant, tabulated along the axis.

    Attributes:
        material_y_mm: (n,) strictly increasing material positions Y of the table, mm.
        spatial_y_mm: (n,) their current positions y, strictly increasing, mm.
        lateral_stretch: (n,) lateral stretch lambda_t at each Y (1 = undeformed).
        half_width_mm: (n,) half of the undeformed specimen width at each Y, mm (the outline
            in material coordinates; the current half-width is lambda_t times this).
    """

    material_y_mm: FloatArray
    spatial_y_mm: FloatArray
    lateral_stretch: FloatArray
    half_width_mm: FloatArray

    def __post_init__(self) -> None:
        arrays = [
            np.ascontiguousarray(np.asarray(a, np.float64))
            for a in (
                self.material_y_mm,
                self.spatial_y_mm,
                self.lateral_stretch,
                self.half_width_mm,
            )
        ]
        n = arrays[0].size
        if n < 2 or any(a.shape != (n,) for a in arrays):
            raise ValueError("deformation tables must be 1-D arrays of one length >= 2")
        if not (np.all(np.diff(arrays[0]) > 0) and np.all(np.diff(arrays[1]) > 0)):
            raise ValueError("material and spatial axial positions must be strictly increasing")
        if not (np.all(arrays[2] > 0) and np.all(arrays[3] >= 0)):
            raise ValueError("lateral stretch must be > 0 and half-width >= 0")
        for name, array in zip(
            ("material_y_mm", "spatial_y_mm", "lateral_stretch", "half_width_mm"),
            arrays,
            strict=True,
        ):
            array.setflags(write=False)
            object.__setattr__(self, name, array)

    def spatial_y(self, Y: npt.ArrayLike) -> FloatArray:
        """Current axial position y of material sections Y, mm (rigid beyond the table)."""
        Y = np.asarray(Y, np.float64)
        y = np.interp(Y, self.material_y_mm, self.spatial_y_mm)
        y = np.where(
            Y < self.material_y_mm[0], self.spatial_y_mm[0] + (Y - self.material_y_mm[0]), y
        )
        return np.where(
            Y > self.material_y_mm[-1], self.spatial_y_mm[-1] + (Y - self.material_y_mm[-1]), y
        )

    def material_y(self, y: npt.ArrayLike) -> FloatArray:
        """Material section Y now at axial position y, mm (inverse of `spatial_y`)."""
        y = np.asarray(y, np.float64)
        Y = np.interp(y, self.spatial_y_mm, self.material_y_mm)
        Y = np.where(
            y < self.spatial_y_mm[0], self.material_y_mm[0] + (y - self.spatial_y_mm[0]), Y
        )
        return np.where(
            y > self.spatial_y_mm[-1], self.material_y_mm[-1] + (y - self.spatial_y_mm[-1]), Y
        )

    def lateral_stretch_at(self, Y: npt.ArrayLike) -> FloatArray:
        """Lateral stretch of material sections Y (1 in the grips)."""
        Y = np.asarray(Y, np.float64)
        inside = (Y >= self.material_y_mm[0]) & (Y <= self.material_y_mm[-1])
        return np.where(inside, np.interp(Y, self.material_y_mm, self.lateral_stretch), 1.0)

    def half_width_at(self, Y: npt.ArrayLike) -> FloatArray:
        """Undeformed half-width of material sections Y, mm (end values beyond the table)."""
        return np.interp(np.asarray(Y, np.float64), self.material_y_mm, self.half_width_mm)

    def forward(self, X: npt.ArrayLike, Y: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Current position (x, y), mm, of material points (X, Y), mm."""
        X, Y = np.broadcast_arrays(np.asarray(X, np.float64), np.asarray(Y, np.float64))
        return X * self.lateral_stretch_at(Y), self.spatial_y(Y)

    def inverse(self, x: npt.ArrayLike, y: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Material point (X, Y), mm, now at (x, y), mm."""
        x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
        Y = self.material_y(y)
        return x / self.lateral_stretch_at(Y), Y
