"""The exact sequential lens tracer (Dr.Jit, vectorised over rays, any float type/backend).

:class:`LensTracer` turns a :class:`~mi_neurallens.optics.prescription.Lens` and a path type into
straight-line Dr.Jit code: the path's steps are unrolled at trace time and every surface constant
is a Python float, so one kernel per (lens, path) is generated and cached by Dr.Jit.  With a
:class:`~mi_neurallens.trace.parameters.LiveGeometry` the surfaces' curvatures, conics, aspheric
coefficients and vertex positions are kernel inputs instead (one kernel for every value they take, and
differentiable in them: the ``realistic_lens`` parameters of ``mi.traverse``).

Inputs and outputs are in lens space (mm, +z toward the sensor) as component tuples.  A ray is
*valid* when it passes every clear aperture, housing and the stop, never undergoes total internal
reflection on a transmit step, always meets each surface from the side the path says, and reaches
the output plane.  Throughput is the product of the Fresnel factors (T = 1 − R for transmissions,
R for reflections) at the ray's own wavelength; radiance scaling by n² is not applied (object and
image spaces are both air for camera lenses).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import drjit as dr

from .interactions import interface_reflectance, reflect, refract
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


def _media_indices(lam_nm):
    """``n_of(m)``: (n, 1/n) of medium ``m`` at each ray's wavelength ``lam_nm`` (nm), computed once per trace."""
    media_n: dict = {}

    def n_of(m):
        if m not in media_n:
            n = m.coefficients[0] if m.is_constant else m.dr_index(lam_nm)
            media_n[m] = (n, 1.0 / n)
        return media_n[m]
    return n_of


class _Rays:
    """The rays of one trace as they go through the path's steps (component tuples, lens space, mm): position,
    direction, validity and Fresnel throughput ``T`` (None until a factor comes), with ``record`` the points passed
    and the validity at each, and the stop-plane crossings.  With ``margin``, the aperture bookkeeping: ``soft`` =
    alive as far as non-aperture failures go; ``m`` = smallest aperture margin met while soft (later values of a
    failed ray are meaningless and ignored); ``hard`` = failed for a non-aperture reason while every aperture so
    far was passed."""

    def __init__(self, o, d, active, record: bool, margin: bool):
        x, y, z = o
        self.x, self.y, self.z = x, y, z
        self.dx, self.dy, self.dz = d
        self.record, self.margin = record, margin
        valid = dr.full(dr.mask_t(x), True, dr.width(x)) & active
        self.valid = valid
        self.T = None
        self.pts = [(x, y, z)] if record else None
        self.stop_points = []
        self.alive = [valid] if record else None
        self.soft = valid if margin else None
        self.m = dr.full(type(x), 1e3, dr.width(x)) if margin else None
        self.hard = ~valid if margin else None

    def note(self, m_k):
        """An aperture's margin ``m_k`` met: the smallest so far, where the rays are still soft."""
        self.m = dr.select(self.soft, dr.minimum(self.m, m_k), self.m)

    def fail(self, ok):
        """A non-aperture condition ``ok``: rays failing it while every aperture so far was passed fail hard."""
        self.hard = self.hard | (self.soft & ~ok & (self.m >= 0.0))
        self.soft = self.soft & ok


