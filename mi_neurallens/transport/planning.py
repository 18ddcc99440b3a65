"""Runtime planning of the transport maps: the reduced input domain and the wavelength sampler.

Used at render time (the sensors and the flare renderer check a map's domain) and by the training
sampler alike, so it lives here rather than under ``training/`` (which imports torch lazily and is
never imported at render time).

The **reduced input domain** (:class:`Domain`, paper §4.1) of a map: ``(r, ωx, ωy, λ)`` with
0 ≤ r ≤ ``r_max`` on the input plane (mm), (ωx, ωy) in the half disk ωx² + ωy² ≤ ``s_max``², ωy ≥ 0,
and λ in [``lam_min``, ``lam_max``] nm.  A sample is addressed by a point ``u`` of the unit cube [0, 1)⁴
(:meth:`Domain.u_to_x`): ``r = r_max·u0``, ``(ωx, ωy) = s_max·√u1·(cos πu2, sin πu2)``, ``λ`` the CIE
sample of u3 (:func:`sample_cie_wavelength`).

A forward (flare) map's domain may also carry a **film reach** (:class:`Reach`): the map is defined for the
rays that come near the film, and a ray that passes the lens but lands far outside it counts as blocked.
Some ghosts (a reflection between the last two surfaces) leave the lens at grazing angles and land metres
away; learning those would set the regressor's output scale and cost the film's rays their precision.
"""
from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from ..constants import VISIBLE_RANGE_NM


#: Mitsuba's visible-range importance curve (``sample_rgb_spectrum``, CIE 1931 on [360, 830] nm)
CIE_MIN_NM, CIE_MAX_NM = VISIBLE_RANGE_NM
_CIE_A, _CIE_B, _CIE_C, _CIE_K = 0.8569106254698279, 1.8275019724092267, 138.88888888888889, 0.0072
_CIE_PDF = 0.003939804229326285


def sample_cie_wavelength(u):
    """λ (nm) and 1/pdf for uniform ``u`` ∈ [0, 1): the same closed form as Mitsuba's
    ``sample_rgb_spectrum`` (pdf ∝ sech²(0.0072 (λ − 538)), a fit to the CIE 1931 ȳ+x̄+z̄ sum on
    [360, 830] nm).  Works on numpy arrays and on any Dr.Jit float type (variant-generic)."""
    if isinstance(u, (np.ndarray, float, int)):
        u = np.asarray(u, dtype=np.float64)
        lam = 538.0 - np.arctanh(_CIE_A - _CIE_B * u) * _CIE_C
        return lam, 1.0 / pdf_cie_wavelength(lam)
    import drjit as dr
    lam = 538.0 - dr.atanh(_CIE_A - _CIE_B * u) * _CIE_C
    return lam, dr.rcp(pdf_cie_wavelength(lam))


def pdf_cie_wavelength(lam):
    """Density (1/nm) of :func:`sample_cie_wavelength`."""
    if isinstance(lam, (np.ndarray, float, int)):
        lam = np.asarray(lam, dtype=np.float64)
        t = 1.0 / np.cosh(_CIE_K * (lam - 538.0))
        return np.where((lam >= CIE_MIN_NM) & (lam <= CIE_MAX_NM), _CIE_PDF * t * t, 0.0)
    import drjit as dr
    t = 1.0 / dr.cosh(_CIE_K * (lam - 538.0))
    return dr.select((lam >= CIE_MIN_NM) & (lam <= CIE_MAX_NM), _CIE_PDF * t * t, 0.0)


def cie_u_of_lambda(lam):
    """Inverse of :func:`sample_cie_wavelength` (numpy): u such that sample(u) = λ."""
    lam = np.asarray(lam, dtype=np.float64)
    return (_CIE_A - np.tanh((538.0 - lam) / _CIE_C)) / _CIE_B


