"""Uniaxial tension of simulated specimen materials: nominal stress against stretch.

Every material here answers, for a bar pulled along its axis:

* `nominal_stress_mpa(stretch)`: the nominal (engineering) stress P = F / A0, MPa, at the
  axial stretch lambda = 1 + e (e the engineering strain), under monotone loading;
* `stretch_at_stress(nominal_stress_mpa)`: its inverse on the rising branch (up to
  `peak_stress_mpa`), accurate to about 1e-12 relative in lambda (1e-10 next to a metal's
  peak, where P is flat) by cubic Hermite interpolation of a dense table and Newton steps;
* `stress_slope_mpa(stretch)`: the tangent dP/dlambda, MPa;
* `lateral_stretch(stretch)`: the stretch lambda_t across the bar's width (a rubber's
  thickness alike; a metal sheet's thickness by its plastic strain ratio r, ISO 10113);
* `plastic_strain(stretch)` and `elastic_state(plastic_strain, nominal_stress_mpa)`: the
  permanent part of the deformation, and the state under a stress with that part frozen (the
  elastic unloading and reloading path);
* `necks`: whether the force peaks and the deformation then localises (metals), and the break
  criterion: `break_stretch` for rubbers, `elongation_after_fracture` for metals.

Rubbers are incompressible hyperelastic solids (lateral stretch lambda^-1/2) with no necking;
they break when the stretch reaches `break_stretch`. Metals are elastic-plastic with Swift
hardening, calibrated to the proof stress Rp0.2 and tensile strength Rm of ISO 6892-1.
`break_strain` is the engineering strain at break for both.

The rubbers are in `appliance.sim.rubber`, the metal in `appliance.sim.metal`; both answer
stress against stretch through `appliance.sim.inverse_table`. Presets:
`MooneyRivlin.filled_rubber()` (a soft filled rubber), `ElasticPlastic.steel_s355()` (a
structural steel).

References:
    R. W. Ogden, Non-Linear Elastic Deformations, Dover 1997, section 7.2 (uniaxial tension
    of incompressible solids; neo-Hookean and Mooney-Rivlin strain energies).
    H. W. Swift, "Plastic instability under plane stress", J. Mech. Phys. Solids 1 (1952) 1-18.
    ISO 6892-1:2019 Metallic materials - Tensile testing - Part 1: Method of test at room
    temperature (Rp0.2, Rm, Ag, Agt, A).
"""

from appliance.sim.metal import ElasticPlastic
from appliance.sim.rubber import MooneyRivlin, NeoHookean

Material = NeoHookean | MooneyRivlin | ElasticPlastic
"""The materials a specimen model accepts."""

__all__ = ["ElasticPlastic", "Material", "MooneyRivlin", "NeoHookean"]
