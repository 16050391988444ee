"""A tensile specimen as a one-dimensional bar: its shape and force for a crosshead position.

Coordinates follow `appliance.sim.deformation`. The clamp edges sit at material Y = +-G/2 (G
the initial grip distance). The fixed grip holds the +Y side: material there stays in place,
y = Y for Y >= G/2. The moving crosshead grip holds the -Y side and opens by the crosshead
displacement d: its clamp edge is at y = -G/2 - d.

Equilibrium of a bar (no inertia, no bending, uniform stress over each section): every
cross-section carries the same force F, so the section at Y, of undeformed area A0(Y), has
nominal stress P = F / A0(Y) and takes the stretch lambda(Y) that the material gives for P.
The free length between the clamps closes the system:

    integral over [-G/2, G/2] of (lambda(Y) - 1) dY = d,                              (1)

and the current positions follow from the fixed grip,

    y(Y) = G/2 - integral from Y to G/2 of lambda(Y') dY'.                            (2)

Phases, in the order a monotone test meets them:

* loading: F rises with d; the parallel (narrowest) section carries the highest stress.
* necking (metals): at the maximum force the parallel section reaches Considere's point and
  further elongation localises. A neck grows around `fracture_position_mm` as extra plastic
  strain a * g(Y), g a Gaussian of full width at half maximum `neck_width_mm`; the neck
  centre follows the material's own falling curve, F = A0 P_flow(eps_u + a), while every
  other section unloads elastically with its plastic strain frozen.
* break: rubbers when the parallel section reaches the break stretch; metals when the
  permanent elongation of the gauge length reaches the elongation after fracture A (so a
  simulated test reproduces the material's A on this specimen's gauge length). After the
  break the force is 0, both halves unload elastically, the half in the fixed grip keeps its
  clamp edge, the half in the moving grip follows the crosshead, and a gap opens at the
  fracture (drawn as a sliver of vanishing width, so nothing is seen there).

Unloading before the break (the crosshead moving back) follows the elastic path from the state
at the largest displacement reached; a crosshead below the fully unloaded length leaves the
specimen slack (it would buckle out of plane): no force, drawn uniformly shortened.

Integrals (1) and (2) use a piecewise-uniform grid whose pieces end at the outline's
breakpoints and at the fracture position, with a fourth-order (cubic) rule within each piece.
The force is solved to about 1e-12 of the grip distance in displacement.

What this model does not capture: the transverse non-uniformity of stress in the shoulders
(a two-dimensional effect), triaxiality in the neck, slip in the grips, rate effects, the
Mullins softening of filled rubbers, yield-point phenomena of steels.
"""

from __future__ import annotations

import enum
import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy import sparse
from scipy.interpolate import PchipInterpolator
from scipy.optimize import brentq

from appliance.sim.deformation import AxialDeformation
from appliance.sim.materials import ElasticPlastic, Material
from appliance.sim.specimen import Specimen

FloatArray = npt.NDArray[np.float64]

_GAP_SLIVER_STRETCH = 1e-6
_SLIVER_MM = 1e-6
_MINIMUM_GAP_MM = 1e-3


class BarPhase(enum.Enum):
    """Which branch of the response a state lies on."""

    SLACK = "slack"
    LOADING = "loading"
    NECKING = "necking"
    UNLOADING = "unloading"
    BROKEN = "broken"


