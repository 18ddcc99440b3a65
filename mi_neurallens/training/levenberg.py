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
        """θ (…, P) → [(W (…, out, in), b (…, out))]: views, with θ's leading (stack) dimensions."""
        out, i = [], 0
        lead = tuple(theta.shape[:-1])
        for ws, bs in self.shapes:
            nw, nb = ws[0] * ws[1], bs[0]
            out.append((theta[..., i:i + nw].reshape(lead + ws), theta[..., i + nw:i + nw + nb]))
            i += nw + nb
        return out

    def forward(self, theta, X):
        """(n, in) → (n, out), in the dtype of ``X`` (θ is cast to it).  Stacked: θ (K, P) and X (K, n, in)
        → (K, n, out), network k on rows k."""
        h = X
        L = self._unpack(theta.to(X.dtype))
        for k, (W, b) in enumerate(L):
            h = h @ W.transpose(-1, -2) + b[..., None, :]
            if k < len(L) - 1:
                h = self.torch.tanh(h)
        return h

    def jacobian(self, theta, X):
        """(outputs (n, out), J (n, out, P)): ∂ output / ∂ θ, in the dtype of ``X``, by one backward pass
        per output column through the stored activations.  Stacked: θ (K, P) and X (K, n, in) → (K, n, out)
        and (K, n, out, P)."""
        torch = self.torch
        L = self._unpack(theta.to(X.dtype))
        hs, h = [X], X
        for k, (W, b) in enumerate(L):
            h = h @ W.transpose(-1, -2) + b[..., None, :]
            if k < len(L) - 1:
                h = torch.tanh(h)
            hs.append(h)
        lead, n, no = tuple(X.shape[:-2]), X.shape[-2], h.shape[-1]
        G = torch.eye(no, dtype=X.dtype, device=X.device).expand(lead + (n, no, no))   # ∂ out / ∂ (pre-activation of layer k)
        blocks = [None] * len(L)
        for k in range(len(L) - 1, -1, -1):
            W, _ = L[k]
            Jw = (G[..., :, :, None] * hs[k][..., None, None, :]).reshape(lead + (n, no, -1))
            blocks[k] = torch.cat([Jw, G], -1)
            if k > 0:
                G = (G @ W[..., None, :, :]) * (1.0 - hs[k] * hs[k])[..., None, :]
        return h, torch.cat(blocks, -1)


def polish(torch, fit, layers, nc, *, seconds: float, max_iterations: int | None = None, rows: int | None = None,
           eval_every: int | None = None, step0: int = 0, lam: float = 1e-3, progress=None) -> list:
    """Levenberg–Marquardt on ``layers`` (the network of the :class:`~.stacked.Problem` ``fit``) for
    ``seconds`` of wall time (and at most ``max_iterations``), or until a validation meets the goals
    (``nc.stop_at_goals``) or ``nc.patience`` validations bring no better score.  Returns the best layers
    by validation score (the starting ones count: they are validated first).  ``rows``: fresh samples per iteration
    (``nc.lm_rows``); ``eval_every``: iterations between validations (``nc.lm_eval_every``).  The
    iterations are appended to ``fit.state`` (``lm``: iterations, seconds, final λ, stop reason) and its
    validations to ``fit.state["history"]`` with ``phase = "lm"`` and step = ``step0`` + iteration.
    One network: :func:`polish_stack` with a stack of one."""
    return polish_stack(torch, [fit], [layers], nc, seconds=seconds, max_iterations=max_iterations, rows=rows,
                        eval_every=eval_every, step0=[step0], lam=lam,
                        progress=None if progress is None else (lambda it, loss, lam_: progress(it, loss[0], lam_[0])))[0]


