"""Taylor polynomial optics (Hullin, Hanika & Heidrich 2012): per-surface transfer polynomials
expanded about the optical axis, composed along a path with truncation to degree D (3 or 5).

Ray state on a plane z = const: position (x, y) and **direction cosines** (u, v) = (dx, dy) of the unit
direction (dz = heading·√(1 − u² − v²)), as in that work.  One *surface step* maps the state on the
previous plane to the state on the vertex plane of the next surface:

1. propagate to the surface and intersect it exactly (sphere, conic — the closed-form quadric root of
   :mod:`mi_neurallens.trace.surfaces` — and even aspheres by Newton iterations from the conic root);
2. refract (Snell, vector form) or reflect about the surface normal at the hit point;
3. re-express the outgoing ray on the vertex plane (propagate along the new direction to z = vertex);

plus the Fresnel factor of the interaction (unpolarised, coatings included: the same formulas as the
tracer).  The stop is a plane step (no bending).  A last step propagates to ``z_out``.

Each step is evaluated in truncated-power-series arithmetic (:class:`~.poly.TPS`) on the identity
variables, which yields its exact degree-D Taylor polynomial about the axis (the axis maps to the axis,
so constant terms vanish); the path polynomial is the truncated composition of the step polynomials
(``build="compose"``, the paper's method).  ``build="direct"`` pushes the series through all steps at
once — the same polynomial up to rounding (tested), a check on the composition.

Wavelength (``wavelength=``):

* ``"interp"`` (default; the paper's method): the whole system is expanded at each of ``wavelengths``
  (default 450, 550, 650 nm; the paper used 500 and 600 with linear interpolation) and every coefficient
  is Lagrange-interpolated in λ (degree K−1 in λ for K nodes, extrapolated outside them);
* ``"variable"``: λ is a fifth variable l = (λ − 550)/100; each medium's n(λ) enters as its degree-D
  least-squares polynomial in l over 360–830 nm and the expansion is of total degree D in (x, y, u, v, l).

Throughput (``fresnel=``): True — the Taylor polynomial (same degree) of the product of the Fresnel
factors along the path (exact series of the Fresnel formulas); False — 1.

Validity (``aperture=``): ``"none"`` (original form: every ray heading the right way whose output
direction cosines satisfy u² + v² < 1), ``"stop"`` (the *aperture polynomial*: the degree-D polynomial
of the stop-plane position, tested against the stop radius) or ``"all"`` (also the hit point on every
surface, tested against its clear semi-diameter/housing).
"""
from __future__ import annotations

import math

import numpy as np

from ..constants import VISIBLE_RANGE_NM
from ..trace.interactions import interface_reflectance
from .common import LAM0_NM, LAM_SCALE_NM, LensSpacePolyMap
from .poly import TPS, SparsePoly, basis, compose

ASPHERE_NEWTON = 4


def _sqrt(a):
    return a.sqrt() if isinstance(a, TPS) else math.sqrt(a)


def _cos(a):
    return a.cos() if isinstance(a, TPS) else math.cos(a)


def _sin(a):
    return a.sin() if isinstance(a, TPS) else math.sin(a)


def _index_poly(medium, degree: int, lam_range=VISIBLE_RANGE_NM, nodes: int = 41):
    """Least-squares polynomial coefficients (low → high) of n(λ) in l = (λ − 550)/100."""
    lo, hi = lam_range
    k = np.arange(nodes)
    lam = 0.5 * (lo + hi) + 0.5 * (hi - lo) * np.cos(np.pi * (k + 0.5) / nodes)
    n = np.asarray(medium.index(lam), np.float64)
    if np.ptp(n) == 0.0:
        return np.array([float(n[0])])
    return np.polynomial.polynomial.polyfit((lam - LAM0_NM) / LAM_SCALE_NM, n, degree)


class _Ctx:
    """Per-build context: how media indices and λ are represented (floats at a node, or TPS in l)."""

    def __init__(self, lam_nm=None, l_var: TPS | None = None, degree: int = 3):
        self.lam_nm, self.l_var, self.degree = lam_nm, l_var, degree
        self.cache = {}

    def n(self, medium):
        if medium not in self.cache:
            if self.l_var is None:
                self.cache[medium] = float(medium.index(self.lam_nm))
            else:
                co = _index_poly(medium, self.degree)
                v = TPS.const(self.l_var.b, float(co[-1]))
                for c in reversed(co[:-1]):
                    v = v * self.l_var + float(c)
                self.cache[medium] = v if len(co) > 1 else float(co[0])
        return self.cache[medium]

    def lam(self):
        return self.lam_nm if self.l_var is None else self.l_var * LAM_SCALE_NM + LAM0_NM