@dataclass(frozen=True)
class Reach:
    """The film reach of a forward map: a ray is part of the map only if it passes within ``radius_mm`` of
    the axis on the plane ``z_near_mm`` or on ``z_far_mm`` (lens space, mm: the sensor plane at the nearest
    and the farthest sensor distance the model supports; ``radius_mm``: the film's half diagonal times a
    margin, so the reach's edge lies outside every supported film and never shows in a render)."""

    z_near_mm: float
    z_far_mm: float
    radius_mm: float

    def margin_dr(self, position, direction):
        """The reach margin of exit rays (Dr.Jit): max over the two planes of 1 − r²/R², ≥ 0 inside (the
        tracer's aperture-margin convention, :attr:`~mi_neurallens.trace.tracer.TraceResult.margin`).
        ``position`` (x, y, z) and ``direction`` (dx, dy, dz): lens space, mm."""
        import drjit as dr
        (x, y, z), (dx, dy, dz) = position, direction
        inv_r2 = 1.0 / (self.radius_mm * self.radius_mm)
        m = None
        for zp in (self.z_near_mm, self.z_far_mm):
            t = (zp - z) / dz
            px, py = dr.fma(t, dx, x), dr.fma(t, dy, y)
            mk = 1.0 - dr.fma(px, px, py * py) * inv_r2
            m = mk if m is None else dr.maximum(m, mk)
        return dr.select(dr.isfinite(m), m, -1.0)

    def to_dict(self):
        return {"z_near_mm": self.z_near_mm, "z_far_mm": self.z_far_mm, "radius_mm": self.radius_mm}


