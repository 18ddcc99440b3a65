"""Training on Ray: the maps of many lenses as jobs on one machine or a cluster (the ``cluster`` extra).

    mi-neurallens train wide-22mm ood-59mm --ray                 # a local Ray instance
    mi-neurallens train wide-22mm --ray ray://head:10001 --jobs 8  # a cluster

Each lens's maps are split into jobs (:func:`plan_jobs`): the backward transmit map, and the forward maps
(transmit and the selected ghosts, strongest first) in ``jobs`` chunks.  A job is
:func:`~mi_neurallens.training.whole_lens.train_lens` on its chunk — one stack per direction, goal-stopped —
writing its own model file ``<work>/<lens>.job<i>.model.safetensors`` with checkpoints in
``<work>/<lens>.job<i>.work/``.  Jobs ask Ray for ``cfg.threads`` CPUs, and one GPU each when the cluster
has GPUs (PyTorch then trains on it).  When a job's worker dies, Ray runs it again (``max_retries``) and it
resumes: finished maps are in its model file, the stack in progress in its checkpoint; rerunning the whole
command resumes the same way (the work folder must be on storage every worker sees).  The driver merges
the jobs' maps into one model file per lens (:func:`~mi_neurallens.training.merge.merge_models`) — into
the model already there when it has the same lens and planes, so its other maps stay — with the lens's
ghost ranking, and prints each job as it ends with an ETA.
"""
from __future__ import annotations

import os
import sys
import time

from ..errors import NeuralLensError

#: test hook: when set to a folder, a job's process dies (``os._exit``) once, right after it finished its
#: maps for the first time — what a worker lost mid-run looks like to Ray (tests/test_distributed.py)
KILL_ONCE_ENV = "MI_NEURALLENS_TEST_KILL_ONCE"


def _ray():
    try:
        import ray
    except ImportError:
        raise NeuralLensError("training on Ray needs the 'cluster' extra: pip install 'mi-neurallens[cluster]' "
                              "(or pip install ray)") from None
    return ray


def plan_jobs(lens, cfg, paths: str | None = None, jobs: int = 1) -> list:
    """The ``--paths`` lists of the jobs of ``lens``: the backward maps as one job, the forward maps
    (transmit, then the selected ghosts in ranking order) split into ``jobs`` chunks of about equal size;
    chunks are interleaved so every job gets strong and weak ghosts.  Returns (paths, ghost ranking or None,
    selected ghosts)."""
    from ..transport.planning import select_ghosts
    from .whole_lens import select_maps
    groups = select_maps(cfg, paths)
    backward = [("transmit" if p == "transmit" else str(p)) for d, p in groups if d == "backward"]
    forward, ranking, selected = [], None, []
    for d, p in groups:
        if d != "forward":
            continue
        if p == "ghosts":
            from ..flare.energy import ghost_energy_ranking
            ranking = ghost_energy_ranking(lens, fresnel=cfg.fresnel)
            selected = select_ghosts(ranking, cfg.ghost_energy_fraction, cfg.max_ghosts)
            forward += [str(g) for g in selected[:cfg.ship_ghosts]]
        elif p == "transmit":
            forward.append("forward-transmit")
        else:
            forward.append(str(p))
    out = []
    if backward:
        out.append(",".join("backward-transmit" if p == "transmit" else p for p in backward))
    n = max(1, min(int(jobs), len(forward)))
    for i in range(n):
        chunk = forward[i::n]
        if chunk:
            out.append(",".join(chunk))
    return out, ranking, selected


def _job(lens, cfg, paths: str, out_path: str, workdir: str) -> tuple:
    """One job (runs in a Ray worker): train ``paths`` of ``lens`` into ``out_path``; returns (out_path,
    wall seconds of this attempt)."""
    from .whole_lens import train_lens
    t0 = time.perf_counter()
    train_lens(lens, cfg, out_path, paths=paths, workdir=workdir, progress=False)
    kill = os.environ.get(KILL_ONCE_ENV)
    if kill:
        marker = os.path.join(kill, os.path.basename(out_path) + ".killed")
        if not os.path.exists(marker):
            open(marker, "w").close()
            os._exit(1)
    return out_path, time.perf_counter() - t0


