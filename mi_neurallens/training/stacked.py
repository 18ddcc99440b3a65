"""Training many networks of one shape at once: stacked weights, batched matrix products, one step.

The maps of a lens are independent small networks of the same shape (every ghost's regressor is a 5×32
tanh MLP on the same four inputs).  Trained one at a time, each step is a handful of 8192×32×32 matrix
products and elementwise passes, and a CPU spends its time in per-operation overhead and in
``torch.tanh``.  Here the K networks of a group are one :class:`StackedMLP` — weights ``(K, in, out)``,
inputs ``(K, B, in)``, every layer one ``baddbmm``, a batch one window of the shuffled pools — and the
loss is the *sum* of the maps' losses, so each map's gradient is its own; :class:`StackedAdam` is
elementwise, hence each map follows exactly the Adam trajectory it would follow alone (same learning-rate
schedule, same batches).  The activation is Eigen's rational tanh
(:func:`~mi_neurallens.neural.mlp.tanh_eigen`, 2.6e-7 from tanh) with the exact derivative 1 − y² as its backward.  On a CPU
with a C compiler a stack's whole forward and backward is one compiled kernel (:mod:`.fused_cpu`, 2.5–3× PyTorch's
operations); otherwise every layer is one ``baddbmm`` and the activation is compiled by ``torch.compile`` into one
fused pass, or is ``torch.tanh`` where nothing compiles (and on a GPU).

A map leaves the stack when it meets its goals (``NetConfig.goals``), stops improving (``patience``) or
the group's budget ends; the stack then shrinks, so finished maps cost nothing.  What each network's
problem is — its sample pool, loss, validation and fresh data — stays with its :class:`Problem` (the
interface, below: :class:`~mi_neurallens.training.regressor.RegressorFit`,
:class:`~mi_neurallens.training.classifier.ClassifierFit`,
:class:`~mi_neurallens.training.stop_head.StopFit`); this module only runs them together.

Checkpoints (``<ckpt>.safetensors`` + ``.json``: weights, Adam moments, best weights, per-map state;
tensors only) are written every ``CHECKPOINT_SECONDS`` and at the end; a rerun resumes, and a finished
stack is not retrained.
"""
from __future__ import annotations

import json
import math
import os
import subprocess
import time

import numpy as np

from . import fused_cpu

CHECKPOINT_SECONDS = 60.0
#: rows per step (maps × batch) of a CPU stack: measured fastest on a 2-core AVX-512 machine (1.37 M
#: samples/s at 4 × 8192, against 1.03 M at 16 × 8192, PyTorch's operations); with the fused step (fused_cpu)
#: the stack size matters less (1, 4 and 16 regressors within 7 % of each other)
CPU_STACK_ROWS = 32768
#: memory the sample pools of one stack may take (bytes); a larger stack gets smaller pools per map
POOL_BYTES = 3 << 30

_ACT = {}


# ----------------------------------------------------------------------------- the interface
class Problem:
    """One network's training problem, as :func:`train_stack` runs it.

    * :meth:`pool` → dict of pool tensors ``(N, ·)`` (rows are samples), read from the attributes that
      :attr:`POOL` names (pool name → attribute; an attribute that is None is left out);
    * :meth:`constants` → dict of per-map loss constants (tensors broadcasting against a batch);
    * :meth:`rows_loss` ``(out, batch, const)`` → the loss of a batch (``out``: the network's outputs on
      ``batch["X"]``), reduced over the sample axis only, so a ``(K, B, ·)`` batch with ``(K, 1, ·)``
      constants gives ``(K,)``;
    * :meth:`fresh_rows` ``(k)`` → dict of ``k`` new pool rows; :meth:`validate` ``(step, loss, seconds)`` →
      (score, postfix), lower is better, with ``self.net`` the map's own network, appending to
      ``self.state["history"]``; :meth:`goals_met` → whether the last validation met the goals;
    * :meth:`lm_residual` ``(z, batch)`` → (r, ∂r/∂z), residuals whose mean square is the loss: what the
      Levenberg–Marquardt finish (:mod:`~mi_neurallens.training.levenberg`) minimises;
    * optionally :meth:`fused_loss` ``(kern, out, batch, const)`` → (loss ``(K,)``, ∂Σloss/∂out): :meth:`rows_loss`
      and its gradient in one pass of the CPU kernel (:mod:`.fused_cpu`), where :meth:`has_fused_loss` says so;
      the loop then runs a step without autograd (:func:`fused_step`).
    """

    POOL: dict = {}

    def pool(self) -> dict:
        return {n: getattr(self, a) for n, a in self.POOL.items() if getattr(self, a) is not None}

    def release_pool(self):
        """Drop this problem's own pool (the stack holds a copy)."""
        for a in self.POOL.values():
            setattr(self, a, None)

    def constants(self) -> dict:
        return {}

    def rows_loss(self, out, batch, const):
        raise NotImplementedError

    def fresh_rows(self, k: int) -> dict:
        raise NotImplementedError

    def validate(self, step, loss, seconds):
        raise NotImplementedError

    def goals_met(self) -> bool:
        raise NotImplementedError

    def lm_residual(self, z, batch):
        raise NotImplementedError

    def has_fused_loss(self) -> bool:
        return False

    def fused_loss(self, kern, out, batch, const):
        raise NotImplementedError


