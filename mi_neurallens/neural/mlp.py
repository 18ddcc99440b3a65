"""Small MLPs, evaluated in numpy (float64 reference) and fused into Dr.Jit kernels.

A network is a list of ``(W, b)`` layers, ``W`` of shape (out, in) (PyTorch's ``nn.Linear`` layout),
``y = W x + b``, with the activation after every layer but the last.

The Dr.Jit evaluation (:func:`mlp_dr`) unrolls every multiply-add with the weights as Python-float
**literals** (notes §4: the fastest fp32-exact way on the LLVM backend; the kernel is cached per
weight set) — or, given a :class:`KernelParams` pool, as opaque scalars (kernel parameters), so that
every network of one architecture compiles to the same kernel — and uses Eigen's 13/6 rational tanh
(:func:`tanh_eigen`), clamped to ±7.90531, whose maximum error is 2.6e-7 (float64 inputs get the exact
tanh: that is the maps' numpy reference path).  It is plain Dr.Jit arithmetic on the float type of its
inputs, so it runs in any Mitsuba variant (``mi.Float``) and on CUDA.
"""
from __future__ import annotations

import numpy as np

TANH_CLAMP = 7.90531110763549805
TANH_P = (4.89352455891786e-3, 6.37261928875436e-4, 1.48572235717979e-5, 5.12229709037114e-8,
       -8.60467152213735e-11, 2.00018790482477e-13, -2.76076847742355e-16)
TANH_Q = (4.89352518554385e-3, 2.26843463243900e-3, 1.18534705686654e-4, 1.19825839466702e-6)

ACTIVATIONS = ("tanh", "relu")


def tanh_eigen(x):
    """Eigen's rational tanh on Dr.Jit floats (or numpy): clamp, then x·P(x²)/Q(x²)."""
    import drjit as dr
    if isinstance(x, np.ndarray):
        x = np.clip(x, -TANH_CLAMP, TANH_CLAMP)
        x2 = x * x
        p = TANH_P[6]
        for c in reversed(TANH_P[:6]):
            p = p * x2 + c
        q = TANH_Q[3]
        for c in reversed(TANH_Q[:3]):
            q = q * x2 + c
        return x * p / q
    x = dr.clip(x, -TANH_CLAMP, TANH_CLAMP)
    x2 = x * x
    p = dr.fma(x2, TANH_P[6], TANH_P[5])
    for c in reversed(TANH_P[:5]):
        p = dr.fma(x2, p, c)
    q = dr.fma(x2, TANH_Q[3], TANH_Q[2])
    for c in reversed(TANH_Q[:2]):
        q = dr.fma(x2, q, c)
    return x * p / q


def _tanh(x):
    """tanh for :func:`mlp_dr`: the rational approximation in float32 (exact to float32 rounding, and
    the fast path), Dr.Jit's own tanh in float64 (the numpy reference path of the maps)."""
    import drjit as dr
    return dr.tanh(x) if dr.type_v(x) == dr.VarType.Float64 else tanh_eigen(x)


def mlp_np(x: np.ndarray, layers, activation: str = "tanh") -> np.ndarray:
    """Reference evaluation, float64: ``x`` (N, in) → (N, out)."""
    h = np.asarray(x, dtype=np.float64)
    act = np.tanh if activation == "tanh" else (lambda v: np.maximum(v, 0.0))
    for i, (W, b) in enumerate(layers):
        h = h @ np.asarray(W, dtype=np.float64).T + np.asarray(b, dtype=np.float64)
        if i < len(layers) - 1:
            h = act(h)
    return h


#: independent partial sums per neuron in :func:`mlp_dr`: breaks the serial FMA dependency chain
#: (measured on 2 AVX-512 cores, classifier + regressor: 1 chain 9.1, 2 chains 10.8, 4 chains
#: 11.5 M rays/s)
ACCUMULATORS = 4


