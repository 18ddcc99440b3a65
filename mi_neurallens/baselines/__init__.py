"""Baselines for the neural lens transport maps (docs/baselines.md).

Every method maps rays from an input plane ``z_in`` to an output plane ``z_out`` (lens space, mm) for
one path id and direction, with the interface of :class:`~mi_neurallens.neural.model.TransportMap`
(``eval_np(o, d, lam_nm)`` → dict, ``eval_dr(o, d, lam_nm, active=True)`` → ``(valid, (position,
direction, throughput))``):

* ``exact``  — the Dr.Jit tracer (:class:`ExactMap`), the reference;
* ``neural`` — the bundled learned map (:class:`~mi_neurallens.neural.model.TransportMap`);
* ``abcd``   — paraxial 4×4 matrices (:mod:`.abcd`);
* ``taylor`` — Taylor polynomial optics, degree 3 or 5 (:mod:`.taylor`; ``taylor3``/``taylor5``);
* ``fitted`` — sparse polynomials fitted to traced rays (:mod:`.fitted`).

Build one with :func:`make_method`.
"""
from __future__ import annotations

import numpy as np

from ..errors import NeuralLensError
from .abcd import ABCDMap
from .common import BaselineMap, default_domain, default_map_planes
from .fitted import FittedMap
from .taylor import TaylorMap

METHODS = ("exact", "neural", "abcd", "taylor", "taylor3", "taylor5", "fitted")

__all__ = ["METHODS", "make_method", "ExactMap", "ABCDMap", "TaylorMap", "FittedMap", "default_domain",
           "default_map_planes"]


class ExactMap(BaselineMap):
    """The exact tracer behind the same interface (float type of the inputs; ``fresnel`` throughput)."""

    method = "exact"

    def __init__(self, lens, path="transmit", direction="forward", z_in=None, z_out=None, *,
                 fresnel: bool = True, precision: str = "float64"):
        super().__init__(lens, path, direction, z_in, z_out)
        from ..trace.tracer import LensTracer
        self.tracer = LensTracer(lens, fresnel=fresnel)
        self.precision = precision

    def eval_dr(self, o, d, lam_nm, active=True):
        import drjit as dr
        t = (self.z_in - o[2]) / d[2]
        o = (dr.fma(t, d[0], o[0]), dr.fma(t, d[1], o[1]), o[2] * 0.0 + self.z_in)
        res = self.tracer.trace(o, d, lam_nm, self.spec, self.direction, z_out=self.z_out, active=active)
        return res.valid, (res.position, res.direction, res.throughput)

    def eval_np(self, o, d, lam_nm):
        from ..trace.api import trace
        o = np.asarray(o, np.float64)
        d = np.asarray(d, np.float64)
        t = (self.z_in - o[:, 2]) / d[:, 2]
        o = o + t[:, None] * d
        r = trace(self.lens, o, d, lam_nm, direction=self.direction, path=self.path_id,
                  fresnel=self.tracer.fresnel, precision=self.precision, z_out=self.z_out)
        return {"valid": r.valid, "position": r.position, "direction": r.direction, "throughput": r.throughput}

    def flops(self) -> int:
        return 0


def make_method(lens, method: str, path="transmit", direction: str = "backward", z_in=None, z_out=None,
                **opts):
    """Build the map of ``method`` for (``path``, ``direction``) from ``z_in`` to ``z_out``.

    ``z_in``/``z_out`` default to the neural maps' planes (forward: z_front → z_rear; backward the
    reverse).  ``opts`` go to the method's constructor (see each class); ``neural`` accepts ``model``
    (a :class:`~mi_neurallens.neural.model.NeuralLensModel` or file; default the bundled one).
    ``taylor3``/``taylor5`` are ``taylor`` with ``degree`` 3/5.
    """
    m = method.lower()
    if m == "exact":
        return ExactMap(lens, path, direction, z_in, z_out, **opts)
    if m == "abcd":
        return ABCDMap(lens, path, direction, z_in, z_out, **opts)
    if m in ("taylor", "taylor3", "taylor5"):
        if m != "taylor":
            opts.setdefault("degree", int(m[-1]))
        return TaylorMap(lens, path, direction, z_in, z_out, **opts)
    if m == "fitted":
        return FittedMap(lens, path, direction, z_in, z_out, **opts)
    if m == "neural":
        from ..neural.model import NeuralLensModel, bundled_model_path, load_model
        model = opts.pop("model", None)
        if model is None:
            model = load_model(bundled_model_path(lens.name), lens)
        elif not isinstance(model, NeuralLensModel):
            model = load_model(model, lens)
        pid = 0 if path == "transmit" else path
        tm = model.map(pid, direction)
        for name, want, have in (("z_in", z_in, tm.z_in), ("z_out", z_out, tm.z_out)):
            if want is not None and abs(float(want) - have) > 1e-6:
                raise NeuralLensError(f"neural map {tm.key} of '{lens.name}' has {name} = {have:.6g} mm, "
                                      f"not {float(want):.6g} mm; retrain or use its planes")
        return tm
    raise NeuralLensError(f"unknown method {method!r}; known: {', '.join(METHODS)}")
