"""Levenberg–Marquardt for small maps: the second-order finish of a tanh MLP's training.

Adam moves a network's weights along a rescaled gradient, so close to the optimum of a least-squares
fit it needs tens of thousands of steps per halving of the error.  A map's networks are small (a 3×16
ghost regressor has 709 weights, a 2×16 classifier 369), and both losses are sums of squared
residuals — the regressor's weighted standardised MSE, the classifier's margin interval loss — so the
Gauss–Newton matrix ``JᵀJ`` of a batch is a few hundred squared and cheap to form and solve.  Each
iteration here takes fresh rows from the map's tracer stream (the :class:`~.stacked.Problem`'s
``fresh_rows``, drawn :data:`ROW_CHUNK` iterations at a time), forms ``JᵀJ`` and ``Jᵀr`` of the Jacobian of the
network's outputs with respect to every weight in closed form (one backward pass per output column; the
output layer's blocks per output, :meth:`FlatMLP.normal_equations`), and takes the damped Gauss–Newton step

    (JᵀJ + λ·diag(JᵀJ)) δ = −Jᵀr,

accepting it when the batch's loss falls (λ ÷ 3) and otherwise raising λ × 4 and solving again.
Measured on the Canon's strongest ghost (3×16 regressor): from its shipped Adam weights (14.3 µm
median exit-position error) to 4.4 µm in 90 s, and from random weights to 3.8 µm in 120 s, where Adam
had reached 14–17 µm in 75 s–5 min.

A run's networks finish after Adam through :func:`finish_results`: those that missed their goals and are small
enough, in stacks of one shape (:func:`lm_stack_size`: one on a CPU, many on a GPU), each saved as it finishes.
A finish-only run (``mi-neurallens train --finish-only``) starts from a model's networks, widened first where the
configuration asks (:func:`widen_as_configured`), and refuses before any work what the finish cannot change
(:func:`check_finishable`).  A network's settings may also ask for a second finish in the same run, after the
first: widened to ``widen_width`` and finished ``widen_minutes`` more (:func:`widened_finish`; refused before any
work where the widened network is too large to finish, :func:`check_widenable`).

What a problem provides (:class:`~.stacked.Problem`): ``fresh_rows(n)``, ``lm_residual(z, batch)`` →
(r, s) with r the residuals (n, outputs) whose mean square is the loss and ``s = ∂r/∂z`` (the losses are
separable per output, so the chain rule is a column scale), and ``validate`` / ``goals_met`` /
``state`` as for Adam.  Cost: O(rows · outputs · P²) per iteration, so networks above
:data:`MAX_PARAMS` weights (a 5×32 regressor has 4 549) are left to Adam, unless a network's configuration raises
its ``lm_max_weights``.
"""
from __future__ import annotations

import json
import math
import os
import sys
import time
from typing import TYPE_CHECKING

import numpy as np

from ..fileio import atomic_write_text

if TYPE_CHECKING:
    from .config import NetConfig

#: networks with more weights than this are not finished (JᵀJ would cost seconds per iteration on a CPU): the
#: default of :attr:`NetConfig.lm_max_weights <mi_neurallens.training.config.NetConfig.lm_max_weights>`, which a
#: recipe raises for one network (the EF 24-70's 4×27 camera regressor: 3 326 weights, 4.8 s an iteration on 2 cores)
MAX_PARAMS = 2500

#: iterations' worth of rows one call of a problem's ``fresh_rows`` draws: a call costs a tracer launch (and a
#: classifier's margin trace) whose Python and launch overhead is about the same for 8 192 rows as for 16×, and
#: was most of a classifier's iteration (dgauss-50mm's ghosts: 0.155 s an iteration, 0.1 of it drawing rows)
ROW_CHUNK = 16


class RowFeed:
    """A problem's fresh rows, ``rows`` per :meth:`next`, drawn :data:`ROW_CHUNK` iterations at a time from
    ``fit.fresh_rows`` and handed out in order (every row once: each iteration's rows are as fresh as one
    call's).  A batch is a dict of tensors (or arrays) whose first dimension is the row."""

    def __init__(self, fit, rows: int, chunk: int = ROW_CHUNK):
        self.fit, self.rows, self.chunk = fit, int(rows), max(int(chunk), 1)
        self.buf, self.pos, self.n = None, 0, 0

    def next(self) -> dict:
        if self.buf is None or self.pos + self.rows > self.n:
            self.buf = self.fit.fresh_rows(self.rows * self.chunk)
            self.n = min(len(v) for v in self.buf.values() if v is not None)
            self.pos = 0
        i, self.pos = self.pos, self.pos + self.rows
        return {k: (None if v is None else v[i:i + self.rows]) for k, v in self.buf.items()}


