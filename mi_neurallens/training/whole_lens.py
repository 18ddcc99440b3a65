"""A whole lens's training run (``mi-neurallens train``): plan, train the maps of each direction, save, verify.

:func:`train_lens` is a short sequence of steps: the base model a run builds on (:func:`_base_model`), the
model file it continues (:func:`_open_model`), the maps to train and their domains (:func:`_plan_maps`: planes and
sensor distances from :mod:`~mi_neurallens.transport.planes`, backward domains pilot-traced and cached in the work
directory, ghosts ranked as the flare ranks them), the base's other maps carried over (:func:`_carry_base`), the
maps of each direction trained together (:func:`_train_directions`, through
:func:`~mi_neurallens.training.maps.train_maps`) with the file re-saved after each, then each ghost map verified
against the tracer and timed (:func:`_verify_flares`), and last, a ghost that misses the flare gate at every band
given the Levenberg–Marquardt finish again past its goals (:func:`_finish_missed`).  Before and after the
training a line says what the budgets allow and where the time went (:func:`_budget_text`, :func:`_spent_text`).
"""
from __future__ import annotations

import dataclasses
import json
import os
import sys
import time

import numpy as np

from ..errors import NeuralLensError
from ..fileio import atomic_write_text
from ..transport import planes as plan
from .config import NETWORK_KINDS, TrainConfig, budget_minutes, minutes_text
from ..transport.planning import Domain
from .keep import mode_text, run_mode, stop_heads_only
from .maps import train_maps
from .stacked import STEP_CHOICE, TANH_CHOICE
from .workdir import claim as claim_workdir, run_identity

#: how a phase of :func:`~mi_neurallens.training.maps.train_maps` is named in the time reports
PHASE_NAMES = {"regressor": "regressors", "classifier": "classifiers", "stop": "stop heads",
               "evaluation": "held-out evaluation"}

#: what a ghost map given the finish again after its verification records (``training[FINISH_MISSED_KEY]``), and
#: what marks a map whose second finish is done, kept or not, so that a rerun does not finish it again (the key
#: keeps the name model files have carried since before "finish" was the one word)
FINISH_MISSED_KEY = "refined_after_verification"


# ----------------------------------------------------------------------------- what the run says
def _budget_text(cfg: TrainConfig, pending: dict) -> str:
    """One line before a lens trains: how many maps, and the most time their networks' budgets allow
    (:func:`~mi_neurallens.training.config.budget_minutes`), per network kind."""
    per = {k: 0.0 for k in NETWORK_KINDS}
    for d, group in pending.items():
        for k, v in budget_minutes(cfg, d, len(group)).items():
            per[k] += v
    counts = ", ".join(f"{len(g)} {d}" for d, g in pending.items() if g)
    parts = ", ".join(f"{PHASE_NAMES[k]} {minutes_text(v)}" for k, v in per.items() if v > 0)
    return (f"{sum(len(g) for g in pending.values())} map(s) to train ({counts}); their budgets allow at most "
            f"{minutes_text(sum(per.values()))} of training ({parts}) plus data and evaluation; each network "
            "stops earlier at its goals")


def _spent_text(direction: str, spent: dict, since_start: float) -> str:
    """One line after a direction's maps: the wall time of each phase."""
    parts = ", ".join(f"{PHASE_NAMES.get(k, k)} {minutes_text(v / 60)}" for k, v in spent["phases"].items())
    return (f"{spent['maps']} {direction} map(s) trained in {minutes_text(spent['seconds'] / 60)}"
            + (f" ({parts}; each with its data)" if parts else "")
            + f"; {minutes_text(since_start / 60)} since the start")


