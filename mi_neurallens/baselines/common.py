"""What every baseline shares: the map planes and domains of the neural maps, the base of the
baseline maps, and normal-incidence Fresnel factors.

The planes and domains come from the bundled model, or, where there is none, from
:mod:`mi_neurallens.transport.planes` with the lens's training recipe (its close focus): nothing here imports
``mi_neurallens.training``.

Every baseline is a :class:`~mi_neurallens.transport.base.TransportMap` from an input plane ``z_in`` to
an output plane ``z_out`` (lens space, mm) for one path id and direction: it provides only its core,
the base class moves, reduces, checks and undoes (``eval_dr``, ``eval_np``).
"""
from __future__ import annotations

import math
import os

import numpy as np

from ..transport import planes
from ..transport.base import TransportMap, heading_of
from ..transport.planning import Domain

LAM0_NM = 550.0      # expansion / normalisation centre of the wavelength variable
LAM_SCALE_NM = 100.0  # l = (λ − 550 nm) / 100 nm


# ----------------------------------------------------------------------------- planes and domains
def bundled_model(lens):
    """The bundled neural model of ``lens`` (None when there is none or it does not load)."""
    from ..errors import ModelError
    from ..neural.model import bundled_model_path, load_model
    p = bundled_model_path(lens.name)
    if not os.path.exists(p):
        return None
    try:
        return load_model(p, lens)
    except ModelError:
        return None


def default_planes(lens, model=None):
    """(z_front, z_rear, (s_min, s_max)) as the neural maps use them: the bundled model's when there is
    one, else :func:`mi_neurallens.transport.planes.planes` with the close focus of the lens's training recipe
    (:func:`~mi_neurallens.transport.planes.recipe_close_focus`)."""
    model = bundled_model(lens) if model is None else model
    if model is not None:
        return model.z_front, model.z_rear, tuple(model.sensor_distance_range)
    s0, s1 = planes.sensor_distance_range(lens, planes.recipe_close_focus(lens.name))
    zf, zr = planes.planes(lens, s0)
    return zf, zr, (s0, s1)


def default_map_planes(lens, direction: str, model=None):
    """(z_in, z_out) of a neural map in ``direction``: forward z_front → z_rear, backward the reverse."""
    zf, zr, _ = default_planes(lens, model)
    return (zf, zr) if direction == "forward" else (zr, zf)


def default_domain(lens, path_id: int, direction: str, model=None, seed: int = 1):
    """The reduced input domain the neural map of (path, direction) uses (or would use):
    the model's stored domain when present; forward: :func:`~mi_neurallens.transport.planes.forward_domain`
    over the default field; backward: the pilot-traced :func:`~mi_neurallens.transport.planes.backward_domain`."""
    model = bundled_model(lens) if model is None else model
    if model is not None and model.has(path_id, direction):
        return Domain.from_dict(model.map(path_id, direction).domain)
    if model is not None:  # same domain as any other map of that direction
        for m in model.maps.values():
            if m.direction == direction and (direction == "forward" or m.path_id == path_id):
                return Domain.from_dict(m.domain)
    zf, zr, _ = default_planes(lens, model)
    if direction == "forward":
        return planes.forward_domain(lens, zf, planes.default_field_half_angle(lens))
    return planes.backward_domain(lens, path_id, zr, zf, np.random.default_rng(seed), n=1 << 20)


# ----------------------------------------------------------------------------- Fresnel at normal incidence
def fresnel_normal_R(m1, m2, coating=None, lam_nm=550.0):
    """Unpolarised reflectance (float) at normal incidence between media ``m1`` and ``m2`` at ``lam_nm`` (nm),
    with the surface's coating: the tracer's formulas (:mod:`mi_neurallens.trace.interactions`) at cos = 1."""
    from ..trace.interactions import interface_reflectance
    lam = float(lam_nm)
    return float(interface_reflectance(coating, m1, m2, float(m1.index(lam)), float(m2.index(lam)), 1.0, 1.0, lam,
                                       lambda m: float(m.index(lam)), sqrt=math.sqrt, cos=math.cos, sin=math.sin))


# ----------------------------------------------------------------------------- the baseline maps
class BaselineMap(TransportMap):
    """A baseline map of ``lens`` for (``path``, ``direction``) from ``z_in`` to ``z_out`` (default: the
    neural maps' planes, :func:`default_map_planes`); provides only its core (see
    :class:`~mi_neurallens.transport.base.TransportMap`)."""

    def __init__(self, lens, path, direction, z_in, z_out):
        from ..trace.paths import resolve_path
        heading_of(direction)
        self.lens = lens
        self.spec = resolve_path(lens, path, direction)
        self.path_id = self.spec.id
        self.direction = direction
        if z_in is None or z_out is None:
            zi, zo = default_map_planes(lens, direction)
            z_in = zi if z_in is None else z_in
            z_out = zo if z_out is None else z_out
        self.z_in, self.z_out = float(z_in), float(z_out)


class LensSpacePolyMap(BaselineMap):
    """A map given by one :class:`~.poly.SparsePoly` ``core`` of the lens-space inputs
    ``(x, y, a, b, λ)`` on ``z_in`` — ``(a, b)`` the direction cosines (``angles = "cosines"``) or the
    slopes dx/dz, dy/dz (``"slopes"``) — with outputs ``[X, Y, A, B, T, ax_0, ay_0, ax_1, ay_1, …]``:
    position on ``z_out``, direction in the same parametrisation, throughput, and for each aperture
    check k the position (ax_k, ay_k) whose radius must not exceed ``self.ap_radii[k]``."""

    angles = "cosines"

    def _setup_core(self, core, ap_radii):
        self.core = core
        self.ap_radii = [float(r) for r in ap_radii]

    def flops(self) -> int:
        return self.core.flops() + 12 + 3 * len(self.ap_radii)

    def core_dr(self, p, d, lam, active):
        import drjit as dr
        px, py = p
        dx, dy, dz = d
        if self.angles == "cosines":
            a, b = dx, dy
        else:
            inv = 1.0 / dz
            a, b = dx * inv, dy * inv
        y = self.core.eval_dr([px, py, a, b, lam])
        valid = active
        for k, R in enumerate(self.ap_radii):
            ax, ay = y[5 + 2 * k], y[6 + 2 * k]
            valid &= dr.fma(ax, ax, ay * ay) <= R * R
        h = float(self.heading)
        A, B = y[2], y[3]
        if self.angles == "cosines":
            s2 = dr.fma(A, A, B * B)
            valid &= s2 < 1.0
            D = (A, B, h * dr.sqrt(dr.maximum(1.0 - s2, 0.0)))
        else:
            inv = h * dr.rsqrt(dr.fma(A, A, dr.fma(B, B, 1.0)))   # d = h·(sx, sy, 1)/‖·‖
            D = (A * inv, B * inv, inv)
        X, Y = y[0], y[1]
        valid &= dr.isfinite(X) & dr.isfinite(Y)
        return valid, (X, Y), D, y[4]
