"""The iris: the aperture-stop shape, and the one test of whether a ray passes it.

The stop surface of a :class:`~mi_neurallens.optics.prescription.Lens` is a plane disk of radius
``semi_diameter`` (mm), or, with ``blades`` = n ≥ 3, the regular n-gon whose *inscribed* circle has that
radius, its first blade's normal at ``blade_rotation_deg`` from +x (counter-clockwise seen from the
sensor, lens space).  The exact tracer, the learned maps (which predict where a ray crosses the stop
plane and test the crossing here at render time) and the layout plot all use this one rule.

A polygon with inscribed radius R *contains* the disk of radius R and lies inside the disk of its
circumscribed radius R / cos(π/n).  A map that learned everything but the iris at the widest circular
opening R₀ (the stop-plane crossing included) reproduces exactly, on the predicted crossing, every iris
inside that disk: any smaller circle, and a polygon once its corners are inside it (R / cos(π/n) ≤ R₀,
i.e. at least 1/cos(π/n) times the widest f-number: 1.155× for 6 blades, 1.236× for 5).  Nearer wide
open the corners reach rays the map learned as blocked, so :meth:`Iris.within` says no and the learned
maps refuse that iris rather than render a polygon clipped by the circle.
"""
from __future__ import annotations

from dataclasses import dataclass
import math


@dataclass(frozen=True)
class Iris:
    """An aperture stop: ``radius_mm`` (inscribed radius for blades), ``blades`` (0: circle, else ≥ 3),
    ``rotation_deg`` (normal of the first blade, from +x)."""

    radius_mm: float
    blades: int = 0
    rotation_deg: float = 0.0

    @staticmethod
    def of_surface(stop) -> "Iris":
        """The iris of a stop :class:`~mi_neurallens.optics.prescription.Surface`."""
        return Iris(float(stop.semi_diameter), int(stop.blades or 0), float(stop.blade_rotation_deg or 0.0))

    @staticmethod
    def of_lens(lens) -> "Iris":
        return Iris.of_surface(lens.stop)

    def normals(self):
        """Unit normals (cos a, sin a) of the blades (empty for a circle)."""
        return [(math.cos(a), math.sin(a)) for a in
                (math.radians(self.rotation_deg) + 2.0 * math.pi * k / self.blades for k in range(self.blades))]

    def contains_dr(self, x, y):
        """Mask: the stop-plane point (x, y) (mm, lens space; any Dr.Jit float type) passes the iris."""
        import drjit as dr
        r = self.radius_mm
        if not self.blades:
            return dr.fma(x, x, y * y) <= r * r          # no square root on the hot path
        return self.edge_distance_dr(x, y) >= 0.0         # r − p ≥ 0 exactly where p ≤ r (IEEE subtraction)

    def margin_dr(self, x, y):
        """Aperture margin of (x, y): 1 − ρ²/R² for a circle, min over blades of 2·(1 − p/R) (p the
        distance along a blade's normal) for a polygon; ≥ 0 exactly where :meth:`contains_dr`."""
        import drjit as dr
        r = self.radius_mm
        if not self.blades:
            return 1.0 - dr.fma(x, x, y * y) / (r * r)
        m = None
        for c, s in self.normals():
            mk = 2.0 * (1.0 - dr.fma(x, c, y * s) / r)
            m = mk if m is None else dr.minimum(m, mk)
        return m

    def edge_distance_dr(self, x, y):
        """Signed distance (mm) of the stop-plane point (x, y) from the iris's edge, positive inside: R − ρ for a
        circle, min over blades of R − p (p the distance along a blade's normal; near a corner, the distance to
        the nearer blade's line) for a polygon; ≥ 0 exactly where :meth:`contains_dr`."""
        import drjit as dr
        r = self.radius_mm
        if not self.blades:
            return r - dr.sqrt(dr.fma(x, x, y * y))
        m = None
        for c, s in self.normals():
            mk = r - dr.fma(x, c, y * s)
            m = mk if m is None else dr.minimum(m, mk)
        return m

    def contains_np(self, x, y):
        """numpy twin of :meth:`contains_dr` for plots and tests (same rule)."""
        import numpy as np
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        if not self.blades:
            return x * x + y * y <= self.radius_mm ** 2
        ok = np.ones(np.broadcast(x, y).shape, bool)
        for c, s in self.normals():
            ok &= x * c + y * s <= self.radius_mm
        return ok

    @property
    def outer_radius_mm(self) -> float:
        """Radius of the smallest disk around the axis that holds the iris: the circle's radius, or the
        polygon's circumscribed radius R / cos(π/n)."""
        return self.radius_mm / math.cos(math.pi / self.blades) if self.blades else self.radius_mm

    def within(self, other: "Iris", rtol: float = 1e-9) -> bool:
        """True when this iris is a subset of the circular ``other``: its outer radius (a polygon's
        corners) is not larger than ``other``'s radius."""
        if other.blades:
            raise ValueError("Iris.within: the other iris must be circular")
        return self.outer_radius_mm <= other.radius_mm * (1.0 + rtol)

    def same_as(self, other: "Iris", rtol: float = 1e-9) -> bool:
        return (self.blades == other.blades and abs(self.radius_mm - other.radius_mm) <= rtol * other.radius_mm
                and (not self.blades or abs(self.rotation_deg - other.rotation_deg) < 1e-9))

    def describe(self) -> str:
        shape = "circle" if not self.blades else f"{self.blades} blades at {self.rotation_deg:g}°"
        return f"r = {self.radius_mm:.4g} mm, {shape}"
