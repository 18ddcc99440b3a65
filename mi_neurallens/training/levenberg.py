"""Levenberg–Marquardt for small maps: the second-order finish of a tanh MLP's training.

Adam moves a network's weights along a rescaled gradient, so close to the optimum of a least-squares
fit it needs tens of thousands of steps per halving of the error.  A map's networks are small (a 3×16
ghost regressor has 709 weights, a 2×16 classifier 369), and both losses are sums of squared
residuals — the regressor's weighted standardised MSE, the classifier's margin interval loss — so the
Gauss–Newton matrix ``JᵀJ`` of a batch is a few hundred squared and cheap to form and solve.  Each
iteration here draws fresh rows from the map's tracer stream (the :class:`~.stacked.Problem`'s
``fresh_rows``), forms the Jacobian of the network's outputs with respect to every weight in closed
form (one backward pass per output column), and takes the damped Gauss–Newton step

    (JᵀJ + λ·diag(JᵀJ)) δ = −Jᵀr,

accepting it when the batch's loss falls (λ ÷ 3) and otherwise raising λ × 4 and solving again.
Measured on the Canon's strongest ghost (3×16 regressor): from its shipped Adam weights (14.3 µm
median exit-position error) to 4.4 µm in 90 s, and from random weights to 3.8 µm in 120 s, where Adam
had reached 14–17 µm in 75 s–5 min (docs/results.md, "Second-order training").

What a problem provides (:class:`~.stacked.Problem`): ``fresh_rows(n)``, ``lm_residual(z, batch)`` →
(r, s) with r the residuals (n, outputs) whose mean square is the loss and ``s = ∂r/∂z`` (the losses are
separable per output, so the chain rule is a column scale), and ``validate`` / ``goals_met`` /
``state`` as for Adam.  Cost: O(rows · outputs · P²) per iteration, so networks above
:data:`MAX_PARAMS` weights (a 5×32 regressor has 4 549) are left to Adam.
"""
from __future__ import annotations

import math
import time

import numpy as np

#: networks with more weights than this are not polished (JᵀJ would cost seconds per iteration on a CPU)
MAX_PARAMS = 2500


def n_params(layers) -> int:
    """Weights and biases of ``layers`` ([(W (out, in), b (out,))])."""
    return int(sum(np.size(W) + np.size(b) for W, b in layers))


class FlatMLP:
    """A tanh MLP whose weights are one flat vector θ = [W₀ (row-major), b₀, W₁, b₁, …], with its
    outputs and their Jacobian with respect to θ.  ``layers``: [(W (out, in), b (out,))], the model
    file's layout."""

    def __init__(self, torch, layers, dev=None):
        self.torch = torch
        self.shapes = [(tuple(np.shape(W)), tuple(np.shape(b))) for W, b in layers]
        self.P = n_params(layers)
        self.dev = dev

    def flatten(self, layers):
        flat = np.concatenate([np.concatenate([np.asarray(W, np.float64).ravel(), np.asarray(b, np.float64).ravel()])
                               for W, b in layers])
        return self.torch.as_tensor(flat, device=self.dev)

    def layers(self, theta) -> list:
        """θ → [(W, b)] float64 numpy (the model file's layout)."""
        t = theta.detach().cpu().double().numpy()
        out, i = [], 0
        for ws, bs in self.shapes:
            nw, nb = ws[0] * ws[1], bs[0]
            out.append((t[i:i + nw].reshape(ws).copy(), t[i + nw:i + nw + nb].copy()))
            i += nw + nb
        return out

    def _unpack(self, theta):
        out, i = [], 0
        for ws, bs in self.shapes:
            nw, nb = ws[0] * ws[1], bs[0]
            out.append((theta[i:i + nw].view(ws), theta[i + nw:i + nw + nb]))
            i += nw + nb
        return out

    def forward(self, theta, X):
        """(n, in) → (n, out), in the dtype of ``X`` (θ is cast to it)."""
        h = X
        L = self._unpack(theta.to(X.dtype))
        for k, (W, b) in enumerate(L):
            h = self.torch.addmm(b, h, W.T)
            if k < len(L) - 1:
                h = self.torch.tanh(h)
        return h

    def jacobian(self, theta, X):
        """(outputs (n, out), J (n, out, P)): ∂ output / ∂ θ, in the dtype of ``X``, by one backward pass
        per output column through the stored activations."""
        torch = self.torch
        L = self._unpack(theta.to(X.dtype))
        hs, h = [X], X
        for k, (W, b) in enumerate(L):
            h = torch.addmm(b, h, W.T)
            if k < len(L) - 1:
                h = torch.tanh(h)
            hs.append(h)
        n, no = X.shape[0], h.shape[1]
        G = torch.eye(no, dtype=X.dtype, device=X.device).expand(n, no, no)   # ∂ out / ∂ (pre-activation of layer k)
        blocks = [None] * len(L)
        for k in range(len(L) - 1, -1, -1):
            W, _ = L[k]
            Jw = (G[:, :, :, None] * hs[k][:, None, None, :]).reshape(n, no, -1)
            blocks[k] = torch.cat([Jw, G], 2)
            if k > 0:
                G = (G @ W) * (1.0 - hs[k] * hs[k])[:, None, :]
        return h, torch.cat(blocks, 2)


