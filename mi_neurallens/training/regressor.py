"""The regressor of a map: its training problem (:class:`RegressorFit`) and its training, several maps as one
stack (:func:`train_regressors`), Adam then the Levenberg–Marquardt finish.

A regressor predicts a ray's exit (position (x, y) on the output plane in mm, direction cosines (dx, dy),
throughput T; reduced frame) from its normalised reduced inputs, as the standardised residual of a
least-squares linear guess (:mod:`~mi_neurallens.training.outputs`).  Data are streamed from the tracer into
an in-memory pool that is partly refreshed with fresh samples every ``refresh_every`` steps
(:class:`~mi_neurallens.training.data.RegressorStream`; no data files).  Checkpoints resume a stack
(:mod:`~mi_neurallens.training.stacked`); the data streams after a resume are re-seeded deterministically from
(seed, map, step).
"""
from __future__ import annotations

import math
import time

import numpy as np

from ..errors import NeuralLensError
from .config import NetConfig, table_name
from .data import RegressorStream
from .input_box import fold_input_box, input_box, is_box
from .levenberg import FINISH_POOL, check_widenable, finish_results, widened_finish
from .nets import load_torch, new_state, pick_device
from .outputs import (ODD_COLUMNS, edge_weights, fit_output_transform, loss_weights, odd_factor,
                      wants_position_cos)
from .stacked import Problem


def train_regressor(stream: RegressorStream, val, nc: NetConfig, *, heading: int, center, scale_in, seed: int,
                    ckpt: str | None, threads: int = 2, device: str = "auto", progress: bool = True,
                    desc: str = "regressor", log=None, s_max: float | None = None) -> dict:
    """Train one regressor.  ``val``: (x, y) float64 held-out (valid) samples for validation.
    ``s_max`` (the domain's) is needed when ``nc.odd_y`` (see :func:`~mi_neurallens.training.outputs.odd_factor`)."""
    p = dict(stream=stream, val=val, heading=heading, center=center, scale_in=scale_in, seed=seed, s_max=s_max,
             key=desc)
    return train_regressors([p], nc, ckpt=ckpt, threads=threads, device=device, progress=progress, log=log,
                            desc=desc)[0]


def train_regressors(problems, nc: NetConfig, *, ckpt: str | None = None, threads: int = 2, device: str = "auto",
                     progress: bool = True, log=None, desc: str = "regressors", start=None) -> list:
    """Train the regressors of several maps as one stack (:func:`~mi_neurallens.training.stacked.train_stack`),
    then finish each with Levenberg–Marquardt for ``nc.lm_minutes``
    (:func:`~mi_neurallens.training.levenberg.finish_results`), and, where ``nc.widen_width`` asks, widen and finish
    it again (:func:`~mi_neurallens.training.levenberg.widened_finish`).

    ``problems``: one dict per map with ``stream`` (:class:`~mi_neurallens.training.data.RegressorStream`), ``val``
    ((x, y) float64 held-out valid samples), ``heading``, ``center``, ``scale_in``, ``seed``, ``s_max`` (the
    domain's; needed when ``nc.odd_y``) and ``key``.  ``start``: one trained regressor per map (as returned here,
    or :func:`~mi_neurallens.training.keep.kept_network`): no Adam, only the Levenberg–Marquardt finish from those
    weights and their output transform (what ``--finish-only maps`` runs).  Returns one result dict per map
    (layers, output transform, training state), in order."""
    from .stacked import peek_stack, pool_rows, train_stack
    torch = load_torch(threads)
    dev = pick_device(torch, device)
    torch.manual_seed(int(problems[0]["seed"]))
    keys = [p["key"] for p in problems]
    prior = peek_stack(ckpt, keys)
    n_in = len(problems[0]["center"])
    check_widenable(nc, n_in, 5, table_name("regressor", keys[0].split(".")[0]))
    n_pool = pool_rows(nc, len(problems), 4 * (n_in + 5 + 5 + 1)) if start is None else FINISH_POOL
    t_start = time.perf_counter()
    fits = [_regressor_fit(torch, dev, p, nc, prior, None if start is None else start[j], n_pool, ckpt, log,
                           f"{p['key']} regressor" if len(problems) > 1 else desc)
            for j, p in enumerate(problems)]
    if start is None:
        res = train_stack(torch, dev, fits, nc, seeds=[p["seed"] for p in problems], n_in=n_in, n_out=5, keys=keys,
                          ckpt=ckpt, progress=progress, desc=desc, log=log)
    else:
        res = [{"layers": s0["layers"], "state": f.state} for s0, f in zip(start, fits)]
    finish_results(torch, fits, res, nc, keys, ckpt, log, progress)
    widened_finish(torch, fits, res, nc, keys, ckpt, log, progress)
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