def widen(layers, width: int, rng) -> list:
    """The tanh MLP ``layers`` ([(W (out, in), b), …], the last the output layer) with every hidden layer
    ``width`` units wide, computing exactly the same function: each new unit takes random inputs (N(0, 1/fan-in),
    the usual initialisation) and feeds nothing yet — its outgoing weights, and the old units' weights from it,
    are zero.  What the finish then starts from when a map's network is too small for its goals: the optimum it
    reached, with room (the Jacobian of the zero outgoing weights is the new units' activations, so the first
    damped step already uses them).  Layers at least ``width`` wide are kept as they are."""
    out, prev_new = [], None
    for i, (W, b) in enumerate(layers):
        W, b = np.asarray(W, np.float64), np.asarray(b, np.float64)
        last = i == len(layers) - 1
        n_out = W.shape[0] if last else max(W.shape[0], int(width))
        n_in = W.shape[1] if prev_new is None else prev_new
        W2 = np.zeros((n_out, n_in))
        W2[:W.shape[0], :W.shape[1]] = W
        if n_out > W.shape[0]:                 # the new units: random inputs from every unit before
            W2[W.shape[0]:, :] = rng.normal(0.0, 1.0 / math.sqrt(n_in), (n_out - W.shape[0], n_in))
        b2 = np.zeros(n_out)
        b2[:len(b)] = b
        out.append((W2, b2))
        prev_new = n_out
    return out


def widen_as_configured(layers, hidden: int, width: int, seed) -> tuple:
    """What a finish-only run starts from (regressors, classifiers, stop heads alike): ``(layers widened to width,
    the hidden widths before)`` where ``layers`` has ``hidden`` hidden layers and one of them is narrower than
    ``width`` (:func:`widen`, random inputs from ``numpy.random.default_rng(seed)``), else ``(layers, None)``:
    any other architecture asked for is not the one a finish-only run keeps."""
    before = [np.shape(W)[0] for W, _ in layers[:-1]]
    if len(before) != int(hidden) or all(h >= int(width) for h in before):
        return layers, None
    return widen(layers, width, np.random.default_rng(seed)), before


def too_large_to_finish(named_layers, hidden: int, width: int, max_weights: int = MAX_PARAMS) -> list:
    """What a finish-only run (regressors, classifiers, stop heads alike) cannot do: ``"key (P weights)"`` for each
    ``(key, layers)`` whose network, widened as configured (:func:`widen_as_configured`), has more than
    ``max_weights`` weights, so the finish would hand it back unchanged.  Empty where every one can be finished."""
    out = []
    for key, layers in named_layers:
        layers = [(np.asarray(W), np.asarray(b)) for W, b in layers]
        P = n_params(widen_as_configured(layers, hidden, width, 0)[0])
        if P > max_weights:
            out.append(f"{key} ({P} weights)")
    return out


def check_finishable(named_layers, nc, owner: str, table: str, way_out: str, what: str = "") -> None:
    """The one rule of every finish-only run (``--finish-only maps``: regressors and classifiers; ``--finish-only
    stop-heads``: stop heads): a :class:`~mi_neurallens.errors.NeuralLensError`, before any training, where ``nc``
    (a NetConfig) gives the finish no time or a network of ``named_layers`` ((key, layers) pairs) is too large for
    it (:func:`too_large_to_finish`), since either would come back unchanged.  ``owner``: whose ``lm_minutes`` the
    message names (e.g. "the classifier's"); ``table``: its config table; ``what``: the message's lead before the
    networks' names; ``way_out``: the retrain that works."""
    from ..errors import NeuralLensError
    if nc.lm_minutes <= 0:
        raise NeuralLensError(f"a finish-only run runs only the Levenberg–Marquardt finish, and {owner} lm_minutes "
                              f"is 0: give it time, e.g. --set {table}.lm_minutes=1.5")
    big = too_large_to_finish(named_layers, nc.hidden, nc.width, nc.lm_max_weights)
    if big:
        raise NeuralLensError(f"{what}{', '.join(big)} is larger than the Levenberg-Marquardt finish takes "
                              f"({nc.lm_max_weights} weights, {table}.lm_max_weights), so the finish would leave it "
                              f"as it is; train it anew as a network the finish takes, e.g. {way_out}")


def n_params(layers) -> int:
    """Weights and biases of ``layers`` ([(W (out, in), b (out,))])."""
    return int(sum(np.size(W) + np.size(b) for W, b in layers))


