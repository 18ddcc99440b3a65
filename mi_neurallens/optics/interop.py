"""Interoperability: a :class:`~mi_neurallens.optics.prescription.Lens` as an optiland optic.

Used as the independent reference of the tracer (tests/test_tracer.py) and of its speed
(benchmarks/bench_tracer.py), and by users who want to check a lens in optiland.  optiland is an
optional dependency (the ``dev`` extra), imported when a function is called.

Media are handed over as constant indices evaluated by our :class:`~mi_neurallens.optics.glass.Medium` at
the given wavelength, so a comparison isolates the tracer (intersection, refraction) from the glass model.
"""
from __future__ import annotations

import math

import numpy as np


def optiland_optic(lens, wavelength_nm: float):
    from optiland import optic
    from optiland.materials import IdealMaterial

    lam = wavelength_nm
    def mat(m):
        return IdealMaterial(n=float(m.index(lam)))

    L = optic.Optic()
    L.surfaces.add(index=0, radius=np.inf, thickness=np.inf, material=mat(lens.object_medium))
    for i, s in enumerate(lens.surfaces):
        kw = dict(index=i + 1, radius=(np.inf if math.isinf(s.radius) else s.radius),
                  thickness=s.thickness, material=mat(s.medium), is_stop=s.is_stop)
        if s.conic or s.is_aspheric:
            kw.update(surface_type="even_asphere", conic=s.conic,
                      coefficients=[0.0] + [float(a) for a in s.aspheric])
        L.surfaces.add(**kw)
    L.surfaces.add(index=len(lens.surfaces) + 1, material=mat(lens.surfaces[-1].medium))
    L.set_aperture(aperture_type="EPD", value=1.0)
    L.fields.set_type(field_type="angle")
    L.fields.add(y=0.0)
    L.wavelengths.add(value=lam * 1e-3, is_primary=True)
    for s in L.surfaces.surfaces if hasattr(L.surfaces, "surfaces") else L.surface_group.surfaces:
        g = s.geometry
        if hasattr(g, "tol"):  # optiland's default Newton tolerance (1e-10 on F) leaves ~1e-7 mm errors
            g.tol, g.max_iter = 1e-14, 200
    return L


def optiland_trace(lens, origins, directions, wavelength_nm: float):
    """Trace explicit rays (lens space, mm) with optiland; returns (position, direction) at the
    image plane.  optiland applies no clear-aperture clipping here (none was set)."""
    from optiland.rays import RealRays
    L = optiland_optic(lens, wavelength_nm)
    o = np.asarray(origins, float)
    d = np.asarray(directions, float)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    n = len(o)
    rays = RealRays(o[:, 0].copy(), o[:, 1].copy(), o[:, 2].copy(), d[:, 0].copy(), d[:, 1].copy(),
                    d[:, 2].copy(), np.ones(n), np.full(n, wavelength_nm * 1e-3))
    (L.surfaces if hasattr(L.surfaces, 'trace') else L.surface_group).trace(rays, skip=1)
    pos = np.stack([np.asarray(rays.x), np.asarray(rays.y), np.asarray(rays.z)], 1)
    dirn = np.stack([np.asarray(rays.L), np.asarray(rays.M), np.asarray(rays.N)], 1)
    return pos, dirn