def _regressor_fit(torch, dev, p: dict, nc: NetConfig, prior: dict, s0, n_pool: int, ckpt, log, desc: str):
    """The :class:`RegressorFit` of one problem ``p`` of :func:`train_regressors`: its state new, resumed from
    ``prior`` (the stack's checkpointed states) or, with ``s0`` (a trained regressor), the start of only the
    finish; its first pool of ``n_pool`` rows; whether it regresses position × |dz| and on which input box, and
    its output transform — fitted to that pool when new, else as it was."""
    from ..neural.model import position_cos
    odd_s = None
    if nc.odd_y:
        if p.get("s_max") is None:
            raise NeuralLensError("train_regressor: odd_y needs the domain's s_max")
        odd_s = float(p["s_max"])
    stream, center, scale_in = p["stream"], p["center"], p["scale_in"]
    resumed = p["key"] in prior
    state = prior[p["key"]] if resumed else new_state()
    if s0 is not None:
        if bool(s0["odd_y"]) != (odd_s is not None):
            raise NeuralLensError(f"{p['key']}: the regressor to finish was trained with odd_y={s0['odd_y']}")
        # "refined": the state's mark of a finish-only run since before it had that name (checkpoints carry it)
        state = {**new_state(), "step": int(s0["state"].get("step", 0)), "refined": True}
        state.update(odd_y=odd_s is not None, skip=np.asarray(s0["skip"]).tolist(),
                     shift=np.asarray(s0["out_shift"]).tolist(), oscale=np.asarray(s0["out_scale"]).tolist())
        resumed = True
    elif resumed:
        if bool(state.get("odd_y", False)) != (odd_s is not None):
            raise NeuralLensError(f"{ckpt}: checkpoint was trained with odd_y={state.get('odd_y', False)}; "
                                  "use another work directory or the same setting")
        stream.reseed([int(p["seed"]), state["step"]])
    u0, x0, y0 = stream.sample(n_pool)
    # position_cos: decided once from the first pool (a finish-only run from its map, a resume from its checkpoint)
    if s0 is not None:
        cos = bool(s0.get("position_cos", False))
    elif resumed:
        cos = bool(state.get("position_cos", False))
    else:
        cos = wants_position_cos(nc.exit_position, y0)
    state["position_cos"] = cos
    # input_box: train on the valid rays' box (folded back at the end); a checkpoint resumes on the box it had
    if nc.input_box and s0 is None and not resumed:
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
    return RegressorFit(torch, dev, None, nc, stream, p["val"], (u0, x0, y0), state=state, heading=p["heading"],
                        center=center, scale_in=scale_in, transform=transform, odd_s=odd_s, position_cos=cos,
                        log=log, desc=desc)


def huber_residual(torch, r, delta):
    """The residuals ``r`` as Levenberg–Marquardt residuals of the Huber loss: ``r'`` with ``r'² = ρ(r)``,
    ρ(r) = r² for |r| ≤ δ and 2δ|r| − δ² beyond (squares near zero, linear in the tail: a fit of the bulk, whose
    median is what the goals judge, where squares spend the network on the tail), and ∂r'/∂r (1 inside, δ/|r'|
    beyond).  ``delta`` broadcasts against ``r`` (per output column)."""
    a = r.abs()
    big = a > delta
    q = torch.sqrt(torch.clamp(2.0 * delta * a - delta * delta, min=1e-30))
    return torch.where(big, torch.sign(r) * q, r), torch.where(big, delta / q, torch.ones_like(r))