@dataclass(frozen=True)
class BarState:
    """The specimen at one crosshead position.

    Attributes:
        crosshead_mm: crosshead displacement d from the start, mm (positive = opening).
        max_crosshead_mm: largest displacement reached so far, mm (sets plastic strain and
            break).
        force_n: axial force, N (0 when slack or broken).
        phase: the branch of the response.
        deformation: the shape, for rendering and for truth positions of material points.
        stretch: (n,) axial stretch lambda at the bar's grid `BarModel.material_y_mm`.
        plastic_strain: (n,) true plastic strain at the same grid.
    """

    crosshead_mm: float
    max_crosshead_mm: float
    force_n: float
    phase: BarPhase
    deformation: AxialDeformation
    stretch: FloatArray
    plastic_strain: FloatArray

    @property
    def broken(self) -> bool:
        """The specimen has broken."""
        return self.phase is BarPhase.BROKEN

    def spatial_y(self, Y: npt.ArrayLike) -> FloatArray:
        """Current axial positions, mm, of material sections Y, mm."""
        return self.deformation.spatial_y(Y)

    def gauge_strain(self, Y1: float, Y2: float) -> float:
        """Engineering strain between the material sections Y1 and Y2 (the extensometer truth).

        (y(Y2) - y(Y1)) / (Y2 - Y1) - 1; across a fracture it includes the gap.
        """
        if Y1 == Y2:
            raise ValueError("gauge marks must differ")
        y1, y2 = self.deformation.spatial_y([Y1, Y2])
        return float((y2 - y1) / (Y2 - Y1) - 1.0)


@dataclass(frozen=True)
class _Solution:
    displacement_mm: float
    force_n: float
    stretch: FloatArray
    lateral: FloatArray
    plastic: FloatArray


def _piece_nodes(start: float, stop: float, spacing: float) -> FloatArray:
    if stop <= 0.0:
        return -_piece_nodes(-stop, -start, spacing)[::-1]
    intervals = max(3, math.ceil((stop - start) / spacing - 1e-9))
    return np.linspace(start, stop, intervals + 1)


def _interval_rule(nodes: int) -> list[tuple[list[int], list[float]]]:
    intervals = nodes - 1
    if intervals == 1:
        return [([0, 1], [0.5, 0.5])]
    if intervals == 2:
        return [([0, 1, 2], [5 / 12, 8 / 12, -1 / 12]), ([0, 1, 2], [-1 / 12, 8 / 12, 5 / 12])]
    rule = [([0, 1, 2, 3], [9 / 24, 19 / 24, -5 / 24, 1 / 24])]
    for j in range(1, intervals - 1):
        rule.append(([j - 1, j, j + 1, j + 2], [-1 / 24, 13 / 24, 13 / 24, -1 / 24]))
    last = intervals - 1
    rule.append(([last - 2, last - 1, last, last + 1], [1 / 24, -5 / 24, 19 / 24, 9 / 24]))
    return rule


class _AxialGrid:
    """Piecewise-uniform nodes over [-G/2, G/2] and a cubic quadrature over each interval."""

    def __init__(self, breakpoints: list[float], points: int) -> None:
        span = breakpoints[-1] - breakpoints[0]
        spacing = span / (points - 1)
        pieces = [
            _piece_nodes(a, b, spacing)
            for a, b in zip(breakpoints[:-1], breakpoints[1:], strict=True)
        ]
        rows, cols, values = [], [], []
        offset = 0
        interval = 0
        nodes = [pieces[0][:1]]
        for piece in pieces:
            h = piece[1] - piece[0]
            for columns, weights in _interval_rule(piece.size):
                rows.extend([interval] * len(columns))
                cols.extend(offset + c for c in columns)
                values.extend(h * w for w in weights)
                interval += 1
            nodes.append(piece[1:])
            offset += piece.size - 1
        self.y = np.concatenate(nodes)
        self.intervals = sparse.csr_matrix(
            (values, (rows, cols)), shape=(self.y.size - 1, self.y.size)
        )
        self.weights = np.asarray(self.intervals.sum(axis=0)).ravel()

    def cumulative(self, values: FloatArray) -> FloatArray:
        """Integral of `values` from the first node to each node."""
        return np.concatenate([[0.0], np.cumsum(self.intervals @ values)])


