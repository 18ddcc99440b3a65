"""Training the maps of one direction: each map's classifier, regressor and stop head, the maps together.

:func:`train_maps` trains several maps of one direction at once: their regressors as one stack, then their
classifiers, then their stop heads per stop-crossing count (:mod:`~mi_neurallens.training.stacked`: stacked
weights, batched products, each network leaving when it meets its goals), each network at the smallest
architecture of ``NetConfig.sizes`` that meets its goals (:func:`train_sized`).  One map
(:func:`train_map`) is a stack of one.  A run may build on a base model's maps instead
(:mod:`~mi_neurallens.training.keep`: networks kept, or only their Levenberg–Marquardt finish).

Each map's data, held-out sets and initial weights are seeded from (``cfg.seed``, path, direction)
(:func:`map_seed`); its problems (:func:`regressor_problem`, :func:`classifier_problem`) say what each network is
trained and validated on.  Checkpoints (``<workdir>/<stack>.ckpt.safetensors`` + ``.json``; tensors only, never
pickle) hold weights, Adam state, best weights, steps and histories; they are written atomically every minute
and at the end.  A rerun with the same workdir resumes from them; a finished stack is not retrained.
"""
from __future__ import annotations

import dataclasses
import math
import os
import time

import numpy as np

from ..errors import NeuralLensError
from .classifier import calibrate_classifier, train_classifiers
from .config import NetConfig, TrainConfig, parse_size
from ..transport.planning import Domain
from ..transport.sampling import PathSampler, heldout_valid
from .data import RegressorStream
from .evaluate import map_outputs_np
from .keep import (FINISHED_RECORD, carry_history, check_finish_only, check_keep, finishing_config, kept_network,
                   run_mode, stop_heads_only, widened)
from .nets import load_torch, pick_device
from .regressor import train_regressors

#: rays uniform over the domain that pick the classifier's best weights
CLASSIFIER_VALIDATION = 400_000


# ----------------------------------------------------------------------------- the maps' problems
def map_seed(cfg: TrainConfig, path_id: int, direction: str) -> int:
    """The seed of one map (its data streams, held-out sets and initial weights)."""
    return int(cfg.seed) * 1_000_003 + int(path_id) * 2 + (direction == "forward")


#: held-out rays a regressor is validated on (fewer where ``heldout`` is smaller)
REGRESSOR_VALIDATION = 20_000
#: ... and one whose goals are checked at the corners of its configurations (``goal_corners``): a corner holds about
#: 1.3 % of the rays (the EF 24-70's 200-270 of 20 000), and a cell's median needs
#: :data:`~mi_neurallens.transport.configurations.CELL_MIN_RAYS`
CORNER_VALIDATION = 100_000


def regressor_problem(lens, spec, stream, seed: int, key: str, cfg: TrainConfig, corners: bool = False) -> dict:
    """One map's problem for :func:`~mi_neurallens.training.regressor.train_regressors`: ``spec`` = (path_id,
    direction, z_in, z_out, domain), ``stream`` its :class:`~mi_neurallens.training.data.RegressorStream`,
    validated on ≤ :data:`REGRESSOR_VALIDATION` (``corners``: :data:`CORNER_VALIDATION`) held-out valid rays traced
    with ``seed + 7``."""
    p, d, zi, zo, dom = spec
    center, scale_in = dom.norm_center_scale()
    n_val = CORNER_VALIDATION if corners and dom.conditions is not None else REGRESSOR_VALIDATION
    val = heldout_valid(lens, (p, d, zi, zo), dom, min(cfg.heldout, n_val), seed + 7, cfg.mcmc_threshold,
                        cfg.fresnel)
    return dict(stream=stream, val=val, heading=1 if d == "forward" else -1, center=center, scale_in=scale_in,
                seed=seed, s_max=dom.s_max, key=key)


def classifier_validation_size(cfg: TrainConfig) -> int:
    """Rays of a classifier's validation set: :data:`CLASSIFIER_VALIDATION`, or 4 × ``cfg.heldout`` where that is
    fewer (a quick run with a small held-out set validates its classifier on fewer rays too)."""
    return min(CLASSIFIER_VALIDATION, 4 * int(cfg.heldout))