@dataclass
class Domain:
    """The sampled reduced input domain of one map (lens space, mm), and for forward maps optionally the
    film reach of its rays (:class:`Reach`; None: every ray that passes the lens)."""

    r_max: float
    s_max: float
    lam_min: float = CIE_MIN_NM
    lam_max: float = CIE_MAX_NM
    reach: Reach | None = None
    #: a lens with moving groups: its configuration inputs (:class:`~mi_neurallens.transport.configurations.
    #: Configurations`), one column each after λ; None: a lens of one configuration
    conditions: object = None

    @property
    def dims(self) -> int:
        """Columns of the unit cube and of the inputs a sample is traced from: 4, plus one per configuration input."""
        return 4 + (self.conditions.dims if self.conditions is not None else 0)

    @property
    def n_inputs(self) -> int:
        """Columns of the networks' inputs: :attr:`dims`, plus a lens with moving groups' product inputs
        (:attr:`~mi_neurallens.transport.configurations.Configurations.monomials`), computed from the others."""
        return self.dims + (self.conditions.n_products if self.conditions is not None else 0)

    def u_to_x(self, u: np.ndarray) -> np.ndarray:
        """(N, :attr:`dims`) unit-cube points → (N, :attr:`n_inputs`) reduced inputs (r, ωx, ωy, λ (, zoom, focus,
        products)), float64."""
        u = np.asarray(u, dtype=np.float64)
        x = np.empty((len(u), self.n_inputs))
        if self.conditions is not None:
            t, f = self.conditions.u_to_tf(u[:, 4:])
            x[:, 4:self.dims] = np.stack([t if n == "zoom" else f for n in self.conditions.names], 1)
        for a in range(0, len(u), 1 << 16):     # in blocks: the temporaries stay in the cache
            b = u[a:a + (1 << 16)]
            rho = self.s_max * np.sqrt(b[:, 1])
            th = math.pi * b[:, 2]
            x[a:a + len(b), 0] = self.r_max * b[:, 0]
            x[a:a + len(b), 1] = rho * np.cos(th)
            x[a:a + len(b), 2] = rho * np.sin(th)
            x[a:a + len(b), 3] = 538.0 - np.arctanh(_CIE_A - _CIE_B * b[:, 3]) * _CIE_C   # sample_cie_wavelength's λ
        if self.n_inputs > self.dims:
            x[:, self.dims:] = self.conditions.products_np(x)
        return x

    def u_to_x_dr(self, u):
        """Unit-cube components (:attr:`dims` Dr.Jit floats) → reduced inputs (r, ωx, ωy, λ (, zoom, focus)) in
        Dr.Jit: :meth:`u_to_x` in a kernel."""
        import drjit as dr
        rho = self.s_max * dr.sqrt(u[1])
        s, c = dr.sincos(math.pi * u[2])
        lam, _ = sample_cie_wavelength(u[3])
        cond = tuple(self.conditions.u_to_tf_dr(list(u[4:]))) if self.conditions is not None else ()
        return (self.r_max * u[0], rho * c, rho * s, lam) + cond

    def x_to_u(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        rho = np.hypot(x[:, 1], x[:, 2])
        u = np.stack([x[:, 0] / self.r_max, (rho / self.s_max) ** 2,
                      np.arctan2(x[:, 2], x[:, 1]) / math.pi, cie_u_of_lambda(x[:, 3])], 1)
        if self.conditions is None:
            return u
        t, f = self.conditions.split([x[:, 4 + j] for j in range(self.conditions.dims)])
        t = np.broadcast_to(np.asarray(t, np.float64), (len(x),))
        f = np.broadcast_to(np.asarray(f, np.float64), (len(x),))
        return np.concatenate([u, self.conditions.tf_to_u(t, f)], 1)

    # input normalisation used by the networks: every column to about [-1, 1]
    def norm_center_scale(self):
        c = np.array([0.5 * self.r_max, 0.0, 0.5 * self.s_max, 0.5 * (self.lam_min + self.lam_max)])
        s = np.array([0.5 * self.r_max, self.s_max, 0.5 * self.s_max, 0.5 * (self.lam_max - self.lam_min)])
        if self.conditions is not None:
            cc, cs = self.conditions.norm_center_scale()
            pc, ps = self.conditions.products_center_scale((self.r_max, self.s_max, self.s_max))
            c, s = np.concatenate([c, cc, pc]), np.concatenate([s, cs, ps])
        return c, s

    def to_dict(self):
        d = {"r_max_mm": self.r_max, "s_max": self.s_max, "lambda_min_nm": self.lam_min,
             "lambda_max_nm": self.lam_max}
        if self.reach is not None:
            d["reach"] = self.reach.to_dict()
        if self.conditions is not None:
            d["conditions"] = self.conditions.to_dict()
        return d

    def contains_dr(self, x, number=None):
        """Mask of the reduced inputs ``x = (r, ωx, ωy, λ)`` (Dr.Jit floats) inside the domain.
        ``number(key, value, like)``: how the bounds enter the kernel (a map's
        :meth:`~mi_neurallens.transport.base.TransportMap.number`; None: literals)."""
        import drjit as dr
        k = number or (lambda key, v, like: float(v))
        r, wx, wy, lam = x[:4]
        ok = (r <= k("domain.r_max", self.r_max, r)) & (dr.fma(wx, wx, wy * wy) <= k("domain.s_max^2", self.s_max ** 2, wx))
        return ok & (lam >= k("domain.lam_min", self.lam_min, lam)) & (lam <= k("domain.lam_max", self.lam_max, lam))

    @staticmethod
    def from_dict(d):
        """A :class:`Domain` from its :meth:`to_dict` form (a :class:`Domain` is returned as is)."""
        if isinstance(d, Domain):
            return d
        reach = Reach(**{k: float(v) for k, v in d["reach"].items()}) if d.get("reach") else None
        cond = None
        if d.get("conditions"):
            from .configurations import Configurations
            cond = Configurations.from_dict(d["conditions"])
        return Domain(float(d["r_max_mm"]), float(d["s_max"]), float(d["lambda_min_nm"]), float(d["lambda_max_nm"]),
                      reach, cond)


# ----------------------------------------------------------------------------- ghost selection
def select_ghosts(ranking, energy_fraction: float = 0.99, max_ghosts: int = 32):
    """The smallest strongest-first prefix of ``ranking`` carrying ``energy_fraction`` of the ghost
    energy, at most ``max_ghosts`` long; ghosts with zero energy are never kept."""
    rk = sorted(ranking, key=lambda dd: -float(dd.get("energy", 0.0)))
    tot = sum(float(dd.get("energy", 0.0)) for dd in rk) or 1.0
    keep, c = [], 0.0
    for dd in rk:
        if len(keep) >= max_ghosts or float(dd.get("energy", 0.0)) <= 0:
            break
        keep.append(int(dd["path_id"]))
        c += float(dd["energy"]) / tot
        if c >= energy_fraction - 1e-12:
            break
    return keep