# ----------------------------------------------------------------------------- which maps
def select_maps(cfg: TrainConfig, paths: str | None):
    """Which (direction, path) groups to train: ``paths`` is a comma list of ``transmit`` (the configured transmit
    maps of both directions), ``backward``, ``forward`` (the configured maps of that direction), ``ghosts``,
    ``backward-transmit``, ``forward-transmit`` or integer path ids (forward); the last four are trained though the
    configuration does not list them; None: everything configured."""
    want = None if not paths else [p.strip() for p in paths.split(",") if p.strip()]
    groups = []
    for d in ("backward", "forward"):
        for p in getattr(cfg, d):
            if want is None or p in want or d in want or (p == "transmit" and f"{d}-transmit" in want):
                groups.append((d, p))
    if want:
        named = {"ghosts": [("forward", "ghosts")], "backward-transmit": [("backward", "transmit")],
                 "forward-transmit": [("forward", "transmit")]}
        for w in want:
            if w.isdigit():
                groups.append(("forward", int(w)))
            elif w in named:            # named outright: trained though the recipe does not list it
                groups += [g for g in named[w] if g not in groups]
            elif w not in ("transmit", "backward", "forward"):
                raise NeuralLensError(f"--paths: unknown item {w!r}; use transmit, ghosts, backward, forward, "
                                      "backward-transmit, forward-transmit or integer path ids")
    return groups


# ----------------------------------------------------------------------------- the run
def train_lens(lens, cfg: TrainConfig, out_path: str, paths: str | None = None, workdir: str | None = None,
               progress: bool = True, log=None, keep: str | None = None, base_path: str | None = None,
               finish_only: str | None = None, provenance: dict | None = None):
    """Plan, train and save every selected map of ``lens`` to ``out_path`` (re-saved atomically after each
    direction's maps, so an interruption loses at most the maps in progress — whose networks resume from
    checkpoints in ``workdir``, default ``<out_path>.work``).

    ``keep`` ("regressor", "classifier" or "networks": train only the stop heads) or ``finish_only`` ("maps" or
    "stop-heads": only the Levenberg–Marquardt finish of those networks): build each selected map on the same map
    of the model file ``base_path`` (:mod:`~mi_neurallens.training.keep`; ``keep``'s old spellings are
    accepted); the base model's maps that are not selected are carried over unchanged.

    ``provenance`` (the command line, recipe, package version, date and machine of this run: what
    ``mi-neurallens train`` passes) is appended to the file's ``extra["runs"]``, which ``mi-neurallens evaluate``
    prints: a model says how it was made.

    Then, with ``cfg.verify_flare``, every selected ghost map without a verified flare record is rendered against
    the tracer and its record kept in the file (:func:`~mi_neurallens.flare.verify.record_flare_errors`; the
    ``verify_flare*`` settings), and with ``cfg.verify_flare_cost`` timed against tracing its ghost
    (:func:`~mi_neurallens.flare.verify.record_flare_costs`): the model leaves training ready for the flare's mode
    ``auto``, which learns a ghost only where its record passes and the map is the faster.  Last, with
    ``cfg.verify_flare_refine_minutes`` and no base, a ghost whose records all miss the gate gets its regressor's
    finish again past its goals and the better map kept (:func:`_finish_missed`).  Returns the model."""
    keep, finish_only = run_mode(keep, finish_only)
    based = keep is not None or finish_only is not None
    base_model = _base_model(lens, keep, finish_only, base_path)
    configs = _configurations(lens, cfg)
    if configs is None:
        s_range = plan.sensor_distance_range(lens, cfg.close_focus_mm)
        z_planes = plan.planes(lens, s_range[0])
    else:
        z_planes = plan.moving_planes(configs)
        s_range = _moving_sensor_distances(configs)
    workdir = workdir or (out_path + ".work")
    claim_workdir(workdir, run_identity(cfg, keep, finish_only, base_path if based else None, out_path))
    model = _open_model(lens, cfg, out_path, z_planes, s_range, configs)
    record_run(model, provenance, base_model)
    groups = select_maps(cfg, paths)
    if configs is not None:
        groups = _moving_groups(lens, groups)
    todo = _plan_maps(lens, cfg, model, groups, z_planes, s_range, workdir, configs)
    if base_model is not None:
        _carry_base(model, base_model, todo)
    # the maps left to train, one stack per direction (maps of one direction share shape and domain)
    pending = {d: [t for t in todo if t[1] == d and f"{d}.{t[0]}" not in model.maps] for d in ("backward", "forward")}
    say = (lambda m: print(f"{lens.name}: {m}", file=sys.stderr, flush=True)) if progress or log else (lambda m: None)
    if not based and any(pending.values()):
        say(_budget_text(cfg, pending))
    t_run = time.perf_counter()
    _train_directions(lens, cfg, model, pending, out_path, workdir, (keep, finish_only), base_model, base_path,
                      progress, log, say, t_run)
    model.save(out_path)
    if not cfg.verify_flare:
        return model
    wanted = {f"{d}.{pid}" for pid, d, *_ in todo}
    trained = [tm.path_id for k, tm in model.maps.items()
               if k in wanted and tm.direction == "forward" and tm.path_id != 0]
    model = _verify_flares(lens, cfg, model, out_path, trained, workdir, say, t_run)
    # a run on a base is surgery on chosen networks: it keeps what it was told to keep, finishes nothing else
    if model is not None and cfg.verify_flare_refine_minutes > 0 and not based:
        model = _finish_missed(lens, cfg, out_path, trained, workdir, progress, log, say, t_run)
    if model is None:               # the verification stopped: the maps as saved
        from ..neural.model import load_model
        return load_model(out_path, lens)
    return model


