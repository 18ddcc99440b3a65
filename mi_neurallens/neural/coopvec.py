"""MLP evaluation with Dr.Jit's cooperative vectors (``drjit.nn``), the alternative to literal weights.

:func:`mlp_dr <mi_neurallens.neural.mlp.mlp_dr>` bakes every weight into the kernel as a literal:
fastest on the LLVM backend and exact in fp32, but every new weight set compiles a new kernel
(~1 s).  Cooperative vectors keep the weights in a packed buffer that the kernel reads, so changing
weights costs no compilation, and on CUDA the matrix–vector products run on tensor cores.

* LLVM (this project's CPU default): fp32, same results as the literal path to ~1e-6.
* CUDA: ``drjit.nn`` requires half precision for ``matvec`` (driver ≥ R570); weights and activations
  are then fp16: several times the rate of the literal kernels, but exit rays tens of µm off the fp32
  network's (rates and errors: docs/performance.md, "On a GPU") — so ``fused`` stays the default there too.

The activation is Dr.Jit's ``tanh`` on the cooperative vector (no division is available on
``CoopVec``, so the rational tanh of the literal path cannot be used).
"""
from __future__ import annotations

import numpy as np


class CoopVecMLP:
    """A packed ``drjit.nn`` network equal to ``layers`` (list of (W (out, in), b)) for inputs of the Dr.Jit
    float type ``float_t`` (the current Mitsuba variant's ``Float`` when None).  Call it with a list of
    Dr.Jit floats; returns a list of the same type."""

    def __init__(self, layers, activation: str = "tanh", float_t=None):
        import drjit as dr
        import drjit.nn as nn
        if activation not in ("tanh", "relu"):
            raise ValueError(f"unknown activation {activation!r}")
        if float_t is None:
            import mitsuba as mi
            float_t = mi.Float
        cuda = dr.backend_v(float_t) == dr.JitBackend.CUDA
        self.float_t = float_t
        self.half_t = dr.float16_array_t(float_t) if cuda else None
        tensor = dr.tensor_t(self.half_t if cuda else float_t)
        mods = []
        for i, (W, b) in enumerate(layers):
            W = np.asarray(W)
            mods.append(nn.Linear(W.shape[1], W.shape[0]))
            if i < len(layers) - 1:
                mods.append(nn.Tanh() if activation == "tanh" else nn.ReLU())
        net = nn.Sequential(*mods).alloc(tensor, int(np.asarray(layers[0][0]).shape[1]))
        dt = np.float16 if cuda else np.float32
        for i, (W, b) in enumerate(layers):
            net[f"layers.{2 * i}.weights"] = tensor(np.asarray(W, dtype=dt))
            net[f"layers.{2 * i}.bias"] = tensor(np.asarray(b, dtype=dt))
        self.cuda = cuda
        self.net = nn.pack(net, layout="inference")
        self.n_out = int(np.asarray(layers[-1][1]).shape[0])

    def __call__(self, xs):
        import drjit.nn as nn
        if self.cuda:
            xs = [self.half_t(x) for x in xs]
        out = list(self.net(nn.CoopVec(*xs)))
        return [self.float_t(o) for o in out] if self.cuda else out


def packed(owner, name: str, layers, activation: str, like) -> CoopVecMLP:
    """``owner``'s :class:`CoopVecMLP` of ``layers`` for inputs like the Dr.Jit array ``like``, built once
    per float type and kept in ``owner.__dict__`` (a map or stop head whose layers do not change)."""
    cache = owner.__dict__.setdefault("_coopvec_cache", {})
    key = (name, type(like))
    if key not in cache:
        cache[key] = CoopVecMLP(layers, activation, type(like))
    return cache[key]


class LiveNetwork:
    """A network whose weights are Dr.Jit arrays, possibly with gradients enabled: the learned map's regressor
    while ``mi.traverse`` has changed it (``neural_lens``: docs/differentiable.md).

    ``layers``: list of ``(W, b)``, ``W`` a ``TensorXf`` of shape (out, in) and ``b`` a ``Float`` of width out, the
    model file's layers (before the output transform); ``out_scale``, ``out_shift``: the map's output transform
    ``shift + scale·y``, folded into the last layer here (numpy).  The layers are packed once, at construction, into
    one cooperative-vector buffer (``drjit.nn.pack``: differentiable, so a reverse pass reaches ``layers``; its
    training layout when a weight has gradients enabled), read by the kernel as an input: a new weight set
    compiles no kernel.  fp32 on the CPU; on CUDA fp16, as ``mlp = "coopvec"``."""

    def __init__(self, layers, out_scale, out_shift, activation: str = "tanh", float_t=None):
        import drjit as dr
        import drjit.nn as nn
        if float_t is None:
            import mitsuba as mi
            float_t = mi.Float
        cuda = dr.backend_v(float_t) == dr.JitBackend.CUDA
        self.cuda, self.float_t = cuda, float_t
        self.half_t = dr.float16_array_t(float_t) if cuda else None
        tensor32 = dr.tensor_t(float_t)
        tensor = dr.tensor_t(self.half_t) if cuda else tensor32
        sc, sh = np.asarray(out_scale, np.float64), np.asarray(out_shift, np.float64)
        mods, shapes = [], []
        for i, (W, b) in enumerate(layers):
            o, k = (int(v) for v in W.shape)
            shapes.append((o, k))
            mods.append(nn.Linear(k, o))
            if i < len(layers) - 1:
                mods.append(nn.Tanh() if activation == "tanh" else nn.ReLU())
        net = nn.Sequential(*mods).alloc(tensor, shapes[0][1])
        differentiable = False
        for i, (W, b) in enumerate(layers):
            o, k = shapes[i]
            w, bb = W.array, b
            if i == len(layers) - 1:                     # shift + scale·(W x + b), folded
                w = w * float_t(np.repeat(sc, k).astype(np.float32))
                bb = dr.fma(bb, float_t(sc.astype(np.float32)), float_t(sh.astype(np.float32)))
            differentiable |= dr.grad_enabled(w) or dr.grad_enabled(bb)
            net[f"layers.{2 * i}.weights"] = tensor(tensor32(w, (o, k)))
            net[f"layers.{2 * i}.bias"] = tensor(tensor32(bb, (o,)))
        self.net = nn.pack(net, layout="training" if differentiable else "inference")
        self.n_out = shapes[-1][0]

    def __call__(self, xs):
        import drjit.nn as nn
        if self.cuda:
            xs = [self.half_t(x) for x in xs]
        out = list(self.net(nn.CoopVec(*xs)))
        return [self.float_t(o) for o in out] if self.cuda else out
