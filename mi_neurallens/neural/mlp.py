"""Small MLPs, evaluated in numpy (float64 reference) and fused into Dr.Jit kernels.

A network is a list of ``(W, b)`` layers, ``W`` of shape (out, in) (PyTorch's ``nn.Linear`` layout),
``y = W x + b``, with the activation after every layer but the last.

The Dr.Jit evaluation (:func:`mlp_dr`) unrolls every multiply-add with the weights as Python-float
**literals** (notes §4: the fastest fp32-exact way on the LLVM backend; the kernel is cached per
weight set) — or, given a :class:`KernelParams` pool, as opaque scalars (kernel parameters), so that
every network of one architecture compiles to the same kernel.  How it spends the operations is the
backend's **style** (:data:`MLP_STYLES`, :func:`mlp_style`): on the CPU four interleaved partial sums per
neuron and a minimax 7/6 rational tanh (:func:`tanh_minimax`), clamped to ±7, maximum error 1.2e-6 in
float32; on CUDA one multiply-add chain per neuron and tanh from the GPU's exp2 and reciprocal
(:func:`tanh_exp2`): a third fewer machine instructions there (counted in the compiled kernels' SASS).
Training evaluates Eigen's 13/6 rational (:func:`tanh_eigen`, maximum error 2.6e-7) or ``torch.tanh``.  On the
CPU the render-time tanh and float32 move a bundled camera map's outputs by up to about a fifth of its own
error, median (the EF 24-70's directions; ``benchmarks/bench_mlp.py``, docs/performance.md "The render-time
tanh").  Float64 inputs get the exact
tanh: that is the maps' numpy reference path.  It is plain Dr.Jit arithmetic on the float type of its
inputs, so it runs in any Mitsuba variant (``mi.Float``).
"""
from __future__ import annotations

import contextlib
import os

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


#: a minimax rational of the form x·N(x²)/D(x²) (N, D in ascending powers of x², D's first 1) on [0, 7]: 6
#: multiply-adds where Eigen's has 9, maximum error 9.0e-7 in float64 and 1.2e-6 evaluated in float32.  Fitted by
#: Loeb's linearised least squares with Lawson's weights moving toward the largest errors; at the clamp it is
#: 0.9999992, so it stays within ±1 and continuous
TANH_MINIMAX_N = (0.9999956876832581, 0.12302166530294488, 0.0022769744824863852, 3.929948006950457e-06)
TANH_MINIMAX_D = (1.0, 0.45634014989381044, 0.021072111668128765, 0.00014234931101998402)
TANH_MINIMAX_CLAMP = 7.0
#: floating-point operations of one :func:`tanh_minimax` (the clamp's 2, x² 1, two 3-term Horner chains as 6
#: multiply-adds, the product and the division): what a map's FLOP count charges a tanh
TANH_FLOPS = 17


def tanh_minimax(x):
    """The CPU style's tanh on Dr.Jit floats: clamp to ±:data:`TANH_MINIMAX_CLAMP`, then x·N(x²)/D(x²)
    (:data:`TANH_MINIMAX_N`, :data:`TANH_MINIMAX_D`): a third fewer multiply-adds than :func:`tanh_eigen`, at
    4.6 times its error (1.2e-6 against 2.6e-7 in float32, absolute), which makes the camera maps faster on the
    CPU, where the activation is about a third of their cost."""
    import drjit as dr
    n, d = TANH_MINIMAX_N, TANH_MINIMAX_D
    x = dr.clip(x, -TANH_MINIMAX_CLAMP, TANH_MINIMAX_CLAMP)
    u = x * x
    p = dr.fma(u, dr.fma(u, dr.fma(u, n[3], n[2]), n[1]), n[0])
    q = dr.fma(u, dr.fma(u, dr.fma(u, d[3], d[2]), d[1]), d[0])
    return x * p / q


#: 2/ln 2: tanh(x) = 1 − 2 / (1 + 2^(x · 2/ln 2))
_TWO_OVER_LN2 = 2.8853900817779268


def tanh_exp2(x):
    """tanh from an exponential and a reciprocal: ``1 − 2 / (1 + 2^(2x/ln 2))`` on Dr.Jit floats.

    On CUDA in float32 (fast math, Dr.Jit's default) ``dr.exp2`` and ``dr.rcp`` are the hardware's
    ``ex2.approx.ftz`` and ``rcp.approx.ftz`` (2 and 1 ulp), which run on the special-function units beside
    the FMA pipes: 3 FMA-pipe instructions a tanh against 13 (and a division) for :func:`tanh_eigen`.  No
    clamp is needed: 2^(big) is inf and 1/inf is 0, 2^(−big) flushes to 0.  The error is absolute, about
    1e-7 near 0 (where 1 − 2·½ cancels), which the next layer's sum sees the same as :func:`tanh_eigen`'s
    2.6e-7.  On the CPU ``exp2`` is a polynomial and ``rcp`` a division, which makes it slower than
    :func:`tanh_minimax` there (:func:`mlp_style`)."""
    import drjit as dr
    t = dr.exp2(x * _TWO_OVER_LN2)
    return dr.fma(dr.rcp(t + 1.0), -2.0, 1.0)