def _configurations(lens, cfg: TrainConfig):
    """A lens with moving groups: the configurations its maps take as inputs
    (:class:`~mi_neurallens.transport.configurations.Configurations`: the zoom range, and from infinity to the
    prescription's close focus, or to the recipe's ``close_focus_mm`` where it gives a number, mm from the sensor;
    its training rays drawn with the recipe's ``zoom_end_weight`` / ``focus_end_weight``, ``zoom_margin`` and
    ``zoom_dense_at``); None for a lens of one configuration."""
    if getattr(lens, "moving", None) is None:
        return None
    from ..transport.configurations import Configurations
    close = cfg.close_focus_mm if isinstance(cfg.close_focus_mm, (int, float)) and cfg.close_focus_mm > 0 else None
    configs = Configurations.of_lens(lens, close)
    weights = tuple(d if w is None else w for w, d in zip((cfg.zoom_end_weight, cfg.focus_end_weight),
                                                         configs.end_weights))
    for name, w in zip(("zoom_end_weight", "focus_end_weight"), weights):
        if not (isinstance(w, (int, float)) and 0.0 <= w < 1.0):
            raise NeuralLensError(f"training config: {name} = {w!r}: give a number in [0, 1) (0: uniform sampling)")
    margin = configs.zoom_margin if cfg.zoom_margin is None else cfg.zoom_margin
    if not (isinstance(margin, (int, float)) and 0.0 <= margin <= 0.25):
        raise NeuralLensError(f"training config: zoom_margin = {margin!r}: give a fraction of the zoom range in "
                              f"[0, 0.25] (0: the listed range only)")
    if cfg.zoom_dense_at not in ("ends", "positions"):
        raise NeuralLensError(f"training config: zoom_dense_at = {cfg.zoom_dense_at!r}: give \"ends\" or \"positions\"")
    periods = max(lens.moving.positions - 1, 1) if cfg.zoom_dense_at == "positions" else 1
    return dataclasses.replace(configs, end_weights=tuple(float(w) for w in weights), zoom_margin=float(margin),
                               zoom_periods=periods)


def _base_domain(base_domain, planned: Domain) -> Domain:
    """The domain a run on a base map trains on: the base's (its bounds, film reach and configurations, which its
    kept networks' inputs are normalised by), its rays drawn as ``planned`` (this run's own domain) draws them:
    the configurations' sampling (:func:`~mi_neurallens.transport.configurations.end_warp`'s weights and periods,
    the zoom margin) normalises nothing, so a finish takes the sampling of the version that runs it, and the model file records it."""
    dom = Domain.from_dict(base_domain)
    if dom.conditions is None or getattr(planned, "conditions", None) is None:
        return dom
    return dataclasses.replace(dom, conditions=dataclasses.replace(dom.conditions,
                                                                   end_weights=planned.conditions.end_weights,
                                                                   zoom_margin=planned.conditions.zoom_margin,
                                                                   zoom_periods=planned.conditions.zoom_periods))


