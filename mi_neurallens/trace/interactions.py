"""Refraction, reflection and Fresnel factors at one interface, for any Dr.Jit float type.

* Directions are unit (x, y, z) tuples; ``nf`` is the unit normal facing the incoming ray
  (``cos_i = −d·nf > 0``).
* Fresnel: unpolarised average of the s and p power reflectances, ``R = (R_s + R_p)/2``,
  ``T = 1 − R`` (lossless dielectrics).  Under total internal reflection ``R = 1``.
* Optional single-layer coating (index ``n_c``, physical thickness ``h``; quarter-wave at its
  design wavelength): exact thin-film (Airy) reflectance per polarisation,
  ``|r|² = (r12² + r23² + 2 r12 r23 cos 2β) / (1 + r12² r23² + 2 r12 r23 cos 2β)``,
  ``β = 2π n_c h cos θ_c / λ``, then averaged.  When the ray is evanescent inside the layer
  (only possible at glass–glass interfaces, which are never coated by ``Lens.with_coating``)
  ``cos θ_c`` is clamped to 0.
"""
from __future__ import annotations

import math

import drjit as dr


def refract(d, nf, cos_i, eta):
    """Snell refraction.  ``eta = n1/n2``.  Returns (direction, cos_t, tir_mask)."""
    k = 1.0 - eta * eta * (1.0 - cos_i * cos_i)
    tir = k < 0.0
    cos_t = dr.sqrt(dr.maximum(k, 0.0))
    f = eta * cos_i - cos_t
    out = tuple(dr.fma(eta, di, f * ni) for di, ni in zip(d, nf))
    return out, cos_t, tir


def reflect(d, nf, cos_i):
    """Mirror reflection about ``nf``."""
    f = 2.0 * cos_i
    return tuple(dr.fma(f, ni, di) for di, ni in zip(d, nf))


def _rs_rp(na, ca, nb, cb):
    rs = (na * ca - nb * cb) / (na * ca + nb * cb)
    rp = (nb * ca - na * cb) / (nb * ca + na * cb)
    return rs, rp


def fresnel_reflectance(n1, n2, cos_i, cos_t):
    """Unpolarised power reflectance of a bare interface (valid outside TIR).  Plain arithmetic, so
    any number type works (Dr.Jit arrays, floats, the Taylor baseline's power series).

    Written with a single division: r_s = (a−b)/(a+b), r_p = (c−e)/(c+e) with a = n1 cos_i,
    b = n2 cos_t, c = n2 cos_i, e = n1 cos_t.
    """
    a, b = n1 * cos_i, n2 * cos_t
    c, e = n2 * cos_i, n1 * cos_t
    sa, sc = a + b, c + e
    rs_num, rp_num = (a - b) * sc, (c - e) * sa
    inv = 1.0 / (sa * sc)
    return 0.5 * (rs_num * rs_num + rp_num * rp_num) * (inv * inv)


def _dr_sqrt0(a):
    return dr.sqrt(dr.maximum(a, 0.0))


def coated_reflectance(n1, n2, cos_i, cos_t, lam_nm, n_c: float, h_nm: float, *, sqrt=_dr_sqrt0,
                       cos=dr.cos):
    """Unpolarised reflectance of an interface carrying one thin layer (index ``n_c``, ``h_nm`` thick).

    Plain arithmetic apart from ``sqrt`` and ``cos``, so other number types (the Taylor baseline's
    truncated power series) evaluate the same formula by passing theirs."""
    sin2_c = (n1 / n_c) * (n1 / n_c) * (1.0 - cos_i * cos_i)
    cos_c = sqrt(1.0 - sin2_c)
    rs12, rp12 = _rs_rp(n1, cos_i, n_c, cos_c)
    rs23, rp23 = _rs_rp(n_c, cos_c, n2, cos_t)
    cos2b = cos((4.0 * math.pi * n_c * h_nm) * cos_c / lam_nm)

    def airy(a, b):
        ab2 = 2.0 * a * b * cos2b
        return (a * a + b * b + ab2) / (1.0 + a * a * b * b + ab2)

    return 0.5 * (airy(rs12, rs23) + airy(rp12, rp23))