#: how :func:`mlp_dr` spends a network's operations, per style: (partial sums per neuron, tanh in float32)
MLP_STYLES = {
    # CPU (LLVM): one SIMD lane per ray, so an FMA chain's latency is the ray's; 4 interleaved partial
    # sums (measured on 2 AVX-512 cores, classifier + regressor: 1 chain 9.1, 2 chains 10.8, 4 chains
    # 11.5 M rays/s) and a rational tanh (exp2 is a polynomial on the CPU): the minimax 7/6 (tanh_minimax)
    "cpu": (4, tanh_minimax),
    # GPU (CUDA): other warps hide an FMA's latency, so the partial sums' pairwise adds are only extra
    # instructions (one chain per neuron), and tanh from the special-function units (tanh_exp2)
    "gpu": (1, tanh_exp2),
}

#: the environment variable that overrides :func:`mlp_style` (``cpu`` or ``gpu``; benchmarks compare them)
STYLE_ENV = "MI_NEURALLENS_MLP_STYLE"


@contextlib.contextmanager
def forced_style(style: str | None):
    """Within the block, kernels traced use ``style`` (a key of :data:`MLP_STYLES`; None: as the backend
    chooses); the environment is restored after.  For benchmarks that time both styles in one process."""
    old = os.environ.get(STYLE_ENV)
    if style is not None:
        os.environ[STYLE_ENV] = style
    try:
        yield
    finally:
        if style is not None:
            if old is None:
                os.environ.pop(STYLE_ENV, None)
            else:
                os.environ[STYLE_ENV] = old


def mlp_style(like) -> str:
    """``"gpu"`` for a CUDA Dr.Jit array ``like``, ``"cpu"`` otherwise, unless :data:`STYLE_ENV` names one
    of :data:`MLP_STYLES`.  Read each time a kernel is traced, so a process can time both."""
    import drjit as dr
    forced = os.environ.get(STYLE_ENV, "").strip().lower()
    if forced and forced != "auto":
        if forced not in MLP_STYLES:
            raise ValueError(f"{STYLE_ENV}={forced!r}: use one of {sorted(MLP_STYLES)} or auto")
        return forced
    return "gpu" if dr.backend_v(like) == dr.JitBackend.CUDA else "cpu"


def _tanh(x, style: str = "cpu"):
    """tanh for :func:`mlp_dr`: in float32 the ``style``'s approximation (:data:`MLP_STYLES`; both exact to
    about 1e-6), Dr.Jit's own tanh in float64 (the numpy reference path of the maps)."""
    import drjit as dr
    return dr.tanh(x) if dr.type_v(x) == dr.VarType.Float64 else MLP_STYLES[style][1](x)


def mlp_np(x: np.ndarray, layers, activation: str = "tanh") -> np.ndarray:
    """Reference evaluation, float64: ``x`` (N, in) → (N, out)."""
    h = np.asarray(x, dtype=np.float64)
    act = np.tanh if activation == "tanh" else (lambda v: np.maximum(v, 0.0))
    for i, (W, b) in enumerate(layers):
        h = h @ np.asarray(W, dtype=np.float64).T + np.asarray(b, dtype=np.float64)
        if i < len(layers) - 1:
            h = act(h)
    return h


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


def mlp_dr(xs, layers, activation: str = "tanh", params: KernelParams | None = None, tag="mlp",
           first_params: KernelParams | None = None):
    """Fused Dr.Jit evaluation: ``xs`` a list of Dr.Jit floats (one per input) → list of outputs.
    Weights become kernel literals (a kernel per weight set, cached by Dr.Jit), or with ``params`` kernel
    parameters named ``(tag, layer, row, column)`` (one kernel per architecture; zero weights then stay in,
    so that the source does not depend on the values); ``first_params``: the first layer's from these instead
    (a configured map's folded first layer, :meth:`~mi_neurallens.neural.model.NeuralMap.condition_fold`).  Each neuron's dot
    product is split into the style's interleaved partial sums added pairwise at the end (on the CPU, so
    the multiply-adds do not form one long dependency chain), and tanh is the style's (:func:`mlp_style`:
    per backend)."""
    import drjit as dr
    h = list(xs)
    like = h[0]
    style = mlp_style(like)
    accumulators = MLP_STYLES[style][0]
    outer = params
    for li, (W, b) in enumerate(layers):
        params = first_params if (li == 0 and first_params is not None) else outer
        W = np.asarray(W, dtype=np.float64).tolist()
        b = np.asarray(b, dtype=np.float64).tolist()
        out = []
        for j in range(len(b)):
            parts = [None] * accumulators
            seeded = accumulators == 1             # one chain: it starts from the bias (no add at the end)
            if seeded:
                parts[0] = bj = number(params, (tag, li, j, "b"), b[j], like)
            terms = 0
            for i in range(len(h)):
                w = float(W[j][i])
                if w == 0.0 and params is None:
                    continue
                w = number(params, (tag, li, j, i), w, like)
                k = i % accumulators
                parts[k] = h[i] * w if parts[k] is None else dr.fma(h[i], w, parts[k])
                terms += 1
            if not seeded:                          # created after the weights, as always on the CPU (same kernel)
                bj = number(params, (tag, li, j, "b"), b[j], like)
            if not terms:
                out.append(h[0] * 0.0 + bj)
                continue
            parts = [p for p in parts if p is not None]
            if not seeded:
                parts[0] = parts[0] + bj
            while len(parts) > 1:
                parts = [parts[a] + parts[a + 1] if a + 1 < len(parts) else parts[a]
                         for a in range(0, len(parts), 2)]
            out.append(parts[0])
        if li < len(layers) - 1:
            out = [_tanh(v, style) for v in out] if activation == "tanh" else [dr.maximum(v, 0.0) for v in out]
        h = out
    return h