def _moving_sensor_distances(configs) -> tuple:
    """(least, greatest) sensor distance behind the last vertex (mm) over the configurations a map learns: what a
    model file records as its sensor-distance range (the sensor itself does not move)."""
    from ..optics import moving as mv
    s = [mv.at(configs.lens, t, f, check=False).surfaces[-1].thickness for t, f in configs.corner_configurations()]
    return float(min(s)), float(max(s))


def _moving_groups(lens, groups):
    """The (direction, path) groups a lens with moving groups trains: every map, zoom and focus as inputs beside
    the ray; said once, since its ghosts are ranked over the configurations (the strongest at any zoom)."""
    if any(g[0] == "forward" for g in groups):
        from ..flare.energy import RANK_ZOOMS
        mg = lens.moving
        inputs = {(True, True): "zoom and focus parameters as inputs", (True, False): "zoom parameter as an input",
                  (False, True): "focus parameter as an input"}[(mg.is_zoom, mg.focuses)]
        where = f"at {RANK_ZOOMS} zooms, each at both ends of its focus band" if mg.is_zoom else \
            "at both ends of the focus range"
        print(f"{lens.name}: moving groups: every map takes the {inputs}; the ghosts are ranked {where}",
              file=sys.stderr, flush=True)
    return groups


def _base_model(lens, keep, finish_only, base_path):
    """The model a run with ``keep`` or ``finish_only`` builds on (read from ``base_path``), or None."""
    if keep is None and finish_only is None:
        return None
    if not base_path:
        raise NeuralLensError(f"{mode_text(keep, finish_only)}: name the model file whose networks are kept or "
                              "finished (base_path)")
    from ..neural.model import load_model
    return load_model(base_path, lens)


def record_run(model, provenance: dict | None, base=None) -> None:
    """Append a run's ``provenance`` to ``model.extra["runs"]``; a rerun of the same command with the same
    configuration (resuming an interrupted run) updates the last entry instead of adding one.  A run built on a
    ``base`` model (``keep``, ``finish_only``) first takes the base's runs it lacks: the file still says how the
    networks it finished were made."""
    runs = [r for r in model.extra.get("runs", []) if isinstance(r, dict)]
    if base is not None:
        runs = [r for r in runs_with_times(base) if not has_run(runs, r)] + runs
    if provenance:
        same = ("command", "config_digest")
        if runs and all(runs[-1].get(k) == provenance.get(k) for k in same):
            runs[-1] = {**provenance, "started": runs[-1].get("started", provenance.get("started")), "resumed": True}
        else:
            runs.append(dict(provenance))
    if runs:
        model.extra["runs"] = runs


def own_run(runs) -> int | None:
    """Index in ``runs`` (a model file's ``extra["runs"]``) of the run that wrote the file, whose time is its
    ``extra["training_time"]``: the last one not merged in from another file (a base's runs come first)."""
    own = [i for i, r in enumerate(runs) if not r.get("merged_maps")]
    return own[-1] if own else None


def runs_with_times(model) -> list:
    """``model.extra["runs"]``, the run that wrote the file given the time its file records
    (``extra["training_time"]["seconds"]``) where the run lacks one: what another file that takes these runs
    (a finish built on this one, a merge of its maps) keeps, since that file's own time is another run's."""
    runs = [dict(r) for r in model.extra.get("runs", []) if isinstance(r, dict)]
    own, seconds = own_run(runs), (model.extra.get("training_time") or {}).get("seconds")
    if own is not None and seconds and "seconds" not in runs[own]:
        runs[own]["seconds"] = seconds
    return runs


def has_run(runs, run) -> bool:
    """Whether ``runs`` holds ``run`` (the same command started at the same time)."""
    return any(r.get("command") == run.get("command") and r.get("started") == run.get("started") for r in runs)