def n_params_of(dims) -> int:
    """Weights and biases of a dense network whose layer sizes are ``dims`` (inputs, each hidden width, outputs):
    :func:`n_params` of its layers, before there are any."""
    return int(sum(a * b + b for a, b in zip(dims[:-1], dims[1:])))


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

    def activations(self, theta, X) -> list:
        """[X, h₁, …, h_L = outputs] of the network on ``X`` (what :meth:`normal_equations` reuses): ``X``
        (…, n, in), θ (…, P) cast to ``X``'s dtype, the hidden ones after tanh."""
        L = self._unpack(theta.to(X.dtype))
        hs, h = [X], X
        for k, (W, b) in enumerate(L):
            h = h @ W.transpose(-1, -2) + b[..., None, :]
            if k < len(L) - 1:
                h = self.torch.tanh(h)
            hs.append(h)
        return hs

    def normal_equations(self, theta, hs, s, r):
        """(JᵀJ (…, P, P), Jᵀr (…, P)) of the scaled Jacobian J[n, o, :] = s[n, o] · ∂ output o / ∂ θ (row n),
        the Gauss–Newton system of residuals ``r`` (…, n, out) whose derivative with respect to output o is
        ``s`` (…, n, out), in the dtype of the activations ``hs`` (:meth:`activations`).  The same numbers as
        forming ``J`` with :meth:`jacobian` and multiplying, at about half the cost: the output layer's weights
        reach only their own output, so their columns of J are zero on every other output's rows, and only
        the hidden layers' columns are formed (in one buffer, already scaled); the output layer's blocks of
        JᵀJ are per output, (width + 1)² each (``tests/test_levenberg.py``)."""
        torch = self.torch
        L = self._unpack(theta.to(hs[0].dtype))
        lead, n, no = tuple(hs[0].shape[:-2]), hs[0].shape[-2], hs[-1].shape[-1]
        d = hs[-2].shape[-1]
        Pl = no * d + no                                     # the output layer's weights and biases, last in θ
        Ph = self.P - Pl
        hl = torch.cat([hs[-2], torch.ones_like(hs[-2][..., :1])], -1)           # (…, n, d + 1)
        S = s[..., None] * hl[..., None, :]                                       # (…, n, out, d + 1)
        # the hidden layers' columns, and r as one more column: the Gram matrix of [J | r] holds JᵀJ and Jᵀr, and
        # as a product of many columns it sums in the same order whatever the stack's size (a product with one
        # column does not), so a stacked network takes the steps it would take alone (tests/test_levenberg.py)
        onednn = _onednn_gram(torch, hs[0])
        if onednn:     # J stored column by column (Ph + 1, out, n): its Gram is then a product oneDNN takes as it is
            Jb = torch.empty(lead + (Ph + 1, no, n), dtype=hs[0].dtype, device=hs[0].device)
            nl = len(lead)
            Jh = Jb.permute(*range(nl), nl + 2, nl + 1, nl)                      # (…, n, out, Ph + 1), a view
        else:
            Jh = torch.empty(lead + (n, no, Ph + 1), dtype=hs[0].dtype, device=hs[0].device)
        Jh[..., Ph] = r
        # ∂ output o / ∂ (pre-activation of the last hidden layer), scaled: s[n, o] · W_L[o, :] · (1 − h²)
        G = (s[..., None] * L[-1][0][..., None, :, :]) * (1.0 - hs[-2] * hs[-2])[..., None, :]
        off = Ph
        for k in range(len(L) - 2, -1, -1):
            W, _ = L[k]
            o_, i_ = W.shape[-2], W.shape[-1]
            off -= o_ * i_ + o_
            if onednn:      # written along the rows, as Jb lies: (o_, i_, out, n) = G (o_, ·, out, n) · h (·, i_, ·, n)
                Gt = G.permute(*range(nl), nl + 2, nl + 1, nl).contiguous()           # (…, o_, out, n)
                ht = hs[k].transpose(-1, -2).contiguous()                             # (…, i_, n)
                torch.mul(Gt[..., :, None, :, :], ht[..., None, :, None, :],
                          out=Jb[..., off:off + o_ * i_, :, :].unflatten(-3, (o_, i_)))
                Jb[..., off + o_ * i_:off + o_ * i_ + o_, :, :] = Gt
            else:
                torch.mul(G[..., :, :, None], hs[k][..., None, None, :],
                          out=Jh[..., off:off + o_ * i_].unflatten(-1, (o_, i_)))
                Jh[..., off + o_ * i_:off + o_ * i_ + o_] = G
            if k > 0:
                G = (G @ W[..., None, :, :]) * (1.0 - hs[k] * hs[k])[..., None, :]
        gram_out = torch.empty(lead + (Ph + 1, Ph + 1), dtype=hs[0].dtype, device=hs[0].device)
        Gr = (_gram_columns(torch, Jb.reshape(lead + (Ph + 1, no * n)), gram_out) if onednn else
              _gram(Jh.reshape(lead + (n * no, Ph + 1)), gram_out))
        A = torch.zeros(lead + (self.P, self.P), dtype=hs[0].dtype, device=hs[0].device)
        A[..., :Ph, :Ph] = Gr[..., :Ph, :Ph]
        g = torch.empty(lead + (self.P,), dtype=hs[0].dtype, device=hs[0].device)
        g[..., :Ph] = Gr[..., :Ph, Ph]
        # the output layer: output o's columns are W_L[o, :] (at Ph + o·d) and b_L[o] (at Ph + no·d + o)
        Ahl = torch.einsum("...nop,...noq->...opq", Jh, S)                      # (…, out, Ph + 1, d + 1)
        All = torch.einsum("...nop,...noq->...opq", S, S)                       # (…, out, d + 1, d + 1)
        for o in range(no):
            cols = list(range(Ph + o * d, Ph + o * d + d)) + [Ph + no * d + o]
            ci = torch.as_tensor(cols, device=A.device)
            A[..., :Ph, ci] = Ahl[..., o, :Ph, :]
            A[..., ci, :Ph] = Ahl[..., o, :Ph, :].transpose(-1, -2)
            A[..., ci[:, None], ci[None, :]] = All[..., o, :, :]
            g[..., ci] = Ahl[..., o, Ph, :]
        return A, g


