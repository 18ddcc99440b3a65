"""The lens transport map: one interface for sending a ray from one plane to another through the lens.

* :mod:`.base` — :class:`TransportMap` (move → reduce → domain → core → undo, written once) and its
  result :class:`MapResult`;
* :mod:`.exact` — :class:`ExactMap`, the tracer behind the interface;
* :mod:`.planning` — the reduced input :class:`Domain` and the wavelength sampler (runtime, no torch);
* :mod:`.planes` — where a lens's maps live: planes, sensor distances, default domains;
* :mod:`.sampling` and :mod:`.bounds` — the exact map sampled over its reduced domain (training data, held-out
  sets, the fitted baseline's fit, the accuracy tables), with pilot-traced bounds of the valid region;
* the learned map is :class:`mi_neurallens.neural.model.NeuralMap`; the polynomial baselines live in
  :mod:`mi_neurallens.baselines` (imported only when one is asked for).

Build any of them by name with :func:`make_map`.
"""
from __future__ import annotations

from ..errors import NeuralLensError
from .base import MapResult, TransportMap, heading_of
from .exact import ExactMap
from .planning import Domain

#: the map methods :func:`make_map` builds (``taylor3``/``taylor5``: ``taylor`` of that degree)
METHODS = ("exact", "neural", "abcd", "taylor", "taylor3", "taylor5", "fitted")

__all__ = ["METHODS", "make_map", "MapResult", "TransportMap", "ExactMap", "Domain", "heading_of"]


def make_map(lens, method: str, path="transmit", direction: str = "backward", z_in=None, z_out=None,
             **opts) -> TransportMap:
    """The ``method`` map of ``lens`` for (``path``, ``direction``) from ``z_in`` to ``z_out`` (mm).

    ``z_in``/``z_out`` default to the neural maps' planes (forward: z_front → z_rear; backward the
    reverse; :func:`mi_neurallens.baselines.common.default_map_planes`).  ``opts`` go to the method's
    constructor; ``neural`` takes ``model`` (a :class:`~mi_neurallens.neural.model.NeuralLensModel` or a
    file; default the lens's bundled model) and refuses planes other than the model's.
    """
    m = method.lower()
    if m not in METHODS:
        raise NeuralLensError(f"unknown method {method!r}; known: {', '.join(METHODS)}")
    if m == "neural":
        from ..neural.model import NeuralLensModel, bundled_model_path, load_model
        model = opts.pop("model", None)
        if model is None:
            model = load_model(bundled_model_path(lens.name), lens)
        elif not isinstance(model, NeuralLensModel):
            model = load_model(model, lens)
        tm = model.map(0 if path == "transmit" else path, direction)
        for name, want, have in (("z_in", z_in, tm.z_in), ("z_out", z_out, tm.z_out)):
            if want is not None and abs(float(want) - have) > 1e-6:
                raise NeuralLensError(f"neural map {tm.key} of '{lens.name}' has {name} = {have:.6g} mm, "
                                      f"not {float(want):.6g} mm; retrain or use its planes")
        return tm
    if z_in is None or z_out is None:
        from ..baselines.common import default_map_planes
        zi, zo = default_map_planes(lens, direction)
        z_in = zi if z_in is None else z_in
        z_out = zo if z_out is None else z_out
    if m == "exact":
        return ExactMap(lens, path, direction, z_in, z_out, **opts)
    from .. import baselines
    if m == "abcd":
        return baselines.ABCDMap(lens, path, direction, z_in, z_out, **opts)
    if m == "fitted":
        return baselines.FittedMap(lens, path, direction, z_in, z_out, **opts)
    if m != "taylor":
        opts.setdefault("degree", int(m[-1]))
    return baselines.TaylorMap(lens, path, direction, z_in, z_out, **opts)
