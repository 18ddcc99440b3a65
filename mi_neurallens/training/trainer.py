"""The PyTorch trainer (torch is imported lazily, inside the functions).

One map = a classifier (2–3×32 tanh; trained on the tracer's aperture margin, or BCE on the labels as in
the paper) and a regressor (5×32 tanh) on normalised reduced inputs.
The regressor predicts the standardised *residual* of a least-squares linear guess (``residual =
"linear"``; the linear part is kept as a skip connection in the model file) — see docs/training.md for
what that buys.  Data are streamed from the tracer into an in-memory pool that is partly refreshed
with fresh samples every ``refresh_every`` steps (no data files; nothing is re-used for long).

Checkpoints (``<workdir>/<map>.<net>.ckpt.safetensors`` + ``.json``; tensors only, never pickle) hold
weights, Adam state, best weights, step and history; they are written atomically every
``checkpoint_seconds`` and at the end.  A rerun with the same workdir resumes from them; a finished
network is not retrained.  The data stream after a resume is re-seeded deterministically from
(seed, map, step).
"""
from __future__ import annotations

import json
import math
import os
import time

import numpy as np

from ..constants import ARCSEC_PER_RAD
from ..errors import NeuralLensError
from ..fileio import atomic_write, atomic_write_text
from .config import NetConfig, TrainConfig
from .data import Domain, PathSampler, RegressorStream, classifier_samples

CHECKPOINT_SECONDS = 60.0
CLASSIFIER_VALIDATION = 400_000   # rays uniform over the domain that pick the classifier's best weights


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