def surface_step(lens, step, state, h: int, z_p: float, ctx: _Ctx, fresnel: bool = True):
    """One step on series (or floats): ``state`` = (x, y, u, v) on plane ``z_p`` travelling with heading
    ``h`` → ((x', y', u', v') on the step's vertex plane, h', z_vertex, Fresnel factor, hit (X, Y)).

    The module's three stages: the hit point (:func:`_intersect`), the bend about the surface normal there
    (:func:`_normal`, :func:`_bend`) with its Fresnel factor, back to the vertex plane along the new direction."""
    x, y, u, v = state
    zv = float(lens.vertex_z[step.surface])
    surf = lens.surfaces[step.surface]
    w = h * _sqrt(1.0 - u * u - v * v)
    pz = z_p - zv
    c, k = surf.curvature, surf.conic
    asph = tuple(a for a in surf.aspheric)
    while asph and asph[-1] == 0.0:
        asph = asph[:-1]
    t = _intersect(c, k, asph, (x, y, u, v, w), pz, h)
    X, Y, Zr = x + t * u, y + t * v, pz + t * w
    if step.kind == "stop":
        return (X, Y, u, v), h, zv, None, (X, Y)
    nx, ny, nz = _normal(c, k, asph, X, Y, Zr, h)
    cos_i = -(u * nx + v * ny + w * nz)
    u2, v2, w2, h2, F = _bend(step, surf, (u, v, w), h, (nx, ny, nz), cos_i, ctx, fresnel)
    # --- back to the vertex plane along the new direction
    t2 = -Zr / w2
    return (X + t2 * u2, Y + t2 * v2, u2, v2), h2, zv, F, (X, Y)


def _sag_slope(c, k, asph, s):
    """Sag and d(sag)/ds of a surface of curvature ``c`` (1/mm), conic ``k`` and even aspheric coefficients
    ``asph`` (of r⁴, r⁶, …) at s = r² (mm²)."""
    if c != 0.0:
        root = _sqrt(1.0 - (1.0 + k) * c * c * s)
        sag, dsag = c * s / (1.0 + root), (c * 0.5) / root
    else:
        sag, dsag = s * 0.0, s * 0.0
    p, dp = 0.0, 0.0
    for i in reversed(range(len(asph))):
        p = p * s + asph[i]
        dp = dp * s + (i + 2) * asph[i]
    return sag + p * s * s, dsag + dp * s


def _intersect(c, k, asph, ray, pz, h):
    """Distance t along the ray ``ray`` = (x, y, u, v, w) (position on its plane, direction cosines, dz), whose
    plane lies ``pz`` (mm) from the surface's vertex, to the surface (curvature ``c``, conic ``k``, aspheric
    ``asph``) met with heading ``h``: the closed-form quadric root, refined by Newton iterations on an asphere."""
    x, y, u, v, w = ray
    if c == 0.0:
        t = -pz / w
    else:
        ck = c * (1.0 + k)
        a = c * (u * u + v * v) + ck * w * w
        hb = c * (x * u + y * v) + ck * pz * w - w
        cc = c * (x * x + y * y) + (ck * pz * pz - 2.0 * pz)
        sq = _sqrt(hb * hb - a * cc)
        t = cc / (sq - hb) if h > 0 else -cc / (hb + sq)
    if asph:
        for _ in range(ASPHERE_NEWTON):
            X, Y, Zr = x + t * u, y + t * v, pz + t * w
            sag, dsag = _sag_slope(c, k, asph, X * X + Y * Y)
            t = t - (Zr - sag) / (w - dsag * 2.0 * (X * u + Y * v))
    return t


def _normal(c, k, asph, X, Y, Zr, h):
    """The unit surface normal at the hit point (``X``, ``Y``, ``Zr`` from the vertex; mm), toward −z, turned to
    face a ray of heading ``h``."""
    if c == 0.0 and not asph:
        nx, ny, nz = X * 0.0, Y * 0.0, X * 0.0 - 1.0
    elif not asph:
        nx, ny, nz = c * X, c * Y, c * (1.0 + k) * Zr - 1.0
        if k != 0.0:
            inv = 1.0 / _sqrt(nx * nx + ny * ny + nz * nz)
            nx, ny, nz = nx * inv, ny * inv, nz * inv
    else:
        _, dsag = _sag_slope(c, k, asph, X * X + Y * Y)
        nx, ny, nz = 2.0 * dsag * X, 2.0 * dsag * Y, X * 0.0 - 1.0
        inv = 1.0 / _sqrt(nx * nx + ny * ny + nz * nz)
        nx, ny, nz = nx * inv, ny * inv, nz * inv
    if h < 0:
        nx, ny, nz = -nx, -ny, -nz
    return nx, ny, nz


