"""Ray–surface intersection and normals, written for any Dr.Jit float type.

Every function works on vector *components* (tuples of Dr.Jit arrays) so the same code runs
in ``mi.Float`` (any Mitsuba variant, float32), ``Float64`` reference mode, LLVM or CUDA.
Surface constants are Python floats and become literals in the generated kernel, unless a
:class:`~mi_neurallens.trace.parameters.LiveGeometry` hands them in as Dr.Jit arrays of width 1 (kernel
inputs that may carry gradients; :mod:`mi_neurallens.trace.parameters`): then the code takes the general
branches (a live curvature of 0 is traced by the quadric formulas, which reduce to the plane's).

Frame: lens space, mm, +z toward the sensor (see :mod:`mi_neurallens.optics.prescription`).
"""
from __future__ import annotations

import drjit as dr

#: Newton iterations for even aspheres, started from the exact conic intersection.  The tests
#: (tests/test_tracer.py::test_asphere_newton_converges) check the sag residual after this many
#: iterations is below 1e-9 mm in float64 over the whole clear aperture of every bundled asphere.
ASPHERE_NEWTON_ITERATIONS = 4


def _zero(v) -> bool:
    """True for a Python number equal to 0 (a Dr.Jit array, a kernel input, is never taken as 0)."""
    return isinstance(v, (int, float)) and v == 0.0


class SurfaceGeometry:
    """The constants of one surface (vertex z, curvature, conic, aspheric): Python floats, or where ``live``
    gives them (a dict with any of ``"z"``, ``"c"``, ``"k"``, ``"asph"``), Dr.Jit arrays of width 1."""

    def __init__(self, surface, vertex_z: float, live: dict | None = None):
        live = live or {}
        self.z = live.get("z", float(vertex_z))
        self.c = live.get("c", float(surface.curvature))
        self.k = live.get("k", float(surface.conic))
        self.asph = tuple(live["asph"]) if "asph" in live else tuple(float(a) for a in surface.aspheric)
        while self.asph and _zero(self.asph[-1]):
            self.asph = self.asph[:-1]
        self.flat = _zero(self.c) and not self.asph

    # -------------------------------------------------------------------------------- sag
    def _sag_and_slope(self, s):
        """sag(s) and d sag/ds at s = r² (mm, 1/mm)."""
        c, k = self.c, self.k
        if not _zero(c):
            root = dr.sqrt(dr.maximum(1.0 - (1.0 + k) * c * c * s, 0.0))
            sag = c * s / (1.0 + root)
            dsag = c * 0.5 / root
        else:
            sag = s * 0.0
            dsag = s * 0.0
        if self.asph:
            # Horner in s for Σ A_{2i+4} s^{i+2} and its derivative Σ (i+2) A s^{i+1}
            p = 0.0
            dp = 0.0
            for i in reversed(range(len(self.asph))):
                a = self.asph[i]
                p = dr.fma(p, s, a) if not isinstance(p, float) else p * s + a
                dp = dr.fma(dp, s, (i + 2) * a) if not isinstance(dp, float) else dp * s + (i + 2) * a
            sag = sag + p * s * s
            dsag = dsag + dp * s
        return sag, dsag

    # -------------------------------------------------------------------------------- intersect
    def intersect(self, o, d, heading: int = 1):
        """Distance ``t`` along ``d`` from ``o`` to this surface, and a validity mask.

        ``o``/``d`` are (x, y, z) tuples.  ``heading`` (+1: the ray travels toward +z, −1: toward
        −z) picks the root: of the two intersections with the quadric, the one where the ray
        meets the surface from the side it is travelling from, i.e. ``F'(t) = 2 ∇F·d`` has the sign
        that makes the ray *enter* through the vertex sheet (this is independent of where the
        origin lies, e.g. inside the sphere).  Each root is written in the form that is stable for
        the usual sign of the half-linear coefficient for that heading.
        """
        ox, oy, oz = o
        dx, dy, dz = d
        pz = oz - self.z
        if _zero(self.c):
            t = -pz / dz
            ok = dz != 0.0
        else:
            c, ck = self.c, self.c * (1.0 + self.k)
            a = dr.fma(c, dx * dx + dy * dy, ck * dz * dz)
            hb = c * dr.fma(ox, dx, oy * dy) + dr.fma(ck * pz, dz, -dz)
            cc = dr.fma(c, ox * ox + oy * oy, dr.fma(ck * pz, pz, -2.0 * pz))
            disc = dr.fma(hb, hb, -a * cc)
            ok = disc >= 0.0
            sq = dr.sqrt(dr.maximum(disc, 0.0))
            # heading +1: t = (−hb − sq)/a = cc/(sq − hb); heading −1: t = (sq − hb)/a = −cc/(hb + sq)
            t = cc / (sq - hb) if heading > 0 else -cc / (hb + sq)
            # the vertex sheet: 1 - c(1+K) z' >= 0
            ok &= dr.fma(-ck, dr.fma(t, dz, pz), 1.0) >= 0.0
        if self.asph:
            for _ in range(ASPHERE_NEWTON_ITERATIONS):
                x = dr.fma(t, dx, ox)
                y = dr.fma(t, dy, oy)
                zr = dr.fma(t, dz, pz)
                s = x * x + y * y
                sag, dsag = self._sag_and_slope(s)
                f = zr - sag
                df = dz - dsag * 2.0 * dr.fma(x, dx, y * dy)
                t = t - f / df
        return t, ok

    def normal(self, p):
        """Unit normal at the surface point ``p`` (lens space), oriented toward −z (object side)."""
        x, y, z = p
        if self.flat:
            zero = x * 0.0
            return zero, zero, zero - 1.0
        if not self.asph:
            ck = self.c * (1.0 + self.k)
            nx, ny, nz = self.c * x, self.c * y, dr.fma(ck, z - self.z, -1.0)
            if _zero(self.k):
                # sphere: c·(p − centre) already has unit length on the surface
                return nx, ny, nz
        else:
            _, dsag = self._sag_and_slope(x * x + y * y)
            nx, ny, nz = 2.0 * dsag * x, 2.0 * dsag * y, x * 0.0 - 1.0
        inv = dr.rsqrt(dr.fma(nx, nx, dr.fma(ny, ny, nz * nz)))
        return nx * inv, ny * inv, nz * inv

    def residual(self, p):
        """z − vertex − sag(r) at ``p`` (mm): 0 on the surface (for tests of the solver)."""
        x, y, z = p
        sag, _ = self._sag_and_slope(x * x + y * y)
        return (z - self.z) - sag