def lr_at(step: int, nc: NetConfig, seconds: float = 0.0) -> float:
    """Learning rate.  ``paper``: lr·decay^(step // decay_every).  ``fast``: linear warm-up, then a
    cosine from lr to lr_min whose progress is the larger of the step fraction and the fraction of the
    wall-clock budget used, so the decay completes whichever limit is hit first."""
    if nc.schedule == "paper":
        return nc.lr * nc.decay ** (step // max(nc.decay_every, 1))
    if step < nc.warmup_steps:
        return nc.lr * (step + 1) / nc.warmup_steps
    t = min(max((step - nc.warmup_steps) / max(nc.max_steps - nc.warmup_steps, 1),
                seconds / max(nc.max_minutes * 60.0, 1e-9)), 1.0)
    return nc.lr_min + 0.5 * (nc.lr - nc.lr_min) * (1.0 + math.cos(math.pi * t))


def save_checkpoint(path: str, net, opt, best_state, state: dict):
    """Weights + Adam moments + best weights as safetensors, the rest as JSON (both atomic)."""
    from safetensors.torch import save_file
    t = {f"net.{k}": v.detach().cpu().contiguous() for k, v in net.state_dict().items()}
    t.update({f"best.{k}": v.detach().cpu().contiguous() for k, v in best_state.items()})
    for i, (pid, st) in enumerate(opt.state.items()):
        for name in ("exp_avg", "exp_avg_sq"):
            if name in st:
                t[f"adam.{i}.{name}"] = st[name].detach().cpu().contiguous()
        if "step" in st:
            state.setdefault("adam_steps", {})[str(i)] = float(st["step"])
    atomic_write(path + ".safetensors", lambda p: save_file(t, p))
    atomic_write_text(path + ".json", json.dumps(state))


def load_checkpoint(path: str, net, opt, torch):
    if not (os.path.exists(path + ".safetensors") and os.path.exists(path + ".json")):
        return None
    from safetensors.torch import load_file
    try:
        t = load_file(path + ".safetensors")
        state = json.loads(open(path + ".json").read())
    except Exception:
        return None          # a broken checkpoint is ignored (training restarts)
    dev = next(net.parameters()).device
    net.load_state_dict({k[4:]: v.to(dev) for k, v in t.items() if k.startswith("net.")})
    best = {k[5:]: v.to(dev) for k, v in t.items() if k.startswith("best.")}
    params = [p for g in opt.param_groups for p in g["params"]]
    for i, p in enumerate(params):
        if f"adam.{i}.exp_avg" in t:
            opt.state[p] = {"step": torch.tensor(state.get("adam_steps", {}).get(str(i), 0.0)),
                            "exp_avg": t[f"adam.{i}.exp_avg"].to(dev),
                            "exp_avg_sq": t[f"adam.{i}.exp_avg_sq"].to(dev)}
    return state, best


def _progress(total, desc, enabled):
    try:
        from tqdm.auto import tqdm
        return tqdm(total=total, desc=desc, disable=not enabled, leave=False, dynamic_ncols=True)
    except ImportError:  # pragma: no cover
        class _N:
            def update(self, *a): pass
            def set_postfix(self, *a, **k): pass
            def close(self): pass
        return _N()


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


def fit_output_transform(xn: np.ndarray, y: np.ndarray, residual: str, M: np.ndarray | None = None):
    """(skip (5, 4), out_shift (5,), out_scale (5,)) of the regressor's output transform
    ``y = M · (shift + skip·xn + scale·network)`` (``M`` from :func:`odd_factor`; None = ones): the
    linear part is the least-squares fit of y (``residual = "linear"``) or the mean (``"none"``), and
    ``scale`` the spread of what is left, so the network's target has about unit variance."""
    M = np.ones_like(y) if M is None else M
    n, k = xn.shape
    skip, shift, scale = np.zeros((y.shape[1], k)), np.zeros(y.shape[1]), np.zeros(y.shape[1])
    if residual not in ("linear", "none"):
        raise NeuralLensError(f"unknown residual mode {residual!r}: use 'linear' or 'none'")
    for j in range(y.shape[1]):
        A = np.concatenate([xn, np.ones((n, 1))], 1) if residual == "linear" else np.ones((n, 1))
        A = A * M[:, j:j + 1]
        coef, *_ = np.linalg.lstsq(A, y[:, j], rcond=None)
        res = y[:, j] - A @ coef
        if residual == "linear":
            skip[j], shift[j] = coef[:-1], coef[-1]
        else:
            shift[j] = coef[0]
        scale[j] = res.std()
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


# ----------------------------------------------------------------------------- regressor
def _fit(torch, net, opt, nc: NetConfig, state: dict, best: dict, *, n_pool: int, batch_loss, refresh,
         validate, ckpt, bar, dev):
    """The optimisation loop both networks share: Adam steps on random batches of a sample pool that is
    partly refreshed every ``nc.refresh_every`` steps, validation every ``nc.eval_every`` steps with the
    best weights kept, early stop after ``nc.patience`` evaluations without progress, a wall-clock
    budget (``nc.max_minutes``, resumed time included) and periodic checkpoints.

    ``batch_loss(idx)`` → loss tensor of pool rows ``idx``; ``refresh(k)`` replaces ``k`` random pool
    rows; ``validate(step, loss, seconds)`` → (score, postfix dict) — lower score is better (it also
    logs).  Returns ``(best, stop_reason)``; ``state`` is updated in place.
    """
    t0 = time.perf_counter() - state["seconds"]
    last_ckpt = time.perf_counter()
    step = state["step"]
    stop_reason = "max_steps"
    loss = None

    def evaluate_now():
        nonlocal best
        score, postfix = validate(step, loss, time.perf_counter() - t0)
        bar.set_postfix(**postfix)
        if score < state["best_val"]:
            state.update(best_val=score, best_step=step, evals_since_best=0)
            best = {k: v.detach().clone() for k, v in net.state_dict().items()}
        else:
            state["evals_since_best"] += 1
        return state["evals_since_best"] >= nc.patience

    while step < nc.max_steps:
        if step > 0 and step % nc.refresh_every == 0:
            refresh(int(nc.pool * nc.refresh_fraction))
        for g in opt.param_groups:
            g["lr"] = lr_at(step, nc, time.perf_counter() - t0)
        loss = batch_loss(torch.randint(0, n_pool, (nc.batch,), device=dev))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step += 1
        state["samples"] += nc.batch
        bar.update(1)
        if step % nc.eval_every == 0 or step == nc.max_steps:
            if evaluate_now():
                stop_reason = "early_stop"
                break
        state["step"] = step
        state["seconds"] = time.perf_counter() - t0
        if state["seconds"] > nc.max_minutes * 60.0:
            stop_reason = "time_budget"
            break
        if ckpt and time.perf_counter() - last_ckpt > CHECKPOINT_SECONDS:
            save_checkpoint(ckpt, net, opt, best, state)
            last_ckpt = time.perf_counter()
    state["step"] = step
    if not state["history"] or state["history"][-1]["step"] != step:
        evaluate_now()                           # the budget ended between evaluations
    bar.close()
    state.update(step=step, seconds=time.perf_counter() - t0, done=True, stop_reason=stop_reason)
    return best, stop_reason


def _start(torch, dev, nc: NetConfig, n_out: int, ckpt: str | None):
    """A fresh network, its Adam optimiser, training state and best weights, or all of them resumed
    from ``ckpt``.  Returns (net, opt, state, best, resumed)."""
    net = make_net(torch, 4, n_out, nc.hidden, nc.width, nc.activation).to(dev)
    opt = torch.optim.Adam(net.parameters(), lr=nc.lr)
    state = {"step": 0, "best_val": math.inf, "best_step": 0, "history": [], "evals_since_best": 0,
             "seconds": 0.0, "samples": 0}
    best = {k: v.detach().clone() for k, v in net.state_dict().items()}
    got = load_checkpoint(ckpt, net, opt, torch) if ckpt else None
    if got is not None:
        state, best = got
    return net, opt, state, best, got is not None


def train_regressor(stream: RegressorStream, val, nc: NetConfig, *, heading: int, center, scale_in, seed: int,
                    ckpt: str | None, threads: int = 2, device: str = "auto", progress: bool = True,
                    desc: str = "regressor", log=None, s_max: float | None = None) -> dict:
    """Train one regressor.  ``val``: (x, y) float64 held-out (valid) samples for validation.
    ``s_max`` (the domain's) is needed when ``nc.odd_y`` (see :func:`odd_factor`)."""
    torch = _torch(threads)
    dev = pick_device(torch, device)
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    t_start = time.perf_counter()
    odd_s = None
    if nc.odd_y:
        if s_max is None:
            raise NeuralLensError("train_regressor: odd_y needs the domain's s_max")
        odd_s = float(s_max)
    u0, x0, y0 = stream.sample(nc.pool)
    xn0 = (x0 - center) / scale_in
    skip, shift, oscale = fit_output_transform(xn0, y0, nc.residual, odd_factor(x0[:, 2], odd_s))
    net, opt, state, best, resumed = _start(torch, dev, nc, 5, ckpt)
    if resumed:
        skip, shift, oscale = (np.asarray(state["skip"]), np.asarray(state["shift"]), np.asarray(state["oscale"]))
        if bool(state.get("odd_y", False)) != (odd_s is not None):
            raise NeuralLensError(f"{ckpt}: checkpoint was trained with odd_y={state.get('odd_y', False)}; "
                                  "use another work directory or the same setting")
        if state.get("done"):
            net.load_state_dict(best)
            return _reg_result(net, skip, shift, oscale, state)
        stream.rng = np.random.default_rng([seed, state["step"]])
        u0, x0, y0 = stream.sample(nc.pool)
        xn0 = (x0 - center) / scale_in
    state.update(odd_y=odd_s is not None, skip=skip.tolist(), shift=shift.tolist(), oscale=oscale.tolist())
    fit = RegressorFit(torch, dev, net, nc, stream, val, (u0, x0, y0), rng=rng, state=state, heading=heading,
                       center=center, scale_in=scale_in, transform=(skip, shift, oscale), odd_s=odd_s,
                       log=log, desc=desc)
    bar = _progress(nc.max_steps, desc, progress)
    bar.update(state["step"])
    best, _ = _fit(torch, net, opt, nc, state, best, n_pool=len(fit.X), batch_loss=fit.batch_loss,
                   refresh=fit.refresh, validate=fit.validate, ckpt=ckpt, bar=bar, dev=dev)
    state["wall_seconds_total"] = time.perf_counter() - t_start
    net.load_state_dict(best)
    if ckpt:
        save_checkpoint(ckpt, net, opt, best, state)
    return _reg_result(net, skip, shift, oscale, state)


class RegressorFit:
    """One regressor's training problem, its pieces as methods (what :func:`train_regressor` runs and
    tests call): the sample pool and its targets, the loss, validation and pool refresh.

    ``transform`` = (skip, shift, oscale) of :func:`fit_output_transform`; the network's output ``p``
    relates to the reduced-frame outputs ``y`` by ``y = M·(shift + skip·xn) + oscale·(M·p)`` with ``M``
    the odd-y factor (1 unless ``odd_s``).  ``pool0`` = (u, x, y) of the first pool.
    """

    def __init__(self, torch, dev, net, nc: NetConfig, stream, val, pool0, *, rng, state, heading: int,
                 center, scale_in, transform, odd_s, log=None, desc="regressor"):
        self.torch, self.dev, self.net, self.nc, self.stream = torch, dev, net, nc, stream
        self.rng, self.state, self.heading, self.log, self.desc = rng, state, heading, log, desc
        self.center, self.scale_in, self.odd_s = center, scale_in, odd_s
        self.skip, self.shift, self.oscale = transform
        self.T_skip, self.T_shift, self.T_scale = (self.f32(v) for v in transform)
        u0, x0, y0 = pool0
        xn0 = (x0 - center) / scale_in
        self.sig_d2 = float(np.mean(self.oscale[2:4] ** 2))
        self.W = self.f32(loss_weights(nc.loss_weights, self.oscale, y0))
        # M of a batch from its normalised inputs (ωy = center + scale·xn)
        self.wy_c, self.wy_s = float(center[2]), float(scale_in[2])
        self.X = self.f32(xn0)
        self.Y = self.f32(self.targets(x0, xn0, y0))
        self.Yraw = self.f32(y0)
        self.Wedge = self.f32(edge_weights(stream.ps, u0, nc)) if nc.edge_weight > 0 else None
        self.xv, self.yv = val
        self.xvn = (self.xv - center) / scale_in
        self.Xv, self.Yv = self.f32(self.xvn), self.f32(self.targets(self.xv, self.xvn, self.yv))
        # the validation rays within edge_margin of an aperture edge: their error is logged on its own
        _, mv, _ = stream.ps.margin_u(stream.ps.domain.x_to_u(self.xv))
        self.near_edge = mv < nc.edge_margin

    def f32(self, a):
        return self.torch.as_tensor(np.ascontiguousarray(a, dtype=np.float32), device=self.dev)

    def targets(self, x, xn, y):
        """What the network's output times M should equal: (y − M·(shift + skip·xn)) / scale."""
        return (y - odd_factor(x[:, 2], self.odd_s) * (self.shift + xn @ self.skip.T)) / self.oscale

    def outputs(self, x, xn, p):
        """The inverse of :meth:`targets`: reduced-frame outputs from the network's output times M."""
        return p * self.oscale + odd_factor(x[:, 2], self.odd_s) * (self.shift + xn @ self.skip.T)

    def M_of(self, xb):
        """The odd-y factor M of a batch of normalised inputs (ones unless ``odd_s``)."""
        M = self.torch.ones((xb.shape[0], 5), device=self.dev)
        if self.odd_s is not None:
            m = (self.wy_c + self.wy_s * xb[:, 2]) / self.odd_s
            for j in ODD_COLUMNS:
                M[:, j] = m
        return M

    def dir3(self, dxy):
        """Unit 3-vectors from (dx, dy) with dz of the map's heading."""
        torch = self.torch
        dz = self.heading * torch.sqrt(torch.clamp(1.0 - (dxy * dxy).sum(1, keepdim=True), min=0.0))
        v = torch.cat([dxy, dz], 1)
        return v / v.norm(dim=1, keepdim=True)

    def predict(self, xb):
        """Network output times M (compared with the targets) and M."""
        M = self.M_of(xb)
        return self.net(xb) * M, M

    def loss(self, xb, tb, yb_raw, wb=None):
        """Per-sample squared errors (and cosine term), averaged with the sample weights ``wb``
        (edge emphasis; ``None``: uniform)."""
        nc = self.nc
        p, M = self.predict(xb)
        mean = (lambda v: v.mean()) if wb is None else (lambda v: (v * wb).mean())
        if nc.direction_loss == "cosine":
            l = mean((((p - tb) ** 2) * self.W)[:, [0, 1, 4]].mean(1)) * 3.0 / 5.0
        else:
            l = mean((((p - tb) ** 2) * self.W).mean(1))
        if nc.direction_loss in ("cosine", "mse+cosine"):
            d_pred = M[:, 2:4] * (self.T_shift[2:4] + xb @ self.T_skip[2:4].T) + self.T_scale[2:4] * p[:, 2:4]
            # 1 − cos(a, b) = |â − b̂|²/2 for unit vectors (the stable form in float32)
            cos_term = mean(((self.dir3(d_pred) - self.dir3(yb_raw[:, 2:4])) ** 2).sum(1)) / (2.0 * self.sig_d2)
            l = l + nc.cosine_weight * cos_term * (2.0 / 5.0)
        return l

    def batch_loss(self, bi):
        """The loss of pool rows ``bi``."""
        return self.loss(self.X[bi], self.Y[bi], self.Yraw[bi], None if self.Wedge is None else self.Wedge[bi])

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

    def refresh(self, k):
        """Replace ``k`` random pool rows with fresh samples of the stream."""
        ur, xr, yr = self.stream.sample(k)
        xrn = (xr - self.center) / self.scale_in
        idx = self.torch.as_tensor(self.rng.choice(len(self.X), k, replace=False), device=self.dev)
        self.X[idx], self.Y[idx], self.Yraw[idx] = self.f32(xrn), self.f32(self.targets(xr, xrn, yr)), self.f32(yr)
        if self.Wedge is not None:
            self.Wedge[idx] = self.f32(edge_weights(self.stream.ps, ur, self.nc))


def _reg_result(net, skip, shift, oscale, state):
    return {"layers": net_layers(net), "skip": np.asarray(skip), "out_shift": np.asarray(shift),
            "out_scale": np.asarray(oscale), "odd_y": bool(state.get("odd_y", False)), "state": state}


# ----------------------------------------------------------------------------- classifier
def train_classifier(ps: PathSampler, valid_u_source, val, nc: NetConfig, *, center, scale_in, seed: int,
                     ckpt: str | None, threads: int = 2, device: str = "auto", progress: bool = True,
                     desc: str = "classifier", log=None) -> dict:
    """``valid_u_source(n)`` → (n, 4) valid unit-cube samples; ``val``: (x, label) natural-mix held-out."""
    torch = _torch(threads)
    dev = pick_device(torch, device)
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    net, opt, state, best, resumed = _start(torch, dev, nc, 1, ckpt)
    if resumed:
        if state.get("done"):
            net.load_state_dict(best)
            return {"layers": net_layers(net), "state": state}
        rng = np.random.default_rng([seed, state["step"]])
    fit = ClassifierFit(torch, dev, net, nc, ps, valid_u_source, val, rng=rng, state=state, center=center,
                        scale_in=scale_in, log=log, desc=desc)
    bar = _progress(nc.max_steps, desc, progress)
    bar.update(state["step"])
    best, _ = _fit(torch, net, opt, nc, state, best, n_pool=len(fit.X), batch_loss=fit.batch_loss,
                   refresh=fit.refresh, validate=fit.validate, ckpt=ckpt, bar=bar, dev=dev)
    net.load_state_dict(best)
    if ckpt:
        save_checkpoint(ckpt, net, opt, best, state)
    return {"layers": net_layers(net), "state": state}


class ClassifierFit:
    """One classifier's training problem, its pieces as methods (what :func:`train_classifier` runs and
    tests call): the labelled (or margin-target) pool, the loss, validation and pool refresh."""

    def __init__(self, torch, dev, net, nc: NetConfig, ps: PathSampler, valid_u_source, val, *, rng, state,
                 center, scale_in, log=None, desc="classifier"):
        self.torch, self.dev, self.net, self.nc, self.ps = torch, dev, net, nc, ps
        self.valid_u_source, self.rng, self.state = valid_u_source, rng, state
        self.center, self.scale_in, self.log, self.desc = center, scale_in, log, desc
        self.margin = nc.target == "margin"
        self.X, self.L = self.pool(nc.pool)
        xv, lv = val
        self.Xv, self.Lv = self.f32((xv - center) / scale_in), torch.as_tensor(lv.astype(bool), device=dev)
        self.bce = torch.nn.BCEWithLogitsLoss()

    def f32(self, a):
        return self.torch.as_tensor(np.ascontiguousarray(a, dtype=np.float32), device=self.dev)

    def pool(self, n):
        """(inputs, training target): the 0/1 label, or scale·margin clipped to ±clip (−clip on a hard
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
        return torch.mean(torch.relu(lo - logit) ** 2 + torch.relu(logit - hi) ** 2)

    def batch_loss(self, bi):
        """The loss of pool rows ``bi``: the margin interval loss or binary cross-entropy."""
        logit = self.net(self.X[bi])[:, 0]
        return self.margin_loss(logit, self.L[bi]) if self.margin else self.bce(logit, self.L[bi])

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

    def refresh(self, k):
        """Replace ``k`` random pool rows with fresh samples."""
        xr, lr_ = self.pool(k)
        idx = self.torch.as_tensor(self.rng.choice(len(self.X), k, replace=False), device=self.dev)
        self.X[idx], self.L[idx] = xr, lr_


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
    logit, _ = tm.eval_reduced_np(x)
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
#: ``"both"`` (train only the stop head)
NETWORKS = ("regressor", "classifier", "both")


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
                   out_scale=np.asarray(base.out_scale), odd_y=bool(base.odd_y))
    return out


def train_map(lens, path_id: int, direction: str, z_in: float, z_out: float, domain: Domain, cfg: TrainConfig,
              workdir: str | None = None, progress: bool = True, log=None, evaluate: bool = True,
              eval_n: int | None = None, keep: str | None = None, base=None):
    """Train the classifier, regressor and stop head of one map; returns a
    :class:`~mi_neurallens.neural.model.NeuralMap` with held-out metrics.

    The stop head (:mod:`~mi_neurallens.training.stop_head`) is trained when the path crosses the stop
    plane and ``cfg.stop.max_minutes > 0``; with ``keep``, a stop head the base map has is kept.
    ``keep = "both"`` keeps the classifier and the regressor and trains only the stop head (what adds a
    render-time aperture to a shipped map without changing anything else it outputs).
    ``keep = "regressor"`` (or ``"classifier"``) takes that network unchanged from ``base`` (a
    :class:`~mi_neurallens.neural.model.NeuralMap` of the same path, planes and domain) and trains only
    the other one: e.g. a longer or wider classifier for a ghost whose flare error sits on its edge,
    without paying for (or changing) its regressor.  The kept network's training record is carried over
    under ``training["kept"]``."""
    from ..neural.model import NeuralMap
    from .evaluate import evaluate_map, heldout_valid
    _check_keep(keep, base, path_id, direction, z_in, z_out, domain)
    key = f"{direction}.{path_id}"
    seed = int(cfg.seed) * 1_000_003 + int(path_id) * 2 + (direction == "forward")
    if keep == "both":
        return _add_stop_head(lens, base, cfg, seed, progress, log)
    rc, cc = cfg.net("regressor", direction), cfg.net("classifier", direction)
    ps = PathSampler(lens, path_id, direction, z_in, z_out, domain, fresnel=cfg.fresnel)
    stream = RegressorStream(ps, seed, cfg.mcmc_threshold, cfg.mcmc_chains, cfg.mcmc_p_large, cfg.mcmc_sigma)
    center, scale_in = domain.norm_center_scale()
    ck = (lambda n: os.path.join(workdir, f"{key}.{n}.ckpt")) if workdir else (lambda n: None)
    t0 = time.perf_counter()
    if keep == "regressor":
        reg = _kept(base, "regressor")
    else:
        val = heldout_valid(lens, (path_id, direction, z_in, z_out), domain, min(cfg.heldout, 20_000), seed + 7,
                            cfg.mcmc_threshold, cfg.fresnel)
        reg = train_regressor(stream, val, rc, heading=1 if direction == "forward" else -1, center=center,
                              scale_in=scale_in, seed=seed, ckpt=ck("regressor"), threads=cfg.threads,
                              device=cfg.device, progress=progress, desc=f"{key} regressor", log=log,
                              s_max=domain.s_max)
    t1 = time.perf_counter()
    if keep == "classifier":
        cls = _kept(base, "classifier")
    else:
        # classifier validation: the natural mix (uniform over the domain), float64 labels; large, because
        # only the few rays near the boundary tell two good classifiers apart (0.02 % of 400 k = 80 errors)
        vrng = np.random.default_rng(seed + 11)
        psv = PathSampler(lens, path_id, direction, z_in, z_out, domain, fresnel=cfg.fresnel, precision="float64")
        xcv = domain.u_to_x(vrng.random((CLASSIFIER_VALIDATION, 4)))
        lcv, _ = psv.trace_x(xcv)
        cls = train_classifier(ps, lambda n: stream.sample(n)[0], (xcv, lcv), cc, center=center,
                               scale_in=scale_in, seed=seed + 1, ckpt=ck("classifier"), threads=cfg.threads,
                               device=cfg.device, progress=progress, desc=f"{key} classifier", log=log)
    t2 = time.perf_counter()
    training = {"config_digest": cfg.digest(),
                "regressor": reg.get("config", {k: v for k, v in rc.__dict__.items()}),
                "classifier": cls.get("config", {k: v for k, v in cc.__dict__.items()}),
                "regressor_steps": reg["state"]["step"], "classifier_steps": cls["state"]["step"],
                "regressor_seconds": reg["state"]["seconds"], "classifier_seconds": cls["state"]["seconds"],
                "regressor_stop": reg["state"].get("stop_reason"), "classifier_stop": cls["state"].get("stop_reason"),
                "regressor_samples": reg["state"]["samples"], "classifier_samples": cls["state"]["samples"],
                "data_sampler": stream.method, "valid_fraction": stream.fraction,
                "mcmc": stream.mcmc.stats() if stream.mcmc is not None else None,
                "wall_seconds_this_run": t2 - t0, "regressor_wall_this_run": t1 - t0,
                "seed": cfg.seed, "device": str(pick_device(_torch(0), cfg.device)),
                "regressor_history": reg["state"]["history"], "classifier_history": cls["state"]["history"]}
    if keep is not None:
        training["kept"] = {"network": keep, "from_config_digest": base.training.get("config_digest")}
        if keep == "classifier":       # its calibration offset is already folded into its last bias
            for k in ("classifier_logit_offset", "classifier_calibration"):
                if k in base.training:
                    training[k] = base.training[k]
    tm = NeuralMap(path_id=int(path_id), direction=direction, z_in=float(z_in), z_out=float(z_out),
                      domain=domain.to_dict(), input_center=center, input_scale=scale_in,
                      classifier=cls["layers"], regressor=reg["layers"], skip=reg["skip"],
                      out_scale=reg["out_scale"], out_shift=reg["out_shift"], odd_y=reg["odd_y"],
                      classifier_activation=cls.get("activation", cc.activation),
                      regressor_activation=reg.get("activation", rc.activation), training=training)
    if keep != "classifier":
        calibrate_classifier(lens, tm, min(cfg.heldout, 200_000), seed + 13, cfg.fresnel)
    tm.stop_head = base.stop_head if (keep is not None and base.stop_head is not None) else \
        _stop_head_of(lens, tm, cfg, seed, progress, log)
    if evaluate:
        tm.metrics = evaluate_map(lens, tm, n=eval_n or cfg.heldout, seed=seed + 99,
                                  mcmc_threshold=cfg.mcmc_threshold, fresnel=cfg.fresnel)
    return tm


def _stop_head_of(lens, tm, cfg: TrainConfig, seed: int, progress: bool, log):
    """The stop head of ``tm`` trained with ``cfg.stop`` (None when disabled or the path never crosses
    the stop plane)."""
    from ..transport.exact import ExactMap
    nc = cfg.net("stop", tm.direction)
    if nc.max_minutes <= 0 or ExactMap(lens, tm.path_id, tm.direction, tm.z_in, tm.z_out).stop_crossings == 0:
        return None
    from .stop_head import train_stop_head
    return train_stop_head(lens, tm, nc, seed=seed + 17, fresnel=cfg.fresnel, mcmc_threshold=cfg.mcmc_threshold,
                           threads=cfg.threads, device=cfg.device, progress=progress, log=log)


def _add_stop_head(lens, base, cfg: TrainConfig, seed: int, progress: bool, log):
    """``keep = "both"``: ``base`` with a (new) stop head and its held-out stop metrics; the classifier,
    regressor and their metrics are unchanged."""
    import dataclasses
    from .evaluate import heldout_valid, stop_errors
    head = _stop_head_of(lens, base, cfg, seed, progress, log)
    if head is None:
        raise NeuralLensError(f"map {base.key}: no stop head to train (its path does not cross the stop plane, "
                              "or stop.max_minutes = 0)")
    tm = dataclasses.replace(base, stop_head=head)
    x, y = heldout_valid(lens, (tm.path_id, tm.direction, tm.z_in, tm.z_out), tm.domain, cfg.heldout, seed + 101,
                         cfg.mcmc_threshold, cfg.fresnel, stops=True)
    _, yp = tm.eval_reduced_np(x)
    head.metrics = stop_errors(yp[:, 5:], y[:, 5:])
    tm.metrics = {**tm.metrics, "stop": head.metrics}
    return tm


# ----------------------------------------------------------------------------- a whole lens
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
    :func:`train_map`); the base model's maps that are not selected are carried over unchanged."""
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
    fwd_domain = plan.forward_domain(lens, z_front, plan.default_field_half_angle(
        lens, cfg.film_half_diagonal_mm, cfg.field_margin))
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
    for pid, d, zi, zo, dom in todo:
        key = f"{d}.{pid}"
        if key in model.maps:
            continue
        base = None
        if base_model is not None:
            if key not in base_model.maps:
                raise ModelError(f"{base_path}: no map {key!r} to keep the {keep} of; it has {sorted(base_model.maps)}")
            base = base_model.maps[key]
        tm = train_map(lens, pid, d, zi, zo, dom, cfg, workdir, progress=progress, log=log, keep=keep, base=base)
        model.maps[key] = tm
        if base_model is not None:      # the base's order (ghosts: strongest first), new maps after
            order = list(base_model.maps) + [k for k in model.maps if k not in base_model.maps]
            model.maps = {k: model.maps[k] for k in order if k in model.maps}
        model.save(out_path)
    model.save(out_path)
    return model