def polish_stack(torch, fits, layers, nc, *, seconds: float, max_iterations: int | None = None,
                 rows: int | None = None, eval_every: int | None = None, step0=None, lam: float = 1e-3,
                 progress=None) -> list:
    """:func:`polish` for K networks of one shape at once (``fits``: their problems, ``layers``: their
    starting weights): each iteration forms the K Jacobians as one batched product and solves the K damped
    systems as one batched solve, so on a GPU a stack of ghost maps costs about what one does.  Every
    network keeps its own rows (``fit.fresh_rows``, in the order :func:`polish` would draw them), its own λ,
    validations, best weights and stop reason — the result is :func:`polish`'s, network by network
    (``tests/test_levenberg.py``).  A network leaves the stack when it stops; the stack's wall budget is
    K × ``seconds`` (the time the networks would get one at a time).  ``step0``: one Adam step count per
    network.  ``progress(iteration, losses, λs)``: the networks still running.  Returns their best layers,
    in order."""
    K = len(fits)
    if K == 0:
        return []
    rows = int(rows or nc.lm_rows)
    eval_every = int(eval_every or nc.lm_eval_every)
    step0 = [0] * K if step0 is None else [int(s) for s in step0]
    dev = getattr(fits[0], "dev", None)
    net = FlatMLP(torch, layers[0], dev)
    for lay in layers[1:]:
        if FlatMLP(torch, lay).shapes != net.shapes:
            raise ValueError("polish_stack: the networks of one stack must have one shape")
    theta = torch.stack([net.flatten(lay) for lay in layers])          # (K, P) float64
    f32, f64 = torch.float32, torch.float64
    t0 = time.perf_counter()
    states = [f.state for f in fits]
    base_seconds = [float(st.get("seconds", 0.0)) for st in states]
    lams = [float(lam)] * K
    its, reasons, since_best = [0] * K, [None] * K, [0] * K
    ended = [0.0] * K

    def validate(k, th, loss):
        fits[k].net = lambda x, th=th: net.forward(th, x)
        hist = states[k]["history"]
        n_hist = len(hist)
        with torch.no_grad():
            score, _ = fits[k].validate(step0[k] + its[k], None if loss is None else torch.as_tensor(loss),
                                        base_seconds[k] + time.perf_counter() - t0)
        for rec in hist[n_hist:]:
            rec["phase"] = "lm"
        return score

    best_theta = [theta[k].clone() for k in range(K)]
    best = [validate(k, theta[k], None) for k in range(K)]
    for k in range(K):
        if nc.stop_at_goals and fits[k].goals_met():
            reasons[k] = "goals"
    active = [k for k in range(K) if reasons[k] is None]
    budget = float(seconds) * K
    while active:
        if time.perf_counter() - t0 >= budget:
            break
        if max_iterations is not None and its[active[0]] >= max_iterations:
            for k in active:
                reasons[k] = "max_iterations"
            break
        batches = [fits[k].fresh_rows(rows) for k in active]
        X = torch.stack([b["X"].to(f32) for b in batches])                 # (A, n, in)
        idx = torch.as_tensor(active, device=theta.device)
        th = theta[idx]
        A_n = len(active)
        with torch.no_grad():
            z, J = net.jacobian(th, X)                                        # (A, n, out), (A, n, out, P)
            rs = [fits[k].lm_residual(z[a], batches[a]) for a, k in enumerate(active)]
            r = torch.stack([q[0] for q in rs])
            s = torch.stack([q[1].expand_as(q[0]) for q in rs])
            Js = (J * s[..., None]).reshape(A_n, -1, net.P)
            del J
            Amat = (Js.transpose(1, 2) @ Js).to(f64)                          # (A, P, P)
            g = (Js.transpose(1, 2) @ r.reshape(A_n, -1, 1)).to(f64)[..., 0]  # (A, P)
            del Js
            loss0 = (r.to(f64) ** 2).mean((1, 2)).tolist()
            d = torch.diagonal(Amat, dim1=1, dim2=2).clone()
            d = d + 1e-9 * d.max(1, keepdim=True).values + 1e-30
            accepted = [False] * A_n
            tries = [0] * A_n
            pending = list(range(A_n))
            while pending:
                lam_t = torch.as_tensor([lams[active[a]] for a in pending], dtype=f64, device=Amat.device)
                pi = torch.as_tensor(pending, device=Amat.device)
                M = Amat[pi] + lam_t[:, None, None] * torch.diag_embed(d[pi])
                # JᵀJ + λ·diag is symmetric positive definite: Cholesky (and torch 2.13's batched LU solve fails
                # on a CPU with more than one thread: MKL's DLASWP rejects its pivots)
                L, info = torch.linalg.cholesky_ex(M)
                delta = torch.cholesky_solve(-g[pi][..., None], L)[..., 0]
                info = info.tolist()
                ok = [j for j, a in enumerate(pending) if info[j] == 0 and bool(torch.isfinite(delta[j]).all())]
                better = set()
                if ok:
                    oi = torch.as_tensor(ok, device=Amat.device)
                    cand = th[pi[oi]] + delta[oi]
                    zc = net.forward(cand, X[pi[oi]])
                    for j, c in zip(ok, range(len(ok))):
                        a = pending[j]
                        r1, _ = fits[active[a]].lm_residual(zc[c], batches[a])
                        if float((r1.to(f64) ** 2).mean()) < loss0[a]:
                            better.add(a)
                            theta[active[a]] = cand[c]
                            lams[active[a]] = max(lams[active[a]] / 3.0, 1e-12)
                            accepted[a] = True
                nxt = []
                for a in pending:
                    tries[a] += 1
                    if a in better:
                        continue
                    lams[active[a]] *= 4.0                    # singular or no lower loss: damp harder
                    if tries[a] < 8:
                        nxt.append(a)
                pending = nxt
        done = []
        for a, k in enumerate(active):
            if not accepted[a] and lams[k] > 1e8:         # no step lowers the loss: at a minimum of what rows can tell
                reasons[k] = "converged"
            its[k] += 1
            states[k]["samples"] = int(states[k].get("samples", 0)) + rows
        if progress is not None:
            progress(its[active[0]], loss0, [lams[k] for k in active])
        for a, k in enumerate(active):
            if its[k] % eval_every == 0 or reasons[k] == "converged":
                score = validate(k, theta[k], loss0[a])
                if not math.isfinite(score):
                    reasons[k] = "diverged"
                else:
                    if score < best[k]:
                        best[k], best_theta[k], since_best[k] = score, theta[k].clone(), 0
                    else:
                        since_best[k] += 1
                    if nc.stop_at_goals and fits[k].goals_met():
                        best_theta[k], reasons[k] = theta[k].clone(), "goals"
                    elif since_best[k] >= nc.patience:
                        reasons[k] = "early_stop"
            if reasons[k] is not None:
                ended[k] = time.perf_counter() - t0
                done.append(k)
        active = [k for k in active if k not in done]
    for k in range(K):
        if reasons[k] is None:
            reasons[k] = "time_budget"
        if reasons[k] in ("time_budget", "max_iterations"):
            ended[k] = time.perf_counter() - t0
            if its[k] % eval_every != 0:
                score = validate(k, theta[k], None)
                if math.isfinite(score) and score < best[k]:
                    best[k], best_theta[k] = score, theta[k].clone()
        states[k]["lm"] = {"iterations": its[k], "seconds": ended[k], "rows": rows, "lambda": lams[k],
                           "stop_reason": reasons[k], "best_val": best[k], "stacked_with": K}
        states[k]["seconds"] = base_seconds[k] + ended[k]
    return [net.layers(best_theta[k]) for k in range(K)]
