"""Flat dumb-bell tensile specimens: the undeformed outline of a simulated test piece.

Coordinates follow `appliance.sim.deformation`: material Y along the loading axis, origin at
the centre of the specimen, X across it; millimetres throughout.

The outline is symmetric about both axes. A parallel (narrow) section of width b and length
Lc joins each gripped end (tab) of width B through a transition (shoulder) made of circular
arcs:

* two arcs (rubber dumb-bells, ISO 37 Figure 2 and Table 2): an inside arc of radius R_i
  tangent to the parallel section and an outside arc of radius R_o tangent to the tab edge,
  tangent to each other. With rise h = (B - b) / 2 each arc turns through the angle theta,
  cos(theta) = 1 - h / (R_i + R_o), and the shoulder is (R_i + R_o) sin(theta) long;
* one arc (machined metal test pieces, ISO 6892-1 Annex B): the arc of radius R tangent to the
  parallel section meets the tab edge at a corner; the shoulder is sqrt(R^2 - (R - h)^2) long.

The grips clamp the tabs: the clamp edges sit at Y = +-L_g / 2, where L_g is the initial
distance between the grips, and must lie on the tabs.

Presets: `Specimen.iso37_type1`, `Specimen.iso37_type1a` (rubber), `Specimen.iso6892_flat`
(sheet metal).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Specimen:
    """A flat dumb-bell test piece in its undeformed state.

    Attributes:
        overall_length_mm: overall length of the test piece, mm.
        end_width_mm: width B of the gripped ends (tabs), mm.
        parallel_length_mm: length Lc of the parallel (narrow) section, mm.
        parallel_width_mm: width b of the parallel section, mm.
        transition_radius_mm: radius of the arc tangent to the parallel section (the inside
            radius of ISO 37, the transition radius of ISO 6892-1), mm.
        thickness_mm: thickness a of the parallel section (uniform over the piece here), mm.
        gauge_length_mm: original gauge length L0, centred on the specimen, mm.
        grip_distance_mm: initial distance L_g between the clamp edges, centred, mm.
        outer_radius_mm: radius of the arc tangent to the tab edge (the outside radius of
            ISO 37), mm; 0 for a single transition arc ending in a corner at the tab.
        name: what the piece is, for reports.

    Raises:
        ValueError: a dimension is not positive (the outer radius may be 0), the tabs are not
            wider than the parallel section, the arcs cannot span the shoulder rise, the
            outline does not fit in the overall length, the gauge length exceeds the parallel
            length, or a clamp edge lies off the tabs.
    """

    overall_length_mm: float
    end_width_mm: float
    parallel_length_mm: float
    parallel_width_mm: float
    transition_radius_mm: float
    thickness_mm: float
    gauge_length_mm: float
    grip_distance_mm: float
    outer_radius_mm: float = 0.0
    name: str = ""

    def __post_init__(self) -> None:
        positive = (
            "overall_length_mm",
            "end_width_mm",
            "parallel_length_mm",
            "parallel_width_mm",
            "transition_radius_mm",
            "thickness_mm",
            "gauge_length_mm",
            "grip_distance_mm",
        )
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"specimen {name} must be a positive number, got {value}")
        if not (math.isfinite(self.outer_radius_mm) and self.outer_radius_mm >= 0):
            raise ValueError(f"specimen outer_radius_mm must be >= 0, got {self.outer_radius_mm}")
        if self.end_width_mm <= self.parallel_width_mm:
            raise ValueError(
                f"specimen end_width_mm ({self.end_width_mm}) must exceed parallel_width_mm "
                f"({self.parallel_width_mm})"
            )
        rise = 0.5 * (self.end_width_mm - self.parallel_width_mm)
        radii = self.transition_radius_mm + self.outer_radius_mm
        if rise > radii:
            raise ValueError(
                f"specimen transition radii ({radii} mm in all) cannot span the shoulder rise "
                f"of {rise} mm"
            )
        if self.gauge_length_mm > self.parallel_length_mm:
            raise ValueError(
                f"specimen gauge_length_mm ({self.gauge_length_mm}) exceeds parallel_length_mm "
                f"({self.parallel_length_mm})"
            )
        tabs_apart = 2.0 * self.shoulder_end_mm
        if tabs_apart > self.overall_length_mm:
            raise ValueError(
                f"specimen outline needs {tabs_apart:.3f} mm between the tabs, more than "
                f"overall_length_mm ({self.overall_length_mm})"
            )
        if not (tabs_apart - 1e-9 <= self.grip_distance_mm <= self.overall_length_mm):
            raise ValueError(
                f"specimen grip_distance_mm ({self.grip_distance_mm}) must put the clamp edges "
                f"on the tabs: between {tabs_apart:.3f} and {self.overall_length_mm} mm"
            )

    @property
    def transition_angle_rad(self) -> float:
        """Angle theta, rad, through which each transition arc turns."""
        rise = 0.5 * (self.end_width_mm - self.parallel_width_mm)
        return math.acos(1.0 - rise / (self.transition_radius_mm + self.outer_radius_mm))

    @property
    def arc_joint_mm(self) -> float:
        """Axial position |Y|, mm, where the inside arc ends (joins the outside arc or the tab)."""
        angle = self.transition_angle_rad
        if self.outer_radius_mm == 0.0:
            rise = 0.5 * (self.end_width_mm - self.parallel_width_mm)
            radius = self.transition_radius_mm
            return 0.5 * self.parallel_length_mm + math.sqrt(
                max(radius**2 - (radius - rise) ** 2, 0.0)
            )
        return 0.5 * self.parallel_length_mm + self.transition_radius_mm * math.sin(angle)

    @property
    def shoulder_end_mm(self) -> float:
        """Axial position |Y|, mm, where the shoulder reaches the full tab width."""
        return self.arc_joint_mm + self.outer_radius_mm * math.sin(self.transition_angle_rad)

    @property
    def parallel_area_mm2(self) -> float:
        """Original cross-section S0 of the parallel section, mm^2."""
        return self.parallel_width_mm * self.thickness_mm

    @property
    def clamp_edges_mm(self) -> tuple[float, float]:
        """Material Y of the clamp edges, mm: (moving crosshead side, fixed side)."""
        return (-0.5 * self.grip_distance_mm, 0.5 * self.grip_distance_mm)

    @property
    def gauge_marks_mm(self) -> tuple[float, float]:
        """Material Y of the gauge marks, mm, centred on the specimen."""
        return (-0.5 * self.gauge_length_mm, 0.5 * self.gauge_length_mm)

    def breakpoints_mm(self) -> tuple[float, ...]:
        """Positive |Y|, mm, where the outline changes curve: parallel end, arc joint, tab."""
        points = [0.5 * self.parallel_length_mm, self.arc_joint_mm, self.shoulder_end_mm]
        return tuple(sorted(set(points)))

    def half_width_mm(self, Y: npt.ArrayLike) -> FloatArray:
        """Half of the undeformed width at material positions Y, mm (0 beyond the ends).

        Args:
            Y: material axial positions, mm, any shape.

        Returns:
            Half-widths, mm, of the shape of `Y`.
        """
        u = np.abs(np.asarray(Y, np.float64))
        half_parallel = 0.5 * self.parallel_width_mm
        half_end = 0.5 * self.end_width_mm
        start = 0.5 * self.parallel_length_mm
        joint = self.arc_joint_mm
        end = self.shoulder_end_mm
        r_in = self.transition_radius_mm
        r_out = self.outer_radius_mm
        inner = half_parallel + r_in - np.sqrt(np.maximum(r_in**2 - (u - start) ** 2, 0.0))
        width = np.where(u <= start, half_parallel, inner)
        if r_out > 0.0:
            outer = half_end - r_out + np.sqrt(np.maximum(r_out**2 - (end - u) ** 2, 0.0))
            width = np.where(u > joint, outer, width)
        width = np.where(u >= end, half_end, width)
        width = np.minimum(width, half_end)
        return np.where(u > 0.5 * self.overall_length_mm, 0.0, width)

    def cross_section_mm2(self, Y: npt.ArrayLike) -> FloatArray:
        """Undeformed cross-section area A0 at material positions Y, mm^2."""
        return 2.0 * self.half_width_mm(Y) * self.thickness_mm

    @classmethod
    def iso37_type1(cls, *, grip_distance_mm: float = 90.0) -> Specimen:
        """ISO 37 type 1 rubber dumb-bell.

        Dimensions from ISO 37:2017, Table 2 (die) and Table 1 (test length): overall length
        115 mm, ends 25 mm wide, narrow portion 33 mm long and 6.2 mm wide (6.0 mm in earlier
        editions), outside transition radius 14 mm, inside 25 mm, thickness 2.0 mm, test (gauge)
        length 25 mm. The narrow portion meets the tabs at |Y| = 41.9 mm.

        The standard does not fix the grip separation; 90 mm clamps 12.5 mm of each tab.
        """
        return cls(
            overall_length_mm=115.0,
            end_width_mm=25.0,
            parallel_length_mm=33.0,
            parallel_width_mm=6.2,
            transition_radius_mm=25.0,
            outer_radius_mm=14.0,
            thickness_mm=2.0,
            gauge_length_mm=25.0,
            grip_distance_mm=grip_distance_mm,
            name="ISO 37 type 1",
        )

    @classmethod
    def iso37_type1a(cls, *, grip_distance_mm: float = 76.0) -> Specimen:
        """ISO 37 type 1A rubber dumb-bell.

        Dimensions from ISO 37:2017, Table 2 (die) and Table 1 (test length): overall length
        100 mm, ends 25 mm wide, narrow portion 21 mm long and 5 mm wide, outside transition
        radius 11 mm, inside 25 mm, thickness 2.0 mm, test (gauge) length 20 mm. The narrow
        portion meets the tabs at |Y| = 35.4 mm.

        The standard does not fix the grip separation; 76 mm clamps 12 mm of each tab.
        """
        return cls(
            overall_length_mm=100.0,
            end_width_mm=25.0,
            parallel_length_mm=21.0,
            parallel_width_mm=5.0,
            transition_radius_mm=25.0,
            outer_radius_mm=11.0,
            thickness_mm=2.0,
            gauge_length_mm=20.0,
            grip_distance_mm=grip_distance_mm,
            name="ISO 37 type 1A",
        )

    @classmethod
    def iso6892_flat(cls, *, specimen_type: int = 1, thickness_mm: float = 2.0) -> Specimen:
        """ISO 6892-1 Annex B flat (sheet) test piece with shoulders.

        From ISO 6892-1:2019, Annex B, Table B.1 (non-proportional test pieces):

        * type 1: width b0 = 12.5 mm, gauge length L0 = 50 mm, parallel length Lc = 75 mm;
        * type 2: b0 = 20 mm, L0 = 80 mm, Lc = 120 mm.

        Annex B asks for a transition radius of at least 20 mm (20 mm here) and gripped ends
        wider than the parallel section (20 mm and 30 mm here). The grip separation (120 mm and
        170 mm) and overall length (200 mm and 250 mm) are free choices of this simulation.

        Args:
            specimen_type: 1 or 2, the row of Table B.1.
            thickness_mm: sheet thickness a0, mm (Annex B covers 0.1 mm to 3 mm).
        """
        if specimen_type == 1:
            return cls(
                overall_length_mm=200.0,
                end_width_mm=20.0,
                parallel_length_mm=75.0,
                parallel_width_mm=12.5,
                transition_radius_mm=20.0,
                thickness_mm=thickness_mm,
                gauge_length_mm=50.0,
                grip_distance_mm=120.0,
                name="ISO 6892-1 Annex B type 1",
            )
        if specimen_type == 2:
            return cls(
                overall_length_mm=250.0,
                end_width_mm=30.0,
                parallel_length_mm=120.0,
                parallel_width_mm=20.0,
                transition_radius_mm=20.0,
                thickness_mm=thickness_mm,
                gauge_length_mm=80.0,
                grip_distance_mm=170.0,
                name="ISO 6892-1 Annex B type 2",
            )
        raise ValueError(f"ISO 6892-1 Annex B specimen_type must be 1 or 2, got {specimen_type}")