def fused_step(net, fit, batch, const):
    """One step's forward, loss and backward with neither autograd nor PyTorch's operations: the network through
    the fused kernel and the loss through the problem's :meth:`Problem.fused_loss`, each parameter's gradient left
    in ``.grad`` as ``loss.sum().backward()`` leaves it.  Returns the per-map loss ``(K,)``, or None where the
    stack has no kernel or the problem no fused loss (then the caller differentiates :meth:`Problem.rows_loss`)."""
    kern = net.fused
    if kern is None or not fit.has_fused_loss() or batch["X"].dtype != net.torch.float32:
        return None
    X = batch["X"]
    out, acts = kern.forward(net.torch, X, net.params)
    loss, gout = fit.fused_loss(kern, out, batch, const)
    for q, g in zip(net.params, kern.backward(net.torch, X, net.params, acts, gout)):
        q.grad = g
    return loss


def lr_at(step: int, nc, seconds: float = 0.0) -> float:
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


# ----------------------------------------------------------------------------- the activation
def training_tanh(torch, device=None):
    """tanh for Adam on ``device``: on a CPU Eigen's clamped 13/6 rational (:func:`~mi_neurallens.neural.mlp.tanh_eigen`), fused by
    ``torch.compile`` with the backward ``g·(1 − y²)``; ``torch.tanh`` on a GPU, and wherever compiling is
    unavailable or disabled (``MI_NEURALLENS_TORCH_COMPILE=0``).  Cached per process and device type; what
    was chosen, and the compilation's seconds, are in :data:`TANH_CHOICE` (the training log reports them).

    Both are tanh to float32 rounding (the rational is checked against ``torch.tanh`` to 1e-6 before it is
    used), and the Levenberg–Marquardt finish, which sets the weights a map ships with, uses ``torch.tanh``
    anyway.  On a CPU the fused rational takes 167 µs for the 1 M activations of a 4 × 8192 × 32 stack, where
    ``torch.tanh`` takes 1.1 ms (2 cores, AVX-512), for a one-time compilation a process (≈ 17 s on an empty cache; a C++
    compiler).  On a
    GPU ``torch.tanh`` is already one kernel forward and one backward, the most a fused version could be,
    so compiling (Inductor and Triton, on an empty cache) could only add to the set-up."""
    kind = torch.device(device).type if device is not None else "cpu"
    if kind in _ACT:
        return _ACT[kind]
    fn, how = torch.tanh, "torch.tanh"
    if kind == "cpu" and os.environ.get("MI_NEURALLENS_TORCH_COMPILE", "1") != "0":
        from ..neural.mlp import TANH_CLAMP, TANH_P, TANH_Q

        def rational(x):
            x = x.clamp(-TANH_CLAMP, TANH_CLAMP)
            x2 = x * x
            p = TANH_P[-1]
            for a in reversed(TANH_P[:-1]):
                p = p * x2 + a
            q = TANH_Q[-1]
            for b in reversed(TANH_Q[:-1]):
                q = q * x2 + b
            return x * p / q

        t0 = time.perf_counter()
        try:
            import torch._dynamo
            # The polynomial's coefficients are Python floats; with dynamic shapes Dynamo would make them kernel
            # inputs (float64 pointers), and Inductor then emits a serial loop: 2.0-2.4x slower on 2 cores.
            # Kept as literals, the loop is vectorised and parallel (every (re)compilation runs inside this patch).
            literals = torch._dynamo.config.patch(specialize_float=True)
            compiled = torch.compile(rational, dynamic=True)
            compiled_grad = torch.compile(lambda g, y: g * (1.0 - y * y), dynamic=True)

            class RationalTanh(torch.autograd.Function):
                @staticmethod
                def forward(ctx, x):
                    with literals:
                        y = compiled(x)
                    ctx.save_for_backward(y)
                    return y

                @staticmethod
                def backward(ctx, g):
                    (y,) = ctx.saved_tensors
                    with literals:
                        return compiled_grad(g, y)

            probe = torch.linspace(-9.0, 9.0, 258).reshape(2, 3, 43).requires_grad_()   # (K, B, width), as trained
            out = RationalTanh.apply(probe)
            out.sum().backward()                  # compile the backward too, here, where it is timed
            if float((out.detach() - torch.tanh(probe.detach())).abs().max()) < 1e-6:
                fn, how = RationalTanh.apply, "Eigen's rational tanh, fused by torch.compile"
        # no C++ compiler, an unsupported platform: the exact torch.tanh.  Dynamo's and Inductor's failures are
        # RuntimeErrors (InvalidCxxCompiler, CppCompileError, BackendCompilerFailed, ...); ImportError where
        # torch._dynamo is absent; OSError and CalledProcessError from running the compiler
        except (RuntimeError, ImportError, OSError, subprocess.CalledProcessError):
            fn, how = torch.tanh, "torch.tanh (torch.compile failed)"
        how += f" ({time.perf_counter() - t0:.1f} s to compile)"
    _ACT[kind] = fn
    TANH_CHOICE[kind] = how
    return fn


