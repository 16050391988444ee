"""An elastic-plastic metal in uniaxial tension, Swift hardening calibrated to Rp0.2 and Rm.

The common interface of the materials is described in `appliance.sim.materials`.

References:
    H. W. Swift, "Plastic instability under plane stress", J. Mech. Phys. Solids 1 (1952) 1-18.
    ISO 6892-1:2019 Metallic materials - Tensile testing - Part 1: Method of test at room
    temperature (Rp0.2, Rm, Ag, Agt, A).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import numpy.typing as npt
from scipy.optimize import brentq

from appliance.sim.inverse_table import FloatArray, InverseTable

PROOF_OFFSET_STRAIN = 0.002
"""Non-proportional extension of the proof stress Rp0.2 (ISO 6892-1, 3.10.3.1)."""


@dataclass(frozen=True)
class ElasticPlastic:
    """Elastic-plastic metal in uniaxial tension, Swift hardening, calibrated to Rp0.2 and Rm.

    Kinematics (true strain, additive): ln(lambda) = sigma / E + eps_p, with sigma the true
    stress and eps_p the true plastic strain. Width stretch lambda_w = (1 - nu sigma / E)
    exp(-r eps_p / (1 + r)) and thickness stretch lambda_a = (1 - nu sigma / E)
    exp(-eps_p / (1 + r)): elastic contraction with Poisson's ratio nu, plastic flow at
    constant volume split between width and thickness by the plastic strain ratio
    r = eps_w / eps_a (ISO 10113; r = 1 is an isotropic sheet, both contract alike). Nominal
    stress P = sigma lambda_w lambda_a = sigma (1 - nu sigma / E)^2 exp(-eps_p), whatever r.
    `lateral_stretch` and the lateral stretch of `loading_state` and `elastic_state` are the
    width's (what a camera facing the sheet sees).

    Flow stress (Swift 1952): sigma_f = K (eps_0 + eps_p)^n for eps_p >= 0; the material is
    elastic below the initial yield stress K eps_0^n. K and n are solved so that the generated
    engineering curve has its 0.2 % offset proof stress (the line of slope E through
    e = 0.002, ISO 6892-1 13.1) at `proof_stress_mpa` and its maximum (Considere's point,
    d(sigma)/d(eps) = sigma) at `tensile_strength_mpa`, both to about 1e-9 MPa.

    Compression is taken as elastic (no compressive yield).

    Attributes:
        youngs_modulus_mpa: E, MPa.
        poisson_ratio: nu, elastic, in [0, 0.5).
        proof_stress_mpa: Rp0.2, MPa.
        tensile_strength_mpa: Rm, MPa, > Rp0.2.
        elongation_after_fracture: A, the permanent elongation of the gauge length after
            fracture as a fraction of L0 (0.25 = 25 %); must exceed the plastic uniform
            elongation Ag. The specimen model places the extra elongation in a neck.
        swift_prestrain: eps_0 of the Swift law; sets how gradual yielding is (the initial
            yield stress is K eps_0^n).
        plastic_anisotropy: r, the plastic strain ratio of the sheet along the pulling
            direction (width over thickness true plastic strain, ISO 10113), > 0.
        hardening_exponent: n, solved (not an argument).
        swift_coefficient_mpa: K, MPa, solved (not an argument).

    Raises:
        ValueError: a property is out of range, or no Swift curve has this Rp0.2 and Rm.
    """

    youngs_modulus_mpa: float
    poisson_ratio: float
    proof_stress_mpa: float
    tensile_strength_mpa: float
    elongation_after_fracture: float
    swift_prestrain: float = 0.002
    plastic_anisotropy: float = 1.0
    hardening_exponent: float = field(init=False)
    swift_coefficient_mpa: float = field(init=False)

    necks: ClassVar[bool] = True

    def __post_init__(self) -> None:
        for name in (
            "youngs_modulus_mpa",
            "proof_stress_mpa",
            "tensile_strength_mpa",
            "elongation_after_fracture",
            "swift_prestrain",
            "plastic_anisotropy",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value}")
        if not (0.0 <= self.poisson_ratio < 0.5):
            raise ValueError(f"poisson_ratio must be in [0, 0.5), got {self.poisson_ratio}")
        if self.tensile_strength_mpa <= self.proof_stress_mpa:
            raise ValueError(
                f"tensile_strength_mpa ({self.tensile_strength_mpa}) must exceed "
                f"proof_stress_mpa ({self.proof_stress_mpa})"
            )
        exponent, coefficient = self._calibrate()
        object.__setattr__(self, "hardening_exponent", exponent)
        object.__setattr__(self, "swift_coefficient_mpa", coefficient)
        if self.elongation_after_fracture <= self.uniform_elongation:
            raise ValueError(
                f"elongation_after_fracture ({self.elongation_after_fracture}) must exceed the "
                f"plastic uniform elongation Ag ({self.uniform_elongation:.4f})"
            )

    @classmethod
    def steel_s355(cls) -> ElasticPlastic:
        """A steel sheet with the strength of S355 (EN 10025-2): E = 210 GPa, nu = 0.3,
        Rp0.2 = 355 MPa, Rm = 510 MPa, A = 25 %; continuous yielding (no upper yield point or
        Lueders band); a plastic strain ratio r = 1.8, a cold-rolled deep-drawing sheet's
        (DC04 has 1.6 to 2), so that the width and the thickness contract differently and
        r is measurable (a hot-rolled S355 plate is about isotropic, r near 1).

        The calibrated Swift law has n = 0.140, giving Agt = 15.1 % and Ag = 14.9 %.
        """
        return cls(
            youngs_modulus_mpa=210_000.0,
            poisson_ratio=0.3,
            proof_stress_mpa=355.0,
            tensile_strength_mpa=510.0,
            elongation_after_fracture=0.25,
            plastic_anisotropy=1.8,
        )

    def _swift_stress(
        self, plastic_strain: FloatArray, exponent: float, coefficient: float
    ) -> FloatArray:
        return coefficient * (self.swift_prestrain + plastic_strain) ** exponent

    def _calibrate(self) -> tuple[float, float]:
        E, nu, proof = self.youngs_modulus_mpa, self.poisson_ratio, self.proof_stress_mpa
        target = math.log1p(PROOF_OFFSET_STRAIN + proof / E)

        def proof_condition(sigma: float) -> float:
            return sigma / E + math.log(sigma * (1.0 - nu * sigma / E) ** 2 / proof) - target

        sigma_proof = brentq(proof_condition, 0.5 * proof, 2.0 * proof, xtol=1e-13, rtol=1e-15)
        strain_proof = math.log(sigma_proof * (1.0 - nu * sigma_proof / E) ** 2 / proof)
        base = self.swift_prestrain + strain_proof

        def contraction(sigma: float) -> float:
            ratio = nu * sigma / E
            return 1.0 - 2.0 * ratio / (1.0 - ratio)

        def peak(exponent: float) -> float:
            coefficient = sigma_proof / base**exponent

            def slope(plastic: float) -> float:
                sigma = coefficient * (self.swift_prestrain + plastic) ** exponent
                return exponent / (self.swift_prestrain + plastic) * contraction(sigma) - 1.0

            plastic = brentq(slope, strain_proof, 10.0, xtol=1e-15, rtol=1e-15)
            sigma = coefficient * (self.swift_prestrain + plastic) ** exponent
            return sigma * (1.0 - nu * sigma / E) ** 2 * math.exp(-plastic)

        lowest = base / contraction(sigma_proof) * (1.0 + 1e-9)
        highest = 0.6
        if not peak(lowest) < self.tensile_strength_mpa < peak(highest):
            raise ValueError(
                f"no Swift curve with swift_prestrain {self.swift_prestrain} has "
                f"Rp0.2 = {proof} MPa and Rm = {self.tensile_strength_mpa} MPa"
            )
        exponent = brentq(
            lambda n: peak(n) - self.tensile_strength_mpa, lowest, highest, xtol=1e-15, rtol=1e-15
        )
        return exponent, sigma_proof / base**exponent

    @property
    def initial_yield_stress_mpa(self) -> float:
        """True stress at which plastic flow starts, K eps_0^n, MPa."""
        return self.swift_coefficient_mpa * self.swift_prestrain**self.hardening_exponent

    def flow_stress_mpa(self, plastic_strain: npt.ArrayLike) -> FloatArray:
        """Swift flow stress sigma_f = K (eps_0 + eps_p)^n, MPa (true stress)."""
        plastic = np.maximum(np.asarray(plastic_strain, np.float64), 0.0)
        return self._swift_stress(plastic, self.hardening_exponent, self.swift_coefficient_mpa)

    def flow_nominal_stress_mpa(self, plastic_strain: npt.ArrayLike) -> FloatArray:
        """Nominal stress at which a section with plastic strain eps_p flows, MPa.

        sigma_f (1 - nu sigma_f / E)^2 exp(-eps_p): the loading curve parameterised by the
        plastic strain; it rises to Rm at the uniform plastic strain, then falls.
        """
        plastic = np.maximum(np.asarray(plastic_strain, np.float64), 0.0)
        sigma = self.flow_stress_mpa(plastic)
        return (
            sigma
            * (1.0 - self.poisson_ratio * sigma / self.youngs_modulus_mpa) ** 2
            * (np.exp(-plastic))
        )

    def _plastic_of_sigma(self, sigma: FloatArray) -> FloatArray:
        ratio = np.maximum(sigma, self.initial_yield_stress_mpa) / self.swift_coefficient_mpa
        return np.maximum(ratio ** (1.0 / self.hardening_exponent) - self.swift_prestrain, 0.0)

    def _plastic_slope_of_sigma(self, sigma: FloatArray) -> FloatArray:
        flowing = sigma > self.initial_yield_stress_mpa
        safe = np.maximum(sigma, self.initial_yield_stress_mpa)
        slope = (safe / self.swift_coefficient_mpa) ** (1.0 / self.hardening_exponent) / (
            self.hardening_exponent * safe
        )
        return np.where(flowing, slope, 0.0)

    def _log_strain_of_sigma(self, sigma: FloatArray) -> FloatArray:
        return sigma / self.youngs_modulus_mpa + self._plastic_of_sigma(sigma)

    def _log_strain_slope_of_sigma(self, sigma: FloatArray) -> FloatArray:
        return 1.0 / self.youngs_modulus_mpa + self._plastic_slope_of_sigma(sigma)

    def _nominal_of_sigma(self, sigma: FloatArray) -> FloatArray:
        contraction = 1.0 - self.poisson_ratio * sigma / self.youngs_modulus_mpa
        return sigma * contraction**2 * np.exp(-self._plastic_of_sigma(sigma))

    def _nominal_slope_of_sigma(self, sigma: FloatArray) -> FloatArray:
        ratio = self.poisson_ratio * sigma / self.youngs_modulus_mpa
        elastic = (1.0 - ratio) * (1.0 - 3.0 * ratio) * np.exp(-self._plastic_of_sigma(sigma))
        return elastic - self._nominal_of_sigma(sigma) * self._plastic_slope_of_sigma(sigma)

    def _tables(self) -> dict[str, InverseTable]:
        tables = self.__dict__.get("_inverse_tables")
        if tables is not None:
            return tables
        yield_stress = self.initial_yield_stress_mpa
        uniform = self.uniform_plastic_strain
        plastic = np.geomspace(1e-9, 5.0, 2000)
        plastic = plastic[np.abs(plastic / uniform - 1.0) > 1e-3]
        plastic = np.sort(np.concatenate([[0.0, uniform], plastic]))
        sigma = np.concatenate(
            [
                np.linspace(-yield_stress, yield_stress, 65)[:-1],
                self._swift_stress(plastic, self.hardening_exponent, self.swift_coefficient_mpa),
            ]
        )
        tables = {
            "log_strain": InverseTable(
                sigma, self._log_strain_of_sigma, self._log_strain_slope_of_sigma
            ),
            "rising": InverseTable(
                sigma[: np.searchsorted(plastic, uniform) + 65],
                self._nominal_of_sigma,
                self._nominal_slope_of_sigma,
                peak_at_end=True,
                newton_steps=3,
            ),
        }
        self.__dict__["_inverse_tables"] = tables
        return tables

    @property
    def uniform_plastic_strain(self) -> float:
        """True plastic strain at the maximum force (Considere's point)."""
        cached = self.__dict__.get("_uniform_plastic_strain")
        if cached is not None:
            return cached
        E, nu = self.youngs_modulus_mpa, self.poisson_ratio

        def slope(plastic: float) -> float:
            sigma = float(self.flow_stress_mpa(plastic))
            ratio = nu * sigma / E
            total = self.swift_prestrain + plastic
            return self.hardening_exponent / total * (1.0 - 2.0 * ratio / (1.0 - ratio)) - 1.0

        plastic = brentq(slope, 0.0, 10.0, xtol=1e-15, rtol=1e-15)
        self.__dict__["_uniform_plastic_strain"] = plastic
        return plastic

    def _sigma_of_stretch(self, stretch: npt.ArrayLike) -> FloatArray:
        return self._tables()["log_strain"](np.log(np.asarray(stretch, np.float64)))

    @property
    def peak_stress_mpa(self) -> float:
        """Largest nominal stress of the curve, MPa (Rm, reproduced by the calibration)."""
        return float(self.flow_nominal_stress_mpa(self.uniform_plastic_strain))

    @property
    def stretch_at_peak(self) -> float:
        """Axial stretch at the maximum force, 1 + Agt."""
        plastic = self.uniform_plastic_strain
        sigma = float(self.flow_stress_mpa(plastic))
        return math.exp(sigma / self.youngs_modulus_mpa + plastic)

    @property
    def break_strain(self) -> float:
        """Engineering strain of the gauge length at break, taken as A (the elastic part at
        fracture, about F / (E S0), is left out)."""
        return self.elongation_after_fracture

    @property
    def total_uniform_elongation(self) -> float:
        """Agt: total engineering strain at the maximum force (ISO 6892-1, 3.6.4)."""
        return self.stretch_at_peak - 1.0

    @property
    def uniform_elongation(self) -> float:
        """Ag: plastic engineering strain at the maximum force, Agt - Rm / E (ISO 6892-1, 3.6.3)."""
        return self.total_uniform_elongation - self.peak_stress_mpa / self.youngs_modulus_mpa

    def nominal_stress_mpa(self, stretch: npt.ArrayLike) -> FloatArray:
        """Nominal stress P, MPa, at the axial stretch lambda under monotone loading.

        Beyond the uniform elongation this is the falling material curve (the stress a
        section would carry if it alone kept straining).
        """
        return self._nominal_of_sigma(self._sigma_of_stretch(stretch))

    def stress_slope_mpa(self, stretch: npt.ArrayLike) -> FloatArray:
        """Tangent dP/dlambda under monotone loading, MPa (the plastic tangent at yield)."""
        stretch = np.asarray(stretch, np.float64)
        sigma = self._sigma_of_stretch(stretch)
        return self._nominal_slope_of_sigma(sigma) / (
            stretch * self._log_strain_slope_of_sigma(sigma)
        )

    def stretch_at_stress(self, nominal_stress_mpa: npt.ArrayLike) -> FloatArray:
        """Axial stretch on the rising branch carrying the nominal stress P, MPa.

        Args:
            nominal_stress_mpa: P, MPa, any shape, at most `peak_stress_mpa` (values above it
                by less than 1e-12 relative are taken as the peak; larger ones give NaN).

        Returns:
            Stretches lambda with P(lambda) = P and lambda <= 1 + Agt.
        """
        return self.loading_state(nominal_stress_mpa)[0]

    def loading_state(
        self, nominal_stress_mpa: npt.ArrayLike
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(axial stretch, lateral stretch, plastic strain) on the rising branch at P, MPa.

        As `stretch_at_stress`, with the lateral stretch and true plastic strain of the same
        state; NaN above the peak.
        """
        rising = self._tables()["rising"]
        stress = np.asarray(nominal_stress_mpa, np.float64)
        sigma = rising(np.minimum(stress, rising.f[-1]))
        sigma = np.where(stress > self.peak_stress_mpa * (1.0 + 1e-12), np.nan, sigma)
        plastic = self._plastic_of_sigma(sigma)
        stretch = np.exp(sigma / self.youngs_modulus_mpa + plastic)
        lateral = (1.0 - self.poisson_ratio * sigma / self.youngs_modulus_mpa) * np.exp(
            -self.width_share * plastic
        )
        return stretch, lateral, plastic

    @property
    def width_share(self) -> float:
        """r / (1 + r): the share of the plastic axial strain the width gives up (the
        thickness gives up the rest)."""
        return self.plastic_anisotropy / (1.0 + self.plastic_anisotropy)

    def lateral_stretch(self, stretch: npt.ArrayLike) -> FloatArray:
        """Width stretch (1 - nu sigma / E) exp(-r eps_p / (1 + r)) under monotone loading."""
        sigma = self._sigma_of_stretch(stretch)
        return (1.0 - self.poisson_ratio * sigma / self.youngs_modulus_mpa) * np.exp(
            -self.width_share * self._plastic_of_sigma(sigma)
        )

    def thickness_stretch(self, stretch: npt.ArrayLike) -> FloatArray:
        """Thickness stretch (1 - nu sigma / E) exp(-eps_p / (1 + r)) under monotone loading."""
        sigma = self._sigma_of_stretch(stretch)
        return (1.0 - self.poisson_ratio * sigma / self.youngs_modulus_mpa) * np.exp(
            -(1.0 - self.width_share) * self._plastic_of_sigma(sigma)
        )

    def plastic_strain(self, stretch: npt.ArrayLike) -> FloatArray:
        """True plastic strain eps_p after monotone loading to the stretch lambda."""
        return self._plastic_of_sigma(self._sigma_of_stretch(stretch))

    def elastic_state(
        self, plastic_strain: npt.ArrayLike, nominal_stress_mpa: npt.ArrayLike
    ) -> tuple[FloatArray, FloatArray]:
        """(axial stretch, lateral stretch) under the nominal stress P with eps_p frozen.

        Solves sigma (1 - nu sigma / E)^2 = P exp(eps_p) for the true stress, then
        lambda = exp(sigma / E + eps_p), the width's lambda_t = (1 - nu sigma / E)
        exp(-r eps_p / (1 + r)). Valid
        while sigma stays at or below the section's flow stress (unloading, reloading).
        """
        plastic, stress = np.broadcast_arrays(
            np.asarray(plastic_strain, np.float64), np.asarray(nominal_stress_mpa, np.float64)
        )
        scaled = stress * np.exp(plastic)
        sigma = scaled
        for _ in range(6):
            sigma = scaled / (1.0 - self.poisson_ratio * sigma / self.youngs_modulus_mpa) ** 2
        contraction = 1.0 - self.poisson_ratio * sigma / self.youngs_modulus_mpa
        return (
            np.exp(sigma / self.youngs_modulus_mpa + plastic),
            contraction * np.exp(-self.width_share * plastic),
        )