def _open_model(lens, cfg: TrainConfig, out_path: str, z_planes, s_range, configs=None):
    """The model this run writes: new for the lens's planes (z_front, z_rear; mm) and sensor distances, holding
    the maps of a model already at ``out_path`` that were trained with this configuration (a resumed run) and that
    model's extra records; a file there that does not load as a model of the lens is replaced.  ``configs``: a
    lens with moving groups, whose planes lie in the configurations' frame (the sensor at ``z_sensor``)."""
    from ..errors import ModelError
    from ..neural.model import NeuralLensModel, load_model
    z_front, z_rear = z_planes
    z_last = float(lens.total_track) if configs is None else float(configs.z_sensor - lens.surfaces[-1].thickness)
    model = NeuralLensModel(lens_name=lens.name, fingerprint=lens.fingerprint(), z_front=z_front, z_rear=z_rear,
                            z_last_vertex=z_last, sensor_distance_range=tuple(s_range))
    if os.path.exists(out_path):
        try:
            old = load_model(out_path, lens)
        except ModelError:
            old = None
        if old is not None:
            for k, m in old.maps.items():
                if m.training.get("config_digest") == cfg.digest():
                    model.maps[k] = m
            model.extra.update(old.extra)
    model.extra.update({"software": "mi-neurallens", "training_config": cfg.to_dict()})
    return model


def _plan_maps(lens, cfg: TrainConfig, model, groups, z_planes, s_range, workdir: str, configs=None) -> list:
    """(path_id, direction, z_in, z_out, domain) of every map of the (direction, path) ``groups``
    (:func:`select_maps`): a backward map's domain pilot-traced (cached as ``<workdir>/domain.backward.<id>.json``),
    the forward maps' one domain over the configured field and film reach; ``"ghosts"``: the ghosts the flare's
    ranking selects (cached as ``<workdir>/ghost_ranking.json``; the ranking and selection recorded in
    ``model.extra``)."""
    from ..transport.planning import select_ghosts
    z_front, z_rear = z_planes
    if configs is None:
        reach = plan.film_reach(lens, s_range, cfg.film_reach * cfg.film_half_diagonal_mm) if cfg.film_reach else None
        fwd_domain = plan.forward_domain(lens, z_front, plan.default_field_half_angle(
            lens, cfg.film_half_diagonal_mm, cfg.field_margin), reach=reach)
    else:
        fwd_domain = plan.moving_forward_domain(configs, z_front, cfg.film_half_diagonal_mm, cfg.field_margin,
                                                cfg.film_reach * cfg.film_half_diagonal_mm or None)
    todo = []
    for d, p in groups:
        if d == "backward":
            pid = 0 if p == "transmit" else int(p)
            dom_path = os.path.join(workdir, f"domain.backward.{pid}.json")
            if os.path.exists(dom_path):
                dom = Domain.from_dict(json.load(open(dom_path)))
            else:
                dom = plan.backward_domain(lens, pid, z_rear, z_front, np.random.default_rng(cfg.seed),
                                           conditions=configs)
                atomic_write_text(dom_path, json.dumps(dom.to_dict()))
            todo.append((pid, "backward", z_rear, z_front, dom))
        elif p == "ghosts":
            rk_path = os.path.join(workdir, "ghost_ranking.json")
            if os.path.exists(rk_path):
                ranking = json.load(open(rk_path))
            else:
                # the render-time ranking (flare/energy.py), so the ghosts trained are the ones a flare
                # render selects, and a neural flare selects the same ghosts as an exact one
                from ..flare.energy import ghost_energy_ranking, moving_ghost_ranking
                ranking = (ghost_energy_ranking(lens, fresnel=cfg.fresnel) if configs is None
                           else moving_ghost_ranking(configs, fresnel=cfg.fresnel))
                atomic_write_text(rk_path, json.dumps(ranking))
            selected = select_ghosts(ranking, cfg.ghost_energy_fraction, cfg.max_ghosts)
            model.extra["ghost_ranking"] = ranking
            model.extra["ghosts_selected"] = selected
            model.extra["ghosts_trained"] = selected[:cfg.ship_ghosts]
            for pid in selected[:cfg.ship_ghosts]:
                todo.append((pid, "forward", z_front, z_rear, fwd_domain))
        else:
            pid = 0 if p == "transmit" else int(p)
            todo.append((pid, "forward", z_front, z_rear, fwd_domain))
    return todo


def _carry_base(model, base_model, todo) -> None:
    """A run on a base: the base's extra records under this run's, and the base's maps this run does not train
    carried over unchanged."""
    model.extra = {**base_model.extra, **model.extra}
    wanted = {f"{d}.{pid}" for pid, d, *_ in todo}
    for k, m in base_model.maps.items():
        if k not in wanted:
            model.maps.setdefault(k, m)


