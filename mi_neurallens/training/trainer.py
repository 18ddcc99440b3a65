"""The PyTorch trainer (torch is imported lazily, inside the functions).

One map = a classifier (2–3×32 tanh; trained on the tracer's aperture margin, or BCE on the labels as in
the paper) and a regressor (5×32 tanh) on normalised reduced inputs.
The regressor predicts the standardised *residual* of a least-squares linear guess (``residual =
"linear"``; the linear part is kept as a skip connection in the model file) — see docs/training.md for
what that buys.  Data are streamed from the tracer into an in-memory pool that is partly refreshed
with fresh samples every ``refresh_every`` steps (no data files; nothing is re-used for long).

The maps of one direction train together (:func:`train_maps`): their regressors as one stack, their
classifiers as another, their stop heads per crossing count (:mod:`~mi_neurallens.training.stacked`:
stacked weights, batched products, each network leaving when it meets its goals).  One map is a stack
of one.  Checkpoints (``<workdir>/<stack>.ckpt.safetensors`` + ``.json``; tensors only, never pickle)
hold weights, Adam state, best weights, steps and histories; they are written atomically every minute
and at the end.  A rerun with the same workdir resumes from them; a finished stack is not retrained.
The data streams after a resume are re-seeded deterministically from (seed, map, step).
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import time

import numpy as np

from ..constants import ARCSEC_PER_RAD
from ..errors import NeuralLensError
from ..fileio import atomic_write_text
from .config import NETWORK_KINDS, NetConfig, TrainConfig, budget_minutes, minutes_text, parse_size
from .data import Domain, PathSampler, RegressorStream, classifier_samples
from .evaluate import map_outputs_np
from .input_box import fold_input_box, input_box, is_box
from .stacked import STEP_CHOICE, TANH_CHOICE, Problem

CLASSIFIER_VALIDATION = 400_000   # rays uniform over the domain that pick the classifier's best weights
#: the first pool of a network that is only refined (Levenberg–Marquardt draws fresh rows per iteration; the
#: pool gives the loss weights alone)
REFINE_POOL = 1 << 16


# ----------------------------------------------------------------------------- torch helpers
def _torch(threads: int = 2):
    import torch
    if threads:
        torch.set_num_threads(int(threads))
    return torch


def pick_device(torch, want: str = "auto"):
    if want == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(want)


def make_net(torch, n_in: int, n_out: int, hidden: int, width: int, activation: str):
    nn = torch.nn
    act = {"tanh": nn.Tanh, "relu": nn.ReLU}[activation]
    layers, w = [], n_in
    for _ in range(hidden):
        layers += [nn.Linear(w, width), act()]
        w = width
    layers.append(nn.Linear(w, n_out))
    return nn.Sequential(*layers)


def net_layers(net) -> list:
    import torch
    return [(m.weight.detach().cpu().double().numpy(), m.bias.detach().cpu().double().numpy())
            for m in net if isinstance(m, torch.nn.Linear)]


# ----------------------------------------------------------------------------- output standardisation
#: output columns that are odd under the mirror reduction ωy → −ωy (y and dy of the reduced frame)
ODD_COLUMNS = (1, 3)


def odd_factor(x_wy: np.ndarray, s_max: float | None, n_out: int = 5) -> np.ndarray:
    """(N, n_out) multiplier ``M`` of the odd-output parametrisation: ωy / s_max in the odd columns
    (:data:`ODD_COLUMNS`), 1 elsewhere; all ones when ``s_max`` is None (plain outputs).  ``x_wy``: ωy
    (direction cosine, ≥ 0 in the reduced domain)."""
    M = np.ones((len(x_wy), n_out))
    if s_max is not None:
        for j in ODD_COLUMNS:
            M[:, j] = np.asarray(x_wy, np.float64) / float(s_max)
    return M


#: rows per block of :func:`fit_output_transform`'s two passes (its temporaries stay in the cache)
FIT_BLOCK_ROWS = 1 << 16


#: ``exit_position = "auto"``: a regressor regresses its exit position times |dz|
#: (:func:`~mi_neurallens.neural.model.position_cos`) where its first pool's exit rays reach beyond this angle to the
#: axis: a fisheye's camera map (rays leaving the front at up to 90°); no bundled lens's maps come near it
POSITION_COS_FROM_DEG = 60.0


def wants_position_cos(setting: str, y: np.ndarray) -> bool:
    """Whether a regressor with ``NetConfig.exit_position = setting`` regresses position × |dz|, given reduced-frame
    outputs ``y`` (N, 5) of its first pool: ``"cos"`` yes, ``"plane"`` no, ``"auto"`` where an exit direction lies
    more than :data:`POSITION_COS_FROM_DEG` off the axis."""
    if setting in ("cos", "plane"):
        return setting == "cos"
    s = np.hypot(y[:, 2], y[:, 3]) if len(y) else np.zeros(1)
    return bool(s.max() > math.sin(math.radians(POSITION_COS_FROM_DEG)))


def fit_output_transform(xn: np.ndarray, y: np.ndarray, residual: str, M: np.ndarray | None = None):
    """(skip (c, k), out_shift (c,), out_scale (c,)) of the regressor's output transform
    ``y = M · (shift + skip·xn + scale·network)`` (``M`` from :func:`odd_factor`; None = ones), for inputs
    ``xn`` (N, k) and targets ``y`` (N, c): the linear part is the least-squares fit of y (``residual =
    "linear"``) or the mean (``"none"``), and ``scale`` the spread of what is left, so the network's target
    has about unit variance.

    The fit solves the normal equations, accumulated in float64 over blocks of :data:`FIT_BLOCK_ROWS` rows
    (a (k+1)² system per column: the columns are the normalised inputs, about [−1, 1], and a constant, so it
    is well conditioned), and a second blocked pass takes the residuals' spread.  ``np.linalg.lstsq`` on
    the whole (N, k+1) design matrix cost 0.11 s a column on a map's two million pool rows, mostly memory
    traffic through full-size temporaries: 15 s of a lens's 28 forward maps' set-up (docs/results.md, "The
    data set-up")."""
    n, k = xn.shape
    c = y.shape[1]
    if residual not in ("linear", "none"):
        raise NeuralLensError(f"unknown residual mode {residual!r}: use 'linear' or 'none'")
    p = k + 1 if residual == "linear" else 1

    def base(sl):
        m = sl.stop - sl.start
        return np.concatenate([xn[sl], np.ones((m, 1))], 1) if p > 1 else np.ones((m, 1))

    blocks = [slice(a, min(a + FIT_BLOCK_ROWS, n)) for a in range(0, n, FIT_BLOCK_ROWS)]
    G, b = np.zeros((c, p, p)), np.zeros((c, p))
    for sl in blocks:
        B = base(sl)
        for j in range(c):
            A = B if M is None else B * M[sl, j:j + 1]
            G[j] += A.T @ A
            b[j] += A.T @ y[sl, j]
    coef = np.stack([np.linalg.lstsq(G[j], b[j], rcond=None)[0] for j in range(c)])   # rank-safe
    s1, s2 = np.zeros(c), np.zeros(c)
    for sl in blocks:
        B = base(sl)
        for j in range(c):
            A = B if M is None else B * M[sl, j:j + 1]
            r = y[sl, j] - A @ coef[j]
            s1[j] += r.sum()
            s2[j] += r @ r
    scale = np.sqrt(np.maximum(s2 / max(n, 1) - (s1 / max(n, 1)) ** 2, 0.0))
    skip = coef[:, :-1] if p > 1 else np.zeros((c, k))
    shift = coef[:, -1]
    scale = np.where(scale > 1e-9, scale, 1e-9)
    return skip, shift, scale


#: accuracy goals per output column (x, y in mm; dx, dy; T relative), used by loss_weights="goals"
GOAL_UNITS = (0.002, 0.002, 5.0 / ARCSEC_PER_RAD, 5.0 / ARCSEC_PER_RAD, 0.005)


def loss_weights(mode: str, oscale, y) -> np.ndarray:
    """Per-column weights of the standardised MSE.  ``goals``: ∝ std / goal, i.e. columns whose
    residual spread is large compared with their accuracy goal (directions, usually) get more weight;
    normalised to mean 1 and floored at 0.05 so no column is ignored.  ``uniform``: all 1."""
    if mode == "uniform":
        return np.ones(5)
    if mode != "goals":
        raise NeuralLensError(f"unknown loss_weights {mode!r}: use 'goals' or 'uniform'")
    goal = np.array(GOAL_UNITS, dtype=np.float64)
    goal[4] *= max(float(np.mean(np.abs(y[:, 4]))), 1e-6)
    w = np.asarray(oscale, np.float64) / goal
    w = w / w.mean()
    return np.maximum(w, 0.05)


def edge_weights(ps, u: np.ndarray, nc: NetConfig) -> np.ndarray:
    """Per-sample loss weights of valid regressor samples (unit-cube ``u``): ``1 + edge_weight ·
    exp(−margin / edge_margin)``, with the tracer's aperture margin (1 − r²/R² at the tightest aperture,
    :attr:`~mi_neurallens.trace.tracer.TraceResult.margin`).  Rays that graze an aperture land on the
    sharp edge of a ghost, where a few µm of position error is a visible shift of the edge."""
    _, m, _ = ps.margin_u(u)
    return 1.0 + nc.edge_weight * np.exp(-np.maximum(m, 0.0) / nc.edge_margin)


# ----------------------------------------------------------------------------- second-order finish
def polish_results(torch, fits, results, nc: NetConfig, keys, ckpt: str | None = None, log=None,
                   progress: bool = False) -> None:
    """The Levenberg–Marquardt finish (:mod:`~mi_neurallens.training.levenberg`) of each network in
    ``results`` (what :func:`~mi_neurallens.training.stacked.train_stack` returned for ``fits``), in place,
    for ``nc.lm_minutes`` per network (and at most ``nc.lm_iterations``): skipped for networks that met their
    goals already, for networks of more than :data:`~mi_neurallens.training.levenberg.MAX_PARAMS` weights and
    when ``lm_minutes`` is 0.  The networks finish in stacks of :func:`lm_stack_size` (on a GPU all of a
    shape at once, :func:`~mi_neurallens.training.levenberg.polish_stack`; on a CPU one by one).
    A network that meets its goals here gets ``stop_reason = "goals"`` (Adam's is kept as
    ``adam_stop_reason``).  With ``ckpt``, each finished network is saved to ``<ckpt>.lm.<key>.json`` and
    a rerun takes it from there.  ``progress``: a bar per stack (seconds of its budget, iterations, loss)."""
    from .levenberg import MAX_PARAMS, n_params, polish_stack
    if nc.lm_minutes <= 0:
        return
    todo = []
    for j, (f, r, key) in enumerate(zip(fits, results, keys)):
        st = r["state"]
        if st.get("stop_reason") == "goals" or "lm" in st:
            continue
        P = n_params(r["layers"])
        if P > MAX_PARAMS:
            st["lm"] = {"skipped": f"{P} weights > {MAX_PARAMS}"}
            continue
        path = None if not ckpt else f"{ckpt}.lm.{key}.json"
        if path and os.path.exists(path):
            saved = json.loads(open(path).read())
            r["layers"] = [(np.asarray(W, np.float64), np.asarray(b, np.float64)) for W, b in saved["layers"]]
            r["state"] = saved["state"]
            continue
        todo.append(j)
    if not todo:
        return
    shapes: dict = {}              # one stack per architecture (refined base maps may mix them)
    for j in todo:
        shapes.setdefault(tuple(np.shape(W) for W, _ in results[j]["layers"]), []).append(j)
    stacks = []
    for group in shapes.values():
        P = n_params(results[group[0]]["layers"])
        n_out = int(np.shape(results[group[0]]["layers"][-1][1])[0])
        size = lm_stack_size(getattr(fits[group[0]], "dev", None), nc.lm_rows, n_out, P)
        stacks += [(group[c:c + size], P) for c in range(0, len(group), size)]
    for idx, P in stacks:
        for j in idx:
            fits[j].state = results[j]["state"]
            if log:
                log(getattr(fits[j], "desc", keys[j]), {"phase": "lm", "start_step": fits[j].state.get("step", 0),
                                                        "weights": P, "stacked_with": len(idx)})
        name = keys[idx[0]] if len(idx) == 1 else f"{keys[idx[0]]} + {len(idx) - 1}"
        bar, tick = _lm_bar(progress, f"{name} finish", 60.0 * nc.lm_minutes * len(idx))
        try:
            got = polish_stack(torch, [fits[j] for j in idx], [results[j]["layers"] for j in idx], nc,
                               seconds=60.0 * nc.lm_minutes, step0=[int(fits[j].state.get("step", 0)) for j in idx],
                               max_iterations=nc.lm_iterations or None, progress=tick)
        finally:
            if bar is not None:
                bar.close()
        for j, layers in zip(idx, got):
            r, st = results[j], fits[j].state
            r["layers"], r["state"] = layers, st
            st["adam_stop_reason"] = st.get("stop_reason")
            if st["lm"]["stop_reason"] == "goals":
                st["stop_reason"] = "goals"
            if ckpt:
                atomic_write_text(f"{ckpt}.lm.{keys[j]}.json",
                                  json.dumps({"layers": [(W.tolist(), b.tolist()) for W, b in layers], "state": st}))


#: a stack's Jacobians on a GPU stay below this (bytes; float32, with the scaled copy)
LM_STACK_BYTES = 8 << 30


def lm_stack_size(dev, rows: int, n_out: int, n_params_: int) -> int:
    """How many networks the finish polishes at once: one on a CPU (its cost is the Jacobian's
    multiply-adds, which a stack does not reduce, and one network's is already a 100 MB array); on a GPU as
    many as keep the stack's Jacobians within :data:`LM_STACK_BYTES` (32 ghost regressors: 7 GB)."""
    if not str(dev).startswith("cuda"):
        return 1
    return max(1, LM_STACK_BYTES // max(2 * 4 * int(rows) * int(n_out) * int(n_params_), 1))


def _lm_bar(enabled: bool, desc: str, seconds: float):
    """(tqdm bar or None, callback ``(iteration, losses, λs)``) for one stack's finish: the bar counts the
    seconds of its budget (it may end earlier, at the goals)."""
    if not enabled:
        return None, None
    try:
        from tqdm.auto import tqdm
    except ImportError:  # pragma: no cover
        return None, None
    bar = tqdm(total=int(round(seconds)), desc=desc, unit="s", leave=False, dynamic_ncols=True)
    t0 = time.perf_counter()

    def tick(it, loss, lam):        # the stack's networks still running: their losses and λs
        bar.n = min(int(time.perf_counter() - t0), bar.total)
        run = f"{len(loss)} running, " if len(loss) > 1 else ""
        bar.set_postfix_str(f"{run}iteration {it}, loss {max(loss):.3g}, λ {max(lam):.0e}")
    return bar, tick


# ----------------------------------------------------------------------------- regressor
def _new_state() -> dict:
    return {"step": 0, "best_val": math.inf, "best_step": 0, "history": [], "evals_since_best": 0,
            "seconds": 0.0, "samples": 0}


def train_regressor(stream: RegressorStream, val, nc: NetConfig, *, heading: int, center, scale_in, seed: int,
                    ckpt: str | None, threads: int = 2, device: str = "auto", progress: bool = True,
                    desc: str = "regressor", log=None, s_max: float | None = None) -> dict:
    """Train one regressor.  ``val``: (x, y) float64 held-out (valid) samples for validation.
    ``s_max`` (the domain's) is needed when ``nc.odd_y`` (see :func:`odd_factor`)."""
    p = dict(stream=stream, val=val, heading=heading, center=center, scale_in=scale_in, seed=seed, s_max=s_max,
             key=desc)
    return train_regressors([p], nc, ckpt=ckpt, threads=threads, device=device, progress=progress, log=log,
                            desc=desc)[0]


def train_regressors(problems, nc: NetConfig, *, ckpt: str | None = None, threads: int = 2, device: str = "auto",
                     progress: bool = True, log=None, desc: str = "regressors", start=None) -> list:
    """Train the regressors of several maps as one stack (:func:`~mi_neurallens.training.stacked.train_stack`),
    then finish each with Levenberg–Marquardt for ``nc.lm_minutes`` (:func:`polish_results`).

    ``problems``: one dict per map with ``stream`` (:class:`RegressorStream`), ``val`` ((x, y) float64
    held-out valid samples), ``heading``, ``center``, ``scale_in``, ``seed``, ``s_max`` (the domain's;
    needed when ``nc.odd_y``) and ``key``.  ``start``: one trained regressor per map (as returned here, or
    :func:`_kept`): no Adam, only the Levenberg–Marquardt finish from those weights and their output
    transform (what ``--refine`` runs).  Returns one result dict per map (layers, output transform,
    training state), in order."""
    from .stacked import peek_stack, pool_rows, train_stack
    from ..neural.model import position_cos
    torch = _torch(threads)
    dev = pick_device(torch, device)
    torch.manual_seed(int(problems[0]["seed"]))
    keys = [p["key"] for p in problems]
    prior = peek_stack(ckpt, keys)
    n_pool = pool_rows(nc, len(problems), 4 * (4 + 5 + 5 + 1)) if start is None else REFINE_POOL
    t_start = time.perf_counter()
    fits = []
    for p in problems:
        odd_s = None
        if nc.odd_y:
            if p.get("s_max") is None:
                raise NeuralLensError("train_regressor: odd_y needs the domain's s_max")
            odd_s = float(p["s_max"])
        stream, center, scale_in = p["stream"], p["center"], p["scale_in"]
        resumed = p["key"] in prior
        state = prior[p["key"]] if resumed else _new_state()
        if start is not None:
            s0 = start[len(fits)]
            if bool(s0["odd_y"]) != (odd_s is not None):
                raise NeuralLensError(f"{p['key']}: the regressor to refine was trained with odd_y={s0['odd_y']}")
            state = {**_new_state(), "step": int(s0["state"].get("step", 0)), "refined": True}
            state.update(odd_y=odd_s is not None, skip=np.asarray(s0["skip"]).tolist(),
                         shift=np.asarray(s0["out_shift"]).tolist(), oscale=np.asarray(s0["out_scale"]).tolist())
            resumed = True
        elif resumed:
            if bool(state.get("odd_y", False)) != (odd_s is not None):
                raise NeuralLensError(f"{ckpt}: checkpoint was trained with odd_y={state.get('odd_y', False)}; "
                                      "use another work directory or the same setting")
            stream.reseed([int(p["seed"]), state["step"]])
        u0, x0, y0 = stream.sample(n_pool)
        # position_cos: decided once from the first pool (a refine from its map, a resume from its checkpoint)
        if start is not None:
            cos = bool(start[len(fits)].get("position_cos", False))
        elif resumed:
            cos = bool(state.get("position_cos", False))
        else:
            cos = wants_position_cos(nc.exit_position, y0)
        state["position_cos"] = cos
        # input_box: train on the valid rays' box (folded back at the end); a checkpoint resumes on the box it had
        if nc.input_box and start is None and not resumed:
            state["input_box"] = [v.tolist() for v in input_box(x0, center, scale_in)]
        if "input_box" in state:
            center, scale_in = (np.asarray(v, np.float64) for v in state["input_box"])
        xn0 = (x0 - center) / scale_in
        if not resumed:
            transform = fit_output_transform(xn0, position_cos(y0) if cos else y0, nc.residual,
                                             odd_factor(x0[:, 2], odd_s))
            state.update(odd_y=odd_s is not None, skip=transform[0].tolist(), shift=transform[1].tolist(),
                         oscale=transform[2].tolist())
        else:
            transform = tuple(np.asarray(state[n]) for n in ("skip", "shift", "oscale"))
        fits.append(RegressorFit(torch, dev, None, nc, stream, p["val"], (u0, x0, y0),
                                 state=state, heading=p["heading"],
                                 center=center, scale_in=scale_in, transform=transform, odd_s=odd_s,
                                 position_cos=cos, log=log,
                                 desc=f"{p['key']} regressor" if len(problems) > 1 else desc))
    if start is None:
        res = train_stack(torch, dev, fits, nc, seeds=[p["seed"] for p in problems], n_in=4, n_out=5, keys=keys,
                          ckpt=ckpt, progress=progress, desc=desc, log=log)
    else:
        res = [{"layers": s0["layers"], "state": f.state} for s0, f in zip(start, fits)]
    polish_results(torch, fits, res, nc, keys, ckpt, log, progress)
    out = []
    for r, f, p in zip(res, fits, problems):
        st = r["state"]
        st["wall_seconds_total"] = time.perf_counter() - t_start
        st["stacked_with"] = len(problems)
        layers, skip, shift = r["layers"], np.asarray(f.skip), np.asarray(f.shift)
        if is_box((f.center, f.scale_in), p["center"], p["scale_in"]):
            layers, skip, shift = fold_input_box(layers, skip, shift, (f.center, f.scale_in),
                                                 (p["center"], p["scale_in"]))
        out.append({"layers": layers, "skip": skip, "out_shift": shift, "out_scale": np.asarray(f.oscale),
                    "odd_y": f.odd_s is not None, "position_cos": f.position_cos, "state": st})
    return out


class RegressorFit(Problem):
    """One regressor's training problem, its pieces as methods (what :func:`train_regressor` runs and
    tests call): the sample pool and its targets, the loss, validation and pool refresh.

    ``transform`` = (skip, shift, oscale) of :func:`fit_output_transform`; the network's output ``p``
    relates to the reduced-frame outputs ``y`` by ``y = M·(shift + skip·xn) + oscale·(M·p)`` with ``M``
    the odd-y factor (1 unless ``odd_s``).  ``pool0`` = (u, x, y) of the first pool.
    """

    POOL = {"X": "X", "Y": "Y", "Yraw": "Yraw", "W": "Wedge"}   # inputs, targets, raw outputs, edge weights

    def __init__(self, torch, dev, net, nc: NetConfig, stream, val, pool0, *, state, heading: int,
                 center, scale_in, transform, odd_s, position_cos=False, log=None, desc="regressor"):
        self.torch, self.dev, self.net, self.nc, self.stream = torch, dev, net, nc, stream
        self.state, self.heading, self.log, self.desc = state, heading, log, desc
        self.center, self.scale_in, self.odd_s = center, scale_in, odd_s
        #: the map regresses the exit position times |dz| (:func:`~mi_neurallens.neural.model.position_cos`): its
        #: targets, held-out outputs and validation errors are in that space (a ray's offset, not a plane's)
        self.position_cos = bool(position_cos)
        self.skip, self.shift, self.oscale = transform
        self.T_skip, self.T_shift, self.T_scale = (self.f32(v) for v in transform)
        u0, x0, y0 = pool0
        xn0 = (x0 - center) / scale_in
        self.sig_d2 = float(np.mean(self.oscale[2:4] ** 2))
        self.W = self.f32(loss_weights(nc.loss_weights, self.oscale, y0))
        # M of a batch from its normalised inputs (ωy = center + scale·xn)
        self.wy_c, self.wy_s = float(center[2]), float(scale_in[2])
        self.X = self.f32(xn0)
        self.Y = self.f32(self.targets(x0, xn0, self.space(y0)))
        self.Yraw = self.f32(y0)
        self.Wedge = self.f32(edge_weights(stream.ps, u0, nc)) if nc.edge_weight > 0 else None
        self.xv, self.yv = val[0], self.space(val[1])
        self.xvn = (self.xv - center) / scale_in
        self.Xv, self.Yv = self.f32(self.xvn), self.f32(self.targets(self.xv, self.xvn, self.yv))
        # the validation rays within edge_margin of an aperture edge: their error is logged on its own
        _, mv, _ = stream.ps.margin_u(stream.ps.domain.x_to_u(self.xv))
        self.near_edge = mv < nc.edge_margin

    def f32(self, a):
        return self.torch.as_tensor(np.ascontiguousarray(a, dtype=np.float32), device=self.dev)

    def space(self, y):
        """Reduced-frame outputs ``y`` as this map regresses them: as they are, or with ``position_cos`` the
        exit position times |dz|."""
        if not self.position_cos:
            return y
        from ..neural.model import position_cos
        return position_cos(y)

    def targets(self, x, xn, y):
        """What the network's output times M should equal: (y − M·(shift + skip·xn)) / scale."""
        return (y - odd_factor(x[:, 2], self.odd_s) * (self.shift + xn @ self.skip.T)) / self.oscale

    def outputs(self, x, xn, p):
        """The inverse of :meth:`targets`: reduced-frame outputs from the network's output times M."""
        return p * self.oscale + odd_factor(x[:, 2], self.odd_s) * (self.shift + xn @ self.skip.T)

    def M_of(self, xb, const=None):
        """The odd-y factor M of a batch of normalised inputs ``xb`` (…, B, 4) (ones unless ``odd_s``);
        ``const``: the (stacked) constants of :meth:`constants`, default this map's."""
        M = self.torch.ones(xb.shape[:-1] + (5,), device=xb.device, dtype=xb.dtype)
        if self.odd_s is not None:
            c = {"wy_c": self.wy_c, "wy_s": self.wy_s, "odd_s": self.odd_s} if const is None else const
            m = (c["wy_c"] + c["wy_s"] * xb[..., 2]) / c["odd_s"]
            for j in ODD_COLUMNS:
                M[..., j] = m
        return M

    def dir3(self, dxy):
        """Unit 3-vectors from (dx, dy) (…, 2) with dz of the map's heading."""
        torch = self.torch
        # floored above 0: √ has an infinite slope there, and a fisheye's grazing exit rays (|dz| → 0) turned Adam's
        # gradient into NaN (a ray within 0.006° of 90° is all this floor changes)
        dz = self.heading * torch.sqrt(torch.clamp(1.0 - (dxy * dxy).sum(-1, keepdim=True), min=1e-8))
        v = torch.cat([dxy, dz], -1)
        return v / v.norm(dim=-1, keepdim=True)

    def predict(self, xb):
        """Network output times M (compared with the targets) and M."""
        M = self.M_of(xb)
        return self.net(xb) * M, M

    # -- the pieces :func:`~mi_neurallens.training.stacked.train_stack` runs --------------------------
    def constants(self):
        """This map's loss constants, shaped to broadcast against a (B, ·) batch (stacked: (K, B, ·))."""
        t = self.torch
        one = lambda v: t.as_tensor(np.float32(v), device=self.dev).reshape(1)
        return {"W": self.W[None], "shift": self.T_shift[None], "skip": self.T_skip, "scale": self.T_scale[None],
                "sig_d2": t.as_tensor(np.float32(self.sig_d2), device=self.dev), "wy_c": one(self.wy_c),
                "wy_s": one(self.wy_s), "odd_s": one(self.odd_s if self.odd_s is not None else 1.0)}

    def rows_loss(self, out, batch, const):
        """The loss of a batch (dict of :meth:`pool` rows, (B, ·) or stacked (K, B, ·); ``out``: the
        network's outputs on ``batch["X"]``), reduced over the samples only: weighted standardised MSE
        (position and T; directions too unless ``cosine``) plus the cosine term 1 − cos of the exit
        directions.  ``batch["W"]``: edge weights (absent: uniform)."""
        nc = self.nc
        xb, tb, yb_raw, wb = batch["X"], batch["Y"], batch["Yraw"], batch.get("W")
        M = self.M_of(xb, const)
        p = out * M
        mean = (lambda v: v.mean(-1)) if wb is None else (lambda v: (v * wb).mean(-1))
        if nc.direction_loss == "cosine":
            l = mean((((p - tb) ** 2) * const["W"])[..., [0, 1, 4]].mean(-1)) * 3.0 / 5.0
        else:
            l = mean((((p - tb) ** 2) * const["W"]).mean(-1))
        if nc.direction_loss in ("cosine", "mse+cosine"):
            d_pred = M[..., 2:4] * (const["shift"][..., 2:4] + xb @ const["skip"][..., 2:4, :].transpose(-1, -2)) \
                + const["scale"][..., 2:4] * p[..., 2:4]
            # 1 − cos(a, b) = |â − b̂|²/2 for unit vectors (the stable form in float32)
            cos_term = mean(((self.dir3(d_pred) - self.dir3(yb_raw[..., 2:4])) ** 2).sum(-1)) / (2.0 * const["sig_d2"])
            l = l + nc.cosine_weight * cos_term * (2.0 / 5.0)
        return l

    #: RegressorFit's direction losses as the fused kernel's loss_regressor numbers them (else: MSE alone)
    FUSED_COS_MODE = {"cosine": 1, "mse+cosine": 2}

    def has_fused_loss(self) -> bool:
        return self.T_skip.shape == (5, 4)

    def fused_loss(self, kern, out, batch, const):
        """:meth:`rows_loss` and its gradient in one pass of ``kern`` (:mod:`~mi_neurallens.training.fused_cpu`)."""
        return kern.loss_regressor(self.torch, out, batch, const, odd=self.odd_s is not None,
                                   cos_mode=self.FUSED_COS_MODE.get(self.nc.direction_loss, 0),
                                   cosine_weight=self.nc.cosine_weight, heading=float(self.heading))

    def lm_residual(self, z, batch):
        """Levenberg–Marquardt's residuals of the network's outputs ``z`` (n, 5) on ``batch`` and their
        derivative ∂r/∂z (:mod:`~mi_neurallens.training.levenberg`): the weighted standardised errors whose mean
        square is the MSE part of :meth:`rows_loss` (the cosine term, which only re-weights the directions, is
        left out)."""
        w = self.torch.sqrt(self.W).to(z.dtype).expand(z.shape[0], -1)
        if batch.get("W") is not None:
            w = w * self.torch.sqrt(batch["W"]).to(z.dtype)[:, None]
        M = self.M_of(batch["X"]).to(z.dtype)
        return w * (z * M - batch["Y"].to(z.dtype)), w * M

    def fresh_rows(self, k):
        """``k`` fresh pool rows from the stream."""
        ur, xr, yr = self.stream.sample(k)
        xrn = (xr - self.center) / self.scale_in
        out = {"X": self.f32(xrn), "Y": self.f32(self.targets(xr, xrn, self.space(yr))), "Yraw": self.f32(yr)}
        if self.nc.edge_weight > 0:
            out["W"] = self.f32(edge_weights(self.stream.ps, ur, self.nc))
        return out

    def goals_met(self) -> bool:
        """The last validation meets ``nc.goal_position_um`` and ``nc.goal_direction_arcsec`` (median, p99),
        with the margin ``nc.goal_margin``."""
        r = self.state["history"][-1] if self.state["history"] else None
        if r is None:
            return False
        g = self.nc.goal_margin
        (pm, pp), (dm, dp) = self.nc.goal_position_um, self.nc.goal_direction_arcsec
        return r["pos_um_med"] <= g * pm and r["pos_um_p99"] <= g * pp and r["dir_as_med"] <= g * dm \
            and r["dir_as_p99"] <= g * dp

    def validate(self, step, loss, seconds):
        """Held-out errors, appended to the training history; returns (score, progress-bar postfix)."""
        from .evaluate import regression_errors
        with self.torch.no_grad():
            pv, _ = self.predict(self.Xv)
            vl = float(((pv - self.Yv) ** 2).mean())
            yp = self.outputs(self.xv, self.xvn, pv.double().cpu().numpy())
        m = regression_errors(yp, self.yv, self.heading)
        rec = {"step": step, "loss": loss.item() if loss is not None else math.nan, "val_mse": vl,
               "seconds": seconds,
               "pos_um_med": m["position_um_median"], "pos_um_p99": m["position_um_p99"],
               "dir_as_med": m["direction_arcsec_median"], "dir_as_p99": m["direction_arcsec_p99"],
               "T_rel_med": m["throughput_rel_median"]}
        if self.near_edge.any():
            e = regression_errors(yp[self.near_edge], self.yv[self.near_edge], self.heading)
            rec.update(edge_pos_um_med=e["position_um_median"], edge_pos_um_p99=e["position_um_p99"])
        self.state["history"].append(rec)
        if self.log:
            self.log(self.desc, rec)
        return vl, dict(val=f"{vl:.2e}", pos=f"{m['position_um_median']:.2f}µm",
                        dir=f"{m['direction_arcsec_median']:.2f}\"")


# ----------------------------------------------------------------------------- classifier
def train_classifier(ps: PathSampler, valid_u_source, val, nc: NetConfig, *, center, scale_in, seed: int,
                     ckpt: str | None, threads: int = 2, device: str = "auto", progress: bool = True,
                     desc: str = "classifier", log=None) -> dict:
    """``valid_u_source(n)`` → (n, 4) valid unit-cube samples; ``val``: (x, label) natural-mix held-out."""
    p = dict(ps=ps, valid_u_source=valid_u_source, val=val, center=center, scale_in=scale_in, seed=seed, key=desc)
    return train_classifiers([p], nc, ckpt=ckpt, threads=threads, device=device, progress=progress, log=log,
                             desc=desc)[0]


def train_classifiers(problems, nc: NetConfig, *, ckpt: str | None = None, threads: int = 2, device: str = "auto",
                      progress: bool = True, log=None, desc: str = "classifiers", start=None) -> list:
    """Train the classifiers of several maps as one stack, then (margin target only) finish each with
    Levenberg–Marquardt for ``nc.lm_minutes`` (:func:`polish_results`).  ``problems``: one dict per map
    with ``ps`` (:class:`PathSampler`), ``valid_u_source`` (n → (n, 4) valid unit-cube samples), ``val``
    ((x, label) natural-mix held-out), ``center``, ``scale_in``, ``seed`` and ``key``.  ``start``: one
    trained classifier per map (``{"layers", …}``): only the finish, from those weights.  Returns
    ``{"layers", "state"}`` per map, in order."""
    from .stacked import peek_stack, pool_rows, train_stack
    torch = _torch(threads)
    dev = pick_device(torch, device)
    torch.manual_seed(int(problems[0]["seed"]))
    keys = [p["key"] for p in problems]
    prior = peek_stack(ckpt, keys)
    ncp = dataclasses.replace(nc, pool=pool_rows(nc, len(problems), 4 * 5) if start is None else REFINE_POOL)
    fits = []
    for p in problems:
        resumed = p["key"] in prior
        state = prior[p["key"]] if resumed else _new_state()
        rng = np.random.default_rng([int(p["seed"]), state["step"]] if resumed else p["seed"])
        fits.append(ClassifierFit(torch, dev, None, ncp, p["ps"], p["valid_u_source"], p["val"], rng=rng, state=state,
                                  center=p["center"], scale_in=p["scale_in"], log=log,
                                  desc=f"{p['key']} classifier" if len(problems) > 1 else desc))
    if start is None:
        res = train_stack(torch, dev, fits, nc, seeds=[p["seed"] for p in problems], n_in=4, n_out=1, keys=keys,
                          ckpt=ckpt, progress=progress, desc=desc, log=log)
    else:
        for f, s0 in zip(fits, start):
            f.state.update(step=int(s0["state"].get("step", 0)), refined=True)
        res = [{"layers": s0["layers"], "state": f.state} for s0, f in zip(start, fits)]
    if nc.target == "margin":
        polish_results(torch, fits, res, nc, keys, ckpt, log, progress)
    for r in res:
        r["state"]["stacked_with"] = len(problems)
    return res


def train_sized(train, problems, nc: NetConfig, ckpt, net: str, **kw) -> list:
    """Train one network per problem with ``train`` (:func:`train_regressors` or :func:`train_classifiers`),
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


class ClassifierFit(Problem):
    """One classifier's training problem, its pieces as methods (what :func:`train_classifier` runs and
    tests call): the labelled (or margin-target) pool, the loss, validation and pool refresh."""

    POOL = {"X": "X", "L": "L"}         # inputs, training targets (labels or scaled margins)

    def __init__(self, torch, dev, net, nc: NetConfig, ps: PathSampler, valid_u_source, val, *, rng, state,
                 center, scale_in, log=None, desc="classifier"):
        self.torch, self.dev, self.net, self.nc, self.ps = torch, dev, net, nc, ps
        self.valid_u_source, self.rng, self.state = valid_u_source, rng, state
        self.center, self.scale_in, self.log, self.desc = center, scale_in, log, desc
        self.margin = nc.target == "margin"
        self.X, self.L = self.samples(nc.pool)
        xv, lv = val
        self.Xv, self.Lv = self.f32((xv - center) / scale_in), torch.as_tensor(lv.astype(bool), device=dev)
        self.bce = torch.nn.BCEWithLogitsLoss()

    def f32(self, a):
        return self.torch.as_tensor(np.ascontiguousarray(a, dtype=np.float32), device=self.dev)

    def samples(self, n):
        """``n`` new pool rows (inputs, training target): the 0/1 label, or scale·margin clipped to ±clip (−clip on a hard
        failure)."""
        nc = self.nc
        got = classifier_samples(self.ps, self.valid_u_source(max(n // 3, 1024)), n, self.rng, margin=self.margin,
                                 sigma_range=tuple(nc.boundary_sigma))
        if not self.margin:
            return self.f32((got[0] - self.center) / self.scale_in), self.f32(got[1])
        x, _, m, hard = got
        c = nc.margin_clip
        t = np.where(hard, -c, np.clip(m * nc.margin_scale, -c, c))
        return self.f32((x - self.center) / self.scale_in), self.f32(t)

    def margin_loss(self, logit, t):
        """Interval regression: logit = scale·margin inside the band |t| < clip; at the clip only the
        side counts (logit ≥ clip where the margin is large, ≤ −clip where it is very negative or the ray
        fails for a non-aperture reason), so the network spends nothing on fitting far-away targets."""
        torch, c = self.torch, self.nc.margin_clip
        lo = torch.where(t <= -c, torch.full_like(t, -math.inf), t)
        hi = torch.where(t >= c, torch.full_like(t, math.inf), t)
        return (torch.relu(lo - logit) ** 2 + torch.relu(logit - hi) ** 2).mean(-1)

    # -- the pieces :func:`~mi_neurallens.training.stacked.train_stack` runs --------------------------
    def rows_loss(self, out, batch, const):
        """The loss of a batch ((B, ·) or stacked (K, B, ·); ``out``: the logits), reduced over the samples:
        the margin interval loss or binary cross-entropy."""
        logit, t = out[..., 0], batch["L"]
        if self.margin:
            return self.margin_loss(logit, t)
        return self.torch.nn.functional.binary_cross_entropy_with_logits(logit, t, reduction="none").mean(-1)

    def has_fused_loss(self) -> bool:
        return self.margin

    def fused_loss(self, kern, out, batch, const):
        """:meth:`margin_loss` of the logits and its gradient in one pass of ``kern``
        (:mod:`~mi_neurallens.training.fused_cpu`)."""
        return kern.loss_margin(self.torch, out, batch["L"], self.nc.margin_clip)

    def fresh_rows(self, k):
        X, L = self.samples(k)
        return {"X": X, "L": L}

    def lm_residual(self, z, batch):
        """Levenberg–Marquardt's residuals of the logits ``z`` (n, 1) on ``batch`` and ∂r/∂z: the distance of
        each logit from its target interval (:meth:`margin_loss`), 0 inside it.  The margin target only (BCE
        is not a sum of squares)."""
        if not self.margin:
            raise NeuralLensError("Levenberg–Marquardt needs the classifier's margin target (target = 'margin')")
        torch, c = self.torch, self.nc.margin_clip
        t = batch["L"].to(z.dtype)[:, None]
        lo = torch.where(t <= -c, torch.full_like(t, -math.inf), t)
        hi = torch.where(t >= c, torch.full_like(t, math.inf), t)
        r = z - torch.maximum(torch.minimum(z, hi), lo)
        return r, (r != 0).to(z.dtype)

    def goals_met(self) -> bool:
        """The last validation's misclassification is at most ``nc.goal_misclassification``."""
        h = self.state["history"]
        return bool(h) and h[-1]["val_misclass"] <= self.nc.goal_margin * self.nc.goal_misclassification

    def validate(self, step, loss, seconds):
        """Held-out misclassification and BCE, appended to the history; returns (score, postfix)."""
        with self.torch.no_grad():
            lg = self.net(self.Xv)[:, 0]
            err = float(((lg > 0) != self.Lv).float().mean())
            vb = float(self.bce(lg, self.Lv.float()))
        rec = {"step": step, "loss": loss.item() if loss is not None else math.nan, "val_bce": vb,
               "val_misclass": err, "seconds": seconds}
        self.state["history"].append(rec)
        if self.log:
            self.log(self.desc, rec)
        return err + 0.01 * vb, dict(miscls=f"{100 * err:.3f}%")


# ----------------------------------------------------------------------------- prior calibration
def calibrate_classifier(lens, tm, n: int = 200_000, seed: int = 0, fresnel: bool = True) -> float:
    """Shift the classifier's decision threshold to the natural class prior.

    The classifier is trained on a balanced mix (valid samples and boundary perturbations are
    over-represented, by about 1/valid-fraction), so its logit carries a prior offset of roughly
    log(1 + 1/f) in regions it cannot resolve.  This picks the logit offset that minimises the
    misclassification on ``n`` fresh rays uniform over the domain (a calibration set, seeded apart from
    the held-out evaluation) and folds it into the last bias.  Returns the offset."""
    rng = np.random.default_rng(seed)
    dom = Domain.from_dict(tm.domain)
    ps = PathSampler(lens, tm.path_id, tm.direction, tm.z_in, tm.z_out, dom, fresnel=fresnel, precision="float64")
    x = dom.u_to_x(rng.random((n, 4)))
    v, _ = ps.trace_x(x)
    logit, _ = map_outputs_np(tm, x)
    grid = np.linspace(-8.0, 8.0, 641)
    err = np.array([np.mean((logit > b) != v) for b in grid])
    best = np.flatnonzero(err <= err.min() + 1e-12)
    off = float(grid[best[np.argmin(np.abs(grid[best]))]])
    W, b = tm.classifier[-1]
    tm.classifier[-1] = (W, np.asarray(b) - off)
    tm.training["classifier_logit_offset"] = off
    tm.training["classifier_calibration"] = {"n": n, "misclassification_before": float(np.mean((logit > 0) != v)),
                                             "misclassification_after": float(err.min())}
    return off


# ----------------------------------------------------------------------------- one map
#: what :func:`train_map` can keep from an earlier map instead of training it: one network, or
#: ``"both"`` (train only the stop head), ``"refine"`` (start both networks from it and run only the
#: Levenberg–Marquardt finish, ``lm_minutes`` per network), or ``"refine-stop"`` (keep both networks and run only
#: the finish of its stop head, from the base's)
NETWORKS = ("regressor", "classifier", "both", "refine", "refine-stop")


def _check_keep(keep: str | None, base, path_id: int, direction: str, z_in: float, z_out: float, domain: Domain):
    """Validate a ``keep``/``base`` pair of :func:`train_map` (the kept network must come from a map of the
    same path, direction, planes and domain: its inputs and outputs mean the same only then)."""
    if keep is None:
        return
    if keep not in NETWORKS:
        raise NeuralLensError(f"keep = {keep!r}: choose one of {list(NETWORKS)} (or None to train all)")
    if base is None:
        raise NeuralLensError(f"keep = {keep!r} needs the map whose {keep} is kept (base)")
    want = (int(path_id), direction)
    if (int(base.path_id), base.direction) != want:
        raise NeuralLensError(f"keep = {keep!r}: the base map is {base.key}, not {direction}.{path_id}")
    if abs(base.z_in - z_in) > 1e-9 or abs(base.z_out - z_out) > 1e-9:
        raise NeuralLensError(f"keep = {keep!r}: the base map {base.key} uses planes z = {base.z_in:g} -> "
                              f"{base.z_out:g} mm, this training {z_in:g} -> {z_out:g} mm (another close_focus_mm?)")
    bd = Domain.from_dict(base.domain)
    if not np.allclose([bd.r_max, bd.s_max, bd.lam_min, bd.lam_max],
                       [domain.r_max, domain.s_max, domain.lam_min, domain.lam_max], rtol=1e-9, atol=0.0):
        raise NeuralLensError(f"keep = {keep!r}: the base map {base.key} was trained on another input domain "
                              f"({base.domain}) than this training ({domain.to_dict()})")
    if bd.reach != domain.reach:
        raise NeuralLensError(f"keep = {keep!r}: the base map {base.key} was trained with film reach {bd.reach}, "
                              f"this training with {domain.reach}")


def _kept(base, network: str) -> dict:
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


def _widened(kept: dict, nc: NetConfig, base, log) -> dict:
    """A ``refine`` run's start: the network ``kept`` (:func:`_kept`) as it is, or, where ``nc`` asks for the same
    number of hidden layers but wider ones (``--set forward_regressor.width=32`` on a 3×16 map), widened to
    ``nc.width`` without changing what it computes (:func:`~mi_neurallens.training.levenberg.widen`), so the
    finish continues from the optimum it had with room to go lower.  Any other architecture in ``nc`` is ignored:
    refining keeps the base's."""
    from .levenberg import widen_as_configured
    layers, hidden = widen_as_configured(kept["layers"], nc.hidden, nc.width, [int(base.path_id), int(nc.width)])
    if hidden is None:
        return kept
    if log:
        log(f"{base.key} widened", {"from": "x".join(map(str, hidden)), "to": f"{nc.hidden}x{nc.width}"})
    return {**kept, "layers": layers, "config": {**kept.get("config", {}), "width": int(nc.width),
                                                  "widened_from": hidden}}


def _carry_history(result: dict, kept: dict) -> None:
    """A refined network's record: its configuration, activation and Adam history from the map it started
    from (``kept``, :func:`_kept`), then the Levenberg–Marquardt validations; samples and seconds add up."""
    st, st0 = result["state"], kept["state"]
    result["config"], result["activation"] = kept["config"], kept["activation"]
    st["history"] = list(st0.get("history", [])) + st["history"]
    st["samples"] = int(st0.get("samples", 0)) + int(st.get("samples", 0))
    st["seconds"] = float(st0.get("seconds", 0.0)) + float(st.get("seconds", 0.0))
    st["adam_stop_reason"] = st0.get("stop_reason")


def _refining(nc: NetConfig, network: str, direction: str, bases) -> NetConfig:
    """The settings of a ``keep = "refine"`` run: ``nc`` as configured (:func:`_check_finishable` has made sure
    it gives the finish some time); a classifier keeps the target (and its scale) it was trained with, so the
    finish minimises the loss its weights were made for."""
    if network == "classifier":
        got = {tuple(b.training.get("classifier", {}).get(k, getattr(nc, k))
                     for k in ("target", "margin_scale", "margin_clip")) for b in bases}
        if len(got) != 1:
            raise NeuralLensError(f"refine: the classifiers of one run must share their target, got {sorted(got)}")
        target, scale, clip = got.pop()
        nc = dataclasses.replace(nc, target=target, margin_scale=float(scale), margin_clip=float(clip))
    return nc


def _check_finishable(bases, nets, direction: str) -> None:
    """:func:`~mi_neurallens.training.levenberg.check_refinable` for each network a ``refine`` run finishes, all
    before any training (not after the other network's finish): one given no time for the finish, or larger than
    it takes (a 5×32 regressor, or one the configured width would widen past it), is a clear error naming the way
    out.  ``nets``: (network, its NetConfig) pairs."""
    from .levenberg import check_refinable
    for network, nc in nets:
        table = f"forward_{network}" if direction == "forward" else network
        other = "classifier" if network == "regressor" else "regressor"
        check_refinable([(b.key, getattr(b, network)) for b in bases], nc, f"the {network}'s", table,
                        f"--keep {other} --set {table}.hidden=3 --set {table}.width=32 --set {table}.lm_minutes=2.5",
                        what=f"refine: the {network} of ")


def _train_networks(train, problems, nc: NetConfig, net: str, ck, keys, cfg: TrainConfig, direction: str,
                    refine_from, progress: bool, log) -> list:
    """One network (``net``: "regressor" or "classifier") of every map of ``problems`` with ``train``
    (:func:`train_regressors` or :func:`train_classifiers`): through :func:`train_sized`, or, with
    ``refine_from`` (one base map per problem), only the Levenberg–Marquardt finish from the base maps'
    networks, their records carried (:func:`_carry_history`)."""
    kw = dict(threads=cfg.threads, device=cfg.device, progress=progress, log=log)
    if refine_from is None:
        return train_sized(train, problems, nc, ck, net, **kw)
    kept = [_widened(_kept(b, net), nc, b, log) for b in refine_from]
    out = train(problems, _refining(nc, net, direction, refine_from), ckpt=ck(f"{net}-refine", keys),
                start=kept, **kw)
    for r, k in zip(out, kept):
        _carry_history(r, k)
    return out


def map_seed(cfg: TrainConfig, path_id: int, direction: str) -> int:
    """The seed of one map (its data streams, held-out sets and initial weights)."""
    return int(cfg.seed) * 1_000_003 + int(path_id) * 2 + (direction == "forward")


def regressor_problem(lens, spec, stream, seed: int, key: str, cfg: TrainConfig) -> dict:
    """One map's problem for :func:`train_regressors`: ``spec`` = (path_id, direction, z_in, z_out, domain),
    ``stream`` its :class:`~mi_neurallens.training.data.RegressorStream`, validated on ≤ 20 000 held-out
    valid rays traced with ``seed + 7``."""
    from .evaluate import heldout_valid
    p, d, zi, zo, dom = spec
    center, scale_in = dom.norm_center_scale()
    val = heldout_valid(lens, (p, d, zi, zo), dom, min(cfg.heldout, 20_000), seed + 7, cfg.mcmc_threshold,
                        cfg.fresnel)
    return dict(stream=stream, val=val, heading=1 if d == "forward" else -1, center=center, scale_in=scale_in,
                seed=seed, s_max=dom.s_max, key=key)


def classifier_problem(lens, spec, ps, stream, seed: int, key: str, cfg: TrainConfig) -> dict:
    """One map's problem for :func:`train_classifiers`: ``ps`` its float32
    :class:`~mi_neurallens.training.data.PathSampler`, valid inputs drawn from ``stream``; validated on the
    natural mix (:data:`CLASSIFIER_VALIDATION` rays uniform over the domain, float64 labels, ``seed + 11``) —
    large, because only the few rays near the boundary tell two good classifiers apart (0.02 % of 400 k = 80
    errors)."""
    p, d, zi, zo, dom = spec
    psv = PathSampler(lens, p, d, zi, zo, dom, fresnel=cfg.fresnel, precision="float64")
    xcv = dom.u_to_x(np.random.default_rng(seed + 11).random((CLASSIFIER_VALIDATION, 4)))
    lcv, _ = psv.trace_x(xcv)
    center, scale_in = dom.norm_center_scale()
    return dict(ps=ps, valid_u_source=(lambda n, s=stream: s.sample(n)[0]), val=(xcv, lcv), center=center,
                scale_in=scale_in, seed=seed + 1, key=key)


def train_map(lens, path_id: int, direction: str, z_in: float, z_out: float, domain: Domain, cfg: TrainConfig,
              workdir: str | None = None, progress: bool = True, log=None, evaluate: bool = True,
              eval_n: int | None = None, keep: str | None = None, base=None):
    """Train the classifier, regressor and stop head of one map; returns a
    :class:`~mi_neurallens.neural.model.NeuralMap` with held-out metrics (:func:`train_maps` of one map).

    The stop head (:mod:`~mi_neurallens.training.stop_head`) is trained when the path crosses the stop
    plane and ``cfg.stop.max_minutes > 0``; with ``keep``, a stop head the base map has is kept.
    ``keep = "both"`` keeps the classifier and the regressor and trains only the stop head (what adds a
    render-time aperture to a shipped map without changing anything else it outputs).
    ``keep = "regressor"`` (or ``"classifier"``) takes that network unchanged from ``base`` (a
    :class:`~mi_neurallens.neural.model.NeuralMap` of the same path, planes and domain) and trains only
    the other one: e.g. a longer or wider classifier for a ghost whose flare error sits on its edge,
    without paying for (or changing) its regressor.  The kept network's training record is carried over
    under ``training["kept"]``."""
    _check_keep(keep, base, path_id, direction, z_in, z_out, domain)
    if keep in ("both", "refine-stop"):
        return _add_stop_heads(lens, [base], cfg, [map_seed(cfg, path_id, direction)], progress, log,
                               refine=keep == "refine-stop")[0]
    return train_maps(lens, [(path_id, direction, z_in, z_out, domain)], cfg, workdir, progress=progress, log=log,
                      evaluate=evaluate, eval_n=eval_n, keep=keep, bases=None if base is None else [base])[0]


def train_maps(lens, specs, cfg: TrainConfig, workdir: str | None = None, progress: bool = True, log=None,
               evaluate: bool = True, eval_n: int | None = None, keep: str | None = None, bases=None) -> list:
    """Train several maps of ``lens`` together: all their regressors as one stack, then all their
    classifiers, then their stop heads (one stack per stop-crossing count), each network leaving its stack
    when it meets its goals (:mod:`~mi_neurallens.training.stacked`).  ``specs``: (path_id, direction,
    z_in, z_out, domain) per map, all of one direction.  ``keep``/``bases``: as :func:`train_map`, one
    base map per spec.  Returns the :class:`~mi_neurallens.neural.model.NeuralMap` s, in order."""
    from ..neural.model import NeuralMap
    from .evaluate import evaluate_map
    from .stacked import stack_name
    specs = [(int(p), d, float(zi), float(zo), dom) for p, d, zi, zo, dom in specs]
    dirs = {d for _, d, *_ in specs}
    if len(dirs) != 1:
        raise NeuralLensError(f"train_maps: one direction per call, got {sorted(dirs)}")
    direction = dirs.pop()
    for j, (p, d, zi, zo, dom) in enumerate(specs):
        _check_keep(keep, None if bases is None else bases[j], p, d, zi, zo, dom)
    if keep in ("both", "refine-stop"):
        return _add_stop_heads(lens, bases, cfg, [map_seed(cfg, p, d) for p, d, *_ in specs], progress, log,
                               refine=keep == "refine-stop")
    keys = [f"{d}.{p}" for p, d, *_ in specs]
    seeds = [map_seed(cfg, p, d) for p, d, *_ in specs]
    rc, cc = cfg.net("regressor", direction), cfg.net("classifier", direction)
    if keep == "refine":
        _check_finishable(bases, (("regressor", rc), ("classifier", cc)), direction)
    ck = (lambda net, ks: os.path.join(workdir, stack_name(net, ks) + ".ckpt")) if workdir else (lambda net, ks: None)
    t0 = time.perf_counter()
    samplers, streams = [], []
    for (p, d, zi, zo, dom), seed in zip(specs, seeds):
        ps = PathSampler(lens, p, d, zi, zo, dom, fresnel=cfg.fresnel)
        samplers.append(ps)
        streams.append(RegressorStream(ps, seed, cfg.mcmc_threshold, cfg.mcmc_chains, cfg.mcmc_p_large,
                                       cfg.mcmc_sigma))
    if keep == "regressor":
        regs = [_kept(b, "regressor") for b in bases]
    else:
        problems = [regressor_problem(lens, spec, stream, seed, key, cfg)
                    for spec, seed, stream, key in zip(specs, seeds, streams, keys)]
        regs = _train_networks(train_regressors, problems, rc, "regressor", ck, keys, cfg, direction,
                               bases if keep == "refine" else None, progress, log)
    t1 = time.perf_counter()
    if keep == "classifier":
        clss = [_kept(b, "classifier") for b in bases]
    else:
        problems = [classifier_problem(lens, spec, ps, stream, seed, key, cfg)
                    for spec, seed, stream, ps, key in zip(specs, seeds, streams, samplers, keys)]
        clss = _train_networks(train_classifiers, problems, cc, "classifier", ck, keys, cfg, direction,
                               bases if keep == "refine" else None, progress, log)
    t2 = time.perf_counter()
    tms = []
    for j, ((p, d, zi, zo, dom), reg, cls, stream) in enumerate(zip(specs, regs, clss, streams)):
        center, scale_in = dom.norm_center_scale()
        base = None if bases is None else bases[j]
        training = {"config_digest": cfg.digest(),
                    "regressor": reg.get("config", {k: v for k, v in rc.__dict__.items()}),
                    "classifier": cls.get("config", {k: v for k, v in cc.__dict__.items()}),
                    "regressor_sizes_tried": reg.get("sizes_tried"), "classifier_sizes_tried": cls.get("sizes_tried"),
                    "regressor_steps": reg["state"]["step"], "classifier_steps": cls["state"]["step"],
                    "regressor_seconds": reg["state"]["seconds"], "classifier_seconds": cls["state"]["seconds"],
                    "regressor_stop": reg["state"].get("stop_reason"), "classifier_stop": cls["state"].get("stop_reason"),
                    "regressor_samples": reg["state"]["samples"], "classifier_samples": cls["state"]["samples"],
                    "stacked_with": len(specs),
                    "data_sampler": stream.method, "valid_fraction": stream.fraction,
                    "mcmc": stream.mcmc.stats() if stream.mcmc is not None else None,
                    "wall_seconds_this_run": t2 - t0, "regressor_wall_this_run": t1 - t0,
                    "seed": cfg.seed, "device": str(pick_device(_torch(0), cfg.device)),
                    "regressor_history": reg["state"]["history"], "classifier_history": cls["state"]["history"]}
        for net_name, r in (("regressor", reg), ("classifier", cls)):
            if r["state"].get("lm"):
                training[f"{net_name}_lm"] = r["state"]["lm"]
        if reg["state"].get("input_box"):      # trained on this box (input_box), folded back into the map's inputs
            training["regressor_input_box"] = dict(zip(("center", "scale"), reg["state"]["input_box"]))
        if keep is not None:
            training["kept"] = {"network": keep, "from_config_digest": base.training.get("config_digest")}
            if keep == "classifier":       # its calibration offset is already folded into its last bias
                for k in ("classifier_logit_offset", "classifier_calibration"):
                    if k in base.training:
                        training[k] = base.training[k]
        tm = NeuralMap(path_id=int(p), direction=d, z_in=float(zi), z_out=float(zo),
                       domain=dom.to_dict(), input_center=center, input_scale=scale_in,
                       classifier=cls["layers"], regressor=reg["layers"], skip=reg["skip"],
                       out_scale=reg["out_scale"], out_shift=reg["out_shift"], odd_y=reg["odd_y"],
                       position_cos=bool(reg.get("position_cos", False)), classifier_activation=cls.get("activation", cc.activation),
                       regressor_activation=reg.get("activation", rc.activation), training=training)
        if keep != "classifier":
            calibrate_classifier(lens, tm, min(cfg.heldout, 200_000), seeds[j] + 13, cfg.fresnel)
        tms.append(tm)
    t3 = time.perf_counter()
    heads = _stop_heads_of(lens, tms, cfg, seeds, progress, log, bases if keep is not None else None, streams=streams)
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


def _stop_heads_of(lens, tms, cfg: TrainConfig, seeds, progress: bool, log, bases=None, refine: bool = False,
                   streams=None) -> list:
    """The stop heads of ``tms`` trained with ``cfg.stop`` — one stack per stop-crossing count; None for a
    map whose path never crosses the stop plane, or all None when ``stop.max_minutes = 0``.  With
    ``bases``, a stop head the base map has is kept.  ``refine``: each map's own stop head (``tms[j].stop_head``)
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
                                 start=[tms[j].stop_head for j in idx] if refine else None,
                                 like_streams=None if streams is None else [streams[j] for j in idx])
        for j, h in zip(idx, heads):
            out[j] = h
    return out


def _add_stop_heads(lens, bases, cfg: TrainConfig, seeds, progress: bool, log, refine: bool = False) -> list:
    """``keep = "both"``: ``bases`` with new stop heads, trained together as in a whole run (one stack per
    stop-crossing count, :func:`_stop_heads_of`), each with its held-out stop metrics; the classifiers,
    regressors and their metrics are unchanged.  ``refine`` (``keep = "refine-stop"``): each base's stop head
    through the finish again instead, widened first where the config's ``stop`` width asks."""
    import dataclasses
    from .evaluate import heldout_valid, stop_errors
    if bases and cfg.net("stop", bases[0].direction).max_minutes <= 0:
        raise NeuralLensError("--keep both trains only stop heads, and stop.max_minutes = 0 asks for none")
    if refine:
        bare = [b.key for b in bases if b.stop_head is None]
        if bare:
            raise NeuralLensError(f"--keep refine-stop: {bare} have no stop head to refine; --keep both trains one")
    heads = _stop_heads_of(lens, bases, cfg, seeds, progress, log, refine=refine)
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


# ----------------------------------------------------------------------------- a whole lens
#: how a phase of :func:`train_maps` is named in the time reports
PHASE_NAMES = {"regressor": "regressors", "classifier": "classifiers", "stop": "stop heads",
               "evaluation": "held-out evaluation"}


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


def select_maps(cfg: TrainConfig, paths: str | None):
    """Which (direction, path) groups to train: ``paths`` is a comma list of ``transmit`` (the configured
    transmit maps of both directions), ``backward``, ``forward``, ``ghosts`` or integer path ids
    (forward); None: everything configured."""
    want = None if not paths else [p.strip() for p in paths.split(",") if p.strip()]
    groups = []
    for d in ("backward", "forward"):
        for p in getattr(cfg, d):
            if want is None or p in want or d in want or (p == "transmit" and f"{d}-transmit" in want):
                groups.append((d, p))
    if want:
        for w in want:
            if w.isdigit():
                groups.append(("forward", int(w)))
            elif w not in ("transmit", "backward", "forward", "ghosts", "backward-transmit", "forward-transmit"):
                raise NeuralLensError(f"--paths: unknown item {w!r}; use transmit, ghosts, backward, forward, "
                                      "backward-transmit, forward-transmit or integer path ids")
    return groups


def train_lens(lens, cfg: TrainConfig, out_path: str, paths: str | None = None, workdir: str | None = None,
               progress: bool = True, log=None, keep: str | None = None, base_path: str | None = None):
    """Plan, train and save every selected map of ``lens`` to ``out_path`` (re-saved atomically after each
    map, so an interruption loses at most the map in progress — whose networks resume from checkpoints).

    ``keep`` ("regressor", "classifier" or "both"): keep that network (both: train only the stop
    heads) of each selected map from the same map of the model file ``base_path`` (see
    :func:`train_map`); the base model's maps that are not selected are carried over unchanged.

    Then, with ``cfg.verify_flare``, every selected ghost map without a verified flare record is rendered against
    the tracer and its record kept in the file (:func:`~mi_neurallens.flare.verify.record_flare_errors`; the
    ``verify_flare*`` settings), and with ``cfg.verify_flare_cost`` timed against tracing its ghost
    (:func:`~mi_neurallens.flare.verify.record_flare_costs`): the model leaves training ready for the flare's mode
    ``auto``, which learns a ghost only where its record passes and the map is the faster.  Last, with
    ``cfg.verify_flare_refine_minutes`` and no ``keep``, a ghost whose records all miss the gate gets its regressor
    refined past its goals and the better map kept (:func:`_refine_missed`)."""
    from ..neural.model import NeuralLensModel, load_model
    from . import plan
    from ..transport.planning import select_ghosts
    from ..errors import ModelError
    base_model = None
    if keep is not None:
        if not base_path:
            raise NeuralLensError(f"keep = {keep!r}: name the model file whose {keep}s are kept (base_path)")
        base_model = load_model(base_path, lens)
    s0, s1 = plan.sensor_distance_range(lens, cfg.close_focus_mm)
    z_front, z_rear = plan.planes(lens, s0)
    workdir = workdir or (out_path + ".work")
    os.makedirs(workdir, exist_ok=True)
    model = NeuralLensModel(lens_name=lens.name, fingerprint=lens.fingerprint(), z_front=z_front, z_rear=z_rear,
                            z_last_vertex=float(lens.total_track), sensor_distance_range=(s0, s1))
    if os.path.exists(out_path):
        try:
            old = load_model(out_path, lens)
            for k, m in old.maps.items():
                if m.training.get("config_digest") == cfg.digest():
                    model.maps[k] = m
            model.extra.update(old.extra)
        except ModelError:
            pass
    model.extra.update({"software": "mi-neurallens", "training_config": cfg.to_dict()})
    groups = select_maps(cfg, paths)
    reach = plan.film_reach(lens, (s0, s1), cfg.film_reach * cfg.film_half_diagonal_mm) if cfg.film_reach else None
    fwd_domain = plan.forward_domain(lens, z_front, plan.default_field_half_angle(
        lens, cfg.film_half_diagonal_mm, cfg.field_margin), reach=reach)
    todo = []
    for d, p in groups:
        if d == "backward":
            pid = 0 if p == "transmit" else int(p)
            dom_path = os.path.join(workdir, f"domain.backward.{pid}.json")
            if os.path.exists(dom_path):
                dom = Domain.from_dict(json.load(open(dom_path)))
            else:
                dom = plan.backward_domain(lens, pid, z_rear, z_front, np.random.default_rng(cfg.seed))
                atomic_write_text(dom_path, json.dumps(dom.to_dict()))
            todo.append((pid, "backward", z_rear, z_front, dom))
        elif p == "ghosts":
            rk_path = os.path.join(workdir, "ghost_ranking.json")
            if os.path.exists(rk_path):
                ranking = json.load(open(rk_path))
            else:
                # the render-time ranking (flare/energy.py), so the ghosts trained are the ones a flare
                # render selects, and a neural flare selects the same ghosts as an exact one
                from ..flare.energy import ghost_energy_ranking
                ranking = ghost_energy_ranking(lens, fresnel=cfg.fresnel)
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
    if base_model is not None:
        model.extra = {**base_model.extra, **model.extra}
        wanted = {f"{d}.{pid}" for pid, d, *_ in todo}
        for k, m in base_model.maps.items():
            if k not in wanted:
                model.maps.setdefault(k, m)
    # the maps left to train, one stack per direction (maps of one direction share shape and domain)
    pending = {d: [t for t in todo if t[1] == d and f"{d}.{t[0]}" not in model.maps] for d in ("backward", "forward")}
    say = (lambda m: print(f"{lens.name}: {m}", file=sys.stderr, flush=True)) if progress or log else (lambda m: None)
    if keep is None and any(pending.values()):
        say(_budget_text(cfg, pending))
    spent, t_run, told = {}, time.perf_counter(), set()
    for direction in ("backward", "forward"):
        group = pending[direction]
        if not group:
            continue
        bases = None
        if base_model is not None:
            missing = [f"{direction}.{t[0]}" for t in group if f"{direction}.{t[0]}" not in base_model.maps]
            if missing:
                raise ModelError(f"{base_path}: no map {missing[0]!r} to keep the {keep} of; it has "
                                 f"{sorted(base_model.maps)}")
            bases = [base_model.maps[f"{direction}.{t[0]}"] for t in group]
            # a kept network was trained on its map's domain: the new ones learn the same (film reach included)
            group = [(*t[:4], Domain.from_dict(b.domain)) for t, b in zip(group, bases)]
        if progress:
            print(f"{lens.name}: training {len(group)} {direction} map(s) together: "
                  f"{', '.join(str(t[0]) for t in group)}", file=sys.stderr, flush=True)
        t_dir = time.perf_counter()
        tms = train_maps(lens, group, cfg, workdir, progress=progress, log=log, keep=keep, bases=bases)
        # each phase's time, as train_maps records it; a run that trains only stop heads keeps its base maps'
        # records, whose phases are the base's run's, not this one's
        phases = dict(tms[0].training.get("phase_seconds", {})) if tms and keep not in ("both", "refine-stop") else {}
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
    model.save(out_path)
    if cfg.verify_flare:
        from ..flare.options import FlareOptions
        from ..flare.verify import (cost_bands, flare_costs, record_flare_costs, record_flare_errors,
                                    variant_backend, verification_done)
        wanted = {f"{d}.{pid}" for pid, d, *_ in todo}
        trained = [tm.path_id for k, tm in model.maps.items()
                   if k in wanted and tm.direction == "forward" and tm.path_id != 0]
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
        except Exception as e:          # the maps are saved: say how to verify them later, do not lose the run
            print(f"{lens.name}: the flare verification stopped ({type(e).__name__}: {e}); {out_path} holds the "
                  f"trained maps without it (mode auto then gates its ghosts by their held-out accuracy alone): "
                  f"`mi-neurallens evaluate {out_path} --lens <its lens file> --recorded --flare --write` verifies "
                  f"them, and `--recorded --flare-cost --write` times them",
                  file=sys.stderr, flush=True)
            return load_model(out_path, lens)
        if ghosts or timed:
            model = load_model(out_path, lens)
            model.extra.setdefault("training_time", {})["flare_verification_seconds"] = time.perf_counter() - t_v
            model.save(out_path)
            say(f"verified the flares of {len(ghosts)} ghost map(s) and timed {len(timed)} in "
                f"{minutes_text((time.perf_counter() - t_v) / 60)}; "
                f"{minutes_text((time.perf_counter() - t_run) / 60)} since the start")
        # a --keep run is surgery on chosen networks: it keeps what it was told to keep, refines nothing else
        if cfg.verify_flare_refine_minutes > 0 and keep is None:
            model = _refine_missed(lens, cfg, out_path, trained, workdir, progress, log, say, t_run)
    return model


#: what a map refined after its verification records (``training["refined_after_verification"]``), and what marks
#: a map whose refinement is done, kept or not, so that a rerun does not refine it again
REFINED_KEY = "refined_after_verification"


def _refine_missed(lens, cfg: TrainConfig, out_path: str, trained, workdir: str, progress: bool, log, say, t_run):
    """The ghosts among ``trained`` whose verified records all miss the gate (every band): their regressors refined
    past their goals, the finish for ``cfg.verify_flare_refine_minutes`` from the maps as trained (a ``keep =
    "refine"`` run of just those ghosts, ``stop_at_goals`` off, verified as any run), and each ghost's better map
    kept — the refined one where its best record is lower.  A ghost that misses by its regressor (the error inside
    the ghost, or on its edge where no band reaches) usually has more to give than its goals asked for: the Leica
    Summicron-R 50's 2560 and 20 went from 0.0102 and 0.0116 to 0.0080 and 0.0039 (docs/results.md).  Each map
    refined, kept or not, is marked (:data:`REFINED_KEY`), so a rerun refines none twice.  Returns the model."""
    from ..flare.options import FlareOptions
    from ..flare.verify import flare_records, passing_band
    from ..neural.model import load_model
    from .merge import merge_models
    gate = FlareOptions.auto_max_flare_error
    model = load_model(out_path, lens)

    def best(tm):
        recs = [r["paired_mape"] for r in flare_records(tm.metrics) if r.get("paired_mape") is not None]
        return min(recs) if recs else None

    def misses(tm):                     # verified, and no band's record passes the gate
        return best(tm) is not None and passing_band(flare_records(tm.metrics), 0.0, gate) is None

    ghosts = {pid: model.maps.get(f"forward.{pid}") for pid in trained}
    missed = [pid for pid, tm in ghosts.items()
              if tm is not None and REFINED_KEY not in tm.training and misses(tm)]
    if not missed:
        return model
    t0 = time.perf_counter()
    say(f"{len(missed)} ghost map(s) above {gate:g} at every band ({', '.join(map(str, missed))}): their regressors "
        f"refined past their goals, {cfg.verify_flare_refine_minutes:g} min each, then verified again")
    rcfg = dataclasses.replace(cfg, verify_flare_refine_minutes=0.0, forward_regressor={
        **cfg.forward_regressor, "lm_minutes": cfg.verify_flare_refine_minutes, "stop_at_goals": False})
    rpath = os.path.join(workdir, "refined.model.safetensors")
    try:
        refined = train_lens(lens, rcfg, rpath, paths=",".join(map(str, missed)),
                             workdir=os.path.join(workdir, "refined"), progress=progress, log=log, keep="refine",
                             base_path=out_path)
    except NeuralLensError as e:        # the maps as trained are saved and verified: keep them
        say(f"the refinement of the ghosts above the gate stopped ({e}); {out_path} keeps them as trained")
        return model
    model = load_model(out_path, lens)
    took = []
    for pid in missed:
        key = f"forward.{pid}"
        old, new = model.maps[key], refined.maps.get(key)
        b_old, b_new = best(old), (best(new) if new is not None else None)
        better = b_new is not None and b_new < b_old
        mark = {"best_before": b_old, "best_refined": b_new, "kept": "refined" if better else "as trained",
                "lm_minutes": cfg.verify_flare_refine_minutes}
        if better:
            merge_models(refined, model, [key])
            took.append(pid)
        tm = model.maps[key]
        # the map is this run's product either way: its digest stays the run's, so a rerun keeps it
        model.maps[key] = dataclasses.replace(tm, training={**tm.training, "config_digest": cfg.digest(),
                                                            REFINED_KEY: mark})
        say(f"ghost {pid}: best verified error {b_old:.4f} as trained, "
            + (f"{b_new:.4f} refined" if b_new is not None else "no record refined")
            + f": {mark['kept']} kept")
    model.extra.setdefault("training_time", {})["refine_missed_seconds"] = time.perf_counter() - t0
    model.save(out_path)
    passing = sum(1 for pid in missed if not misses(model.map(pid, "forward")))
    say(f"refined {len(missed)} ghost map(s) in {minutes_text((time.perf_counter() - t0) / 60)}: {len(took)} "
        f"better, {passing} now within {gate:g}; {minutes_text((time.perf_counter() - t_run) / 60)} since the start")
    return model


def _lens_spec(lens, workdir: str) -> str:
    """What the verification's ``neural_lens`` sensor loads as ``lens``: the lens as trained, written to
    ``<workdir>/lens.json`` (a user's file, an imported Zemax design or a bundled lens alike), or its bundled name
    where the written file would not read back as the same lens."""
    from ..optics.prescription import Lens
    path = os.path.join(workdir, "lens.json")
    try:
        lens.save(path)
        if Lens.load(path).fingerprint() == lens.fingerprint():
            return path
    except Exception:                   # a lens the project format cannot hold: its name must do
        pass
    return lens.name