def polish(torch, fit, layers, nc, *, seconds: float, max_iterations: int | None = None, rows: int | None = None,
           eval_every: int | None = None, step0: int = 0, lam: float = 1e-3, progress=None) -> list:
    """Levenberg–Marquardt on ``layers`` (the network of the :class:`~.stacked.Problem` ``fit``) for
    ``seconds`` of wall time (and at most ``max_iterations``), or until a validation meets the goals
    (``nc.stop_at_goals``) or ``nc.patience`` validations bring no better score.  Returns the best layers
    by validation score (the starting ones count: they are validated first).  ``rows``: fresh samples per iteration
    (``nc.lm_rows``); ``eval_every``: iterations between validations (``nc.lm_eval_every``).  The
    iterations are appended to ``fit.state`` (``lm``: iterations, seconds, final λ, stop reason) and its
    validations to ``fit.state["history"]`` with ``phase = "lm"`` and step = ``step0`` + iteration."""
    rows = int(rows or nc.lm_rows)
    eval_every = int(eval_every or nc.lm_eval_every)
    dev = getattr(fit, "dev", None)
    net = FlatMLP(torch, layers, dev)
    theta = net.flatten(layers)
    f32 = torch.float32
    t0 = time.perf_counter()
    st = fit.state
    base_seconds = float(st.get("seconds", 0.0))

    def validate(it, loss):
        fit.net = lambda x, th=theta: net.forward(th, x)
        n_hist = len(st["history"])
        with torch.no_grad():
            score, _ = fit.validate(step0 + it, None if loss is None else torch.as_tensor(loss),
                                    base_seconds + time.perf_counter() - t0)
        for rec in st["history"][n_hist:]:
            rec["phase"] = "lm"
        return score

    best_theta, best = theta.clone(), validate(0, None)
    since_best, it, reason = 0, 0, "time_budget"
    if nc.stop_at_goals and fit.goals_met():
        reason = "goals"
    while reason != "goals" and time.perf_counter() - t0 < seconds:
        if max_iterations is not None and it >= max_iterations:
            reason = "max_iterations"
            break
        batch = fit.fresh_rows(rows)
        X = batch["X"].to(f32)
        with torch.no_grad():
            z, J = net.jacobian(theta, X)
            r, s = fit.lm_residual(z, batch)
            Js = (J * s[..., None]).reshape(-1, net.P)
            A = (Js.T @ Js).double()
            g = (Js.T @ r.reshape(-1)).double()
            loss0 = float((r.double() ** 2).mean())
            d = torch.diagonal(A).clone()
            d = d + 1e-9 * float(d.max()) + 1e-30
            accepted = False
            for _ in range(8):
                try:
                    delta = -torch.linalg.solve(A + lam * torch.diag(d), g)
                except RuntimeError:            # singular: damp harder
                    lam *= 4.0
                    continue
                cand = theta + delta
                r1, _ = fit.lm_residual(net.forward(cand, X), batch)
                if float((r1.double() ** 2).mean()) < loss0:
                    theta, lam, accepted = cand, max(lam / 3.0, 1e-12), True
                    break
                lam *= 4.0
            if not accepted and lam > 1e8:      # no step lowers the loss: at a minimum of what rows can tell
                reason = "converged"
        it += 1
        st["samples"] = int(st.get("samples", 0)) + rows
        if progress is not None:
            progress(it, loss0, lam)
        if it % eval_every == 0 or reason == "converged":
            score = validate(it, loss0)
            if not math.isfinite(score):
                reason = "diverged"
                break
            if score < best:
                best, best_theta, since_best = score, theta.clone(), 0
            else:
                since_best += 1
            if nc.stop_at_goals and fit.goals_met():
                best_theta, reason = theta.clone(), "goals"
            elif since_best >= nc.patience:
                reason = "early_stop"
            if reason != "time_budget":
                break
    if it % eval_every != 0 and reason in ("time_budget", "max_iterations"):
        score = validate(it, None)
        if math.isfinite(score) and score < best:
            best, best_theta = score, theta.clone()
    st["lm"] = {"iterations": it, "seconds": time.perf_counter() - t0, "rows": rows, "lambda": lam,
                "stop_reason": reason, "best_val": best}
    st["seconds"] = base_seconds + time.perf_counter() - t0
    return net.layers(best_theta)