def classifier_problem(lens, spec, ps, stream, seed: int, key: str, cfg: TrainConfig) -> dict:
    """One map's problem for :func:`~mi_neurallens.training.classifier.train_classifiers`: ``ps`` its float32
    :class:`~mi_neurallens.transport.sampling.PathSampler`, valid inputs drawn from ``stream``; validated on the
    natural mix (:func:`classifier_validation_size` rays uniform over the domain, float64 labels, ``seed + 11``) —
    large, because only the few rays near the boundary tell two good classifiers apart (0.02 % of 400 k = 80
    errors)."""
    p, d, zi, zo, dom = spec
    psv = PathSampler(lens, p, d, zi, zo, dom, fresnel=cfg.fresnel, precision="float64")
    xcv = dom.u_to_x(np.random.default_rng(seed + 11).random((classifier_validation_size(cfg), dom.dims)))
    lcv, _ = psv.trace_x(xcv)
    center, scale_in = dom.norm_center_scale()
    return dict(ps=ps, valid_u_source=(lambda n, s=stream: s.sample(n)[0]), val=(xcv, lcv), center=center,
                scale_in=scale_in, seed=seed + 1, key=key)


# ----------------------------------------------------------------------------- the architecture ladder
def train_sized(train, problems, nc: NetConfig, ckpt, net: str, **kw) -> list:
    """Train one network per problem with ``train``
    (:func:`~mi_neurallens.training.regressor.train_regressors` or
    :func:`~mi_neurallens.training.classifier.train_classifiers`),
    trying the architectures of ``nc.sizes`` smallest first: every map starts at the first size; a map
    whose network met its goals there keeps it (``stop_reason == "goals"``), the others move on to the next
    size, and at the last size every map keeps what it got.  So each map ends with the smallest network
    that meets its goals within ``nc.max_minutes`` per size — the cheapest to evaluate in a render — and a
    map that needs a large one pays the small ones' budgets first.  Without ``nc.sizes`` it is ``train``
    at ``nc.hidden`` × ``nc.width``.  ``ckpt(name, keys)`` → the checkpoint path of the stack of the maps
    ``keys`` for the network ``name`` (``net``, or ``net-HxW`` with sizes), or None; ``net``: "regressor" or
    "classifier".  Each result carries its ``config`` (the size it was trained at; its ``state`` is that
    size's run) and ``sizes_tried``: per size, its stop reason, seconds, steps and best validation score."""
    sizes = [parse_size(z) for z in nc.sizes] or [(nc.hidden, nc.width)]
    out = [None] * len(problems)
    tried = [[] for _ in problems]
    todo = list(range(len(problems)))
    for i, (h, w) in enumerate(sizes):
        ncs = dataclasses.replace(nc, hidden=h, width=w)
        keys = [problems[j]["key"] for j in todo]
        name = net if not nc.sizes else f"{net}-{h}x{w}"
        desc = f"{len(keys)} {net}s" if len(keys) > 1 else f"{keys[0]} {net}"
        if nc.sizes:
            desc += f" {h}x{w}"
        res = train([problems[j] for j in todo], ncs, ckpt=ckpt(name, keys), desc=desc, **kw)
        last, nxt = i == len(sizes) - 1, []
        for j, r in zip(todo, res):
            st = r["state"]
            tried[j].append({"size": f"{h}x{w}", "stop": st.get("stop_reason"), "seconds": st.get("seconds"),
                             "steps": st.get("step"),
                             "best_val": st["best_val"] if math.isfinite(st.get("best_val", math.inf)) else None})
            if st.get("stop_reason") == "goals" or last:
                out[j] = {**r, "config": dataclasses.asdict(ncs), "sizes_tried": tried[j]}
            else:
                nxt.append(j)
        todo = nxt
        if not todo:
            break
    return out