#: what :func:`training_tanh` chose per device type, in words (for the training log)
TANH_CHOICE = {}
#: how a CPU stack of each network shape ("4-16-16-16-5") takes its steps, in words (for the training log)
STEP_CHOICE = {}


# ----------------------------------------------------------------------------- K networks
class StackedMLP:
    """K MLPs of one shape: ``params`` = [W₀ (K, in, w), b₀ (K, 1, w), …] (``x @ W + b`` per layer),
    initialised as ``torch.nn.Linear`` does (uniform ±1/√fan_in), each map from its own seed."""

    def __init__(self, torch, dev, seeds, n_in: int, n_out: int, hidden: int, width: int, activation: str = "tanh"):
        self.torch, self.dev = torch, dev
        self.dims = [n_in] + [width] * hidden + [n_out]
        self.activation = activation
        Ws = [[] for _ in self.dims[1:]]
        bs = [[] for _ in self.dims[1:]]
        for s in seeds:
            g = torch.Generator().manual_seed(int(s))
            for i, (a, b) in enumerate(zip(self.dims[:-1], self.dims[1:])):
                bound = 1.0 / math.sqrt(a)
                Ws[i].append((torch.rand(a, b, generator=g) * 2 - 1) * bound)
                bs[i].append((torch.rand(1, b, generator=g) * 2 - 1) * bound)
        self.params = []
        for W, b in zip(Ws, bs):
            self.params += [torch.stack(W).to(dev).requires_grad_(), torch.stack(b).to(dev).requires_grad_()]
        self.fused = None           # on a CPU: the forward and backward in one compiled kernel (fused_cpu)
        if activation == "tanh" and torch.device(dev).type == "cpu":
            self.fused = fused_cpu.kernel(torch, self.dims)
            shape = "-".join(map(str, self.dims))
            STEP_CHOICE[shape] = ("one fused C kernel (training/fused_mlp.c, Eigen's rational tanh)"
                                  if self.fused is not None else
                                  f"PyTorch's operations ({fused_cpu.WHY_NOT.get(tuple(self.dims), '')})")
        # the activation of PyTorch's operations (compiled on first use: not needed where the kernel runs)
        self.act = torch.relu if activation != "tanh" else None if self.fused is not None else training_tanh(torch, dev)

    @property
    def k(self) -> int:
        return self.params[0].shape[0]

    def forward(self, x, params=None):
        """(K, B, in) → (K, B, out)."""
        p = self.params if params is None else params
        if self.fused is not None and x.dtype == self.torch.float32 and not x.requires_grad:
            return fused_cpu.fused_forward(self.torch, self.fused, x, p)
        h, n = x, len(p) // 2
        if self.act is None:
            self.act = training_tanh(self.torch, self.dev)
        for i in range(n):
            h = self.torch.baddbmm(p[2 * i + 1], h, p[2 * i])
            if i < n - 1:
                h = self.act(h)
        return h

    def one(self, j: int):
        """Map ``j``'s network as a callable (B, in) → (B, out) on the current weights."""
        def net(x):
            p = [q[j:j + 1] for q in self.params]
            return self.forward(x[None], p)[0]
        return net

    def snapshot(self, j: int) -> list:
        """A copy of map ``j``'s weights (what the best-so-far keeps)."""
        return [q[j].detach().clone() for q in self.params]

    def load(self, j: int, weights: list):
        with self.torch.no_grad():
            for q, w in zip(self.params, weights):
                q[j] = w

    @staticmethod
    def layers(weights: list) -> list:
        """[(W (out, in), b (out,)) float64 numpy] of one map's weights: the model file's layout."""
        return [(weights[2 * i].detach().cpu().double().numpy().T.copy(),
                 weights[2 * i + 1].detach().cpu().double().numpy()[0].copy()) for i in range(len(weights) // 2)]

    def take(self, keep: list):
        """Keep only the maps ``keep`` (indices into the current stack)."""
        idx = self.torch.as_tensor(keep, device=self.dev, dtype=self.torch.long)
        self.params = [q.detach()[idx].clone().requires_grad_() for q in self.params]


class StackedAdam:
    """Adam (PyTorch's update, bias-corrected, ε outside the square root) on stacked parameters; being
    elementwise, each map's slice follows the trajectory it would follow alone.  :meth:`take` drops maps."""

    def __init__(self, params, betas=(0.9, 0.999), eps: float = 1e-8):
        self.b1, self.b2, self.eps = betas[0], betas[1], eps
        self.m = [p.detach().new_zeros(p.shape) for p in params]
        self.v = [p.detach().new_zeros(p.shape) for p in params]
        self.t = 0

    def step(self, params, lr: float):
        self.t += 1
        c1, c2 = 1.0 - self.b1 ** self.t, 1.0 - self.b2 ** self.t
        for p, m, v in zip(params, self.m, self.v):
            g = p.grad
            m.mul_(self.b1).add_(g, alpha=1.0 - self.b1)
            v.mul_(self.b2).addcmul_(g, g, value=1.0 - self.b2)
            denom = (v / c2).sqrt_().add_(self.eps)
            p.data.addcdiv_(m, denom, value=-lr / c1)
            p.grad = None

    def take(self, keep, torch):
        idx = torch.as_tensor(keep, dtype=torch.long, device=self.m[0].device)
        self.m = [m[idx].clone() for m in self.m]
        self.v = [v[idx].clone() for v in self.v]


# ----------------------------------------------------------------------------- the pools of K maps
class PoolStack:
    """The sample pools of the active maps as stacked tensors ``(K, N, ·)`` and their loss constants
    ``(K, …)``; a batch is one gather.  Pools are refreshed per map with that map's fresh data."""

    def __init__(self, torch, fits):
        self.torch = torch
        pools = [f.pool() for f in fits]
        self.names = list(pools[0])
        self.pool = {n: torch.stack([p[n] for p in pools]) for n in self.names}
        consts = [f.constants() for f in fits]
        self.const = {n: torch.stack([c[n] for c in consts]) for n in consts[0]}
        self.n = self.pool[self.names[0]].shape[1]
        for f in fits:              # the per-map copies are no longer needed (memory)
            f.release_pool()

    def batch(self, start: int, size: int):
        """Rows ``start … start + size`` of every pool (views, no copy): dict of (K, size, ·).  The pool's
        rows are in random order (:meth:`shuffle`), so a window is a random batch."""
        return {n: t[:, start:start + size] for n, t in self.pool.items()}

    def shuffle(self, rng):
        """Put every map's pool rows in a fresh random order (after new rows were written)."""
        perm = self.torch.as_tensor(rng.permutation(self.n), device=self.pool[self.names[0]].device)
        self.pool = {n: t.index_select(1, perm) for n, t in self.pool.items()}

    def write(self, j: int, new: dict, rng):
        """Replace random rows of map ``j``'s pools with ``new`` (dict of (k, ·))."""
        k = len(next(iter(new.values())))
        idx = self.torch.as_tensor(rng.choice(self.n, k, replace=False), device=self.pool[self.names[0]].device)
        for n, v in new.items():
            self.pool[n][j, idx] = v

    def take(self, keep):
        idx = self.torch.as_tensor(keep, dtype=self.torch.long)
        self.pool = {n: t[idx] for n, t in self.pool.items()}
        self.const = {n: t[idx] for n, t in self.const.items()}


def pool_rows(nc, n_maps: int, row_bytes: int) -> int:
    """Pool size per map: ``nc.pool`` unless the stack's pools would exceed :data:`POOL_BYTES`."""
    return int(max(min(nc.pool, POOL_BYTES // max(n_maps * row_bytes, 1)), 4 * nc.batch))


# ----------------------------------------------------------------------------- the loop
def stack_size(dev, batch: int) -> int:
    """How many maps one stack holds: on a CPU, stacks of about :data:`CPU_STACK_ROWS` rows per step (K ×
    batch) train fastest — larger ones spill the activations out of cache;
    on a GPU, every map at once."""
    if str(dev).startswith("cuda"):
        return 1 << 30
    return max(1, CPU_STACK_ROWS // max(int(batch), 1))


def train_stack(torch, dev, fits, nc, *, seeds, n_in: int, n_out: int, keys, ckpt: str | None = None,
                progress: bool = True, desc: str = "", log=None):
    """Train one network per :class:`Problem` in ``fits`` (all of one kind and shape, ``nc`` their settings) in
    stacks of :func:`stack_size` maps, one after the other.  Returns a list of ``{"layers", "state"}`` (the
    best weights by each map's validation score) in the order of ``fits``.  ``keys``: the maps' names
    (checkpoints and progress); ``seeds``: one per map (initial weights)."""
    n = stack_size(dev, nc.batch)
    chunks = [list(range(i, min(i + n, len(fits)))) for i in range(0, len(fits), n)]
    out = []
    for c, idx in enumerate(chunks):
        d = desc if len(chunks) == 1 else f"{desc} [stack {c + 1}/{len(chunks)}]"
        out += _train_one_stack(torch, dev, [fits[i] for i in idx], nc, seeds=[seeds[i] for i in idx], n_in=n_in,
                                n_out=n_out, keys=[keys[i] for i in idx],
                                ckpt=None if not ckpt else (ckpt if len(chunks) == 1 else f"{ckpt}.{c}"),
                                progress=progress, desc=d, log=log)
        for r in out[-len(idx):]:
            r["state"]["stack"] = c
    return out


def _train_one_stack(torch, dev, fits, nc, *, seeds, n_in: int, n_out: int, keys, ckpt: str | None = None,
                     progress: bool = True, desc: str = "", log=None):
    """Train the networks of ``fits`` as one stack (what :func:`train_stack` runs per stack).

    A map stops when ``fit.goals_met()`` after a validation (``stop_reason = "goals"``, only when
    ``nc.stop_at_goals``), after ``nc.patience`` validations without a better score (``"early_stop"``), when
    its loss or validation score is no longer finite (``"diverged"``: it keeps its best weights so far),
    at ``nc.max_steps`` or when the stack's wall-clock budget ends (``nc.max_minutes`` per map: K ×
    ``max_minutes`` for the stack, the time the maps would get one at a time)."""
    run = _AdamStack(torch, dev, fits, nc, seeds, n_in, keys, ckpt, progress, desc,
                     StackedMLP(torch, dev, seeds, n_in, n_out, nc.hidden, nc.width, nc.activation))
    while run.active and run.step < nc.max_steps:
        loss = run.adam_step()
        done_now = []
        if run.step % nc.eval_every == 0 or run.step == nc.max_steps:
            done_now = run.validate_all(loss.detach())
        done_now = run.check_budget(loss, done_now)
        run.leave(done_now)
        run.checkpoint()
    return run.close()


class _AdamStack:
    """One stack's Adam run (:func:`_train_one_stack`): the stacked network and optimiser, each map's state and
    best weights, the maps still training (:attr:`active`, indices into ``fits``), their pools, the step and the
    clock.  Made, it resumes from the checkpoint ``ckpt`` where there is one, shuffles the pools with the stack's
    random stream (seeded from (the first map's seed, the step it starts at)) and compiles the activation before
    the clock starts."""

    def __init__(self, torch, dev, fits, nc, seeds, n_in: int, keys, ckpt, progress: bool, desc: str, net):
        self.torch, self.fits, self.nc, self.keys, self.ckpt = torch, fits, nc, keys, ckpt
        self.K = K = len(fits)
        self.net = net
        self.opt = StackedAdam(net.params)
        self.states = [f.state for f in fits]          # each fit logs its validations into its own state
        self.best = [net.snapshot(j) for j in range(K)]
        got = load_stack(ckpt, keys, net, self.opt, torch, dev) if ckpt else None
        self.active = list(range(K))
        self.step0 = 0
        if got is not None:         # resumed: ``net`` and ``opt`` hold only the maps still training
            self.states, self.best, self.active, self.step0 = got
            for f, st in zip(fits, self.states):
                f.state = st
        self.rng = np.random.default_rng([int(seeds[0]), self.step0])
        self.pools = PoolStack(torch, [fits[i] for i in self.active]) if self.active else None
        if self.pools is not None:
            self.pools.shuffle(self.rng)
        if self.active:             # compile the activation (forward and backward) before the clock starts
            net.forward(torch.zeros((net.k, 8, n_in), device=dev)).sum().backward()
            for q in net.params:
                q.grad = None
        self.t0 = time.perf_counter() - (self.states[self.active[0]]["seconds"] if self.active else 0.0)
        self.last_ckpt = time.perf_counter()
        self.step = self.step0
        self.bar = Progress(K, nc, desc, progress, done=K - len(self.active), step=self.step,
                            seconds=time.perf_counter() - self.t0)

    def end(self, i, reason):
        """Map ``i`` stops training, for ``reason``."""
        self.states[i].update(stop_reason=reason, done=True, step=self.step, seconds=time.perf_counter() - self.t0)

    def adam_step(self):
        """One step of every active map: their pools partly refreshed where it is due (every ``refresh_every``
        steps), one random window of them as the batch, the loss and its gradient (the fused CPU kernel where the
        problem has one, else autograd), Adam's update.  Returns the per-map losses ``(K,)``."""
        nc, fits, pools, active = self.nc, self.fits, self.pools, self.active
        if self.step > self.step0 and self.step % nc.refresh_every == 0:
            k = int(pools.n * nc.refresh_fraction)
            for j, i in enumerate(active):
                pools.write(j, fits[i].fresh_rows(k), self.rng)
            pools.shuffle(self.rng)
        seconds = time.perf_counter() - self.t0
        lr = lr_at(self.step, nc, seconds / self.K)       # the schedule's clock: the stack's budget is K × max_minutes
        batch = pools.batch(int(self.rng.integers(0, pools.n - nc.batch + 1)), nc.batch)
        loss = fused_step(self.net, fits[active[0]], batch, pools.const)
        if loss is None:
            loss = fits[active[0]].rows_loss(self.net.forward(batch["X"]), batch, pools.const)
            loss.sum().backward()
        self.opt.step(self.net.params, lr)
        self.step += 1
        for i in active:
            self.states[i]["samples"] += nc.batch
            self.states[i]["step"] = self.step
        self.bar.step(self.step, len(active) * nc.batch)
        return loss

    def validate_all(self, loss):
        """Validate every active map; returns the indices (into ``active``) of maps that are done."""
        torch, nc = self.torch, self.nc
        out = []
        for j, i in enumerate(self.active):
            f, st = self.fits[i], self.states[i]
            f.net = self.net.one(j)
            with torch.no_grad():
                score, postfix = f.validate(self.step, None if loss is None else loss[j],
                                            time.perf_counter() - self.t0)
            if not math.isfinite(score) or (loss is not None and not bool(torch.isfinite(loss[j]))):
                self.end(i, "diverged")              # its best weights so far stay; the others go on
                out.append(j)
                continue
            if score < st["best_val"]:
                st.update(best_val=score, best_step=self.step, evals_since_best=0)
                self.best[i] = self.net.snapshot(j)
            else:
                st["evals_since_best"] += 1
            if nc.stop_at_goals and f.goals_met():
                self.best[i] = self.net.snapshot(j)   # the weights that met the goals
                self.end(i, "goals")
                out.append(j)
            elif st["evals_since_best"] >= nc.patience:
                self.end(i, "early_stop")
                out.append(j)
        return out

    def check_budget(self, loss, done_now: list) -> list:
        """After a step: the active maps' seconds, and where the stack's wall budget (K × ``max_minutes``) is spent,
        every active map validated (unless this step was) and stopped.  Returns the maps done (indices into
        ``active``): ``done_now``, or all of them."""
        seconds = time.perf_counter() - self.t0
        for i in self.active:
            self.states[i]["seconds"] = seconds
        if seconds > self.nc.max_minutes * 60.0 * self.K:
            if self.step % self.nc.eval_every != 0:            # this step was not validated yet
                done_now = self.validate_all(loss.detach())
            for i in self.active:
                if not self.states[i].get("done"):
                    self.end(i, "time_budget")
            done_now = list(range(len(self.active)))
        return done_now

    def leave(self, done_now: list):
        """The maps ``done_now`` (indices into ``active``) leave the stack: its network, optimiser and pools shrink."""
        if not done_now:
            return
        keep = [j for j in range(len(self.active)) if j not in done_now]
        self.bar.finished(len(done_now))
        self.active = [self.active[j] for j in keep]
        if keep:
            self.net.take(keep)
            self.opt.take(keep, self.torch)
            self.pools.take(keep)

    def checkpoint(self):
        """The stack saved to ``ckpt`` where :data:`CHECKPOINT_SECONDS` have passed since the last save."""
        if self.ckpt and time.perf_counter() - self.last_ckpt > CHECKPOINT_SECONDS:
            save_stack(self.ckpt, self.keys, self.net, self.opt, self.states, self.best, self.active, self.step)
            self.last_ckpt = time.perf_counter()

    def close(self) -> list:
        """The end (``max_steps`` reached by the maps still active: validated unless this step was, and stopped);
        the stack saved.  Returns ``{"layers", "state"}`` per map (its best weights), in the order of ``fits``."""
        if self.active:                                  # max_steps reached
            if any(not self.states[i]["history"] or self.states[i]["history"][-1]["step"] != self.step
                   for i in self.active):
                self.validate_all(None)
            for i in self.active:
                if not self.states[i].get("done"):
                    self.end(i, "max_steps")
            self.active = []
        self.bar.close()
        if self.ckpt:
            save_stack(self.ckpt, self.keys, self.net, self.opt, self.states, self.best, self.active, self.step)
        return [{"layers": StackedMLP.layers(self.best[i]), "state": self.states[i]} for i in range(self.K)]


# ----------------------------------------------------------------------------- progress and ETA
class Progress:
    """One line for a stack: maps done / K, step, aggregate samples/s and an ETA — an upper bound: the
    time to ``max_steps`` at the current step rate, capped by what is left of the wall-clock budget (maps
    that meet their goals leave earlier)."""

    def __init__(self, k, nc, desc, enabled, done=0, step=0, seconds=0.0):
        self.k, self.nc, self.done = k, nc, done
        self.t0, self.step0, self.seconds0 = time.perf_counter(), step, seconds
        self.samples, self.last = 0, 0.0
        self.bar = None
        if enabled:
            try:
                from tqdm.auto import tqdm
                self.bar = tqdm(total=nc.max_steps, initial=step, desc=desc, leave=False, dynamic_ncols=True)
            except ImportError:  # pragma: no cover
                self.bar = None

    def step(self, step, samples):
        self.samples += samples
        if self.bar is None:
            return
        self.bar.update(1)
        now = time.perf_counter()
        if now - self.last > 1.0:
            self.last = now
            dt = now - self.t0
            eta = min(dt / max(step - self.step0, 1) * (self.nc.max_steps - step),
                      self.nc.max_minutes * 60.0 * self.k - self.seconds0 - dt)
            self.bar.set_postfix_str(f"maps {self.done}/{self.k} done, {self.samples / max(dt, 1e-9) / 1e6:.2f} M "
                                     f"samples/s, ETA ≤ {max(eta, 0.0) / 60:.1f} min")

    def finished(self, n):
        self.done += n

    def close(self):
        if self.bar is not None:
            self.bar.close()


# ----------------------------------------------------------------------------- checkpoints
def save_stack(path, keys, net, opt, states, best, active, step):
    """Weights and Adam moments of the active maps, every map's best weights and state (atomic)."""
    from safetensors.torch import save_file
    from ..fileio import atomic_write, atomic_write_text
    t = {}
    for n, q in enumerate(net.params):
        t[f"net.{n}"] = q.detach().cpu().contiguous()
        t[f"adam.m.{n}"] = opt.m[n].cpu().contiguous()
        t[f"adam.v.{n}"] = opt.v[n].cpu().contiguous()
    for i, w in enumerate(best):
        for n, q in enumerate(w):
            t[f"best.{i}.{n}"] = q.detach().cpu().contiguous()
    meta = {"keys": list(keys), "active": list(active), "step": int(step), "adam_t": opt.t, "states": states}
    atomic_write(path + ".safetensors", lambda p: save_file(t, p))
    atomic_write_text(path + ".json", json.dumps(meta))


def load_stack(path, keys, net, opt, torch, dev):
    """Resume a stack saved by :func:`save_stack` for the same ``keys``: (states, best, active, step) with
    ``net`` and ``opt`` restored to its active maps, or None (no or another or a broken checkpoint)."""
    if not (os.path.exists(path + ".safetensors") and os.path.exists(path + ".json")):
        return None
    from safetensors import SafetensorError
    from safetensors.torch import load_file
    try:
        t = load_file(path + ".safetensors")
        meta = json.loads(open(path + ".json").read())
    except (OSError, ValueError, SafetensorError):      # unreadable, not JSON (or not UTF-8), not safetensors
        return None
    if meta.get("keys") != list(keys):
        return None
    n = len(net.params)
    net.params = [t[f"net.{i}"].to(dev).requires_grad_() for i in range(n)]
    opt.m = [t[f"adam.m.{i}"].to(dev) for i in range(n)]
    opt.v = [t[f"adam.v.{i}"].to(dev) for i in range(n)]
    opt.t = int(meta["adam_t"])
    best = [[t[f"best.{i}.{j}"].to(dev) for j in range(n)] for i in range(len(keys))]
    return meta["states"], best, list(meta["active"]), int(meta["step"])


def peek_stack(path, keys) -> dict:
    """{map key: state} of the maps of ``keys`` found in the checkpoints of :func:`train_stack` at ``path``
    (``path`` itself, or ``path.0``, ``path.1``… when it ran several stacks): what a resume must restore
    before the pools are built, e.g. a regressor's output transform.  Empty when there is none."""
    out = {}
    if not path:
        return out
    files = [path] + [f"{path}.{c}" for c in range(len(keys))]
    for f in files:
        if not os.path.exists(f + ".json"):
            continue
        try:
            meta = json.loads(open(f + ".json").read())
        except (OSError, ValueError):                   # unreadable or not JSON: no state to restore from it
            continue
        for k, st in zip(meta.get("keys", []), meta.get("states", [])):
            if k in keys:
                out[k] = st
    return out


def stack_name(net: str, keys) -> str:
    """The checkpoint name of a stack: ``<map>.<net>`` for one map, ``<net>.<K>maps.<digest>`` for many."""
    import hashlib
    keys = list(keys)
    if len(keys) == 1:
        return f"{keys[0]}.{net}"
    return f"{net}.{len(keys)}maps.{hashlib.sha256(','.join(keys).encode()).hexdigest()[:10]}"