def train_on_ray(lenses, cfgs, out_dir: str, *, address: str | None = None, jobs: int = 1, paths: str | None = None,
                 work_dir: str | None = None, max_retries: int = 3, log=print) -> dict:
    """Train ``lenses`` (with their configs ``cfgs``) on Ray; returns ``{"models": {lens name: model file},
    "jobs": [{"lens", "job", "paths", "seconds"}]}`` (seconds: the successful attempt's wall time).

    ``address``: a Ray cluster address (``auto``, ``ray://host:10001``…); None starts a local instance
    (or joins the one this process already has).  ``jobs``: forward-map jobs per lens."""
    from ..neural.model import NeuralLensModel, load_model
    from .merge import merge_models
    ray = _ray()
    if not ray.is_initialized():
        ray.init(address=address, include_dashboard=False, log_to_driver=False,
                 runtime_env={"env_vars": {k: os.environ[k] for k in (KILL_ONCE_ENV, "MI_NEURALLENS_LENSES",
                                                                       "MI_NEURALLENS_TORCH_COMPILE")
                                           if k in os.environ}})
    gpus = 1 if ray.cluster_resources().get("GPU", 0) >= 1 else 0
    work_dir = work_dir or os.path.join(out_dir, "ray.work")
    os.makedirs(work_dir, exist_ok=True)
    pending, plans = {}, {}
    for lens, cfg in zip(lenses, cfgs):
        job_paths, ranking, selected = plan_jobs(lens, cfg, paths, jobs)
        plans[lens.name] = (lens, cfg, [], ranking, selected)
        task = ray.remote(num_cpus=max(int(cfg.threads), 1), num_gpus=gpus, max_retries=max_retries)(_job)
        for i, p in enumerate(job_paths):
            out = os.path.join(work_dir, f"{lens.name}.job{i}.model.safetensors")
            ref = task.remote(lens, cfg, p, out, out + ".work")
            pending[ref] = (lens.name, i, p)
            plans[lens.name][2].append(out)
    n, done, t0, jobs_done = len(pending), 0, time.perf_counter(), []
    log(f"ray: {n} jobs for {len(lenses)} lens(es) on {ray.cluster_resources().get('CPU', 0):g} CPUs, "
        f"{ray.cluster_resources().get('GPU', 0):g} GPUs")
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=1)
        name, i, p = pending.pop(ready[0])
        _, secs = ray.get(ready[0])
        jobs_done.append({"lens": name, "job": i, "paths": p, "seconds": secs})
        done += 1
        el = time.perf_counter() - t0
        log(f"ray: [{done}/{n}] {name} job {i} ({p}) done in {secs / 60:.1f} min; "
            f"ETA {el / done * (n - done) / 60:.1f} min")
    results = {}
    for name, (lens, cfg, outs, ranking, selected) in plans.items():
        first = load_model(outs[0], lens)
        path = os.path.join(out_dir, f"{lens.name}.model.safetensors")
        model = _existing(path, lens, first)      # maps of an earlier model that were not retrained stay
        if model is None:
            model = NeuralLensModel(lens_name=lens.name, fingerprint=lens.fingerprint(), z_front=first.z_front,
                                    z_rear=first.z_rear, z_last_vertex=first.z_last_vertex,
                                    sensor_distance_range=first.sensor_distance_range)
        model.extra.update({"software": "mi-neurallens", "training_config": cfg.to_dict()})
        if ranking is not None:
            model.extra.update(ghost_ranking=ranking, ghosts_selected=selected)
        for out in outs:
            merge_models(load_model(out, lens), model)
        model.save(path)
        results[name] = path
        log(f"ray: {name}: {len(model.maps)} maps -> {path}")
    sys.stdout.flush()
    return {"models": results, "jobs": jobs_done}


def _existing(path, lens, like):
    """The model already at ``path`` when it is of ``lens`` with the planes of ``like``, else None."""
    from ..errors import ModelError
    from ..neural.model import load_model
    if not os.path.exists(path):
        return None
    try:
        m = load_model(path, lens)
    except ModelError:
        return None
    same = abs(m.z_front - like.z_front) < 1e-9 and abs(m.z_rear - like.z_rear) < 1e-9
    return m if same else None