def _bend(step, surf, d, h, normal, cos_i, ctx, fresnel):
    """Refract (``step.kind`` T) or reflect the direction ``d`` = (u, v, w) of heading ``h`` about ``normal`` at
    incidence ``cos_i``, between the step's media: ``(u', v', w', h', F)``, F the Fresnel factor (0 for a reflection
    between identical media; None where there is none: ``fresnel`` False, or a transmission between identical
    media)."""
    u, v, w = d
    nx, ny, nz = normal
    m1, m2 = step.media
    n1, n2 = ctx.n(m1), ctx.n(m2)
    F = None
    if step.kind == "T":
        if m1 == m2:
            u2, v2, w2, h2 = u, v, w, h
        else:
            eta = n1 / n2
            cos_t = _sqrt(1.0 - eta * eta * (1.0 - cos_i * cos_i))
            f = eta * cos_i - cos_t
            u2, v2, w2 = eta * u + f * nx, eta * v + f * ny, eta * w + f * nz
            h2 = h
            if fresnel:
                R = _reflectance(surf, m1, m2, n1, n2, cos_i, cos_t, ctx)
                F = 1.0 - R
    else:
        f = 2.0 * cos_i
        u2, v2, w2 = u + f * nx, v + f * ny, w + f * nz
        h2 = -h
        if m1 == m2:
            F = 0.0
        elif fresnel:
            eta = n1 / n2
            cos_t = _sqrt(1.0 - eta * eta * (1.0 - cos_i * cos_i))
            F = _reflectance(surf, m1, m2, n1, n2, cos_i, cos_t, ctx)
    return u2, v2, w2, h2, F


def _reflectance(surf, m1, m2, n1, n2, cos_i, cos_t, ctx):
    """The tracer's Fresnel and coating formulas (trace/interactions.py), evaluated on series."""
    return interface_reflectance(surf.coating, m1, m2, n1, n2, cos_i, cos_t, ctx.lam(), ctx.n, sqrt=_sqrt, cos=_cos,
                                 sin=_sin)


def _end_step(state, h, z_p, z_out):
    x, y, u, v = state
    w = h * _sqrt(1.0 - u * u - v * v)
    t = (z_out - z_p) / w
    return (x + t * u, y + t * v, u, v)


def expand_path(lens, spec, z_in: float, z_out: float, degree: int, ctx_factory, nv: int,
                fresnel: bool = True, aperture: str = "none", build: str = "compose"):
    """Taylor polynomials (list of TPS) of one path: [X, Y, U, V, T, (ax, ay) per aperture check] and
    the aperture radii.  ``ctx_factory(l_var)`` makes the λ context."""
    b = basis(nv, degree)
    ident = [TPS.var(b, i) for i in range(nv)]
    l_var = ident[4] if nv == 5 else None
    checks = [i for i, st in enumerate(spec.steps)
              if (aperture == "stop" and st.kind == "stop") or aperture == "all"]
    radii = [spec.steps[i].clear_radius for i in checks]
    h = spec.steps[0].heading
    z = float(z_in)
    T = TPS.const(b, 1.0)
    aps = []
    if build == "direct":
        ctx = ctx_factory(l_var)
        state = tuple(ident[:4])
        for i, st in enumerate(spec.steps):
            state, h, z, F, hit = surface_step(lens, st, state, h, z, ctx, fresnel)
            if F is not None:
                T = T * F
            if i in checks:
                aps += list(hit)
        state = _end_step(state, h, z, z_out)
    else:
        ctx = ctx_factory(l_var)
        state = tuple(ident[:4])          # accumulated map: state on the current plane as series
        for i, st in enumerate(spec.steps):
            # the step's own Taylor polynomial, on fresh identity variables
            loc, h2, z2, F, hit = surface_step(lens, st, tuple(ident[:4]), h, z, ctx, fresnel)
            outs = list(loc)
            nF = 0
            if F is not None:
                outs.append(F if isinstance(F, TPS) else TPS.const(b, float(F)))
                nF = 1
            if i in checks:
                outs += list(hit)
            args = list(state) + ([ident[4]] if nv == 5 else [])
            comp = compose(outs, args)
            state = tuple(comp[:4])
            if nF:
                T = T * comp[4]
            if i in checks:
                aps += comp[4 + nF:]
            h, z = h2, z2
        loc = _end_step(tuple(ident[:4]), h, z, z_out)
        state = tuple(compose(list(loc), list(state) + ([ident[4]] if nv == 5 else [])))
    if not fresnel:
        T = TPS.const(b, 1.0)
    return list(state) + [T] + aps, radii