def _illinois(
    func: Callable[[float], tuple[float, _Solution]],
    target: float,
    lo: float,
    hi: float,
    f_lo: float,
    f_hi: float,
    guess: float,
    tolerance: float,
) -> _Solution:
    """Root of the increasing func(x) = target in [lo, hi] by the Illinois method."""
    f_lo -= target
    f_hi -= target
    x = min(max(guess, lo), hi)
    side = 0
    for _ in range(100):
        value, solution = func(x)
        residual = value - target
        if abs(residual) <= tolerance or hi - lo <= 4 * np.spacing(max(abs(lo), abs(hi))):
            return solution
        if residual < 0:
            lo, f_lo = x, residual
            if side == -1:
                f_hi *= 0.5
            side = -1
        else:
            hi, f_hi = x, residual
            if side == 1:
                f_lo *= 0.5
            side = 1
        x = lo - f_lo * (hi - lo) / (f_hi - f_lo) if f_hi != f_lo else 0.5 * (lo + hi)
        if not lo < x < hi:
            x = 0.5 * (lo + hi)
    return solution


class BarModel:
    """A specimen of a material in a tensile test, as a one-dimensional bar.

    Args:
        specimen: the test piece.
        material: its material (`NeoHookean`, `MooneyRivlin` or `ElasticPlastic`).
        fracture_position_mm: material Y of the fracture, and of the neck centre of a necking
            material, mm. Off the centre by default, so a break is not symmetric about the
            gauge marks.
        neck_width_mm: full width at half maximum of the neck's plastic strain, mm; the
            parallel width by default.
        axial_points: about how many grid nodes span the grip distance.

    Raises:
        ValueError: the fracture (with the neck around it) does not lie in the parallel section,
            or fewer than 101 axial points.
    """

    def __init__(
        self,
        specimen: Specimen,
        material: Material,
        *,
        fracture_position_mm: float = 3.0,
        neck_width_mm: float | None = None,
        axial_points: int = 2001,
    ) -> None:
        if axial_points < 101:
            raise ValueError(f"axial_points must be >= 101, got {axial_points}")
        self.specimen = specimen
        self.material = material
        self.fracture_position_mm = float(fracture_position_mm)
        self.neck_width_mm = float(
            specimen.parallel_width_mm if neck_width_mm is None else neck_width_mm
        )
        if not self.neck_width_mm > 0:
            raise ValueError(f"neck_width_mm must be positive, got {self.neck_width_mm}")
        reach = 2.0 * self.neck_width_mm if material.necks else 0.0
        if abs(self.fracture_position_mm) + reach >= 0.5 * specimen.parallel_length_mm:
            raise ValueError(
                f"fracture_position_mm ({self.fracture_position_mm}) must lie in the parallel "
                f"section with {reach} mm to spare (half the parallel length is "
                f"{0.5 * specimen.parallel_length_mm} mm)"
            )

        half_grip = 0.5 * specimen.grip_distance_mm
        positive = [p for p in specimen.breakpoints_mm() if p < half_grip - 1e-9] + [half_grip]
        breakpoints = sorted({*(-p for p in positive), *positive, self.fracture_position_mm})
        self._grid = _AxialGrid(breakpoints, axial_points)
        grid = self._grid.y
        mirrored = np.abs(grid)
        self._grip_distance = specimen.grip_distance_mm
        self._half_width = specimen.half_width_mm(mirrored)
        self._area = specimen.cross_section_mm2(mirrored)
        self._sections, self._section_index = np.unique(self._area, return_inverse=True)
        self._parallel_area = float(self._sections[0])
        self._parallel_section = self._sections == self._parallel_area
        self._fracture_node = int(np.argmin(np.abs(grid - self.fracture_position_mm)))
        self._tolerance_mm = 1e-12 * specimen.grip_distance_mm

        if material.necks:
            self._peak_stretch = material.stretch_at_peak
        else:
            self._peak_stretch = material.break_stretch
        self._loading_stretch = np.unique(
            np.concatenate(
                [np.linspace(1.0, self._peak_stretch, 400), self._yield_stretches(material)]
            )
        )
        self._loading_displacement = np.array([self._loading(s)[0] for s in self._loading_stretch])
        self._loading_guess = PchipInterpolator(self._loading_displacement, self._loading_stretch)
        self._peak = self._loading(self._peak_stretch)[1]
        self.peak_force_n = self._peak.force_n
        self.peak_crosshead_mm = self._peak.displacement_mm

        if material.necks:
            sigma = 0.5 * self.neck_width_mm / math.sqrt(2.0 * math.log(2.0))
            self._neck_shape = np.exp(-0.5 * ((grid - self.fracture_position_mm) / sigma) ** 2)
            self._fracture_neck = self._neck_at_fracture(material, sigma)
            self._neck_amplitude = np.linspace(0.0, self._fracture_neck, 200)
            self._neck_displacement = np.array([self._necking(a)[0] for a in self._neck_amplitude])
            self._neck_guess = PchipInterpolator(self._neck_displacement, self._neck_amplitude)
            self._fracture = self._necking(self._fracture_neck)[1]
        else:
            self._fracture = self._peak
        self.breaking_crosshead_mm = self._fracture.displacement_mm
        self.breaking_force_n = self._fracture.force_n

        self._state_cache = functools.lru_cache(maxsize=64)(self._compute_state)
        self._plastic_cache = functools.lru_cache(maxsize=8)(self._solve_monotone)

    @staticmethod
    def _yield_stretches(material: Material) -> FloatArray:
        if isinstance(material, ElasticPlastic):
            sigma = material.initial_yield_stress_mpa
            return np.array([math.exp(sigma / material.youngs_modulus_mpa)])
        return np.empty(0)

    @property
    def material_y_mm(self) -> FloatArray:
        """(n,) material Y of the grid nodes, mm, from -G/2 to G/2."""
        return self._grid.y

    @property
    def half_width_mm(self) -> FloatArray:
        """(n,) undeformed half-width at the grid nodes, mm."""
        return self._half_width

    @property
    def area_mm2(self) -> FloatArray:
        """(n,) undeformed cross-section at the grid nodes, mm^2."""
        return self._area

    def _loading(self, parallel_stretch: float) -> tuple[float, _Solution]:
        material = self.material
        force = float(material.nominal_stress_mpa(parallel_stretch)) * self._parallel_area
        section_stretch, section_lateral, section_plastic = material.loading_state(
            force / self._sections
        )
        section_stretch[self._parallel_section] = parallel_stretch
        stretch = section_stretch[self._section_index]
        lateral = section_lateral[self._section_index]
        plastic = section_plastic[self._section_index]
        displacement = float(self._grid.weights @ stretch) - self._grip_distance
        return displacement, _Solution(displacement, force, stretch, lateral, plastic)

    def _necking(self, amplitude: float) -> tuple[float, _Solution]:
        material = self.material
        centre_strain = material.uniform_plastic_strain + amplitude
        force = float(material.flow_nominal_stress_mpa(centre_strain)) * self._parallel_area
        plastic = self._peak.plastic + amplitude * self._neck_shape
        stretch, lateral = material.elastic_state(plastic, force / self._area)
        displacement = float(self._grid.weights @ stretch) - self._grip_distance
        return displacement, _Solution(displacement, force, stretch, lateral, plastic)

    def _neck_at_fracture(self, material: ElasticPlastic, sigma: float) -> float:
        half_gauge = 0.5 * self.specimen.gauge_length_mm
        nodes, weights = np.polynomial.legendre.leggauss(400)
        Y = half_gauge * nodes
        shape = np.exp(-0.5 * ((Y - self.fracture_position_mm) / sigma) ** 2)
        uniform = material.uniform_plastic_strain
        target = material.elongation_after_fracture * self.specimen.gauge_length_mm

        def permanent_elongation(amplitude: float) -> float:
            return half_gauge * float(weights @ (np.exp(uniform + amplitude * shape) - 1.0))

        return brentq(lambda a: permanent_elongation(a) - target, 0.0, 50.0, xtol=1e-14)

    def _solve_monotone(self, displacement: float) -> _Solution:
        """The state at displacement d under monotone loading to d (loading or necking): the
        branch's tabulated displacements bracket it, their monotone cubic (PCHIP) inverse
        guesses it (about two evaluations of the branch per solve where linear interpolation
        took four), and the Illinois method solves it to the tolerance."""
        if displacement <= 0.0:
            return self._loading(1.0)[1]
        if displacement <= self.peak_crosshead_mm:
            x, f = self._loading_stretch, self._loading_displacement
            func, inverse = self._loading, self._loading_guess
        else:
            x, f = self._neck_amplitude, self._neck_displacement
            func, inverse = self._necking, self._neck_guess
        j = int(np.clip(np.searchsorted(f, displacement) - 1, 0, f.size - 2))
        guess = float(inverse(displacement))
        return _illinois(
            func, displacement, x[j], x[j + 1], f[j], f[j + 1], guess, self._tolerance_mm
        )

    def _elastic(self, plastic: FloatArray, force: float) -> tuple[float, _Solution]:
        stretch, lateral = self.material.elastic_state(plastic, force / self._area)
        displacement = float(self._grid.weights @ stretch) - self._grip_distance
        return displacement, _Solution(displacement, force, stretch, lateral, plastic)

    def _table(self, solution: _Solution, displacement: float, broken: bool) -> AxialDeformation:
        grid = self._grid.y
        along = self._grid.cumulative(solution.stretch)
        half = 0.5 * self._grip_distance
        if not broken:
            spatial = half - (along[-1] - along)
            return AxialDeformation(grid, spatial, solution.lateral, self._half_width)
        k = self._fracture_node
        moving = -half - displacement + along[: k + 1]
        fixed = half - (along[-1] - along[k:])
        shift = min(0.0, fixed[0] - moving[-1] - _MINIMUM_GAP_MM)
        moving = moving + shift
        faces = np.array([moving[-1], moving[-1] + _SLIVER_MM, fixed[0] - _SLIVER_MM, fixed[0]])
        Y_faces = grid[k] + _SLIVER_MM * np.array([-1.0, -0.5, 0.5, 1.0])
        lateral_faces = solution.lateral[k] * np.array(
            [1.0, _GAP_SLIVER_STRETCH, _GAP_SLIVER_STRETCH, 1.0]
        )
        return AxialDeformation(
            np.concatenate([grid[:k], Y_faces, grid[k + 1 :]]),
            np.concatenate([moving[:-1], faces, fixed[1:]]),
            np.concatenate([solution.lateral[:k], lateral_faces, solution.lateral[k + 1 :]]),
            np.concatenate(
                [self._half_width[:k], np.full(4, self._half_width[k]), self._half_width[k + 1 :]]
            ),
        )

    def _compute_state(self, displacement: float, max_displacement: float) -> BarState:
        grip = self._grip_distance
        if displacement <= -grip:
            raise ValueError(f"crosshead {displacement} mm closes the grips (distance {grip} mm)")
        if max_displacement > self.breaking_crosshead_mm:
            solution = self._elastic(self._fracture.plastic, 0.0)[1]
            deformation = self._table(solution, displacement, broken=True)
            return self._state(
                displacement, max_displacement, 0.0, BarPhase.BROKEN, deformation, solution
            )
        necking = self.material.necks and max_displacement > self.peak_crosshead_mm
        phase = BarPhase.NECKING if necking else BarPhase.LOADING
        reached = self._plastic_cache(max(max_displacement, 0.0))
        if displacement == max_displacement and displacement >= 0.0:
            return self._loaded_state(displacement, max_displacement, phase, reached)

        unloaded_displacement, unloaded = self._elastic(reached.plastic, 0.0)
        if displacement <= unloaded_displacement:
            scale = (grip + displacement) / (grip + unloaded_displacement)
            slack = _Solution(
                displacement, 0.0, unloaded.stretch * scale, unloaded.lateral, unloaded.plastic
            )
            return self._loaded_state(displacement, max_displacement, BarPhase.SLACK, slack)
        if self.material.necks:
            solution = _illinois(
                lambda force: self._elastic(reached.plastic, force),
                displacement,
                0.0,
                reached.force_n,
                unloaded_displacement,
                reached.displacement_mm,
                reached.force_n
                * (displacement - unloaded_displacement)
                / (reached.displacement_mm - unloaded_displacement),
                self._tolerance_mm,
            )
        else:
            solution = self._solve_monotone(displacement)
        return self._loaded_state(displacement, max_displacement, BarPhase.UNLOADING, solution)

    def _loaded_state(
        self, displacement: float, max_displacement: float, phase: BarPhase, solution: _Solution
    ) -> BarState:
        deformation = self._table(solution, displacement, broken=False)
        return self._state(
            displacement, max_displacement, solution.force_n, phase, deformation, solution
        )

    @staticmethod
    def _state(
        displacement: float,
        max_displacement: float,
        force: float,
        phase: BarPhase,
        deformation: AxialDeformation,
        solution: _Solution,
    ) -> BarState:
        stretch = solution.stretch.copy()
        plastic = solution.plastic.copy()
        stretch.setflags(write=False)
        plastic.setflags(write=False)
        return BarState(
            crosshead_mm=displacement,
            max_crosshead_mm=max_displacement,
            force_n=force,
            phase=phase,
            deformation=deformation,
            stretch=stretch,
            plastic_strain=plastic,
        )

    def deformation(
        self, crosshead_mm: float, *, max_crosshead_mm: float | None = None
    ) -> BarState:
        """The specimen at crosshead displacement d: force, shape and stretch tables.

        Args:
            crosshead_mm: crosshead displacement d from the start, mm (positive = opening).
            max_crosshead_mm: the largest displacement reached so far, mm; d by default (a
                monotone test). It decides plastic strain and break; a value below d is
                taken as d.

        Returns:
            The state (cached: repeated calls with the same arguments are free).

        Raises:
            ValueError: d <= -G (the grips would meet).
        """
        displacement = float(crosshead_mm)
        reached = displacement if max_crosshead_mm is None else float(max_crosshead_mm)
        return self._state_cache(displacement, max(reached, displacement))

    def force_n(self, crosshead_mm: float, *, max_crosshead_mm: float | None = None) -> float:
        """Axial force, N, at crosshead displacement d, mm; see `deformation`."""
        return self.deformation(crosshead_mm, max_crosshead_mm=max_crosshead_mm).force_n

    def spatial_y(
        self, Y: npt.ArrayLike, crosshead_mm: float, *, max_crosshead_mm: float | None = None
    ) -> FloatArray:
        """Current axial positions, mm, of material sections Y at displacement d, mm."""
        state = self.deformation(crosshead_mm, max_crosshead_mm=max_crosshead_mm)
        return state.spatial_y(Y)

    def gauge_strain(
        self,
        Y1: float,
        Y2: float,
        crosshead_mm: float,
        *,
        max_crosshead_mm: float | None = None,
    ) -> float:
        """Engineering strain between material sections Y1 and Y2 at displacement d, mm."""
        state = self.deformation(crosshead_mm, max_crosshead_mm=max_crosshead_mm)
        return state.gauge_strain(Y1, Y2)

    def crosshead_for_gauge_strain(self, Y1: float, Y2: float, strain: float) -> float:
        """Crosshead displacement, mm, at which the strain between Y1 and Y2 reaches `strain`.

        Monotone loading from the start; the first such displacement. If the specimen breaks
        first, the breaking displacement.

        Args:
            Y1, Y2: material positions of the gauge marks, mm.
            strain: engineering strain to reach, >= 0.
        """
        if strain <= 0.0:
            return 0.0

        def excess(displacement: float) -> float:
            return self.deformation(displacement).gauge_strain(Y1, Y2) - strain

        ends = [0.0, self.peak_crosshead_mm, self.breaking_crosshead_mm]
        for lo, hi in zip(ends[:-1], ends[1:], strict=True):
            if hi > lo and excess(hi) >= 0.0:
                return brentq(excess, lo, hi, xtol=1e-12)
        return self.breaking_crosshead_mm
