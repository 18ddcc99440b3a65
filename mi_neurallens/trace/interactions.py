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
* Optional multilayer stack (:class:`~mi_neurallens.optics.coatings.CoatingStack`): the characteristic
  (transfer) matrix of each layer, ``[[cos δ, i sin δ / η], [i η sin δ, cos δ]]`` with ``δ = 2π n h cos θ / λ``
  and the tilted admittance ``η_s = n cos θ`` or ``η_p = n / cos θ``, multiplied from the ambient inward;
  then ``r = (η0 B − C) / (η0 B + C)`` with ``(B, C) = M (1, η_sub)``.  Lossless layers keep every matrix of
  the form ``[[a, i b], [i c, d]]`` with real a, b, c, d, so it runs in real arithmetic.
  :func:`interface_reflectance` picks the formula of a surface's coating.
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


def stack_reflectance(n_amb, cos_amb, n_sub, cos_sub, lam_nm, layers, *, sqrt=_dr_sqrt0, cos=dr.cos,
                      sin=dr.sin, sincos=None):
    """Unpolarised reflectance of a multilayer stack between an ambient medium (index ``n_amb``, cosine of the
    angle there ``cos_amb``) and a substrate (``n_sub``, ``cos_sub``), by the characteristic-matrix method.

    ``layers``: (index at each ray's wavelength, physical thickness in nm) per layer, **from the ambient
    inward**.  Plain arithmetic apart from ``sqrt``, ``cos`` and ``sin`` (or ``sincos``, both at once): Dr.Jit
    arrays (the default), numpy arrays (pass ``np.sqrt`` of a clamped argument, ``np.cos``, ``np.sin``) and the
    Taylor baseline's series all work.

    Per layer j, with c = cos θ_j and the s admittance η = n c: the s matrix is ``[[cos δ, i sin δ / η],
    [i η sin δ, cos δ]]`` and the p matrix the same with η_p = n / c; written with 1/n and 1/c so that a layer
    costs one square root, one reciprocal and one sine-cosine pair for both polarisations."""
    if sincos is None:
        sincos = dr.sincos if cos is dr.cos and sin is dr.sin else (lambda x: (sin(x), cos(x)))
    s2 = (n_amb * n_amb) * (1.0 - cos_amb * cos_amb)        # (n sin θ)², the same in every layer
    inv_lam = 1.0 / lam_nm
    mats = []
    for n_j, h_nm in layers:
        inv_n = 1.0 / n_j
        cos_j = sqrt(1.0 - s2 * (inv_n * inv_n))
        if not isinstance(cos_j, (int, float)):
            cos_j = _at_least(cos_j, 1e-6)
        sd, cd = sincos(((2.0 * math.pi * h_nm) * inv_lam) * (n_j * cos_j))
        mats.append((n_j, inv_n, cos_j, 1.0 / cos_j, cd, sd))
    total = 0.0
    for pol in ("s", "p"):
        a = b = c = d = None
        for n_j, inv_n, cos_j, inv_c, cd, sd in mats:
            # η and 1/η of this layer for this polarisation
            e, inv_e = (n_j * cos_j, inv_n * inv_c) if pol == "s" else (n_j * inv_c, inv_n * cos_j)
            b2, c2 = sd * inv_e, e * sd
            if a is None:
                a, b, c, d = cd, b2, c2, cd
            else:
                a, b, c, d = a * cd - b * c2, a * b2 + b * cd, c * cd + d * c2, d * cd - c * b2
        e0, es = (n_amb * cos_amb, n_sub * cos_sub) if pol == "s" else (n_amb / cos_amb, n_sub / cos_sub)
        re_n, im_n = e0 * a - es * d, e0 * es * b - c
        re_d, im_d = e0 * a + es * d, e0 * es * b + c
        total = total + (re_n * re_n + im_n * im_n) / (re_d * re_d + im_d * im_d)
    return 0.5 * total


def _at_least(x, lo):
    import numpy as np
    if isinstance(x, np.ndarray):
        return np.maximum(x, lo)
    if hasattr(x, "c0"):            # a truncated power series (Taylor baseline): its constant term is > 0
        return x
    return dr.maximum(x, lo)


def interface_reflectance(coating, m1, m2, n1, n2, cos_i, cos_t, lam_nm, layer_index, *, sqrt=_dr_sqrt0,
                          cos=dr.cos, sin=dr.sin):
    """Unpolarised reflectance of a surface between media ``m1`` (incident side, index ``n1``, incidence cosine
    ``cos_i``) and ``m2`` (``n2``, refraction cosine ``cos_t``) carrying ``coating`` (``None``, a single
    :class:`~mi_neurallens.optics.coatings.Coating` or a :class:`~mi_neurallens.optics.coatings.CoatingStack`).
    ``layer_index(medium)`` gives a stack layer's index at each ray's wavelength ``lam_nm`` (nm)."""
    if coating is None:
        return fresnel_reflectance(n1, n2, cos_i, cos_t)
    if not hasattr(coating, "layers"):
        return coated_reflectance(n1, n2, cos_i, cos_t, lam_nm, coating.index, coating.thickness_nm, sqrt=sqrt,
                                  cos=cos)
    layers = [(layer_index(l.medium), l.thickness_nm) for l in reversed(coating.layers)]
    if coating.ambient_is_first(m1, m2):
        return stack_reflectance(n1, cos_i, n2, cos_t, lam_nm, layers, sqrt=sqrt, cos=cos, sin=sin)
    return stack_reflectance(n2, cos_t, n1, cos_i, lam_nm, layers, sqrt=sqrt, cos=cos, sin=sin)