#: columns per panel of :func:`_gram`: a Gram matrix computed as panels of this many rows, each from the diagonal
#: on (its upper triangle), takes (b + 1) / 2b of one product's multiply-adds (b panels); 17 panels of a 40 960-row
#: Jacobian of 3 598 columns: 2.85 s against 5.2 for one product, and 3.29 as 153 square blocks (2 Zen 4 cores)
GRAM_BLOCK = 208


def _gram_panels(P: int, product, out):
    """``out`` (…, P, P) ← a symmetric Gram matrix by panels of :data:`GRAM_BLOCK` rows: the panel of rows
    i0:i1 from column i0 on as ``product(i0, i1, i0, P)`` (columns i0:i1 against i0:P), its part right of the
    diagonal block transposed below it.  One product per panel: 9–14 % faster than square blocks of the same
    width, whose products are smaller."""
    nb = max(1, round(P / GRAM_BLOCK))
    c = [P * i // nb for i in range(nb + 1)]
    for i in range(nb):
        B = product(c[i], c[i + 1], c[i], P)
        out[..., c[i]:c[i + 1], c[i]:] = B
        out[..., c[i + 1]:, c[i]:c[i + 1]] = B[..., :, c[i + 1] - c[i]:].transpose(-1, -2)
    return out


def _gram(J, out):
    """``out`` (…, P, P) ← JᵀJ of ``J`` (…, rows, P), by :func:`_gram_panels`."""
    return _gram_panels(J.shape[-1], lambda i0, i1, j0, j1: J[..., i0:i1].transpose(-1, -2) @ J[..., j0:j1], out)


def _onednn_gram(torch, like) -> bool:
    """Whether :func:`_gram_columns` serves a Gram matrix of ``like``'s dtype and device: float32 on a CPU whose
    PyTorch has oneDNN's linear (``torch.ops.mkldnn._linear_pointwise``); ``MI_NEURALLENS_ONEDNN=0`` turns it off."""
    if like.device.type != "cpu" or like.dtype != torch.float32 or os.environ.get("MI_NEURALLENS_ONEDNN", "1") == "0":
        return False
    if "ok" not in _ONEDNN:
        try:
            a = torch.arange(6.0).reshape(2, 3)
            got = torch.ops.mkldnn._linear_pointwise(a, a, None, "none", [], "")
            _ONEDNN["ok"] = bool(torch.equal(got, a @ a.T))
        except (AttributeError, RuntimeError, NotImplementedError):
            _ONEDNN["ok"] = False
    return _ONEDNN["ok"]


_ONEDNN = {}


def _gram_columns(torch, JT, out):
    """``out`` (…, P, P) ← JᵀJ from ``JT`` = Jᵀ (…, P, rows), contiguous, by oneDNN's products: the same
    panels (:func:`_gram_panels`).  PyTorch's own CPU product (MKL) runs AVX2 code on AMD processors; oneDNN's uses the
    full vector width: the Gram of a 3×16 regressor's 40 960 × 625 Jacobian took 116 ms through MKL and ≈ 60 here
    (2 Zen 5 cores)."""
    lin = torch.ops.mkldnn._linear_pointwise
    for idx in np.ndindex(*JT.shape[:-2]):
        J1 = JT[idx]
        _gram_panels(JT.shape[-2], lambda i0, i1, j0, j1: lin(J1[i0:i1], J1[j0:j1], None, "none", [], ""), out[idx])
    return out


def finish(torch, fit, layers, nc, *, seconds: float, max_iterations: int | None = None, rows: int | None = None,
           eval_every: int | None = None, step0: int = 0, lam: float = 1e-3, progress=None) -> list:
    """Levenberg–Marquardt on ``layers`` (the network of the :class:`~.stacked.Problem` ``fit``) for
    ``seconds`` of wall time (and at most ``max_iterations``), or until a validation meets the goals
    (``nc.stop_at_goals``) or ``nc.patience`` validations bring no better score.  Returns the best layers
    by validation score (the starting ones count: they are validated first).  ``rows``: fresh samples per iteration
    (``nc.lm_rows``); ``eval_every``: iterations between validations (``nc.lm_eval_every``).  The
    iterations are appended to ``fit.state`` (``lm``: iterations, seconds, final λ, stop reason) and its
    validations to ``fit.state["history"]`` with ``phase = "lm"`` and step = ``step0`` + iteration.
    One network: :func:`finish_stack` with a stack of one."""
    return finish_stack(torch, [fit], [layers], nc, seconds=seconds, max_iterations=max_iterations, rows=rows,
                        eval_every=eval_every, step0=[step0], lam=lam,
                        progress=None if progress is None else (lambda it, loss, lam_: progress(it, loss[0], lam_[0])))[0]


def finish_stack(torch, fits, layers, nc, *, seconds: float, max_iterations: int | None = None,
                 rows: int | None = None, eval_every: int | None = None, step0=None, lam: float = 1e-3,
                 progress=None) -> list:
    """:func:`finish` for K networks of one shape at once (``fits``: their problems, ``layers``: their
    starting weights): each iteration forms the K Jacobians as one batched product and solves the K damped
    systems as one batched solve, so on a GPU a stack of ghost maps costs about what one does.  Every
    network keeps its own rows (``fit.fresh_rows``, in the order :func:`finish` would draw them), its own λ,
    validations, best weights and stop reason — the result is :func:`finish`'s, network by network
    (``tests/test_levenberg.py``).  A network leaves the stack when it stops; the stack's wall budget is
    K × ``seconds`` (the time the networks would get one at a time).  ``step0``: one Adam step count per
    network.  ``progress(iteration, losses, λs)``: the networks still running.  Returns their best layers,
    in order."""
    K = len(fits)
    if K == 0:
        return []
    run = _StackFinish(torch, fits, layers, nc, rows, eval_every, step0, lam)
    active = [k for k in range(K) if run.reasons[k] is None]
    while active and time.perf_counter() - run.t0 < float(seconds) * K:
        if max_iterations is not None and run.it >= max_iterations:
            for k in active:
                run.stop(k, "max_iterations")
            break
        loss0, lam_a, moved = run.iterate(active)
        if progress is not None:
            progress(run.it, loss0, lam_a)
        for a, k in enumerate(active):
            run.judge(k, loss0[a], moved[a])
        active = [k for k in active if run.reasons[k] is None]
    return run.close(active)


class _StackFinish:
    """One :func:`finish_stack` run: the K networks' weights θ (K, P) float64 and, per network, its rows
    (:class:`RowFeed`), λ, best weights and score, validations since the best, stop reason, and the iterations
    and seconds when it stopped; :attr:`it` counts the iterations of the networks still running.  Made, the
    starting weights are validated and a network that already meets its goals stops."""

    def __init__(self, torch, fits, layers, nc, rows, eval_every, step0, lam):
        K = len(fits)
        self.torch, self.fits, self.nc = torch, fits, nc
        self.rows = int(rows or nc.lm_rows)
        self.eval_every = int(eval_every or nc.lm_eval_every)
        self.step0 = [0] * K if step0 is None else [int(s) for s in step0]
        self.net = net = FlatMLP(torch, layers[0], getattr(fits[0], "dev", None))
        for lay in layers[1:]:
            if FlatMLP(torch, lay).shapes != net.shapes:
                raise ValueError("finish_stack: the networks of one stack must have one shape")
        self.theta = torch.stack([net.flatten(lay) for lay in layers])          # (K, P) float64
        self.t0 = time.perf_counter()
        self.states = [f.state for f in fits]
        self.base_seconds = [float(st.get("seconds", 0.0)) for st in self.states]
        self.lams = [float(lam)] * K
        self.reasons, self.since_best = [None] * K, [0] * K
        self.iters, self.ended = [0] * K, [0.0] * K      # each network's iterations and seconds when it stopped
        self.it = 0                                       # the iterations of the networks still running
        self.feeds = [RowFeed(f, self.rows) for f in fits]
        self.best_theta = [self.theta[k].clone() for k in range(K)]
        for k, f in enumerate(fits):              # a problem whose loss depends on where the finish starts
            start = getattr(f, "lm_start", None)
            if start is not None:
                th = self.theta[k].clone()
                start(lambda x, th=th: net.forward(th, x))
        self.best = [self.validate(k, None) for k in range(K)]
        for k in range(K):
            if nc.stop_at_goals and fits[k].goals_met():
                self.stop(k, "goals")

    def validate(self, k, loss):
        """Network ``k``'s validation on its current weights (its records marked ``phase = "lm"``); its score."""
        th = self.theta[k].clone()
        self.fits[k].net = lambda x: self.net.forward(th, x)
        hist = self.states[k]["history"]
        n_hist = len(hist)
        with self.torch.no_grad():
            score, _ = self.fits[k].validate(self.step0[k] + self.it,
                                             None if loss is None else self.torch.as_tensor(loss),
                                             self.base_seconds[k] + time.perf_counter() - self.t0)
        for rec in hist[n_hist:]:
            rec["phase"] = "lm"
        return score

    def stop(self, k, reason):
        self.reasons[k], self.iters[k], self.ended[k] = reason, self.it, time.perf_counter() - self.t0

    def iterate(self, active):
        """One iteration of the networks ``active``: each its next rows, the K Gauss–Newton systems formed as one
        batched product and the damped steps taken (:func:`_damped_step`).  Returns (the rows' losses before the
        step, the λs after it, which networks moved)."""
        torch, net, fits = self.torch, self.net, self.fits
        f32, f64 = torch.float32, torch.float64
        batches = [self.feeds[k].next() for k in active]
        X = torch.stack([b["X"].to(f32) for b in batches])                 # (A, n, in)
        idx = torch.as_tensor(active, device=self.theta.device)
        with torch.no_grad():
            hs = net.activations(self.theta[idx], X)
            z = hs[-1]                                                        # (A, n, out)
            rs = [fits[k].lm_residual(z[a], batches[a]) for a, k in enumerate(active)]
            r = torch.stack([q[0] for q in rs])
            A, g = net.normal_equations(self.theta[idx], hs, torch.stack([q[1].expand_as(q[0]) for q in rs]), r)
            A, g = A.to(f64), g.to(f64)                                       # (A, P, P), (A, P)
            del hs
            loss0 = (r.to(f64) ** 2).mean((1, 2)).tolist()
            lam_a = [self.lams[k] for k in active]
            th, moved = _damped_step(torch, net, self.theta[idx], X, A, g, lam_a, loss0,
                                     lambda a, z1: float((fits[active[a]].lm_residual(z1, batches[a])[0].to(f64) ** 2)
                                                         .mean()))
            self.theta[idx] = th
        self.it += 1
        for a, k in enumerate(active):
            self.lams[k] = lam_a[a]
            self.states[k]["samples"] = int(self.states[k].get("samples", 0)) + self.rows
        return loss0, lam_a, moved

    def judge(self, k, loss, moved: bool):
        """After an iteration: network ``k`` validated where it is due (every ``eval_every`` iterations, or when no
        step lowers its loss), its best weights kept (where the problem's loss follows its residuals, ``lm_refix``,
        it may change at a new best, which is then scored by the new loss), and stopped at its goals, after
        ``patience`` validations without a better score, when it diverges or when it has converged."""
        nc = self.nc
        converged = not moved and self.lams[k] > 1e8     # no step lowers the loss: at a minimum of what rows can tell
        if self.it % self.eval_every and not converged:
            return
        score = self.validate(k, loss)
        if not math.isfinite(score):
            self.stop(k, "diverged")
            return
        if score < self.best[k]:
            self.best[k], self.best_theta[k], self.since_best[k] = score, self.theta[k].clone(), 0
            refix = getattr(self.fits[k], "lm_refix", None)     # a loss that follows the residuals (the Huber δ)
            rescored = None if refix is None else refix()
            if rescored is not None:                          # changed here: the best weights scored by the new loss
                self.best[k] = rescored
        else:
            self.since_best[k] += 1
        if nc.stop_at_goals and self.fits[k].goals_met():
            self.best_theta[k] = self.theta[k].clone()
            self.stop(k, "goals")
        elif self.since_best[k] >= nc.patience:
            self.stop(k, "early_stop")
        elif converged:
            self.stop(k, "converged")

    def close(self, active) -> list:
        """The end: the networks still ``active`` stopped by the wall budget, a last validation of those the
        budget or the iteration cap stopped between validations, each network's ``lm`` record and seconds written
        to its state.  Returns the best layers, in order."""
        for k in active:
            if self.reasons[k] is None:                  # the wall budget ran out
                self.stop(k, "time_budget")
        for k in range(len(self.fits)):
            if self.reasons[k] in ("time_budget", "max_iterations") and self.iters[k] % self.eval_every:
                score = self.validate(k, None)
                if math.isfinite(score) and score < self.best[k]:
                    self.best[k], self.best_theta[k] = score, self.theta[k].clone()
            self.states[k]["lm"] = {"iterations": self.iters[k], "seconds": self.ended[k], "rows": self.rows,
                                    "lambda": self.lams[k], "stop_reason": self.reasons[k], "best_val": self.best[k],
                                    "stacked_with": len(self.fits)}
            self.states[k]["seconds"] = self.base_seconds[k] + self.ended[k]
        return [self.net.layers(self.best_theta[k]) for k in range(len(self.fits))]


def _damped_step(torch, net, th, X, A, g, lams: list, loss0: list, loss_of):
    """One Levenberg–Marquardt step for each network of a stack: solve (A + λ·diag(A)) δ = −g and keep θ + δ
    where the rows' loss falls below ``loss0`` (then λ ÷ 3), otherwise λ × 4 and solve again, up to 8 times.
    ``th`` (S, P), ``X`` (S, n, in), ``A`` (S, P, P) = JᵀJ and ``g`` (S, P) = Jᵀr in float64; ``lams``: each
    network's λ, updated in place; ``loss_of(s, z)``: network s's loss for outputs z on its rows.  Returns
    (θ (S, P), which networks moved)."""
    d = torch.diagonal(A, dim1=1, dim2=2)
    d = d + 1e-9 * d.max(1, keepdim=True).values + 1e-30
    th = th.clone()
    moved = [False] * len(lams)
    pending = list(range(len(lams)))
    for _ in range(8):
        if not pending:
            break
        pi = torch.as_tensor(pending, device=A.device)
        lam_t = torch.as_tensor([lams[a] for a in pending], dtype=A.dtype, device=A.device)
        # JᵀJ + λ·diag is symmetric positive definite: Cholesky (torch 2.13's batched LU solve also fails on a
        # CPU with more than one thread: MKL's DLASWP rejects its pivots)
        M = A[pi]                                   # a copy (index by a tensor), damped on its diagonal in place:
        M.diagonal(dim1=1, dim2=2).add_(lam_t[:, None] * d[pi])     # a dense λ·diag matrix cost 4x this
        L, info = torch.linalg.cholesky_ex(M)
        delta = torch.cholesky_solve(-g[pi][..., None], L)[..., 0]
        ok = ((info == 0) & torch.isfinite(delta).all(1)).tolist()
        cand = th[pi] + delta
        zc = net.forward(cand, X[pi])
        for c, a in enumerate(pending):
            if ok[c] and loss_of(a, zc[c]) < loss0[a]:
                th[a], lams[a], moved[a] = cand[c], max(lams[a] / 3.0, 1e-12), True
            else:
                lams[a] *= 4.0                      # not positive definite, or no lower loss: damp harder
        pending = [a for a in pending if not moved[a]]
    return th, moved


# ----------------------------------------------------------------------------- a run's networks
#: the first pool of a network that only runs the finish (Levenberg–Marquardt draws fresh rows per iteration; the
#: pool gives the loss weights alone)
FINISH_POOL = 1 << 16


def finish_results(torch, fits, results, nc: NetConfig, keys, ckpt: str | None = None, log=None,
                   progress: bool = False) -> None:
    """The Levenberg–Marquardt finish of each network in
    ``results`` (what :func:`~mi_neurallens.training.stacked.train_stack` returned for ``fits``), in place,
    for ``nc.lm_minutes`` per network (and at most ``nc.lm_iterations``): skipped for networks that met their
    goals already, for networks of more than ``nc.lm_max_weights`` weights (:data:`MAX_PARAMS` by default) and
    when ``lm_minutes`` is 0.  The networks finish in stacks of :func:`lm_stack_size` (on a GPU all of a
    shape at once, :func:`finish_stack`; on a CPU one by one).
    A network that meets its goals here gets ``stop_reason = "goals"`` (Adam's is kept as
    ``adam_stop_reason``).  With ``ckpt``, each finished network is saved to ``<ckpt>.lm.<key>.json`` and
    a rerun takes it from there.  ``progress``: a bar per stack (seconds of its budget, iterations, loss)."""
    if nc.lm_minutes <= 0:
        return
    todo = []
    for j, (f, r, key) in enumerate(zip(fits, results, keys)):
        st = r["state"]
        if st.get("stop_reason") == "goals" or "lm" in st:
            continue
        P = n_params(r["layers"])
        if P > nc.lm_max_weights:
            st["lm"] = {"skipped": f"{P} weights > {nc.lm_max_weights}"}
            # said, not only recorded: a recipe that asks minutes of the finish for such a network gets none
            print(f"{key}: the Levenberg-Marquardt finish skips this network ({P} weights > lm_max_weights = "
                  f"{nc.lm_max_weights}): its lm_minutes = {nc.lm_minutes:g} do nothing", file=sys.stderr, flush=True)
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
    shapes: dict = {}              # one stack per architecture (the base maps of a finish-only run may mix them)
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
            got = finish_stack(torch, [fits[j] for j in idx], [results[j]["layers"] for j in idx], nc,
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


def widened_finish(torch, fits, results, nc: NetConfig, keys, ckpt: str | None = None, log=None,
                   progress: bool = False) -> None:
    """The second finish a network's settings may ask for after :func:`finish_results` (``nc.widen_width`` and
    ``nc.widen_minutes``), in place: each network of ``results`` with ``nc.hidden`` hidden layers, one of them
    narrower than ``widen_width``, widened to it (:func:`widen_as_configured`: the same function, with room) and
    finished for ``widen_minutes`` more (at most ``widen_iterations``, or else ``lm_iterations``, iterations) — to
    that budget, or ``patience``, not to its goals: the goals are medians over the validation's configuration cells,
    which a map can meet while one configuration inside a cell misses (the EF 24-70's camera map: its 4×27 finish
    stops at its goals, the close-focus tele corner above them; widened to 4×29, that corner comes to 2.34 µm after
    14 minutes, 2.00 after 45 on a Zen 5; docs/neural_lens.md).  Networks the first finish skipped (larger than
    ``lm_max_weights``) stay as they are.  Each network's state records ``widened``: the hidden widths before, and
    the first finish's ``lm`` record and stop reasons; the second finish's validations are marked
    ``phase = "widened"``; its ``stop_reason`` is ``"goals"`` where the last validation is within them, else
    Adam's.  With ``ckpt``, each is saved to ``<ckpt>.lm.<key>.widened.json`` and a rerun takes it from there."""
    import zlib
    width, minutes = int(getattr(nc, "widen_width", 0)), float(getattr(nc, "widen_minutes", 0.0))
    if width <= 0 or minutes <= 0:
        return
    todo = []
    for j, (r, key) in enumerate(zip(results, keys)):
        st = r["state"]
        if "skipped" in st.get("lm", {}):
            continue
        layers, before = widen_as_configured(r["layers"], nc.hidden, width, [zlib.crc32(key.encode()), width])
        if before is None:
            continue
        first = {k: st.pop(k) for k in ("lm", "stop_reason", "adam_stop_reason") if k in st}
        st["widened"] = {"from": before, "to": width, "first_finish": first}
        r["layers"] = layers
        if log:
            shape = f"{len(before)}x{before[0]}" if len(set(before)) == 1 else "-".join(map(str, before))
            log(getattr(fits[j], "desc", key), {"phase": "widen", "from": shape, "to": f"{nc.hidden}x{width}"})
        todo.append(j)
    if not todo:
        return
    nc2 = _replaced(nc, lm_minutes=minutes, stop_at_goals=False,
                    lm_iterations=int(getattr(nc, "widen_iterations", 0)) or nc.lm_iterations)
    n_first = {j: len(results[j]["state"]["history"]) for j in todo}
    finish_results(torch, [fits[j] for j in todo], [results[j] for j in todo], nc2, [f"{keys[j]}.widened" for j in todo],
                   ckpt, log, progress)
    for j in todo:
        st = fits[j].state = results[j]["state"]
        for rec in st["history"][n_first[j]:]:      # its steps count from Adam's last again, as the first finish's
            rec["phase"] = "widened"
        first = st["widened"]["first_finish"]
        st["adam_stop_reason"] = first.get("adam_stop_reason", first.get("stop_reason"))
        st["stop_reason"] = "goals" if fits[j].goals_met() else st["adam_stop_reason"]


def _replaced(nc, **changes):
    """``nc`` (a :class:`~mi_neurallens.training.config.NetConfig`, or a namespace in tests) with ``changes``."""
    import copy
    out = copy.copy(nc)
    for k, v in changes.items():
        setattr(out, k, v)
    return out


def check_widenable(nc: NetConfig, n_in: int, n_out: int, table: str) -> None:
    """Before any training: a :class:`~mi_neurallens.errors.NeuralLensError` where ``nc`` asks for a widened finish
    (``widen_width``, ``widen_minutes``) of a network (``n_in`` inputs, ``n_out`` outputs, ``nc.hidden`` hidden
    layers) that would then have more weights than the finish takes (``lm_max_weights``), so the widened network
    would be left untrained; ``table``: its configuration table, which the message names."""
    from ..errors import NeuralLensError
    width = int(getattr(nc, "widen_width", 0))
    if width <= 0 or float(getattr(nc, "widen_minutes", 0.0)) <= 0:
        return
    dims = [int(n_in)] + [max(width, int(nc.width))] * int(nc.hidden) + [int(n_out)]
    P = n_params_of(dims)
    if P > nc.lm_max_weights:
        raise NeuralLensError(f"{table}.widen_width = {width} makes a {nc.hidden}x{width} network of {P} weights, more "
                              f"than the Levenberg-Marquardt finish takes ({table}.lm_max_weights = "
                              f"{nc.lm_max_weights}); raise it, e.g. --set {table}.lm_max_weights={P}")


#: a stack's Jacobians on a GPU stay below this (bytes; float32, with the scaled copy)
LM_STACK_BYTES = 8 << 30


def lm_stack_size(dev, rows: int, n_out: int, n_params_: int) -> int:
    """How many networks the finish takes at once: one on a CPU (its cost is the Jacobian's
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