# ----------------------------------------------------------------------------- one network of every map
def _train_networks(train, problems, nc: NetConfig, net: str, ck, keys, cfg: TrainConfig, finish_from,
                    progress: bool, log) -> list:
    """One network (``net``: "regressor" or "classifier") of every map of ``problems`` with ``train``
    (:func:`~mi_neurallens.training.regressor.train_regressors` or
    :func:`~mi_neurallens.training.classifier.train_classifiers`): through :func:`train_sized`, or, with
    ``finish_from`` (one base map per problem), only the Levenberg–Marquardt finish from the base maps'
    networks, their records carried (:func:`~mi_neurallens.training.keep.carry_history`)."""
    kw = dict(threads=cfg.threads, device=cfg.device, progress=progress, log=log)
    if finish_from is None:
        return train_sized(train, problems, nc, ck, net, **kw)
    kept = [widened(kept_network(b, net), nc, b, log) for b in finish_from]
    # "-refine": the checkpoint name finish-only runs have had since before their flag (a rerun resumes from it)
    out = train(problems, finishing_config(nc, net, finish_from), ckpt=ck(f"{net}-refine", keys), start=kept, **kw)
    for r, k in zip(out, kept):
        carry_history(r, k)
    return out


# ----------------------------------------------------------------------------- the maps of one direction
def train_map(lens, path_id: int, direction: str, z_in: float, z_out: float, domain: Domain, cfg: TrainConfig,
              workdir: str | None = None, progress: bool = True, log=None, evaluate: bool = True,
              eval_n: int | None = None, keep: str | None = None, base=None, finish_only: str | None = None):
    """Train the classifier, regressor and stop head of one map; returns a
    :class:`~mi_neurallens.neural.model.NeuralMap` with held-out metrics (:func:`train_maps` of one map).

    The stop head (:mod:`~mi_neurallens.training.stop_head`) is trained when the path crosses the stop
    plane and ``cfg.stop.max_minutes > 0``; with a ``base``, a stop head the base map has is kept.
    ``keep = "networks"`` keeps the classifier and the regressor and trains only the stop head (what adds a
    render-time aperture to a shipped map without changing anything else it outputs).
    ``keep = "regressor"`` (or ``"classifier"``) takes that network unchanged from ``base`` (a
    :class:`~mi_neurallens.neural.model.NeuralMap` of the same path, planes and domain) and trains only
    the other one: e.g. a longer or wider classifier for a ghost whose flare error sits on its edge,
    without paying for (or changing) its regressor.  The kept network's training record is carried over
    under ``training["kept"]``.  ``finish_only = "maps"`` starts both networks from the base's and runs only
    their Levenberg–Marquardt finish (``lm_minutes`` per network); ``"stop-heads"`` keeps both networks and runs
    only the finish of the base's stop head.  ``keep``'s old spellings are accepted
    (:func:`~mi_neurallens.training.keep.run_mode`)."""
    keep, finish_only = run_mode(keep, finish_only)
    check_keep(keep, finish_only, base, path_id, direction, z_in, z_out, domain)
    if stop_heads_only(keep, finish_only):
        return _add_stop_heads(lens, [base], cfg, [map_seed(cfg, path_id, direction)], progress, log,
                               finish=finish_only == "stop-heads")[0]
    return train_maps(lens, [(path_id, direction, z_in, z_out, domain)], cfg, workdir, progress=progress, log=log,
                      evaluate=evaluate, eval_n=eval_n, keep=keep, bases=None if base is None else [base],
                      finish_only=finish_only)[0]


