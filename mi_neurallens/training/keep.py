"""What a run takes from a base model: which networks it keeps, and the finish-only runs.

A training may build on an existing model (``mi-neurallens train --base``), map by map:

* ``keep`` says what it keeps of each base map: ``"regressor"`` or ``"classifier"`` (the other network
  trains anew), or ``"networks"`` (both: only the stop heads train);
* ``finish_only`` says that it trains nothing anew and runs only the Levenberg–Marquardt finish
  (:mod:`~mi_neurallens.training.levenberg`), from the base's networks: ``"maps"`` (the regressors and
  classifiers, each widened first where the configuration asks; the stop heads kept) or ``"stop-heads"``
  (the stop heads alone; the networks kept).

The old spellings of ``keep`` are accepted as aliases (:data:`OLD_KEEP`, :func:`run_mode`): ``"both"`` for
``"networks"``, and ``"refine"`` / ``"refine-stop"``, which chose the finish-only runs.  A base map must be of
the same path, direction, planes and domain (:func:`check_keep`): only then do its networks' inputs and outputs
mean the same.  The module is light (no torch, no training configuration at import): the command line reads
its choices.
"""
from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np

from ..errors import NeuralLensError

if TYPE_CHECKING:
    from ..transport.planning import Domain
    from .config import NetConfig

#: what a run can keep of each base map (``keep``)
KEEP = ("regressor", "classifier", "networks")
#: the finish-only runs (``finish_only``)
FINISH_ONLY = ("maps", "stop-heads")
#: the old spellings of ``keep``: (keep, finish_only) each stands for
OLD_KEEP = {"both": ("networks", None), "refine": (None, "maps"), "refine-stop": (None, "stop-heads")}
#: what a finish-only run of the maps records as the kept network (``training["kept"]["network"]``): its name
#: in the model files written since before it had its own flag
FINISHED_RECORD = "refine"


def run_mode(keep: str | None, finish_only: str | None = None) -> tuple:
    """``(keep, finish_only)`` in today's spelling (:data:`KEEP`, :data:`FINISH_ONLY`; old spellings of ``keep``
    through :data:`OLD_KEEP`), or a :class:`~mi_neurallens.errors.NeuralLensError` for an unknown value or for
    both at once (a finish-only run keeps everything it does not finish)."""
    if keep in OLD_KEEP:
        old_finish = OLD_KEEP[keep][1]
        if finish_only is not None and old_finish is not None and finish_only != old_finish:
            raise NeuralLensError(f"keep = {keep!r} is finish_only = {old_finish!r}, not {finish_only!r}")
        keep, finish_only = OLD_KEEP[keep][0], finish_only or old_finish
    if keep is not None and keep not in KEEP:
        raise NeuralLensError(f"keep = {keep!r}: choose one of {list(KEEP)} (or None to train all)")
    if finish_only is not None and finish_only not in FINISH_ONLY:
        raise NeuralLensError(f"finish_only = {finish_only!r}: choose one of {list(FINISH_ONLY)} (or None)")
    if keep is not None and finish_only is not None:
        raise NeuralLensError(f"keep = {keep!r} with finish_only = {finish_only!r}: a finish-only run keeps what it "
                              "does not finish; give one of them")
    return keep, finish_only


def mode_text(keep: str | None, finish_only: str | None) -> str:
    """``keep = 'regressor'`` or ``finish_only = 'maps'``: how messages name a run's mode."""
    return f"finish_only = {finish_only!r}" if finish_only is not None else f"keep = {keep!r}"


def stop_heads_only(keep: str | None, finish_only: str | None) -> bool:
    """Whether the run trains (or finishes) only stop heads, its maps' networks kept bit for bit."""
    return keep == "networks" or finish_only == "stop-heads"


def check_keep(keep: str | None, finish_only: str | None, base, path_id: int, direction: str, z_in: float,
               z_out: float, domain: Domain):
    """Validate a run's mode and base map (:func:`run_mode`): the networks kept or finished must come from a map
    of the same path, direction, planes (mm) and domain."""
    from ..transport.planning import Domain
    keep, finish_only = run_mode(keep, finish_only)
    if keep is None and finish_only is None:
        return
    what = mode_text(keep, finish_only)
    if base is None:
        raise NeuralLensError(f"{what} needs the map whose networks are kept or finished (base)")
    want = (int(path_id), direction)
    if (int(base.path_id), base.direction) != want:
        raise NeuralLensError(f"{what}: the base map is {base.key}, not {direction}.{path_id}")
    if abs(base.z_in - z_in) > 1e-9 or abs(base.z_out - z_out) > 1e-9:
        raise NeuralLensError(f"{what}: the base map {base.key} uses planes z = {base.z_in:g} -> "
                              f"{base.z_out:g} mm, this training {z_in:g} -> {z_out:g} mm (another close_focus_mm?)")
    bd = Domain.from_dict(base.domain)
    if not np.allclose([bd.r_max, bd.s_max, bd.lam_min, bd.lam_max],
                       [domain.r_max, domain.s_max, domain.lam_min, domain.lam_max], rtol=1e-9, atol=0.0):
        raise NeuralLensError(f"{what}: the base map {base.key} was trained on another input domain "
                              f"({base.domain}) than this training ({domain.to_dict()})")
    if bd.reach != domain.reach:
        raise NeuralLensError(f"{what}: the base map {base.key} was trained with film reach {bd.reach}, "
                              f"this training with {domain.reach}")