class LensTracer:
    """Exact tracer of one lens.  Cheap to construct; kernels are cached by Dr.Jit per path.

    Parameters
    ----------
    lens: the prescription.
    fresnel: multiply throughput by the Fresnel factors (and coatings).  ``False``: purely
        geometric throughput (1 for every valid ray).
    geometry: a :class:`~mi_neurallens.trace.parameters.LiveGeometry` of ``lens``: its live numbers are
        kernel inputs (and carry gradients); None: every number is a literal.
    """

    def __init__(self, lens, fresnel: bool = True, geometry=None):
        self.lens = lens
        self.fresnel = fresnel
        z = lens.vertex_z
        self.geometry = geometry
        live = geometry.surfaces() if geometry is not None else [None] * len(lens.surfaces)
        self.geom = [SurfaceGeometry(s, z[i], live[i]) for i, s in enumerate(lens.surfaces)]
        #: the sensor plane (lens space, mm): a literal, or the live geometry's attached value
        self.image_z = lens.image_z if geometry is None else geometry.image_z
        #: the aperture stop's shape (the lens's stop surface; its radius the live geometry's where it has one)
        self.iris = Iris.of_lens(lens)
        if geometry is not None and geometry.stop_radius is not None:
            self.iris = dataclasses.replace(self.iris, radius_mm=geometry.stop_radius)
        self._paths: dict = {}

    def kernel_inputs(self) -> list:
        """The Dr.Jit arrays of width 1 its kernels read (a live geometry's vertex positions, curvatures, conics,
        aspheric coefficients, sensor plane and stop radius; none where every number is a literal): what a frozen
        function (``dr.freeze``) recording a trace must be handed as inputs."""
        out = []
        for g in self.geom:
            for v in (g.z, g.c, g.k) + tuple(g.asph):
                if dr.is_array_v(v):
                    out.append(v)
        for v in (self.image_z, self.iris.radius_mm):
            if dr.is_array_v(v):
                out.append(v)
        return out

    def path(self, path="transmit", direction: str = FORWARD) -> PathSpec:
        if isinstance(path, PathSpec):
            return resolve_path(self.lens, path, direction)
        key = (path, direction)
        if key not in self._paths:
            self._paths[key] = resolve_path(self.lens, path, direction)
        return self._paths[key]

    def default_output_z(self, direction: str) -> float:
        """Forward: the image plane.  Backward: the plane of the first vertex (z = 0)."""
        return self.image_z if direction == FORWARD else 0.0

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

        The path's steps are unrolled here, in Python: each one records the same Dr.Jit operations, in the
        same order, into the one kernel of this (lens, path) — move to the surface (:meth:`_advance`), the
        stop (:meth:`_stop`) or the clear aperture (:meth:`_clear_aperture`), the incidence
        (:meth:`_incidence`), then refraction or reflection with its Fresnel factor (:meth:`_interact`).
        """
        spec = self.path(path, direction)
        if self.geometry is not None and self.geometry._packed() is not None:
            self._widen(max(dr.width(o[0]), dr.width(d[0])))
        n_of = _media_indices(lam_nm)
        w = _Rays(o, d, active, record, margin)
        for si, step in enumerate(spec.steps):
            g = self.geom[step.surface]
            self._advance(w, g, step, si)
            if step.kind == "stop":
                self._stop(w)
                continue
            self._clear_aperture(w, step.clear_radius)
            normal, cos_i = self._incidence(w, g, step.heading)
            self._interact(w, step, normal, cos_i, n_of, lam_nm)
        return self._to_output(w, direction, z_out)

    def _widen(self, n: int):
        """A live geometry with gradients: its values read per ray from the packed array (one scatter-add kernel
        in the reverse pass, :class:`~mi_neurallens.trace.parameters.Packed`) for a trace of ``n`` rays."""
        live = self.geometry.surfaces(n)
        z = self.lens.vertex_z
        self.geom = [SurfaceGeometry(s, z[i], live[i]) for i, s in enumerate(self.lens.surfaces)]
        if self.geometry.stop_radius is not None:
            self.iris = dataclasses.replace(self.iris, radius_mm=self.geometry.wide("stop_radius", n))

    @staticmethod
    def _advance(w, g, step, si):
        """Move the rays ``w`` to the surface of ``step`` (geometry ``g``); rays that miss it, or (after the first
        step) would go backward to meet it, fail."""
        t, ok = g.intersect((w.x, w.y, w.z), (w.dx, w.dy, w.dz), step.heading)
        w.valid = w.valid & ok
        if si > 0:
            w.valid = w.valid & (t > 0.0)
        if w.margin:
            w.fail(ok & (t > 0.0) if si > 0 else ok)
        w.x, w.y, w.z = dr.fma(t, w.dx, w.x), dr.fma(t, w.dy, w.y), dr.fma(t, w.dz, w.z)
        if w.record:
            w.pts.append((w.x, w.y, w.z))
            w.alive.append(w.valid)

    def _stop(self, w):
        """The rays ``w`` on the stop plane: their crossing kept (:attr:`TraceResult.stop_points`), the iris's
        test (round or bladed) applied."""
        w.stop_points.append((w.x, w.y))
        w.valid = w.valid & self.iris.contains_dr(w.x, w.y)
        if w.margin:
            w.note(self.iris.margin_dr(w.x, w.y))

    @staticmethod
    def _clear_aperture(w, rad):
        """The rays ``w`` on a surface must lie within its clear radius ``rad`` (mm)."""
        w.valid = w.valid & (dr.fma(w.x, w.x, w.y * w.y) <= rad * rad)
        if w.margin:
            w.note(1.0 - dr.fma(w.x, w.x, w.y * w.y) / (rad * rad))

    @staticmethod
    def _incidence(w, g, h):
        """The surface normal at the rays ``w`` (geometry ``g``), facing rays of heading ``h``, and the cosine of
        incidence; rays that meet the surface from the wrong side fail."""
        nx, ny, nz = g.normal((w.x, w.y, w.z))
        if h < 0:
            nx, ny, nz = -nx, -ny, -nz
        cos_i = -(w.dx * nx + w.dy * ny + w.dz * nz)
        w.valid = w.valid & (cos_i > 0.0)
        if w.margin:
            w.fail(cos_i > 0.0)
        return (nx, ny, nz), cos_i

    def _interact(self, w, step, normal, cos_i, n_of, lam_nm):
        """Refract (``T``) or reflect (``R``) the rays ``w`` at the surface of ``step``, between its media, and
        multiply their throughput by the Fresnel factor (with ``fresnel``)."""
        surf = self.lens.surfaces[step.surface]
        m1, m2 = step.media
        same = m1 == m2
        (n1, _), (n2, inv_n2) = n_of(m1), n_of(m2)

        if step.kind == "T":
            if same:
                return  # a dummy surface between identical media: no bending, no loss
            eta = n1 * inv_n2
            (w.dx, w.dy, w.dz), cos_t, tir = refract((w.dx, w.dy, w.dz), normal, cos_i, eta)
            w.valid = w.valid & ~tir
            if w.margin:
                w.fail(~tir)
            if self.fresnel:
                R = interface_reflectance(surf.coating, m1, m2, n1, n2, cos_i, cos_t, lam_nm, lambda m: n_of(m)[0])
                w.T = (1.0 - R) if w.T is None else w.T * (1.0 - R)
        else:
            (w.dx, w.dy, w.dz) = reflect((w.dx, w.dy, w.dz), normal, cos_i)
            if same:
                w.T = w.x * 0.0
            elif self.fresnel:
                eta = n1 * inv_n2
                k = 1.0 - eta * eta * (1.0 - cos_i * cos_i)
                cos_t = dr.sqrt(dr.maximum(k, 0.0))
                R = dr.select(k < 0.0, 1.0, interface_reflectance(surf.coating, m1, m2, n1, n2, cos_i, cos_t, lam_nm,
                                                                  lambda m: n_of(m)[0]))
                w.T = R if w.T is None else w.T * R

    def _to_output(self, w, direction, z_out) -> TraceResult:
        """Continue the rays ``w`` to the output plane ``z_out`` (default :meth:`default_output_z`); rays heading
        away from it fail."""
        zo = self.default_output_z(direction) if z_out is None else z_out
        zo = float(zo) if isinstance(zo, (int, float)) else zo
        w.valid = w.valid & ((w.dz > 0.0) if direction == FORWARD else (w.dz < 0.0))
        if w.margin:
            w.fail((w.dz > 0.0) if direction == FORWARD else (w.dz < 0.0))
        t = (zo - w.z) / w.dz
        x, y = dr.fma(t, w.dx, w.x), dr.fma(t, w.dy, w.y)
        z = x * 0.0 + zo
        if w.record:
            w.pts.append((x, y, z))
            w.alive.append(w.valid)
        T = x * 0.0 + 1.0 if w.T is None else w.T
        if w.margin:
            return TraceResult((x, y, z), (w.dx, w.dy, w.dz), T, w.valid, w.pts, w.alive, w.m, w.hard,
                               w.stop_points)
        return TraceResult((x, y, z), (w.dx, w.dy, w.dz), T, w.valid, w.pts, w.alive, stop_points=w.stop_points)