def train_maps(lens, specs, cfg: TrainConfig, workdir: str | None = None, progress: bool = True, log=None,
               evaluate: bool = True, eval_n: int | None = None, keep: str | None = None, bases=None,
               finish_only: str | None = None) -> list:
    """Train several maps of ``lens`` together: all their regressors as one stack, then all their
    classifiers, then their stop heads (one stack per stop-crossing count), each network leaving its stack
    when it meets its goals (:mod:`~mi_neurallens.training.stacked`).  ``specs``: (path_id, direction,
    z_in, z_out, domain) per map, all of one direction.  ``keep``/``finish_only``/``bases``: as :func:`train_map`,
    one base map per spec.  Returns the :class:`~mi_neurallens.neural.model.NeuralMap` s, in order, each with
    ``training["phase_seconds"]``: the wall seconds of this call's phases, which its maps share."""
    from .evaluate import evaluate_map
    from .stacked import stack_name
    keep, finish_only = run_mode(keep, finish_only)
    specs = [(int(p), d, float(zi), float(zo), dom) for p, d, zi, zo, dom in specs]
    dirs = {d for _, d, *_ in specs}
    if len(dirs) != 1:
        raise NeuralLensError(f"train_maps: one direction per call, got {sorted(dirs)}")
    direction = dirs.pop()
    for j, (p, d, zi, zo, dom) in enumerate(specs):
        check_keep(keep, finish_only, None if bases is None else bases[j], p, d, zi, zo, dom)
    seeds = [map_seed(cfg, p, d) for p, d, *_ in specs]
    if stop_heads_only(keep, finish_only):
        return _add_stop_heads(lens, bases, cfg, seeds, progress, log, finish=finish_only == "stop-heads")
    keys = [f"{d}.{p}" for p, d, *_ in specs]
    rc, cc = cfg.net("regressor", direction), cfg.net("classifier", direction)
    finish_from = bases if finish_only == "maps" else None
    if finish_from is not None:
        check_finish_only(bases, (("regressor", rc), ("classifier", cc)), direction)
    ck = (lambda net, ks: os.path.join(workdir, stack_name(net, ks) + ".ckpt")) if workdir else (lambda net, ks: None)
    t0 = time.perf_counter()
    samplers, streams = [], []
    for (p, d, zi, zo, dom), seed in zip(specs, seeds):
        samplers.append(PathSampler(lens, p, d, zi, zo, dom, fresnel=cfg.fresnel))
        streams.append(RegressorStream(samplers[-1], seed, cfg.mcmc_threshold, cfg.mcmc_chains, cfg.mcmc_p_large,
                                       cfg.mcmc_sigma))
    if keep == "regressor":
        regs = [kept_network(b, "regressor") for b in bases]
    else:
        problems = [regressor_problem(lens, spec, stream, seed, key, cfg, rc.goal_corners)
                    for spec, seed, stream, key in zip(specs, seeds, streams, keys)]
        regs = _train_networks(train_regressors, problems, rc, "regressor", ck, keys, cfg, finish_from, progress, log)
    t1 = time.perf_counter()
    if keep == "classifier":
        clss = [kept_network(b, "classifier") for b in bases]
    else:
        problems = [classifier_problem(lens, spec, ps, stream, seed, key, cfg)
                    for spec, seed, stream, ps, key in zip(specs, seeds, streams, samplers, keys)]
        clss = _train_networks(train_classifiers, problems, cc, "classifier", ck, keys, cfg, finish_from, progress,
                               log)
    t2 = time.perf_counter()
    record = {"stacked_with": len(specs), "wall_seconds_this_run": t2 - t0, "regressor_wall_this_run": t1 - t0}
    tms = [_neural_map(lens, spec, reg, cls, stream, cfg, (rc, cc), (keep, finish_only),
                       None if bases is None else bases[j], seeds[j], record)
           for j, (spec, reg, cls, stream) in enumerate(zip(specs, regs, clss, streams))]
    t3 = time.perf_counter()
    based = keep is not None or finish_only is not None
    heads = _stop_heads_of(lens, tms, cfg, seeds, progress, log, bases if based else None, streams=streams)
    t4 = time.perf_counter()
    for tm, head, seed in zip(tms, heads, seeds):
        tm.stop_head = head
        if evaluate:
            tm.metrics = evaluate_map(lens, tm, n=eval_n or cfg.heldout, seed=seed + 99,
                                      mcmc_threshold=cfg.mcmc_threshold, fresnel=cfg.fresnel)
    # where this call's wall time went (the maps of one call share it): each phase with its data set-up
    phases = {"regressor": t1 - t0, "classifier": t3 - t1, "stop": t4 - t3, "evaluation": time.perf_counter() - t4}
    for tm in tms:
        tm.training["phase_seconds"] = {**phases, "maps": len(tms)}
    return tms