def _train_directions(lens, cfg: TrainConfig, model, pending: dict, out_path: str, workdir: str, mode, base_model,
                      base_path, progress: bool, log, say, t_run: float) -> None:
    """The ``pending`` maps of each direction trained together (:func:`~mi_neurallens.training.maps.train_maps`,
    ``mode`` = (keep, finish_only) on ``base_model``'s maps), into ``model``, saved to ``out_path`` after each
    direction with the time each took (``model.extra["training_time"]``), and how Adam's steps ran, said once."""
    from ..errors import ModelError
    keep, finish_only = mode
    spent, told = {}, set()
    for direction in ("backward", "forward"):
        group = pending[direction]
        if not group:
            continue
        bases = None
        if base_model is not None:
            missing = [f"{direction}.{t[0]}" for t in group if f"{direction}.{t[0]}" not in base_model.maps]
            if missing:
                raise ModelError(f"{base_path}: no map {missing[0]!r} to build on ({mode_text(keep, finish_only)}); "
                                 f"it has {sorted(base_model.maps)}")
            bases = [base_model.maps[f"{direction}.{t[0]}"] for t in group]
            # a kept network was trained on its map's domain: the new ones learn the same (film reach included)
            group = [(*t[:4], _base_domain(b.domain, t[4])) for t, b in zip(group, bases)]
        if progress:
            print(f"{lens.name}: training {len(group)} {direction} map(s) together: "
                  f"{', '.join(str(t[0]) for t in group)}", file=sys.stderr, flush=True)
        t_dir = time.perf_counter()
        tms = train_maps(lens, group, cfg, workdir, progress=progress, log=log, keep=keep, bases=bases,
                         finish_only=finish_only)
        # each phase's time, as train_maps records it; a run that trains only stop heads keeps its base maps'
        # records, whose phases are the base's run's, not this one's
        phases = dict(tms[0].training.get("phase_seconds", {})) if tms and not stop_heads_only(keep, finish_only) \
            else {}
        phases.pop("maps", None)
        spent[direction] = {"maps": len(tms), "seconds": time.perf_counter() - t_dir, "phases": phases}
        model.extra["training_time"] = {"this_run": spent, "seconds": time.perf_counter() - t_run}
        say(_spent_text(direction, spent[direction], time.perf_counter() - t_run))
        for dev, how in TANH_CHOICE.items():
            if dev not in told:
                told.add(dev)
                say(f"Adam's tanh on {dev}: {how}")
        for shape, how in STEP_CHOICE.items():
            if shape not in told:
                told.add(shape)
                say(f"Adam's steps of {shape} networks on the CPU: {how}")
        for tm in tms:
            model.maps[tm.key] = tm
        if base_model is not None:      # the base's order (ghosts: strongest first), new maps after
            order = list(base_model.maps) + [k for k in model.maps if k not in base_model.maps]
            model.maps = {k: model.maps[k] for k in order if k in model.maps}
        model.save(out_path)


# ----------------------------------------------------------------------------- after the training
#: what can stop the flare verification without a bug behind it: our errors (a model or lens the renderer refuses),
#: the renderer's (Dr.Jit and Mitsuba raise RuntimeError; ImportError where the variant cannot start), memory, and
#: the file system
VERIFY_FAILURES = (NeuralLensError, RuntimeError, ImportError, MemoryError, OSError)


