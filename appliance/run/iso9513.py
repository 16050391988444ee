"""Extensometer classes of ISO 9513 (calibration of extensometers used in uniaxial testing).

An extensometer belongs to a class when, at every calibration point, its bias error in the
measured elongation is within the larger of a relative limit (percent of the true elongation)
and an absolute limit (micrometres). The limits on the bias error, from the standard's
table of classes:

    class   relative bias   absolute bias
    0.2     0.2 %           0.6 um
    0.5     0.5 %           1.5 um
    1       1 %             3.0 um
    2       2 %             6.0 um

Only the bias criterion is evaluated here: ISO 9513 also limits the resolution and the gauge
length error, which a calibration procedure checks separately.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ExtensometerClass:
    """Bias limits of one ISO 9513 class."""

    name: str
    relative: float
    absolute_um: float

    def limit_um(self, true_elongation_um: np.ndarray) -> np.ndarray:
        """Allowed |bias| in um at each true elongation (the larger of the two limits)."""
        return np.maximum(self.relative * np.abs(true_elongation_um), self.absolute_um)


CLASSES: tuple[ExtensometerClass, ...] = (
    ExtensometerClass("0.2", 0.002, 0.6),
    ExtensometerClass("0.5", 0.005, 1.5),
    ExtensometerClass("1", 0.01, 3.0),
    ExtensometerClass("2", 0.02, 6.0),
)
"""The classes from best to worst."""


def best_class(
    measured_elongation_um: Sequence[float] | np.ndarray,
    true_elongation_um: Sequence[float] | np.ndarray,
) -> str | None:
    """The best class whose bias limits every reading meets, or None.

    Args:
        measured_elongation_um: indicated elongations, um.
        true_elongation_um: true elongations at the same instants, um.

    Returns:
        The class name ("0.2", "0.5", "1", "2") or None when even class 2 is not met or there
        are no readings. NaN readings fail every class.
    """
    measured = np.asarray(measured_elongation_um, dtype=np.float64)
    true = np.asarray(true_elongation_um, dtype=np.float64)
    if measured.shape != true.shape:
        raise ValueError("measured and true elongations must have the same shape")
    if measured.size == 0:
        return None
    error = np.abs(measured - true)
    for extensometer_class in CLASSES:
        if np.all(error <= extensometer_class.limit_um(true)):
            return extensometer_class.name
    return None