def mlp_cost(layers) -> tuple:
    """(multiply-adds, activations) of one evaluation of the network ``layers`` ([(W (out, in), b), ...]):
    the weight matrices' sizes, and the hidden layers' widths (the output layer is linear)."""
    fma = sum(int(np.shape(W)[0]) * int(np.shape(W)[1]) for W, _ in layers)
    act = sum(int(np.shape(W)[0]) for W, _ in layers[:-1])
    return fma, act


class KernelParams:
    """The numbers of one learned map as **kernel parameters**: opaque Dr.Jit scalars instead of literals.

    A literal is part of the kernel's source, so every weight set compiles its own kernel (2–7 s each on a
    CPU; a flare with 32 learned ghosts compiled 32 of them).  Opaque scalars are inputs of the kernel: maps
    of one architecture then produce the same source and share one compiled kernel (Dr.Jit's in-memory and
    disk caches), at the price of a longer compilation of that one kernel when every weight is one (LLVM
    loads them all at the top of the kernel): on LLVM, ``mlp = "shared"`` therefore passes the networks'
    weights as packed cooperative-vector buffers and keeps these scalars for the map's other numbers
    (:func:`~mi_neurallens.neural.model.packed_networks`).  ``params(key, value, like)``
    returns the scalar named ``key`` (any hashable, stable across evaluations) holding ``value`` in the
    float type of the Dr.Jit array ``like``; it is created once and reused while its value is unchanged."""

    def __init__(self):
        self._vars = {}

    def __call__(self, key, value, like):
        import drjit as dr
        value = float(value)
        t = type(like)
        k = (t, key)
        hit = self._vars.get(k)
        if hit is None or hit[0] != value:
            hit = (value, dr.opaque(t, value))
            self._vars[k] = hit
        return hit[1]

    def __len__(self):
        return len(self._vars)


def number(params, key, value, like):
    """``value`` for a kernel: a Python-float literal without ``params``, else ``params``'s opaque scalar."""
    return float(value) if params is None else params(key, value, like)


def mlp_dr(xs, layers, activation: str = "tanh", params: KernelParams | None = None, tag="mlp"):
    """Fused Dr.Jit evaluation: ``xs`` a list of Dr.Jit floats (one per input) → list of outputs.
    Weights become kernel literals (a kernel per weight set, cached by Dr.Jit), or with ``params`` kernel
    parameters named ``(tag, layer, row, column)`` (one kernel per architecture; zero weights then stay in,
    so that the source does not depend on the values).  Each neuron's dot
    product is split into :data:`ACCUMULATORS` interleaved partial sums added pairwise at the end, so
    the multiply-adds do not form one long dependency chain."""
    import drjit as dr
    h = list(xs)
    like = h[0]
    for li, (W, b) in enumerate(layers):
        W = np.asarray(W, dtype=np.float64).tolist()
        b = np.asarray(b, dtype=np.float64).tolist()
        out = []
        for j in range(len(b)):
            parts = [None] * ACCUMULATORS
            for i in range(len(h)):
                w = float(W[j][i])
                if w == 0.0 and params is None:
                    continue
                w = number(params, (tag, li, j, i), w, like)
                k = i % ACCUMULATORS
                parts[k] = h[i] * w if parts[k] is None else dr.fma(h[i], w, parts[k])
            bj = number(params, (tag, li, j, "b"), b[j], like)
            parts = [p for p in parts if p is not None]
            if not parts:
                out.append(h[0] * 0.0 + bj)
                continue
            parts[0] = parts[0] + bj
            while len(parts) > 1:
                parts = [parts[a] + parts[a + 1] if a + 1 < len(parts) else parts[a]
                         for a in range(0, len(parts), 2)]
            out.append(parts[0])
        if li < len(layers) - 1:
            out = [_tanh(v) for v in out] if activation == "tanh" else [dr.maximum(v, 0.0) for v in out]
        h = out
    return h