def _verify_flares(lens, cfg: TrainConfig, model, out_path: str, trained, workdir: str, say, t_run: float):
    """Each ghost map among ``trained`` (forward path ids) verified against the tracer
    (:func:`~mi_neurallens.flare.verify.record_flare_errors`) where its verification is not complete, then, with
    ``cfg.verify_flare_cost``, timed against tracing it on this backend where it is not yet
    (:func:`~mi_neurallens.flare.verify.record_flare_costs`); the records go into the file at ``out_path``.
    Returns the model as the file now holds it, or None where the verification stopped on one of
    :data:`VERIFY_FAILURES` (said, with how to verify later; the maps stay saved without it)."""
    from ..flare.options import FlareOptions
    from ..flare.verify import (cost_bands, flare_costs, record_flare_costs, record_flare_errors,
                                variant_backend, verification_done)
    from ..neural.model import load_model
    gate = FlareOptions.auto_max_flare_error
    # a resumed run goes on where the last one stopped: ghosts whose verification is complete are skipped, and a
    # ghost's band already measured is kept; then the ghosts not yet timed on this backend are timed
    ghosts = [pid for pid in trained
              if not verification_done(model.map(pid, "forward").metrics, cfg.verify_flare_bands, gate)]
    t_v = time.perf_counter()
    try:
        if ghosts:
            record_flare_errors(out_path, _lens_spec(lens, workdir), ghosts=ghosts, bands=cfg.verify_flare_bands,
                                samples_log2=cfg.verify_flare_samples, keep_measured=True,
                                max_log2=max(cfg.verify_flare_max_samples, cfg.verify_flare_samples), log=say)
        timed = []
        if cfg.verify_flare_cost:
            model = load_model(out_path, lens)
            timed = [pid for pid in trained if variant_backend() not in flare_costs(model.map(pid, "forward").metrics)
                     and cost_bands(model.map(pid, "forward").metrics, gate)]
            if timed:
                record_flare_costs(out_path, _lens_spec(lens, workdir), ghosts=timed,
                                   samples_log2=cfg.verify_flare_cost_samples, log=say)
    except VERIFY_FAILURES as e:        # the maps are saved: say how to verify them later, do not lose the run
        print(f"{lens.name}: the flare verification stopped ({type(e).__name__}: {e}); {out_path} holds the "
              f"trained maps without it (mode auto then gates its ghosts by their held-out accuracy alone): "
              f"`mi-neurallens evaluate {out_path} --lens <its lens file> --recorded --flare --write` verifies "
              f"them, and `--recorded --flare-cost --write` times them",
              file=sys.stderr, flush=True)
        return None
    if ghosts or timed:
        model = load_model(out_path, lens)
        model.extra.setdefault("training_time", {})["flare_verification_seconds"] = time.perf_counter() - t_v
        model.save(out_path)
        say(f"verified the flares of {len(ghosts)} ghost map(s) and timed {len(timed)} in "
            f"{minutes_text((time.perf_counter() - t_v) / 60)}; "
            f"{minutes_text((time.perf_counter() - t_run) / 60)} since the start")
    return model


def _finish_missed(lens, cfg: TrainConfig, out_path: str, trained, workdir: str, progress: bool, log, say,
                   t_run: float):
    """The ghosts among ``trained`` whose verified records all miss the gate (every band): their regressors given
    the finish again past their goals, for ``cfg.verify_flare_refine_minutes`` from the maps as trained (a
    ``finish_only = "maps"`` run of just those ghosts, ``stop_at_goals`` off, verified as any run), and each ghost's
    better map kept — the finished one where its best record is lower.  A ghost that misses by its regressor (the
    error inside the ghost, or on its edge where no band reaches) usually has more to give than its goals asked
    for: the Leica Summicron-R 50's 2560 and 20 went from 0.0102 and 0.0116 to 0.0080 and 0.0039.  Each map so finished, kept or not, is marked (:data:`FINISH_MISSED_KEY`), so a rerun
    finishes none twice.  Returns the model."""
    from ..flare.options import FlareOptions
    from ..flare.verify import flare_records, passing_band
    from ..neural.model import load_model
    gate = FlareOptions.auto_max_flare_error
    model = load_model(out_path, lens)

    def misses(tm):                     # verified, and no band's record passes the gate
        return _best_record(tm) is not None and passing_band(flare_records(tm.metrics), 0.0, gate) is None

    ghosts = {pid: model.maps.get(f"forward.{pid}") for pid in trained}
    missed = [pid for pid, tm in ghosts.items()
              if tm is not None and FINISH_MISSED_KEY not in tm.training and misses(tm)]
    if not missed:
        return model
    t0 = time.perf_counter()
    say(f"{len(missed)} ghost map(s) above {gate:g} at every band ({', '.join(map(str, missed))}): their regressors "
        f"finished past their goals, {cfg.verify_flare_refine_minutes:g} min each, then verified again")
    rcfg = dataclasses.replace(cfg, verify_flare_refine_minutes=0.0, forward_regressor={
        **cfg.forward_regressor, "lm_minutes": cfg.verify_flare_refine_minutes, "stop_at_goals": False})
    # "refined": the file and work directory names of this step since before "finish" was its one word (a rerun
    # resumes from them)
    rpath = os.path.join(workdir, "refined.model.safetensors")
    try:
        finished = train_lens(lens, rcfg, rpath, paths=",".join(map(str, missed)),
                              workdir=os.path.join(workdir, "refined"), progress=progress, log=log,
                              finish_only="maps", base_path=out_path)
    except NeuralLensError as e:        # the maps as trained are saved and verified: keep them
        say(f"the finish of the ghosts above the gate stopped ({e}); {out_path} keeps them as trained")
        return model
    model = load_model(out_path, lens)
    took = _keep_better(model, finished, missed, cfg, say)
    model.extra.setdefault("training_time", {})["refine_missed_seconds"] = time.perf_counter() - t0
    model.save(out_path)
    passing = sum(1 for pid in missed if not misses(model.map(pid, "forward")))
    say(f"finished {len(missed)} ghost map(s) again in {minutes_text((time.perf_counter() - t0) / 60)}: {len(took)} "
        f"better, {passing} now within {gate:g}; {minutes_text((time.perf_counter() - t_run) / 60)} since the start")
    return model