def _neural_map(lens, spec, reg: dict, cls: dict, stream, cfg: TrainConfig, ncs, mode, base, seed: int,
                record: dict):
    """One map of :func:`train_maps` from its trained (or kept) regressor ``reg`` and classifier ``cls``: a
    :class:`~mi_neurallens.neural.model.NeuralMap` (no stop head yet) with its training record — both networks'
    configurations, steps, seconds, stop reasons, samples and histories, the data sampler's, the kept network's
    origin (``mode`` = (keep, finish_only), ``base``) and ``record`` (the call's shared entries) — and its
    classifier calibrated (:func:`~mi_neurallens.training.classifier.calibrate_classifier`) unless kept.
    ``ncs``: the (regressor, classifier) NetConfigs as configured."""
    from ..neural.model import NeuralMap
    (p, d, zi, zo, dom), (rc, cc), (keep, finish_only) = spec, ncs, mode
    center, scale_in = dom.norm_center_scale()
    training = {"config_digest": cfg.digest(),
                "regressor": reg.get("config", {k: v for k, v in rc.__dict__.items()}),
                "classifier": cls.get("config", {k: v for k, v in cc.__dict__.items()}),
                "regressor_sizes_tried": reg.get("sizes_tried"), "classifier_sizes_tried": cls.get("sizes_tried"),
                "regressor_steps": reg["state"]["step"], "classifier_steps": cls["state"]["step"],
                "regressor_seconds": reg["state"]["seconds"], "classifier_seconds": cls["state"]["seconds"],
                "regressor_stop": reg["state"].get("stop_reason"), "classifier_stop": cls["state"].get("stop_reason"),
                "regressor_samples": reg["state"]["samples"], "classifier_samples": cls["state"]["samples"],
                "stacked_with": record["stacked_with"],
                "data_sampler": stream.method, "valid_fraction": stream.fraction,
                "mcmc": stream.mcmc.stats() if stream.mcmc is not None else None,
                "wall_seconds_this_run": record["wall_seconds_this_run"],
                "regressor_wall_this_run": record["regressor_wall_this_run"],
                "seed": cfg.seed, "device": str(pick_device(load_torch(0), cfg.device)),
                "regressor_history": reg["state"]["history"], "classifier_history": cls["state"]["history"]}
    for net_name, r in (("regressor", reg), ("classifier", cls)):
        if r["state"].get("lm"):       # with the regressor's Huber threshold: its last δ, how often it was fixed anew
            huber = {k: r["state"][k] for k in ("lm_huber_delta", "lm_huber_refixes") if k in r["state"]}
            training[f"{net_name}_lm"] = {**r["state"]["lm"], **huber}
        if r["state"].get("widened"):  # widened after its finish and finished again (levenberg.widened_finish)
            training[f"{net_name}_widened"] = r["state"]["widened"]
    if reg["state"].get("input_box"):      # trained on this box (input_box), folded back into the map's inputs
        training["regressor_input_box"] = dict(zip(("center", "scale"), reg["state"]["input_box"]))
    if keep is not None or finish_only is not None:
        training["kept"] = {"network": keep if keep is not None else FINISHED_RECORD,
                            "from_config_digest": base.training.get("config_digest")}
        if keep == "classifier":       # its calibration offset is already folded into its last bias
            for k in ("classifier_logit_offset", "classifier_calibration"):
                if k in base.training:
                    training[k] = base.training[k]
    tm = NeuralMap(path_id=int(p), direction=d, z_in=float(zi), z_out=float(zo),
                   domain=dom.to_dict(), input_center=center, input_scale=scale_in,
                   classifier=cls["layers"], regressor=reg["layers"], skip=reg["skip"],
                   out_scale=reg["out_scale"], out_shift=reg["out_shift"], odd_y=reg["odd_y"],
                   position_cos=bool(reg.get("position_cos", False)),
                   classifier_activation=cls.get("activation", cc.activation),
                   regressor_activation=reg.get("activation", rc.activation), training=training)
    if keep != "classifier":
        calibrate_classifier(lens, tm, min(cfg.heldout, 200_000), seed + 13, cfg.fresnel)
    return tm