def kept_network(base, network: str) -> dict:
    """``network`` ("regressor" or "classifier") of the map ``base`` in the form the trainers return, with
    the training state and configuration it was trained with (read back from ``base.training``)."""
    t = base.training
    state = {"step": t.get(f"{network}_steps", 0), "seconds": t.get(f"{network}_seconds", 0.0),
             "stop_reason": t.get(f"{network}_stop"), "samples": t.get(f"{network}_samples", 0),
             "history": t.get(f"{network}_history", [])}
    out = {"layers": [(np.asarray(W, np.float64), np.asarray(b, np.float64))
                      for W, b in getattr(base, network)], "state": state, "config": t.get(network, {}),
           "activation": getattr(base, f"{network}_activation")}
    if network == "regressor":
        out.update(skip=np.asarray(base.skip), out_shift=np.asarray(base.out_shift),
                   out_scale=np.asarray(base.out_scale), odd_y=bool(base.odd_y),
                   position_cos=bool(base.position_cos))
    return out


def widened(kept: dict, nc: NetConfig, base, log) -> dict:
    """A finish-only run's start: the network ``kept`` (:func:`kept_network`) as it is, or, where ``nc`` asks for
    the same number of hidden layers but wider ones (``--set forward_regressor.width=32`` on a 3×16 map), widened to
    ``nc.width`` without changing what it computes (:func:`~mi_neurallens.training.levenberg.widen`), so the
    finish continues from the optimum it had with room to go lower.  Any other architecture in ``nc`` is ignored:
    the finish keeps the base's."""
    from .levenberg import widen_as_configured
    layers, hidden = widen_as_configured(kept["layers"], nc.hidden, nc.width, [int(base.path_id), int(nc.width)])
    if hidden is None:
        return kept
    if log:
        log(f"{base.key} widened", {"from": "x".join(map(str, hidden)), "to": f"{nc.hidden}x{nc.width}"})
    return {**kept, "layers": layers, "config": {**kept.get("config", {}), "width": int(nc.width),
                                                  "widened_from": hidden}}


def carry_history(result: dict, kept: dict) -> None:
    """A finished network's record: its configuration, activation and Adam history from the map it started
    from (``kept``, :func:`kept_network`), then the Levenberg–Marquardt validations; samples and seconds add up."""
    st, st0 = result["state"], kept["state"]
    result["config"], result["activation"] = kept["config"], kept["activation"]
    st["history"] = list(st0.get("history", [])) + st["history"]
    st["samples"] = int(st0.get("samples", 0)) + int(st.get("samples", 0))
    st["seconds"] = float(st0.get("seconds", 0.0)) + float(st.get("seconds", 0.0))
    st["adam_stop_reason"] = st0.get("stop_reason")


def finishing_config(nc: NetConfig, network: str, bases) -> NetConfig:
    """The settings of a finish-only run of ``network``: ``nc`` as configured (:func:`check_finish_only` has made
    sure it gives the finish some time); a classifier keeps the target (and its scale) it was trained with, so
    the finish minimises the loss its weights were made for."""
    if network == "classifier":
        got = {tuple(b.training.get("classifier", {}).get(k, getattr(nc, k))
                     for k in ("target", "margin_scale", "margin_clip")) for b in bases}
        if len(got) != 1:
            raise NeuralLensError(f"finish_only: the classifiers of one run must share their target, got "
                                  f"{sorted(got)}")
        target, scale, clip = got.pop()
        nc = dataclasses.replace(nc, target=target, margin_scale=float(scale), margin_clip=float(clip))
    return nc


def check_finish_only(bases, nets, direction: str) -> None:
    """:func:`~mi_neurallens.training.levenberg.check_finishable` for each network a finish-only run of the maps
    finishes, all before any training (not after the other network's finish): one given no time for the finish,
    or larger than it takes (a 5×32 regressor, or one the configured width would widen past it), is a clear error
    naming the way out.  ``nets``: (network, its NetConfig) pairs."""
    from .levenberg import check_finishable
    for network, nc in nets:
        table = f"forward_{network}" if direction == "forward" else network
        other = "classifier" if network == "regressor" else "regressor"
        check_finishable([(b.key, getattr(b, network)) for b in bases], nc, f"the {network}'s", table,
                         f"--keep {other} --set {table}.hidden=3 --set {table}.width=32 --set {table}.lm_minutes=2.5",
                         what=f"--finish-only maps: the {network} of ")