def _best_record(tm):
    """The lowest paired flare error among the map's verified records, or None where it has none; a record whose
    band left most of the ghost to the tracer (``flare.verify.MAX_TRACED_SHARE``) says nothing of the map."""
    from ..flare.verify import MAX_TRACED_SHARE, flare_records, traced_share
    recs = [r["paired_mape"] for r in flare_records(tm.metrics)
            if r.get("paired_mape") is not None and not traced_share(r) > MAX_TRACED_SHARE]
    return min(recs) if recs else None


def _keep_better(model, finished, missed, cfg: TrainConfig, say) -> list:
    """Each ghost of ``missed``: the map of ``finished`` merged into ``model`` where its best verified record is
    lower, and either way marked (:data:`FINISH_MISSED_KEY`: both records, which was kept, the minutes) with this
    run's config digest, so a rerun keeps it.  Returns the ghosts whose finished map was kept."""
    from .merge import merge_models
    took = []
    for pid in missed:
        key = f"forward.{pid}"
        old, new = model.maps[key], finished.maps.get(key)
        b_old, b_new = _best_record(old), (_best_record(new) if new is not None else None)
        better = b_new is not None and b_new < b_old
        # the stored mark's words are the ones model files have carried since before "finish" was the one word
        mark = {"best_before": b_old, "best_refined": b_new, "kept": "refined" if better else "as trained",
                "lm_minutes": cfg.verify_flare_refine_minutes}
        if better:
            merge_models(finished, model, [key])
            took.append(pid)
        tm = model.maps[key]
        # the map is this run's product either way: its digest stays the run's, so a rerun keeps it
        model.maps[key] = dataclasses.replace(tm, training={**tm.training, "config_digest": cfg.digest(),
                                                            FINISH_MISSED_KEY: mark})
        say(f"ghost {pid}: best verified error {b_old:.4f} as trained, "
            + (f"{b_new:.4f} finished again" if b_new is not None else "no record finished again")
            + f": {'the finished map' if better else 'the map as trained'} kept")
    return took


def _lens_spec(lens, workdir: str) -> str:
    """What the verification's ``neural_lens`` sensor loads as ``lens``: the lens as trained, written to
    ``<workdir>/lens.json`` (a user's file, an imported Zemax design or a bundled lens alike), or its bundled name
    where the project format cannot hold it (a :class:`~mi_neurallens.errors.LensError` from writing it), the file
    cannot be written (OSError) or it would not read back as the same lens."""
    from ..optics.prescription import Lens
    path = os.path.join(workdir, "lens.json")
    try:
        lens.save(path)
        if Lens.load(path).fingerprint() == lens.fingerprint():
            return path
    except (NeuralLensError, OSError):
        pass
    return lens.name
