"""The classifier of a map: its training problem (:class:`ClassifierFit`), its training, several maps as one
stack (:func:`train_classifiers`), and the calibration of its decision threshold (:func:`calibrate_classifier`).

A classifier says whether a ray passes the lens (a logit > 0) from the map's normalised reduced inputs: trained
on the tracer's aperture margin (``target = "margin"``: scale·margin inside ±clip, one-sided beyond; then the
Levenberg–Marquardt finish) or with binary cross-entropy on the labels (``"label"``, the paper's).  Its pool
mixes valid rays with perturbations across the boundary (:func:`~mi_neurallens.training.data.classifier_samples`).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..errors import NeuralLensError
from .config import NetConfig, table_name
from ..transport.planning import Domain
from ..transport.sampling import PathSampler
from .data import classifier_samples
from .evaluate import map_outputs_np
from .levenberg import FINISH_POOL, check_widenable, finish_results, widened_finish
from .nets import load_torch, new_state, pick_device
from .stacked import Problem


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
    Levenberg–Marquardt for ``nc.lm_minutes`` (:func:`~mi_neurallens.training.levenberg.finish_results`) and, where
    ``nc.widen_width`` asks, widen and finish it again (:func:`~mi_neurallens.training.levenberg.widened_finish`).
    ``problems``: one dict per map with ``ps`` (:class:`~mi_neurallens.transport.sampling.PathSampler`),
    ``valid_u_source`` (n → (n, 4) valid unit-cube samples), ``val`` ((x, label) natural-mix held-out),
    ``center``, ``scale_in``, ``seed`` and ``key``.  ``start``: one trained classifier per map (``{"layers", …}``):
    only the finish, from those weights.  Returns ``{"layers", "state"}`` per map, in order."""
    from .stacked import peek_stack, pool_rows, train_stack
    torch = load_torch(threads)
    dev = pick_device(torch, device)
    torch.manual_seed(int(problems[0]["seed"]))
    keys = [p["key"] for p in problems]
    prior = peek_stack(ckpt, keys)
    if nc.target == "margin":
        check_widenable(nc, len(problems[0]["center"]), 1, table_name("classifier", keys[0].split(".")[0]))
    ncp = dataclasses.replace(nc, pool=pool_rows(nc, len(problems), 4 * (len(problems[0]["center"]) + 1))
                              if start is None else FINISH_POOL)
    fits = []
    for p in problems:
        resumed = p["key"] in prior
        state = prior[p["key"]] if resumed else new_state()
        rng = np.random.default_rng([int(p["seed"]), state["step"]] if resumed else p["seed"])
        fits.append(ClassifierFit(torch, dev, None, ncp, p["ps"], p["valid_u_source"], p["val"], rng=rng, state=state,
                                  center=p["center"], scale_in=p["scale_in"], log=log,
                                  desc=f"{p['key']} classifier" if len(problems) > 1 else desc))
    if start is None:
        res = train_stack(torch, dev, fits, nc, seeds=[p["seed"] for p in problems], n_in=len(problems[0]["center"]),
                          n_out=1, keys=keys,
                          ckpt=ckpt, progress=progress, desc=desc, log=log)
    else:
        for f, s0 in zip(fits, start):        # "refined": a finish-only run's mark in the state (checkpoints carry it)
            f.state.update(step=int(s0["state"].get("step", 0)), refined=True)
        res = [{"layers": s0["layers"], "state": f.state} for s0, f in zip(start, fits)]
    if nc.target == "margin":
        finish_results(torch, fits, res, nc, keys, ckpt, log, progress)
        widened_finish(torch, fits, res, nc, keys, ckpt, log, progress)
    for r in res:
        r["state"]["stacked_with"] = len(problems)
    return res


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
        #: a map over a lens's moving groups: its validation rays by configuration cell (as the regressor's)
        conf = ps.domain.conditions
        self.cells = {k: torch.as_tensor(m, device=dev) for k, m in conf.cells(xv).items()} if conf is not None else {}
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
        """The last validation's misclassification is at most ``nc.goal_misclassification`` (with the margin
        ``nc.goal_margin``).  A map over moving groups meets it in every configuration cell (the worst cell's,
        ``cell_misclass``) at the last **two** validations: a cell holds a few thousand validation rays and a few
        dozen misclassified ones, so its rate moves by about 0.1 percentage points from one validation to the
        next (the EF 24-70's worst cell 0.53 → 0.44 %), and one lucky validation would stop the network."""
        h = self.state["history"]
        goal = self.nc.goal_margin * self.nc.goal_misclassification
        if not h:
            return False
        if "cell_misclass" not in h[-1]:
            return h[-1]["val_misclass"] <= goal
        last = [r["cell_misclass"] for r in h[-2:] if "cell_misclass" in r]
        return len(last) == 2 and max(last) <= goal

    def validate(self, step, loss, seconds):
        """Held-out misclassification and BCE, appended to the history; returns (score, postfix)."""
        with self.torch.no_grad():
            lg = self.net(self.Xv)[:, 0]
            err = float(((lg > 0) != self.Lv).float().mean())
            vb = float(self.bce(lg, self.Lv.float()))
        rec = {"step": step, "loss": loss.item() if loss is not None else math.nan, "val_bce": vb,
               "val_misclass": err, "seconds": seconds}
        post = {}
        if self.cells:
            wrong = (lg > 0) != self.Lv
            per = {k: float(wrong[c].float().mean()) for k, c in self.cells.items()}
            w = max(per, key=per.get)
            rec.update(cell_misclass=per[w], cell_misclass_worst=w)
            post = dict(worst=f"{100 * per[w]:.3f}% ({w})")
        self.state["history"].append(rec)
        if self.log:
            self.log(self.desc, rec)
        return err + 0.01 * vb, dict(miscls=f"{100 * err:.3f}%", **post)


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
    x = dom.u_to_x(rng.random((n, dom.dims)))
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