class RegressorFit(Problem):
    """One regressor's training problem, its pieces as methods (what :func:`train_regressor` runs and
    tests call): the sample pool and its targets, the loss, validation and pool refresh.

    ``transform`` = (skip, shift, oscale) of :func:`~mi_neurallens.training.outputs.fit_output_transform`; the
    network's output ``p`` relates to the reduced-frame outputs ``y`` by ``y = M·(shift + skip·xn) + oscale·(M·p)``
    with ``M`` the odd-y factor (1 unless ``odd_s``).  ``pool0`` = (u, x, y) of the first pool.
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
        self.W = self.f32(loss_weights(nc.loss_weights, self.oscale, y0, nc.direction_weight))
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
        #: a map over a lens's moving groups: its validation rays by configuration cell, whose worst median the goals
        #: are checked on (:meth:`~mi_neurallens.transport.configurations.Configurations.cells`)
        self.conf = conf = stream.ps.domain.conditions
        self.cells = conf.cells(self.xv, corners=nc.goal_corners) if conf is not None else {}
        #: ``nc.lm_cell_weight``: each configuration cell's row weight in the finish, renewed at each validation
        #: (:meth:`cell_weights`); None: uniform
        self.cell_w = None
        self.finishing = False

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
        """The odd-y factor M of a batch of normalised inputs ``xb`` (…, B, inputs) (ones unless ``odd_s``);
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
        return self.T_skip.shape[0] == 5          # the kernel takes any input count (its NIN), checked per call

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
        r, s = w * (z * M - batch["Y"].to(z.dtype)), w * M
        if self.huber_delta is None:
            return r, s
        r, slope = huber_residual(self.torch, r, self.huber_delta.to(z.dtype))
        return r, s * slope

    #: ``nc.lm_huber``'s δ per output column (a tensor), fixed when the finish starts (:meth:`lm_start`) and, with
    #: ``nc.lm_huber_refix``, anew as the residuals fall (:meth:`lm_refix`); None: the finish minimises the squares
    huber_delta = None
    #: the last validation's predictions in the finish on the Huber loss (what :meth:`lm_refix` reads)
    last_pv = None

    def lm_start(self, net):
        """Called by the Levenberg–Marquardt finish with its starting network ``net``: with ``nc.lm_huber`` > 0,
        fixes the Huber threshold δ of each output column at ``lm_huber`` × the median |weighted residual| of the
        held-out rays, so that the finish's loss and its validation score are one function throughout; with
        ``nc.lm_cell_weight`` > 0 turns on the cell weights (:meth:`cell_weights`)."""
        self.finishing = True
        if self.nc.lm_huber <= 0:
            return
        self.net = net
        with self.torch.no_grad():
            pv, _ = self.predict(self.Xv)
        self.huber_delta = self.huber_medians(pv)
        self.state["lm_huber_delta"] = self.huber_delta.tolist()

    def huber_medians(self, pv):
        """``nc.lm_huber`` × the median |weighted residual| of the held-out predictions ``pv`` per output column: the
        Huber threshold δ for weights that predict ``pv`` (at least 1e-12)."""
        r = (self.torch.sqrt(self.W) * (pv - self.Yv)).abs()
        return self.torch.clamp(self.nc.lm_huber * r.median(0).values, min=1e-12)

    def lm_refix(self):
        """Called by the Levenberg–Marquardt finish after a validation that gave it its best weights so far: with
        ``nc.lm_huber_refix`` = f > 0, where some output column's held-out median |weighted residual| has fallen
        f times or more since δ was fixed, δ is fixed anew at ``lm_huber`` × the medians of these weights.  So the
        loss follows the residuals down and keeps fitting the bulk: fixed once, at the start (Adam's errors, several
        times the finished map's), δ soon lies above most residuals and the Huber loss is the squares again.
        Returns the score (:meth:`score`) of the validated weights under the new δ, the finish's best score from
        here, or None where the score stays: δ stays, or the finish keeps its best weights by the worst cell
        (:meth:`scores_by_cell`), which δ does not change (recorded: ``lm_huber_delta``, the refixes counted in
        ``lm_huber_refixes``)."""
        f = float(self.nc.lm_huber_refix)
        if f <= 0 or self.huber_delta is None or self.last_pv is None:
            return None
        delta = self.huber_medians(self.last_pv)
        if float((self.huber_delta / delta).max()) < f:
            return None
        self.huber_delta = delta
        self.state["lm_huber_delta"] = delta.tolist()
        self.state["lm_huber_refixes"] = int(self.state.get("lm_huber_refixes", 0)) + 1
        return None if self.scores_by_cell() else self.score(self.last_pv)

    def scores_by_cell(self) -> bool:
        """The finish keeps its best weights by the worst configuration cell's goal ratio (:meth:`cell_weights`),
        not by :meth:`score`: a map over moving groups finishing with ``nc.lm_cell_weight`` > 0."""
        return bool(self.cells) and self.finishing and self.nc.lm_cell_weight > 0

    def score(self, pv):
        """The held-out score the finish keeps the best weights by: the mean of the loss it minimises per
        residual (squares, or with :attr:`huber_delta` the Huber loss)."""
        if self.huber_delta is None:
            return float(((pv - self.Yv) ** 2).mean())
        r, _ = huber_residual(self.torch, self.torch.sqrt(self.W) * (pv - self.Yv), self.huber_delta)
        return float((r ** 2).mean())

    def fresh_rows(self, k):
        """``k`` fresh pool rows from the stream; in the finish, with :attr:`cell_w`, each row weighted by its
        configuration cell's weight (times its edge weight)."""
        ur, xr, yr = self.stream.sample(k)
        xrn = (xr - self.center) / self.scale_in
        out = {"X": self.f32(xrn), "Y": self.f32(self.targets(xr, xrn, self.space(yr))), "Yraw": self.f32(yr)}
        w = edge_weights(self.stream.ps, ur, self.nc) if self.nc.edge_weight > 0 else None
        if self.cell_w:
            wc = np.ones(len(xr))
            for c, m in self.conf.cells(xr, min_rays=0, margin=True, corners=self.nc.goal_corners).items():
                wc[m] = self.cell_w.get(c, 1.0)
            w = wc if w is None else w * wc
        if w is not None:
            out["W"] = self.f32(w)
        return out

    #: the cell weights' range: a cell weighs at most this many times, at least its inverse, the cells' median one
    CELL_WEIGHT_CLIP = 4.0

    def cell_weights(self, med: dict) -> float:
        """The finish's weighting over configuration cells (``nc.lm_cell_weight`` = p > 0): from each cell's
        validation medians ``med`` ({cell: regression_errors}), its ratio to the goals r = max(position / goal,
        direction / goal), and its rows' weight (r / the cells' median r)^p, within :data:`CELL_WEIGHT_CLIP` either
        way (:attr:`cell_w`, used by the next fresh rows).  So the finish spends the network where the map misses
        its goals most, which decides whether it meets them: they hold per configuration.  Returns the worst r,
        the score the finish keeps its best weights by (a minimax over the cells, since the weighted loss changes
        with the weights)."""
        (pm, _), (dm, _) = self.nc.goal_position_um, self.nc.goal_direction_arcsec
        r = {c: max(e["position_um_median"] / pm, e["direction_arcsec_median"] / dm) for c, e in med.items()}
        mid = float(np.median(list(r.values())))
        p, c_ = float(self.nc.lm_cell_weight), self.CELL_WEIGHT_CLIP
        self.cell_w = {c: float(np.clip((v / mid) ** p, 1.0 / c_, c_)) for c, v in r.items()}
        self.state["lm_cell_weights"] = self.cell_w
        return max(r.values())

    def goals_met(self) -> bool:
        """The last validation meets ``nc.goal_position_um`` and ``nc.goal_direction_arcsec`` (median, p99),
        with the margin ``nc.goal_margin``; a map over moving groups its medians in every configuration cell (the
        worst cell's, ``cell_pos_um_med`` and ``cell_dir_as_med``), since the goals hold per configuration."""
        r = self.state["history"][-1] if self.state["history"] else None
        if r is None:
            return False
        g = self.nc.goal_margin
        (pm, pp), (dm, dp) = self.nc.goal_position_um, self.nc.goal_direction_arcsec
        pos, drc = r.get("cell_pos_um_med", r["pos_um_med"]), r.get("cell_dir_as_med", r["dir_as_med"])
        return pos <= g * pm and r["pos_um_p99"] <= g * pp and drc <= g * dm and r["dir_as_p99"] <= g * dp

    def validate(self, step, loss, seconds):
        """Held-out errors, appended to the training history; returns (score, progress-bar postfix)."""
        from .evaluate import regression_errors
        with self.torch.no_grad():
            pv, _ = self.predict(self.Xv)
            vl = self.score(pv)
            self.last_pv = pv if self.huber_delta is not None else None
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
        post = {}
        if self.cells:
            med = {k: regression_errors(yp[c], self.yv[c], self.heading) for k, c in self.cells.items()}
            wp = max(med, key=lambda k: med[k]["position_um_median"])
            wd = max(med, key=lambda k: med[k]["direction_arcsec_median"])
            rec.update(cell_pos_um_med=med[wp]["position_um_median"], cell_pos_worst=wp,
                       cell_dir_as_med=med[wd]["direction_arcsec_median"], cell_dir_worst=wd)
            if self.scores_by_cell():
                vl = rec["cell_score"] = self.cell_weights(med)
            post = dict(worst=f"{rec['cell_pos_um_med']:.2f}µm/{rec['cell_dir_as_med']:.2f}\" ({wd})")
        self.state["history"].append(rec)
        if self.log:
            self.log(self.desc, rec)
        return vl, dict(val=f"{vl:.2e}", pos=f"{m['position_um_median']:.2f}µm",
                        dir=f"{m['direction_arcsec_median']:.2f}\"", **post)
