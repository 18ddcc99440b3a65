"""A prescription's geometry as named parameters: what ``mi.traverse`` exposes of a ``realistic_lens``, the
lens they describe, and the *live* geometry the tracer reads when they are kernel inputs.

Names (surface ``i`` numbered as in the first column of ``mi-neurallens lens info``, the stop included):

* ``surface_{i}_curvature`` — c = 1/R (1/mm), every surface but the stop;
* ``surface_{i}_conic`` — K, every surface but the stop;
* ``surface_{i}_asphere`` — the even coefficients A4, A6, … (mm^(1−2k)), surfaces that have them;
* ``surface_{i}_thickness`` — the gap after surface ``i`` to the next vertex (mm), every surface but the last:
  the last surface's gap is the sensor distance, which the sensors expose as ``sensor_distance``.

:func:`lens_with` turns values into a validated :class:`~mi_neurallens.optics.prescription.Lens` (a
:class:`~mi_neurallens.errors.LensError` names what is wrong: surfaces that cross, a rim beyond the sphere);
:func:`mi_neurallens.sensors.live.project_values` moves values back into the valid region.

:class:`LiveGeometry` is the tracer's view of a lens whose parameters are Dr.Jit arrays of width 1: the
surfaces' curvature, conic, aspheric coefficients and vertex positions become kernel inputs (the kernel does
not change when their values do, and gradients flow through them), everything else stays a literal.  Vertex
positions are written ``z_i = z_i⁰ + Σ_{j<i} (t_j − detach(t_j))``: the value of the float64 sum, the
derivative of the float32 thicknesses.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..errors import LensError

CURVATURE, CONIC, ASPHERE, THICKNESS = "curvature", "conic", "asphere", "thickness"
KINDS = (CURVATURE, THICKNESS, CONIC, ASPHERE)


def name(i: int, kind: str) -> str:
    """The parameter name of ``kind`` of surface ``i``: ``surface_{i}_{kind}``."""
    return f"surface_{i}_{kind}"


def parse(key: str):
    """``(i, kind)`` of a parameter name (the part after the last dot of a scene key), or None."""
    parts = key.rsplit(".", 1)[-1].split("_")
    if len(parts) == 3 and parts[0] == "surface" and parts[1].isdigit() and parts[2] in KINDS:
        return int(parts[1]), parts[2]
    return None


def parameter_names(lens) -> list[str]:
    """Every parameter of ``lens``, front to back (see the module docstring); the gaps its moving groups set
    (zoom, focusing: :mod:`mi_neurallens.optics.moving`) are not parameters."""
    out = []
    last = len(lens.surfaces) - 1
    moving = getattr(lens, "moving", None)
    variable = set(moving.gaps) if moving is not None else set()
    for i, s in enumerate(lens.surfaces):
        if not s.is_stop:
            out += [name(i, CURVATURE), name(i, CONIC)]
            if s.aspheric:
                out.append(name(i, ASPHERE))
        if i < last and i not in variable:
            out.append(name(i, THICKNESS))
    return out


def value_of(lens, key: str):
    """The value of one parameter of ``lens``: a float, or a tuple of floats for ``asphere``."""
    i, kind = parse(key)
    s = lens.surfaces[i]
    if kind == CURVATURE:
        return float(s.curvature)
    if kind == CONIC:
        return float(s.conic)
    if kind == ASPHERE:
        return tuple(float(a) for a in s.aspheric)
    return float(s.thickness)


def replaced_surfaces(lens, values: dict) -> list:
    """The surfaces of ``lens`` with the parameters ``values`` (name → float, or a sequence for ``asphere``)
    replaced, not validated (a curvature of 0 is a flat surface)."""
    surfs = list(lens.surfaces)
    for key, v in values.items():
        i, kind = parse(key)
        s = surfs[i]
        if kind == CURVATURE:
            surfs[i] = dataclasses.replace(s, radius=math.inf if float(v) == 0.0 else 1.0 / float(v))
        elif kind == CONIC:
            surfs[i] = dataclasses.replace(s, conic=float(v))
        elif kind == ASPHERE:
            surfs[i] = dataclasses.replace(s, aspheric=tuple(float(a) for a in np.ravel(v)))
        else:
            surfs[i] = dataclasses.replace(s, thickness=float(v))
    return surfs


def lens_with(lens, values: dict):
    """``lens`` with the parameters ``values`` replaced (:func:`replaced_surfaces`), validated: a
    :class:`~mi_neurallens.errors.LensError` where the result is not a lens (its message names the surface and
    what to change)."""
    for key, v in values.items():
        i, kind = parse(key)
        if kind == CURVATURE and not math.isfinite(float(v)):
            raise LensError(f"surface {i}: curvature must be finite, got {v}", surface=i, field="radius")
    return dataclasses.replace(lens, surfaces=tuple(replaced_surfaces(lens, values)))


class Packed:
    """Width-1 Dr.Jit values with gradients, read in a wide kernel through one packed array.

    Used directly, a width-1 variable with gradients is broadcast over the rays, and the reverse pass reduces its
    adjoint back to width 1 — one kernel per such variable, each recomputing everything before it (the camera
    ray and its trace: 14 500 operations for wide-22mm; 18 of them made a reverse pass 33x the primal).  Packed,
    each value is a ``gather`` at a constant index from one array, and the reverse pass scatter-adds all their
    adjoints from the one kernel.  ``values``: name → width-1 array (float type ``float_type``)."""

    def __init__(self, float_type, values: dict):
        import drjit as dr
        self.float_type = float_type
        self.index = {k: i for i, k in enumerate(values)}
        K = max(len(values), 1)
        P = dr.zeros(float_type, K)
        for k, i in self.index.items():
            onehot = float_type([1.0 if j == i else 0.0 for j in range(K)])
            P = P + values[k] * onehot
        dr.eval(P)
        self.array = P

    def __contains__(self, key) -> bool:
        return key in self.index

    def wide(self, key, n: int):
        """The value ``key`` on ``n`` lanes (a gather from the packed array)."""
        import drjit as dr
        idx = dr.full(dr.uint32_array_t(self.float_type), self.index[key], n)
        return dr.gather(self.float_type, self.array, idx)


@dataclasses.dataclass
class LiveGeometry:
    """The geometry of ``lens`` with some of its numbers as Dr.Jit arrays of width 1.

    ``live``: name → Dr.Jit float array (width 1; ``asphere``: one entry per coefficient), the parameters that
    are kernel inputs (possibly with gradients enabled), including ``sensor_distance`` (mm) when it is one;
    ``lens`` must hold the same values (it gives the float64 vertex positions and everything that is not a
    parameter).  :meth:`surfaces` gives the tracer's per-surface dicts, :attr:`image_z` the sensor plane."""

    lens: object
    live: dict
    float_type: type
    #: the stop's (inscribed) radius as a Dr.Jit array (mm), or None: the lens's, a literal
    stop_radius: object = None
    #: more width-1 values the caller reads with :meth:`wide` (the sensor's normalisation, its exit pupil)
    extra: dict = dataclasses.field(default_factory=dict)

    @classmethod
    def configuration(cls, lens, float_type) -> "LiveGeometry":
        """The numbers of ``lens`` that a zoom, a focus or an f-number changes — its vertex positions, the sensor
        plane and the stop's radius — as opaque ``float_type`` arrays (no gradients), the surfaces' shapes as
        literals: every configuration of one lens traces with the kernels compiled for the first (Dr.Jit's cache
        by source)."""
        import drjit as dr
        from .iris import Iris
        return cls(lens, {}, float_type, stop_radius=dr.opaque(float_type, float(Iris.of_lens(lens).radius_mm)))

    @classmethod
    def opaque(cls, lens, float_type) -> "LiveGeometry":
        """Every curvature, conic and aspheric coefficient of ``lens`` as an opaque ``float_type`` array (no
        gradients): the kernel stays the same whatever values they take."""
        import drjit as dr
        live = {}
        for key in parameter_names(lens):
            if parse(key)[1] == THICKNESS:
                continue                      # the vertex positions are opaque already
            v = value_of(lens, key)
            live[key] = dr.opaque(float_type, v) if not isinstance(v, tuple) else float_type(v)
        return cls(lens, live, float_type)

    def _value(self, key):
        """The live value of ``key`` in :attr:`float_type` (a detached copy where the type differs, e.g. the
        float64 tracing of the pupil bounds), or None."""
        import drjit as dr
        v = self.live.get(key)
        if v is None or type(v) is self.float_type:
            return v
        return self.float_type(dr.detach(v))

    def _delta(self, key):
        """``v − detach(v)`` of a live parameter with gradients enabled (value 0, its derivative), else None."""
        import drjit as dr
        v = self._value(key)
        return None if v is None or not dr.grad_enabled(v) else v - dr.detach(v)

    def _opaque(self, x: float):
        import drjit as dr
        return dr.opaque(self.float_type, float(x))

    def vertex_z(self):
        """Each vertex's z (lens space, mm): an opaque float64 value plus the attached thickness changes."""
        z0 = self.lens.vertex_z
        out, acc = [], None
        for i in range(len(self.lens.surfaces)):
            z = self._opaque(z0[i])
            out.append(z if acc is None else z + acc)
            d = self._delta(name(i, THICKNESS))
            if d is not None:
                acc = d if acc is None else acc + d
        self._acc = acc
        return out

    @property
    def image_z(self):
        """The sensor plane's z (lens space, mm), attached to every thickness and the sensor distance."""
        self.vertex_z()
        z = self._opaque(self.lens.image_z)
        acc = self._acc
        d = self._delta("sensor_distance")
        if d is not None:
            acc = d if acc is None else acc + d
        return z if acc is None else z + acc

    def _surface_values(self) -> list[dict]:
        """Per surface, its live numbers as width-1 arrays (``z``, ``c``, ``k``, ``asph``)."""
        import drjit as dr
        zs = self.vertex_z()
        out = []
        for i, s in enumerate(self.lens.surfaces):
            d = {"z": zs[i]}
            for kind, key in ((CURVATURE, "c"), (CONIC, "k")):
                v = self._value(name(i, kind))
                if v is not None:
                    d[key] = v
            a = self._value(name(i, ASPHERE))
            if a is not None:
                index = dr.uint32_array_t(self.float_type)
                d["asph"] = tuple(dr.gather(self.float_type, a, index(j)) for j in range(dr.width(a)))
            out.append(d)
        return out

    def _packed(self):
        """The values with gradients, packed (:class:`Packed`), or None when nothing is differentiated."""
        import drjit as dr
        if not hasattr(self, "_pack"):
            flat = {}
            for i, d in enumerate(self._surface_values()):
                for key, v in d.items():
                    for j, x in enumerate(v if key == "asph" else (v,)):
                        flat[(i, key, j)] = x
            flat["image_z"] = self.image_z
            if self.stop_radius is not None:
                flat["stop_radius"] = self.stop_radius
            flat.update(self.extra)
            self._flat = flat
            grad = {k: v for k, v in flat.items() if dr.is_array_v(v) and dr.grad_enabled(v)}
            self._pack = Packed(self.float_type, grad) if grad else None
        return self._pack

    def wide(self, key, n: int | None):
        """The value ``key`` (``"image_z"``, ``"stop_radius"`` or a key of :attr:`extra`) for ``n`` rays: packed where
        it carries gradients (:class:`Packed`), else the width-1 array."""
        pack = self._packed()
        if n is not None and pack is not None and key in pack:
            return pack.wide(key, n)
        return self._flat[key]

    def surfaces(self, n: int | None = None) -> list[dict]:
        """Per surface, the ``live`` dict :class:`~mi_neurallens.trace.surfaces.SurfaceGeometry` takes; with ``n``
        (the rays' width), the values with gradients read from the packed array (:class:`Packed`)."""
        pack = self._packed()
        out = []
        for i, d in enumerate(self._surface_values()):
            if n is not None and pack is not None:
                d = {key: (tuple(pack.wide((i, key, j), n) if (i, key, j) in pack else x for j, x in enumerate(v))
                           if key == "asph" else (pack.wide((i, key, 0), n) if (i, key, 0) in pack else v))
                     for key, v in d.items()}
            out.append(d)
        return out