class TaylorMap(LensSpacePolyMap):
    """Taylor polynomial optics of one path (see the module docstring).

    ``degree``: 3 or 5 (any ≥ 1 works; 1 is the ABCD map in direction cosines).
    """

    method = "taylor"
    angles = "cosines"

    def __init__(self, lens, path="transmit", direction="forward", z_in=None, z_out=None, *,
                 degree: int = 3, wavelength: str = "interp", wavelengths=(450.0, 550.0, 650.0),
                 fresnel: bool = True, aperture: str = "none", build: str = "compose"):
        super().__init__(lens, path, direction, z_in, z_out)
        if wavelength not in ("interp", "variable"):
            raise ValueError(f"taylor wavelength must be 'interp' or 'variable', got {wavelength!r}")
        if aperture not in ("none", "stop", "all"):
            raise ValueError(f"taylor aperture must be 'none', 'stop' or 'all', got {aperture!r}")
        if build not in ("compose", "direct"):
            raise ValueError(f"taylor build must be 'compose' or 'direct', got {build!r}")
        self.degree, self.wavelength, self.aperture, self.fresnel = int(degree), wavelength, aperture, fresnel
        self.method = f"taylor{self.degree}"
        if wavelength == "variable":
            polys, radii = expand_path(lens, self.spec, self.z_in, self.z_out, self.degree,
                                       lambda lv: _Ctx(l_var=lv, degree=self.degree), 5, fresnel, aperture, build)
            self.polys = polys
            sp = SparsePoly.from_tps(polys)
        else:
            lams = [float(v) for v in wavelengths]
            self.nodes = lams
            node_polys = []
            for lam in lams:
                polys, radii = expand_path(lens, self.spec, self.z_in, self.z_out, self.degree,
                                           lambda lv, lam=lam: _Ctx(lam_nm=lam), 4, fresnel, aperture, build)
                node_polys.append(polys)
            self.node_polys = node_polys
            sp = _lagrange(node_polys, lams)
        # normalise position and direction variables for float32 evaluation
        L = 10.0
        sc = np.array([L, L, 0.5, 0.5, 1.0])
        f = np.prod(sc[None, :] ** sp.exps, axis=1)
        C = sp.coefs * f[:, None]
        C[np.abs(C) < 1e-12 * np.abs(C).max(axis=0, keepdims=True)] = 0.0   # rounding noise
        keep = np.any(C != 0.0, axis=1)
        core = SparsePoly(sp.exps[keep], C[keep], center=[0, 0, 0, 0, LAM0_NM],
                          scale=[L, L, 0.5, 0.5, LAM_SCALE_NM])
        self._setup_core(core, radii)

    def describe(self) -> dict:
        return {**super().describe(), "degree": self.degree, "wavelength": self.wavelength,
                "aperture": self.aperture, "fresnel": self.fresnel, "terms": int(len(self.core.exps))}


def _lagrange(node_polys, lams) -> SparsePoly:
    """Per-node 4-variable TPS lists → one SparsePoly in (x, y, u, v, l), coefficients Lagrange-
    interpolated in l = (λ − 550)/100 through the nodes."""
    K = len(lams)
    ls = (np.asarray(lams) - LAM0_NM) / LAM_SCALE_NM
    b = node_polys[0][0].b
    n_out = len(node_polys[0])
    C = np.stack([np.stack([p.c for p in polys], 1) for polys in node_polys], 0)  # (K, M, n_out)
    # Lagrange basis polynomials in l (low → high)
    Lb = []
    for k in range(K):
        p = np.array([1.0])
        for j in range(K):
            if j != k:
                p = np.polynomial.polynomial.polymul(p, np.array([-ls[j], 1.0]) / (ls[k] - ls[j]))
        Lb.append(p)
    exps, rows = [], []
    for m in range(b.M):
        if not np.any(C[:, m, :] != 0.0):
            continue
        for j in range(K):
            coef = sum(Lb[k][j] * C[k, m, :] for k in range(K) if j < len(Lb[k]))
            if np.any(np.abs(coef) > 1e-15 * np.abs(C[:, m, :]).max()) or (m == 0 and j == 0):
                exps.append(list(b.exps[m]) + [j])
                rows.append(coef)
    return SparsePoly(np.array(exps, dtype=np.int64), np.array(rows).reshape(len(rows), n_out))