# ----------------------------------------------------------------------------- stop heads
def _stop_heads_of(lens, tms, cfg: TrainConfig, seeds, progress: bool, log, bases=None, finish: bool = False,
                   streams=None) -> list:
    """The stop heads of ``tms`` trained with ``cfg.stop`` — one stack per stop-crossing count; None for a
    map whose path never crosses the stop plane, or all None when ``stop.max_minutes = 0``.  With
    ``bases``, a stop head the base map has is kept.  ``finish``: each map's own stop head (``tms[j].stop_head``)
    is the start of only the finish (:func:`~mi_neurallens.training.stop_head.train_stop_heads`' ``start``).
    ``streams``: the maps' regressor streams, whose valid fractions and pilot bounds the stop heads' samplers
    take instead of tracing their own (:class:`~mi_neurallens.training.data.RegressorStream`'s ``like``)."""
    from ..transport.exact import ExactMap
    out = [None] * len(tms)
    if not tms:
        return out
    nc = cfg.net("stop", tms[0].direction)
    groups: dict = {}
    for j, tm in enumerate(tms):
        if bases is not None and bases[j].stop_head is not None:
            out[j] = bases[j].stop_head
            continue
        k = ExactMap(lens, tm.path_id, tm.direction, tm.z_in, tm.z_out).stop_crossings
        if nc.max_minutes > 0 and k > 0:
            groups.setdefault(k, []).append(j)
    from .stop_head import train_stop_heads
    for k, idx in groups.items():
        heads = train_stop_heads(lens, [tms[j] for j in idx], nc, seeds=[seeds[j] + 17 for j in idx],
                                 fresnel=cfg.fresnel, mcmc_threshold=cfg.mcmc_threshold, threads=cfg.threads,
                                 device=cfg.device, progress=progress, log=log,
                                 start=[tms[j].stop_head for j in idx] if finish else None,
                                 like_streams=None if streams is None else [streams[j] for j in idx])
        for j, h in zip(idx, heads):
            out[j] = h
    return out


def _add_stop_heads(lens, bases, cfg: TrainConfig, seeds, progress: bool, log, finish: bool = False) -> list:
    """``keep = "networks"``: ``bases`` with new stop heads, trained together as in a whole run (one stack per
    stop-crossing count, :func:`_stop_heads_of`), each with its held-out stop metrics; the classifiers,
    regressors and their metrics are unchanged.  ``finish`` (``finish_only = "stop-heads"``): each base's stop head
    through the finish again instead, widened first where the config's ``stop`` width asks."""
    from .evaluate import stop_errors
    if bases and cfg.net("stop", bases[0].direction).max_minutes <= 0:
        raise NeuralLensError("--keep networks trains only stop heads, and stop.max_minutes = 0 asks for none")
    if finish:
        bare = [b.key for b in bases if b.stop_head is None]
        if bare:
            raise NeuralLensError(f"--finish-only stop-heads: {bare} have no stop head to finish; --keep networks "
                                  "trains one")
    heads = _stop_heads_of(lens, bases, cfg, seeds, progress, log, finish=finish)
    out = []
    for base, head, seed in zip(bases, heads, seeds):
        if head is None:
            raise NeuralLensError(f"map {base.key}: no stop head to train (its path does not cross the stop plane)")
        tm = dataclasses.replace(base, stop_head=head)
        x, y = heldout_valid(lens, (tm.path_id, tm.direction, tm.z_in, tm.z_out), tm.domain, cfg.heldout,
                             seed + 101, cfg.mcmc_threshold, cfg.fresnel, stops=True)
        _, yp = map_outputs_np(tm, x)
        head.metrics = stop_errors(yp[:, 5:], y[:, 5:])
        tm.metrics = {**tm.metrics, "stop": head.metrics}
        out.append(tm)
    return out
