"""Incompressible hyperelastic rubbers in uniaxial tension: neo-Hookean and Mooney-Rivlin.

Lateral stretch lambda^-1/2 (incompressible), no necking, no plastic strain; a rubber breaks
when its stretch reaches `break_stretch`. The common interface of the materials is described
in `appliance.sim.materials`.

Reference:
    R. W. Ogden, Non-Linear Elastic Deformations, Dover 1997, section 7.2 (uniaxial tension
    of incompressible solids; neo-Hookean and Mooney-Rivlin strain energies).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import numpy.typing as npt

from appliance.sim.inverse_table import FloatArray, InverseTable


class IncompressibleRubber:
    """Shared behaviour of the incompressible hyperelastic rubbers.

    Subclasses provide `nominal_stress_mpa`, `stress_slope_mpa` and `break_strain`. Rubber is
    elastic here: no plastic strain, no Mullins softening, no necking.
    """

    necks: ClassVar[bool] = False
    break_strain: float

    def nominal_stress_mpa(self, stretch: npt.ArrayLike) -> FloatArray:
        raise NotImplementedError

    def stress_slope_mpa(self, stretch: npt.ArrayLike) -> FloatArray:
        raise NotImplementedError

    @property
    def break_stretch(self) -> float:
        """Axial stretch at break, 1 + break strain."""
        return 1.0 + self.break_strain

    @property
    def peak_stress_mpa(self) -> float:
        """Nominal stress at break, MPa: the largest the material carries."""
        return float(self.nominal_stress_mpa(self.break_stretch))

    @property
    def small_strain_modulus_mpa(self) -> float:
        """Young's modulus at vanishing strain, dP/dlambda at lambda = 1, MPa."""
        return float(self.stress_slope_mpa(1.0))

    def _inverse(self) -> InverseTable:
        table = self.__dict__.get("_inverse_table")
        if table is None:
            stretch = np.concatenate(
                [
                    np.linspace(0.2, 1.0, 100, endpoint=False),
                    np.geomspace(1.0, 2.0 * max(self.break_stretch, 2.0), 1000),
                ]
            )
            table = InverseTable(stretch, self.nominal_stress_mpa, self.stress_slope_mpa)
            self.__dict__["_inverse_table"] = table
        return table

    def stretch_at_stress(self, nominal_stress_mpa: npt.ArrayLike) -> FloatArray:
        """Axial stretch lambda carrying the nominal stress P, MPa (inverse of P(lambda)).

        Args:
            nominal_stress_mpa: nominal stresses P, MPa, any shape.

        Returns:
            Stretches lambda > 0 with P(lambda) = P, of the same shape.
        """
        return self._inverse()(nominal_stress_mpa)

    def loading_state(
        self, nominal_stress_mpa: npt.ArrayLike
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(axial stretch, lateral stretch, plastic strain) at the nominal stress P, MPa."""
        stretch = self.stretch_at_stress(nominal_stress_mpa)
        return stretch, self.lateral_stretch(stretch), np.zeros_like(stretch)

    def lateral_stretch(self, stretch: npt.ArrayLike) -> FloatArray:
        """Lateral stretch lambda^-1/2 (incompressible: lambda * lambda_t^2 = 1)."""
        return np.asarray(stretch, np.float64) ** -0.5

    def plastic_strain(self, stretch: npt.ArrayLike) -> FloatArray:
        """True plastic strain: zero (rubber is elastic here)."""
        return np.zeros_like(np.asarray(stretch, np.float64))

    def elastic_state(
        self, plastic_strain: npt.ArrayLike, nominal_stress_mpa: npt.ArrayLike
    ) -> tuple[FloatArray, FloatArray]:
        """(axial stretch, lateral stretch) under the nominal stress P, MPa.

        The plastic strain is ignored: unloading retraces the loading curve.
        """
        plastic, stress = np.broadcast_arrays(
            np.asarray(plastic_strain, np.float64), np.asarray(nominal_stress_mpa, np.float64)
        )
        stretch = self.stretch_at_stress(stress)
        return stretch, self.lateral_stretch(stretch)


def _check_break_strain(break_strain: float) -> None:
    if not (math.isfinite(break_strain) and break_strain > 0):
        raise ValueError(f"break_strain must be a positive number, got {break_strain}")


@dataclass(frozen=True)
class NeoHookean(IncompressibleRubber):
    """Incompressible neo-Hookean rubber in uniaxial tension.

    Strain energy W = mu / 2 (I1 - 3); nominal stress P = mu (lambda - lambda^-2) (Ogden 1997,
    eq. 7.2.5 with a single term).

    Attributes:
        shear_modulus_mpa: shear modulus mu, MPa (Young's modulus at small strain is 3 mu).
        break_strain: engineering strain at which the parallel section breaks (6.0 = 600 %).
    """

    shear_modulus_mpa: float
    break_strain: float = 6.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.shear_modulus_mpa) and self.shear_modulus_mpa > 0):
            raise ValueError(f"shear_modulus_mpa must be positive, got {self.shear_modulus_mpa}")
        _check_break_strain(self.break_strain)

    def nominal_stress_mpa(self, stretch: npt.ArrayLike) -> FloatArray:
        """Nominal stress P = mu (lambda - lambda^-2), MPa."""
        stretch = np.asarray(stretch, np.float64)
        return self.shear_modulus_mpa * (stretch - stretch**-2)

    def stress_slope_mpa(self, stretch: npt.ArrayLike) -> FloatArray:
        """Tangent dP/dlambda = mu (1 + 2 lambda^-3), MPa."""
        stretch = np.asarray(stretch, np.float64)
        return self.shear_modulus_mpa * (1.0 + 2.0 * stretch**-3)


@dataclass(frozen=True)
class MooneyRivlin(IncompressibleRubber):
    """Incompressible Mooney-Rivlin rubber in uniaxial tension.

    Strain energy W = C10 (I1 - 3) + C01 (I2 - 3); nominal stress
    P = 2 (lambda - lambda^-2) (C10 + C01 / lambda) (Ogden 1997, section 7.2).

    Attributes:
        c10_mpa: C10, MPa, > 0.
        c01_mpa: C01, MPa, >= 0 (keeps P increasing in lambda).
        break_strain: engineering strain at which the parallel section breaks (6.0 = 600 %).
    """

    c10_mpa: float
    c01_mpa: float
    break_strain: float = 6.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.c10_mpa) and self.c10_mpa > 0):
            raise ValueError(f"c10_mpa must be positive, got {self.c10_mpa}")
        if not (math.isfinite(self.c01_mpa) and self.c01_mpa >= 0):
            raise ValueError(f"c01_mpa must be >= 0, got {self.c01_mpa}")
        _check_break_strain(self.break_strain)

    @classmethod
    def filled_rubber(cls, *, break_strain: float = 6.0) -> MooneyRivlin:
        """A soft filled rubber: C10 = 0.3 MPa, C01 = 0.05 MPa, breaking at 600 %.

        Representative magnitudes, not a fit to one compound: shear modulus 2 (C10 + C01) =
        0.7 MPa, Young's modulus 2.1 MPa, about Shore A 45 by Gent's relation (A. N. Gent,
        Trans. Inst. Rubber Ind. 34 (1958) 46). The nominal stress at 600 % is 4.3 MPa; a
        Mooney-Rivlin solid has no strain-crystallisation upturn.
        """
        return cls(c10_mpa=0.3, c01_mpa=0.05, break_strain=break_strain)

    def nominal_stress_mpa(self, stretch: npt.ArrayLike) -> FloatArray:
        """Nominal stress P = 2 (lambda - lambda^-2) (C10 + C01 / lambda), MPa."""
        stretch = np.asarray(stretch, np.float64)
        return 2.0 * (stretch - stretch**-2) * (self.c10_mpa + self.c01_mpa / stretch)

    def stress_slope_mpa(self, stretch: npt.ArrayLike) -> FloatArray:
        """Tangent dP/dlambda = 2 (C10 (1 + 2 lambda^-3) + 3 C01 lambda^-4), MPa."""
        stretch = np.asarray(stretch, np.float64)
        return 2.0 * (self.c10_mpa * (1.0 + 2.0 * stretch**-3) + 3.0 * self.c01_mpa * stretch**-4)
