"""Extensometer classes of ISO 9513 (calibration of extensometer systems used in uniaxial
testing).

An extensometer system belongs to a class when it meets the class's three limits, from the
standard's table of classes (ISO 9513:2012, Table 2, "Classification of extensometer systems"):

    class  gauge length error  resolution             bias
           relative            relative  absolute     relative  absolute
    0.2    +-0.2 %             0.1 %     0.2 um       +-0.2 %   +-0.6 um
    0.5    +-0.5 %             0.25 %    0.5 um       +-0.5 %   +-1.5 um
    1      +-1 %               0.5 %     1.0 um       +-1 %     +-3.0 um
    2      +-2 %               1 %       2.0 um       +-2 %     +-6.0 um

* bias: at every calibration point, |l_i - l_t| (the extensometer's reading l_i against the
  calibrator's elongation l_t) within the larger of the relative limit (of l_t) and the
  absolute one: below 300 um (0.6 um / 0.2 %) the absolute limit decides;
* resolution: the smallest change the extensometer reads, within the larger of the relative
  limit (of the reading at the calibration point) and the absolute one;
* gauge length: the relative error of the measured gauge length against the nominal one,
  (L_e - L_e,nominal) / L_e,nominal.

`best_class` grades bias alone (what a simulated test's summary can grade against its truth);
`appliance.run.verification` grades all three.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ExtensometerClass:
    """The limits of one ISO 9513 class.

    Attributes:
        name: "0.2", "0.5", "1" or "2".
        relative: relative bias limit (fraction of the true elongation).
        absolute_um: absolute bias limit, um.
        resolution_relative: relative resolution limit (fraction of the reading).
        resolution_um: absolute resolution limit, um.
        gauge_length_relative: limit on the relative gauge length error.
    """

    name: str
    relative: float
    absolute_um: float
    resolution_relative: float = 0.0
    resolution_um: float = 0.0
    gauge_length_relative: float = 0.0

    def limit_um(self, true_elongation_um: np.ndarray) -> np.ndarray:
        """Allowed |bias| in um at each true elongation (the larger of the two limits)."""
        return np.maximum(self.relative * np.abs(true_elongation_um), self.absolute_um)

    def resolution_limit_um(self, reading_um: np.ndarray) -> np.ndarray:
        """Largest resolution allowed, um, at each reading (the larger of the two limits)."""
        return np.maximum(self.resolution_relative * np.abs(reading_um), self.resolution_um)


CLASSES: tuple[ExtensometerClass, ...] = (
    ExtensometerClass("0.2", 0.002, 0.6, 0.001, 0.2, 0.002),
    ExtensometerClass("0.5", 0.005, 1.5, 0.0025, 0.5, 0.005),
    ExtensometerClass("1", 0.01, 3.0, 0.005, 1.0, 0.01),
    ExtensometerClass("2", 0.02, 6.0, 0.01, 2.0, 0.02),
)
"""The classes from best to worst."""


def class_named(name: str) -> ExtensometerClass:
    """The class called `name` ("0.2", "0.5", "1", "2"; "1.0" and "2.0" are accepted).

    Raises:
        ValueError: no such class.
    """
    for extensometer_class in CLASSES:
        if name in (extensometer_class.name, f"{extensometer_class.name}.0"):
            return extensometer_class
    raise ValueError(f"no ISO 9513 class {name!r} (classes: 0.2, 0.5, 1, 2)")


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
