"""The exact sequential lens tracer (Dr.Jit, vectorised over rays, any float type/backend).

:class:`LensTracer` turns a :class:`~mi_neurallens.optics.prescription.Lens` and a path type into
straight-line Dr.Jit code: the path's steps are unrolled at trace time and every surface constant
is a Python float, so one kernel per (lens, path) is generated and cached by Dr.Jit.

Inputs and outputs are in lens space (mm, +z toward the sensor) as component tuples.  A ray is
*valid* when it passes every clear aperture, housing and the stop, never undergoes total internal
reflection on a transmit step, always meets each surface from the side the path says, and reaches
the output plane.  Throughput is the product of the Fresnel factors (T = 1 − R for transmissions,
R for reflections) at the ray's own wavelength; radiance scaling by n² is not applied (object and
image spaces are both air for camera lenses).
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr

from .interactions import coated_reflectance, fresnel_reflectance, reflect, refract
from .iris import Iris
from .paths import FORWARD, PathSpec, resolve_path
from .surfaces import SurfaceGeometry


@dataclass
class TraceResult:
    """Dr.Jit result of :meth:`LensTracer.trace` (component tuples, lens space, mm)."""

    position: tuple
    direction: tuple
    throughput: object
    valid: object
    points: list | None = None
    #: with ``record``: per point, whether the ray was still alive when it reached that point
    alive: list | None = None
    #: with ``margin``: the smallest aperture margin along the path, min over every clear aperture,
    #: housing and the stop of 1 − r²/R² (a polygonal stop: 2·(1 − p/R), p the distance along the
    #: blade's normal), dimensionless, ≥ 0 where all apertures are passed.  Smooth in the ray's
    #: inputs wherever one aperture is the closest, so its zero set is the aperture part of the
    #: validity boundary; used as a classifier training target.
    margin: object = None
    #: with ``margin``: True where the ray fails for a reason other than an aperture (misses a
    #: surface, total internal reflection, turns back) before any aperture blocks it;
    #: ``valid == ~hard_fail & (margin >= 0)``.
    hard_fail: object = None
    #: (x, y) where the ray crosses the stop plane (lens space, mm), one per stop step of the path in
    #: path order (the transmit path crosses once, a ghost one to three times); lazily evaluated, so
    #: free unless used
    stop_points: list | None = None


class LensTracer:
    """Exact tracer of one lens.  Cheap to construct; kernels are cached by Dr.Jit per path.

    Parameters
    ----------
    lens: the prescription.
    fresnel: multiply throughput by the Fresnel factors (and coatings).  ``False``: purely
        geometric throughput (1 for every valid ray).
    """

    def __init__(self, lens, fresnel: bool = True):
        self.lens = lens
        self.fresnel = fresnel
        z = lens.vertex_z
        self.geom = [SurfaceGeometry(s, z[i]) for i, s in enumerate(lens.surfaces)]
        #: the aperture stop's shape (the lens's stop surface)
        self.iris = Iris.of_lens(lens)
        self._paths: dict = {}

    def path(self, path="transmit", direction: str = FORWARD) -> PathSpec:
        if isinstance(path, PathSpec):
            return resolve_path(self.lens, path, direction)
        key = (path, direction)
        if key not in self._paths:
            self._paths[key] = resolve_path(self.lens, path, direction)
        return self._paths[key]

    def default_output_z(self, direction: str) -> float:
        """Forward: the image plane.  Backward: the plane of the first vertex (z = 0)."""
        return self.lens.image_z if direction == FORWARD else 0.0

    # ------------------------------------------------------------------------------ trace
    def trace(self, o, d, lam_nm, path="transmit", direction: str = FORWARD, *,
              z_out: float | None = None, record: bool = False, margin: bool = False,
              active=True) -> TraceResult:
        """Trace rays along one path type.

        ``o``, ``d``: (x, y, z) tuples of Dr.Jit float arrays, lens space, mm; ``d`` unit length.
        ``lam_nm``: wavelength per ray (nm), same float type (or a Python float).
        ``z_out``: output plane (default :meth:`default_output_z`).  Returns the ray where it
        crosses the output plane.  ``margin``: also return :attr:`TraceResult.margin` and
        :attr:`TraceResult.hard_fail`.
        """
        spec = self.path(path, direction)
        lens = self.lens
        media_n: dict = {}

        def n_of(m):
            """(n, 1/n) of medium ``m`` at each ray's wavelength, computed once per trace."""
            if m not in media_n:
                n = m.coefficients[0] if m.is_constant else m.dr_index(lam_nm)
                media_n[m] = (n, 1.0 / n)
            return media_n[m]

        x, y, z = o
        dx, dy, dz = d
        valid = dr.full(dr.mask_t(x), True, dr.width(x)) & active
        T = None
        pts = [(x, y, z)] if record else None
        stop_points = []
        alive = [valid] if record else None
        # margin mode: `soft` = alive as far as non-aperture failures go; `m` = smallest aperture
        # margin met while soft (later values of a failed ray are meaningless and ignored); `hard` =
        # failed for a non-aperture reason while every aperture so far was passed
        soft = valid if margin else None
        m = dr.full(type(x), 1e3, dr.width(x)) if margin else None
        hard = ~valid if margin else None

        def note(m_k):
            nonlocal m
            m = dr.select(soft, dr.minimum(m, m_k), m)

        def fail(ok):
            nonlocal soft, hard
            hard = hard | (soft & ~ok & (m >= 0.0))
            soft = soft & ok

        for si, step in enumerate(spec.steps):
            g = self.geom[step.surface]
            t, ok = g.intersect((x, y, z), (dx, dy, dz), step.heading)
            valid = valid & ok
            if si > 0:
                valid = valid & (t > 0.0)
            if margin:
                fail(ok & (t > 0.0) if si > 0 else ok)
            x, y, z = dr.fma(t, dx, x), dr.fma(t, dy, y), dr.fma(t, dz, z)
            if record:
                pts.append((x, y, z))
                alive.append(valid)
            if step.kind == "stop":
                stop_points.append((x, y))
                valid = valid & self.iris.contains_dr(x, y)
                if margin:
                    note(self.iris.margin_dr(x, y))
                continue
            rad = step.clear_radius
            valid = valid & (dr.fma(x, x, y * y) <= rad * rad)
            if margin:
                note(1.0 - dr.fma(x, x, y * y) / (rad * rad))

            h = step.heading
            nx, ny, nz = g.normal((x, y, z))
            if h < 0:
                nx, ny, nz = -nx, -ny, -nz
            cos_i = -(dx * nx + dy * ny + dz * nz)
            valid = valid & (cos_i > 0.0)
            if margin:
                fail(cos_i > 0.0)

            surf = lens.surfaces[step.surface]
            m1, m2 = step.media
            same = m1 == m2
            (n1, _), (n2, inv_n2) = n_of(m1), n_of(m2)

            if step.kind == "T":
                if same:
                    continue  # a dummy surface between identical media: no bending, no loss
                eta = n1 * inv_n2
                (dx, dy, dz), cos_t, tir = refract((dx, dy, dz), (nx, ny, nz), cos_i, eta)
                valid = valid & ~tir
                if margin:
                    fail(~tir)
                if self.fresnel:
                    R = self._reflectance(surf, n1, n2, cos_i, cos_t, lam_nm)
                    T = (1.0 - R) if T is None else T * (1.0 - R)
            else:
                (dx, dy, dz) = reflect((dx, dy, dz), (nx, ny, nz), cos_i)
                if same:
                    T = x * 0.0
                elif self.fresnel:
                    eta = n1 * inv_n2
                    k = 1.0 - eta * eta * (1.0 - cos_i * cos_i)
                    cos_t = dr.sqrt(dr.maximum(k, 0.0))
                    R = dr.select(k < 0.0, 1.0, self._reflectance(surf, n1, n2, cos_i, cos_t, lam_nm))
                    T = R if T is None else T * R

        # continue to the output plane
        zo = self.default_output_z(direction) if z_out is None else float(z_out)
        valid = valid & ((dz > 0.0) if direction == FORWARD else (dz < 0.0))
        if margin:
            fail((dz > 0.0) if direction == FORWARD else (dz < 0.0))
        t = (zo - z) / dz
        x, y = dr.fma(t, dx, x), dr.fma(t, dy, y)
        z = x * 0.0 + zo
        if record:
            pts.append((x, y, z))
            alive.append(valid)
        if T is None:
            T = x * 0.0 + 1.0
        if margin:
            return TraceResult((x, y, z), (dx, dy, dz), T, valid, pts, alive, m, hard, stop_points)
        return TraceResult((x, y, z), (dx, dy, dz), T, valid, pts, alive, stop_points=stop_points)

    @staticmethod
    def _reflectance(surf, n1, n2, cos_i, cos_t, lam_nm):
        if surf.coating is None:
            return fresnel_reflectance(n1, n2, cos_i, cos_t)
        c = surf.coating
        return coated_reflectance(n1, n2, cos_i, cos_t, lam_nm, c.index, c.thickness_nm)
