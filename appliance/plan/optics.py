"""Camera optics: the thin-lens model of Zhang et al. (2016), Eq. 7-8.

A lens of focal length f images an object at distance u (object to lens) onto the sensor at the
image distance v given by the Gaussian lens law

    1/f = 1/u + 1/v          so  v = f u / (u - f)            (Eq. 7)

and the lateral magnification (image size / object size) is

    m = v / u = f / (u - f)                                    (Eq. 8)

A sensor with pixel pitch p (um) then sees p / m um of the object per pixel. All distances are
in millimetres except the pixel pitch (micrometres), as the keys say.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from appliance.config import Config
from appliance.errors import InputError, ParameterError


@dataclass(frozen=True)
class Optics:
    """Lens and sensor of a camera focused on the specimen.

    Attributes:
        focal_length_mm: focal length f, mm (> 0).
        object_distance_mm: object distance u from the specimen to the lens, mm (> f).
        pixel_size_um: sensor pixel pitch p, um (> 0).
    """

    focal_length_mm: float
    object_distance_mm: float
    pixel_size_um: float

    def __post_init__(self) -> None:
        for name in ("focal_length_mm", "object_distance_mm", "pixel_size_um"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ParameterError(name, f"must be finite and > 0, got {value}")
        if not self.object_distance_mm > self.focal_length_mm:
            raise ParameterError(
                "object_distance_mm",
                f"({self.object_distance_mm:g}) must exceed focal_length_mm "
                f"({self.focal_length_mm:g}) for a real image",
            )

    @property
    def image_distance_mm(self) -> float:
        """Image distance v = f u / (u - f), mm (Eq. 7)."""
        f, u = self.focal_length_mm, self.object_distance_mm
        return f * u / (u - f)

    @property
    def magnification(self) -> float:
        """Lateral magnification m = v / u (Eq. 8)."""
        return self.image_distance_mm / self.object_distance_mm

    @property
    def scale_mm_per_px(self) -> float:
        """Object-plane size of one pixel, mm (p / m)."""
        return self.pixel_size_um * 1e-3 / self.magnification

    def image_um(self, object_mm: float) -> float:
        """Size on the sensor, um, of an object-plane length given in mm."""
        return object_mm * 1e3 * self.magnification

    def image_px(self, object_mm: float) -> float:
        """Size on the sensor, px, of an object-plane length given in mm."""
        return self.image_um(object_mm) / self.pixel_size_um


def configured_optics(config: Config, fallback: Optics | None) -> Optics:
    """The `[optics]` of a configuration; `fallback` (a simulated preset's) when the table
    gives none of its keys. Raises InputError naming a missing or bad key."""
    o = config.optics
    given = (o.focal_length_mm, o.object_distance_mm, o.pixel_size_um)
    if all(v is None for v in given) and fallback is not None:
        return fallback
    missing = [
        k
        for k, v in zip(
            ("focal_length_mm", "object_distance_mm", "pixel_size_um"), given, strict=True
        )
        if v is None
    ]
    if missing:
        raise InputError(f"[optics] {missing[0]}: required (the camera's optics must be known)")
    try:
        return Optics(*given)
    except ValueError as exc:
        raise InputError(f"[optics]: {exc}") from None
