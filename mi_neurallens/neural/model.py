"""The neural lens model file: per-path lens transport maps (classifier + regressor) of one lens.

File format (``*.model.safetensors``, format version 1)
-------------------------------------------------------
A `safetensors <https://huggingface.co/docs/safetensors>`_ file (never pickle).  Its
``__metadata__`` string map holds ``format`` = ``"mi-neurallens-transport-maps"``,
``format_version`` = ``"1"`` and ``model`` = a JSON document::

    {"format_version": 1,
     "lens": {"name": ..., "fingerprint": ...},          # Lens.fingerprint() of the trained lens
     "planes": {"z_front_mm": ..., "z_rear_mm": ..., "z_last_vertex_mm": ...},
     "sensor_distance_mm": [min, max],                    # behind the last vertex; any value works
     "maps": [{"key": "backward.0", "path_id": 0, "direction": "backward",
               "z_in_mm": ..., "z_out_mm": ...,           # lens-space planes of this map
               "domain": {"r_max_mm", "s_max", "lambda_min_nm", "lambda_max_nm"},
               "input_norm": {"center": [4], "scale": [4]},       # xn = (x − center) / scale
               "classifier": {"layers": [4, 32, 32, 1], "activation": "tanh"},
               "regressor": {"layers": [4, 32, 32, 32, 32, 32, 5], "activation": "tanh",
                             "outputs": ["x", "y", "dx", "dy", "throughput"]},
               "stop": {"layers": [4, 32, 32, 32, 2k], "activation": "tanh",   # optional: the
                        "crossings": k, "odd_y": true, "training": {...}, "metrics": {...}},  # stop head
               "training": {...}, "metrics": {...}}, ...],
     "ghost_ranking": [...], "created": ..., "software": ...}

Tensors of map ``K`` (float32): ``K.classifier.{i}.weight`` (out, in), ``K.classifier.{i}.bias``,
``K.regressor.{i}.weight``, ``K.regressor.{i}.bias``, ``K.regressor.skip.weight`` (5, 4) and
``K.regressor.out_scale`` / ``K.regressor.out_shift`` (5,); with a stop head ``K.stop.{i}.weight`` /
``.bias``, ``K.stop.skip.weight`` (2k, 4), ``K.stop.out_scale`` / ``K.stop.out_shift`` (2k,).

Evaluation of one map on reduced inputs x = (r, ωx, ωy, λ) (see :mod:`mi_neurallens.trace.symmetry`):
``xn = (x − center)/scale``; valid iff ``classifier(xn) > 0`` (a logit) and x lies in the domain;
``y = M · (out_shift + out_scale · regressor(xn) + skip · xn)`` = (x, y) exit position on ``z_out``,
(dx, dy) exit direction (dz = ±√(1 − dx² − dy²), + forward, − backward), Fresnel throughput — all in
the reduced frame, undone to lens space by :func:`~mi_neurallens.trace.symmetry.undo`.  ``M`` is 1,
except for maps whose regressor metadata says ``"odd_y": true``: there the y and dy outputs are
multiplied by ωy / s_max, which makes them exactly odd under the mirror reduction ωy → −ωy (y = dy = 0
on the mirror plane, as the exact tracer gives), so the undo leaves no seam across that plane.  Maps whose
regressor metadata says ``"position_cos": true`` regress the exit position times |dz| (:func:`position_cos`; a
fisheye's camera map) and divide by their predicted |dz| after ``M``.

The optional **stop head** (:class:`StopHead`) predicts, from the same normalised inputs, where the ray
crosses the aperture-stop plane — ``k`` crossings ``(sx, sy)`` in the reduced frame, ``sy`` odd like
``y`` — with the iris at the widest opening the classifier learned.  At render time
:attr:`NeuralMap.iris` tests those crossings against any smaller or bladed iris
(:mod:`mi_neurallens.trace.iris`), so one map renders every aperture.  Files without it load as before
(the aperture is then fixed at the trained one).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
import json
import math
import os
import struct

import numpy as np

from ..errors import ModelError
from ..fileio import jsonable
from ..transport.base import TransportMap
from ..transport.planning import Domain
from .coopvec import packed
from .mlp import ACTIVATIONS, TANH_FLOPS, KernelParams, mlp_cost, mlp_dr, number

#: the training record's loss curves (lists under a ``*history`` key; read by people, never by the renderer) keep
#: 4 significant digits and at most HISTORY_POINTS validations (the first, the last and evenly spaced ones between;
#: the training log has them all): at full length and precision they were most of a model file's bytes
HISTORY_KEY_DIGITS = {"history": 4}
HISTORY_POINTS = 16


def _thin_histories(o):
    """``o`` with every list under a ``*history`` key cut to :data:`HISTORY_POINTS` entries."""
    if isinstance(o, dict):
        out = {}
        for k, v in o.items():
            if str(k).endswith("history") and isinstance(v, list) and len(v) > HISTORY_POINTS:
                v = [v[int(i)] for i in np.unique(np.round(np.linspace(0, len(v) - 1, HISTORY_POINTS)))]
            out[k] = _thin_histories(v)
        return out
    if isinstance(o, list):
        return [_thin_histories(v) for v in o]
    return o

FORMAT = "mi-neurallens-transport-maps"
FORMAT_VERSION = 1
OUTPUTS = ("x", "y", "dx", "dy", "throughput")
#: how a learned map's networks are evaluated in a kernel (:class:`NeuralMap`'s ``mlp``)
MLP_MODES = ("fused", "shared", "coopvec")
#: the modes whose kernels take the map's numbers (normalisation, skip, domain, planes) as kernel parameters,
#: so that all maps of one architecture share one compiled kernel
PARAM_MODES = ("shared", "coopvec")


def packed_networks(mlp: str, like) -> bool:
    """Whether ``mlp`` evaluates the networks through Dr.Jit cooperative vectors (weights in one packed
    buffer per network) rather than unrolled multiply-adds: always for ``"coopvec"``; for ``"shared"`` on
    the LLVM backend, where it is the same fp32 arithmetic (to ~1e-6) and compiles several times sooner than one
    opaque scalar per weight, with one upload per network instead of one per weight; on CUDA ``"shared"`` keeps fp32 opaque scalars (its cooperative vectors are fp16), and in
    float64 (``like``: the Dr.Jit input array) it keeps them too."""
    if mlp == "coopvec":
        return True
    if mlp != "shared":
        return False
    import drjit as dr
    return dr.backend_v(like) == dr.JitBackend.LLVM and dr.type_v(like) == dr.VarType.Float32


def _network(owner, name: str, layers, activation: str, xn, params, use_packed: bool, fold=None) -> list:
    """One network of ``owner`` (a map or stop head) on the normalised inputs ``xn``: through its packed
    cooperative-vector buffer (:func:`~mi_neurallens.neural.coopvec.packed`) or unrolled (literals, or
    ``params``' scalars tagged ``name``).  ``fold``: a :class:`ConditionFold` (then ``xn`` are the ray's four)."""
    if fold is not None:
        return mlp_dr(xn, [fold.first[name]] + list(layers[1:]), activation, params, name + ".configured", fold.pool)
    if use_packed:
        return packed(owner, name, layers, activation, xn[0])(xn)
    return mlp_dr(xn, layers, activation, params, name)


def _fold(layers, out_scale, out_shift):
    """``layers`` (float64) with the output transform ``shift + scale·y`` folded into the last layer."""
    layers = [(np.asarray(W, np.float64), np.asarray(b, np.float64)) for W, b in layers]
    W, b = layers[-1]
    sc, sh = np.asarray(out_scale, np.float64), np.asarray(out_shift, np.float64)
    layers[-1] = (W * sc[:, None], b * sc + sh)
    return layers


def _add_skip(y, xn, skip, params=None, tag="skip", fold=None):
    """``y + skip·xn`` on lists of Dr.Jit floats: the linear skip term (zero coefficients skipped, except
    with kernel ``params``, where the source must not depend on the values).  ``fold``: a :class:`ConditionFold`
    (``xn`` the ray's four; the folded skip and its constant, ``tag`` naming which, from its pool)."""
    import drjit as dr
    if fold is not None:
        A, c = fold.skip[tag]
        for j in range(len(y)):
            y[j] = y[j] + fold.pool(("fold", tag, "c", j), c[j], xn[0])
            for i in range(len(xn)):
                y[j] = dr.fma(xn[i], fold.pool(("fold", tag, j, i), A[j, i], xn[i]), y[j])
        return y
    A = np.asarray(skip, np.float64)
    for j in range(len(y)):
        for i in range(len(xn)):
            if A[j, i] != 0.0 or params is not None:
                y[j] = dr.fma(xn[i], number(params, (tag, j, i), A[j, i], xn[i]), y[j])
    return y


@dataclass(frozen=True)
class ConditionFold:
    """A configured map's networks on the ray's four inputs alone.

    With its configuration fixed (:attr:`NeuralMap.condition_values`), a map's condition inputs are constants and its
    product inputs (:attr:`~mi_neurallens.transport.configurations.Configurations.monomials`) are linear in the
    ray's r, ωx, ωy, so every normalised input is an affine function of the ray's four normalised ones,
    ``xn = A·xn₄ + c``: each network's first layer (W, b) becomes (W·A, W·c + b), each linear skip S becomes S·A
    plus the constant S·c — the same function, in float64, before rounding to the kernel's float type.  The EF
    24-70's 33 inputs become 4 (its three first layers and two skips: 2 400 fewer of its ~6 500 multiply-adds a ray).  The
    folded numbers are kernel parameters (``pool``), so another zoom or focus compiles nothing.  Applied where the
    networks are literals (``mlp = "fused"``, what ``neural_lens`` renders with)."""
    first: dict         # network name ("classifier", "regressor", "stop") → its first layer (W (H, 4), b (H,))
    skip: dict          # skip tag ("regressor.skip", "stop.skip") → (S·A (k, 4), S·c (k,))
    pool: KernelParams


@dataclass
class StopHead:
    """Where a learned map's rays cross the aperture-stop plane: ``crossings`` = k points, an MLP on the
    map's normalised inputs with a linear skip, outputs ``M·(out_shift + out_scale·net(xn) + skip·xn)``
    = (sx₁, sy₁, …, sx_k, sy_k) in the reduced frame (mm on the stop plane, lens space z = the stop's
    vertex), ``M`` = ωy/s_max on the sy columns when ``odd_y``.  ``layers``: (W, b) numpy layers."""

    crossings: int
    layers: list
    skip: np.ndarray
    out_scale: np.ndarray
    out_shift: np.ndarray
    activation: str = "tanh"
    odd_y: bool = True
    training: dict = field(default_factory=dict)
    metrics: dict = field(default_factory=dict)

    def _folded(self):
        if getattr(self, "_fold", None) is None:
            self._fold = _fold(self.layers, self.out_scale, self.out_shift)
        return self._fold

    def eval_dr(self, x, xn, s_max: float, params: KernelParams | None = None, coopvec: bool = False, fold=None):
        """Reduced inputs ``x`` and their normalised ``xn`` (Dr.Jit) → the 2k outputs (Dr.Jit list);
        ``params``: the map's kernel parameters (None: literals); ``coopvec``: the network through Dr.Jit's
        cooperative vectors (weights in a packed buffer), the rest with ``params``; ``fold``: the map's
        :class:`ConditionFold` (``xn`` then the ray's four)."""
        net = _network(self, "stop", self._folded(), self.activation, xn, params, coopvec, fold)
        y = _add_skip(net, xn, self.skip, params, "stop.skip", fold)
        if self.odd_y:
            m = x[2] * number(params, "stop.1/s_max", 1.0 / float(s_max), x[2])
            for j in range(1, len(y), 2):
                y[j] = y[j] * m
        return y

    def flops(self) -> int:
        fma, act = mlp_cost(self.layers)
        return 2 * fma + TANH_FLOPS * act + 2 * 4 * 2 * self.crossings

    def meta(self) -> dict:
        return {"layers": _widths(self.layers), "activation": self.activation, "crossings": int(self.crossings),
                "odd_y": bool(self.odd_y), "training": self.training, "metrics": self.metrics}

    def tensors(self, key: str) -> dict:
        t = {}
        for i, (W, b) in enumerate(self.layers):
            t[f"{key}.stop.{i}.weight"] = np.ascontiguousarray(W, np.float32)
            t[f"{key}.stop.{i}.bias"] = np.ascontiguousarray(b, np.float32)
        t[f"{key}.stop.skip.weight"] = np.ascontiguousarray(self.skip, np.float32)
        t[f"{key}.stop.out_scale"] = np.ascontiguousarray(self.out_scale, np.float32)
        t[f"{key}.stop.out_shift"] = np.ascontiguousarray(self.out_shift, np.float32)
        return t


@dataclass
class NeuralMap(TransportMap):
    """One learned (path, direction) map: a :class:`~mi_neurallens.transport.base.TransportMap` whose
    core, in the symmetry-reduced frame, is the classifier (valid iff its logit > 0) then the regressor.
    ``classifier``/``regressor``: lists of (W, b) numpy layers.

    ``stop_head``: optional :class:`StopHead` (the stop-plane crossings, appended to the core's outputs).

    Render-time options (not stored in the file): ``iris`` (an :class:`~mi_neurallens.trace.iris.Iris`
    inside the trained opening, tested on the stop head's crossings; None: the trained aperture),
    ``use_classifier`` (``False``: the paper's ablation,
    every in-domain ray is valid and the classifier is not evaluated at all) and ``mlp`` (``"fused"``:
    weights as kernel literals, the backend's tanh in float32 (:func:`~mi_neurallens.neural.mlp.mlp_style`),
    exact tanh in float64; ``"shared"``: every number
    of the map a kernel input, so that all maps of one architecture share one compiled kernel — the
    normalisation, skip, domain and planes as opaque scalars (:class:`~mi_neurallens.neural.mlp.KernelParams`),
    the networks' weights in packed cooperative-vector buffers on LLVM, as opaque scalars on CUDA
    (:func:`packed_networks`); ``"coopvec"``: the networks through Dr.Jit cooperative vectors on every
    backend (fp16 on CUDA), the other numbers as for ``"shared"``, :mod:`mi_neurallens.neural.coopvec`)."""

    path_id: int
    direction: str
    z_in: float
    z_out: float
    domain: Domain
    input_center: np.ndarray
    input_scale: np.ndarray
    classifier: list
    regressor: list
    skip: np.ndarray
    out_scale: np.ndarray
    out_shift: np.ndarray
    classifier_activation: str = "tanh"
    regressor_activation: str = "tanh"
    odd_y: bool = False            # y, dy outputs multiplied by ωy / s_max (see the module docstring)
    #: the x, y outputs are the exit position times |dz| (:func:`position_cos`): a ray leaving the lens nearly
    #: parallel to the output plane (a fisheye's camera map, 90° off axis) crosses it far away, a number no network
    #: regresses; its product with |dz| stays within the lens
    position_cos: bool = False
    training: dict = field(default_factory=dict)
    metrics: dict = field(default_factory=dict)
    stop_head: StopHead | None = None
    use_classifier: bool = field(default=True, compare=False)
    mlp: str = field(default="fused", compare=False)
    iris: object = field(default=None, compare=False)
    #: the opaque scalars of ``mlp = "shared"``; one pool per map, handed on by ``dataclasses.replace``
    params_pool: KernelParams | None = field(default=None, compare=False, repr=False)
    #: the regressor with its weights as Dr.Jit arrays (a :class:`~mi_neurallens.neural.coopvec.LiveNetwork`, the
    #: output transform folded in), replacing :attr:`regressor` in Dr.Jit evaluations in float32: ``neural_lens``
    #: after ``params.update()`` changed a weight (docs/differentiable.md); None: :attr:`regressor`
    live_regressor: object = field(default=None, compare=False, repr=False)
    #: a map of a lens with moving groups (its domain's ``conditions``): the configuration it renders, its condition
    #: inputs in the domain's order (zoom parameter, focus parameter), kernel inputs beside the ray's four; None
    #: where the map has none, or where every ray brings its own (training, evaluation)
    condition_values: tuple | None = field(default=None, compare=False)
    #: evaluate a configured map (:attr:`condition_values`) through its :class:`ConditionFold` (False: the networks'
    #: full inputs, as trained; the two agree to the float type's rounding)
    fold_conditions: bool = field(default=True, compare=False)

    method = "neural"
    reduced = True

    def __post_init__(self):
        self.domain = Domain.from_dict(self.domain)
        if self.mlp not in MLP_MODES:
            raise ModelError(f"unknown MLP evaluation {self.mlp!r}: use one of {MLP_MODES}")
        if self.params_pool is None:
            self.params_pool = KernelParams()

    @property
    def params(self) -> KernelParams | None:
        """The kernel parameters of this map's numbers (``mlp = "shared"`` or ``"coopvec"``), or None
        (literals)."""
        return self.params_pool if self.mlp in PARAM_MODES else None

    def number(self, key, value, like):
        """A number as it enters the kernel (:meth:`TransportMap.number
        <mi_neurallens.transport.base.TransportMap.number>`): with ``mlp`` shared or coopvec a kernel parameter;
        with literal networks a literal, except a configured map's planes (``z_in``, ``z_out``: they move with the
        zoom and focus), which are parameters of its :class:`ConditionFold`'s pool like its folded layers, so that
        another configuration compiles nothing."""
        if self.params is None and key in ("z_in", "z_out"):
            fold = self.condition_fold()
            if fold is not None:
                return fold.pool(("fold", "plane", key), value, like)
        return number(self.params, key, value, like)

    @property
    def stop_crossings(self) -> int:
        return self.stop_head.crossings if self.stop_head is not None else 0

    def _folded(self):
        """Regressor layers with out_scale/out_shift folded into the last layer (float64)."""
        if getattr(self, "_fold", None) is None:
            self._fold = _fold(self.regressor, self.out_scale, self.out_shift)
        return self._fold

    def flops(self) -> int:
        """Per ray: the multiply-adds of both networks, :data:`~.mlp.TANH_FLOPS` per tanh (the CPU's), 40 for the
        symmetry reduction, domain test and undo, 40 for the skip connection (a configured map: its
        :class:`ConditionFold`'s first layers, with literal networks)."""
        fold = self.condition_fold() if self.mlp not in PARAM_MODES else None
        f = 0
        for name, layers in (("classifier", self.classifier), ("regressor", self.regressor)):
            fma, act = mlp_cost([fold.first[name]] + list(layers[1:]) if fold is not None else layers)
            f += 2 * fma + TANH_FLOPS * act
        if self.stop_head is not None and self.iris is not None:
            sh = self.stop_head
            if fold is not None:
                sh = dataclasses.replace(sh, layers=[fold.first["stop"]] + list(sh.layers[1:]))
            f += sh.flops()
        return f + 40 + 2 * 5 * 4

    # ------------------------------------------------------------------ reduced-frame core
    def normalise_np(self, x):
        return (np.asarray(x, np.float64) - self.input_center) / self.input_scale

    def eval_reduced_dr(self, x, mlp: str | None = None):
        """Reduced inputs (4 Dr.Jit floats) → (logit, [5 outputs, then 2k stop outputs when the map has
        a stop head]) fused into one kernel.  ``mlp``: one of :data:`MLP_MODES` (default: :attr:`mlp`; the
        stop head is evaluated the same way as the two networks)."""
        import drjit as dr
        mlp = self.mlp if mlp is None else mlp
        P = self.params_pool if mlp in PARAM_MODES else None
        if mlp not in MLP_MODES:
            raise ModelError(f"unknown MLP evaluation {mlp!r}: use one of {MLP_MODES}")
        use_packed = packed_networks(mlp, x[0])
        live = self.live_regressor is not None and dr.type_v(x[0]) == dr.VarType.Float32
        # folded with literal networks only: the shared kernels (``params``) keep one variable list per architecture,
        # recorded once by frozen functions (:meth:`kernel_inputs`)
        fold = self.condition_fold() if (len(x) == 4 and P is None and not live) else None
        if fold is not None:                        # the ray's four inputs only (zip stops at them)
            x = tuple(x)
        else:
            x = self._inputs(x, P)
        xn = [dr.fma(v, number(P, ("norm.a", i), 1.0 / float(s), v), number(P, ("norm.b", i), -float(c) / float(s), v))
              for i, (v, c, s) in enumerate(zip(x, self.input_center, self.input_scale))]
        logit = _network(self, "classifier", self.classifier, self.classifier_activation, xn, P, use_packed, fold)[0]
        if live:
            y = self.live_regressor(xn)
        else:
            y = _network(self, "regressor", self._folded(), self.regressor_activation, xn, P, use_packed, fold)
        y = _add_skip(y, xn, self.skip, P, "regressor.skip", fold)
        if self.odd_y:
            m = x[2] * number(P, "1/s_max", 1.0 / float(self.domain.s_max), x[2])
            y[1], y[3] = y[1] * m, y[3] * m
        if self.position_cos:                       # (x, y)·|dz| → (x, y): :func:`position_cos` undone
            inv = dr.rsqrt(dr.maximum(1.0 - dr.fma(y[2], y[2], y[3] * y[3]), POSITION_COS_MIN ** 2))
            y[0], y[1] = y[0] * inv, y[1] * inv
        if self.stop_head is not None:
            y = list(y) + self.stop_head.eval_dr(x, xn, self.domain.s_max, P, coopvec=use_packed, fold=fold)
        return logit, y

    def condition_fold(self) -> ConditionFold | None:
        """This map's :class:`ConditionFold` at :attr:`condition_values` (cached per configuration), or None: a map
        without conditions, none set, or :attr:`fold_conditions` off."""
        cond = self.domain.conditions
        if (cond is None or self.condition_values is None or not self.fold_conditions
                or len(self.condition_values) != cond.dims):
            return None
        key = tuple(float(v) for v in self.condition_values)
        hit = self.__dict__.get("_condition_fold")
        if hit is not None and hit[0] == key:
            return hit[1]
        center, scale = np.asarray(self.input_center, np.float64), np.asarray(self.input_scale, np.float64)
        X = np.vstack([np.zeros(4), np.eye(4)]) * scale[:4] + center[:4]      # xn₄ = 0 and the unit vectors
        X = np.hstack([X, np.tile(np.array(key), (5, 1))])
        if cond.n_products:
            X = np.hstack([X, cond.products_np(X)])
        XN = (X - center) / scale
        c, A = XN[0], (XN[1:] - XN[0]).T                                     # xn = A·xn₄ + c, A (n_in, 4)
        nets = [("classifier", self.classifier), ("regressor", self._folded())]
        skips = [("regressor.skip", self.skip)]
        if self.stop_head is not None:
            nets.append(("stop", self.stop_head._folded()))
            skips.append(("stop.skip", self.stop_head.skip))
        first = {}
        for name, layers in nets:
            W, b = (np.asarray(v, np.float64) for v in layers[0])
            first[name] = (W @ A, W @ c + b)
        skip = {tag: (np.asarray(S, np.float64) @ A, np.asarray(S, np.float64) @ c) for tag, S in skips}
        fold = ConditionFold(first, skip, self.params_pool)
        self.__dict__["_condition_fold"] = (key, fold)
        return fold

    def _inputs(self, x, P) -> tuple:
        """The networks' inputs from the reduced inputs ``x``: the four of the ray, and for a lens with moving groups
        its configuration — ``x``'s next columns, or :attr:`condition_values` as opaque scalars (a new zoom or focus
        compiles nothing) — and the product inputs computed from them
        (:meth:`~mi_neurallens.transport.configurations.Configurations.products_dr`)."""
        cond = self.domain.conditions
        if cond is None:
            return tuple(x)
        x = tuple(x[:4 + cond.dims]) if len(x) >= 4 + cond.dims else tuple(x[:4]) + self._conditions(x, P)
        return x + tuple(cond.products_dr(x))

    def _conditions(self, x, P) -> tuple:
        """:attr:`condition_values` as kernel inputs (see :meth:`_inputs`)."""
        cond = self.domain.conditions
        if self.condition_values is None or len(self.condition_values) != cond.dims:
            raise ModelError(f"map {self.key} takes the configuration ({', '.join(cond.names)}) as inputs; set "
                             "its condition_values (neural_lens does from focal_length and focus_distance)")
        import drjit as dr
        F = type(x[0])
        return tuple(number(P, ("condition", i), v, x[0]) if P is not None else dr.opaque(F, float(v))
                     for i, v in enumerate(self.condition_values))

    # ------------------------------------------------------------------ frozen kernels
    def kernel_signature(self):
        """What the kernel source of this map depends on besides its numbers, with ``mlp`` in
        :data:`PARAM_MODES` (there every number is a kernel input, so maps of one signature record the same
        kernel and one recording of a frozen function, ``dr.freeze``, serves them all:
        :mod:`mi_neurallens.flare.kernels`); None for literals (the kernel is this map's alone)."""
        if self.mlp not in PARAM_MODES:
            return None
        sh = self.stop_head
        stop = None if sh is None else (tuple(_widths(sh.layers)), sh.activation, int(sh.crossings), bool(sh.odd_y))
        return ("neural", self.mlp, self.direction, bool(self.odd_y), bool(self.position_cos), bool(self.use_classifier),
                tuple(_widths(self.classifier)), self.classifier_activation,
                tuple(_widths(self.regressor)), self.regressor_activation, stop, self.iris)

    def kernel_inputs(self, float_t) -> list:
        """The Dr.Jit variables an evaluation with ``mlp`` in :data:`PARAM_MODES` reads for inputs of the float
        type ``float_t``: its kernel parameters (:class:`~mi_neurallens.neural.mlp.KernelParams`) and packed
        networks, in the order of evaluation — the same list structure for every map of one
        :meth:`kernel_signature`.  A one-lane evaluation (never run) creates them first, at every call: the
        parameter pool is shared with copies of the map (``dataclasses.replace``), and a copy with other numbers
        replaces its variables — one created inside a frozen recording aborts the process."""
        z = float_t(0.0)
        self.eval_dr((z, z, z + (self.z_in - self.heading)), (z, z, z + float(self.heading)), z + 550.0, True)
        pool = [var for (t, _), (_, var) in self.params_pool._vars.items() if t is float_t]
        owners = [self] + ([self.stop_head] if self.stop_head is not None else [])
        nets = [c.net for o in owners for (name, t), c in sorted(o.__dict__.get("_coopvec_cache", {}).items(),
                                                                 key=lambda kv: kv[0][0]) if t is float_t]
        return pool + nets

    def core_reduced_dr(self, x, active):
        logit, y = self.eval_reduced_dr(x)
        valid = (active & (logit > 0.0)) if self.use_classifier else active
        return valid, y, logit

    def eval_reduced_np(self, x):
        """Reduced inputs (N, 4) → (logit (N,), outputs (N, 5 + 2k)), float64, through the Dr.Jit core."""
        _, y, logit = self.core_reduced_np(x)
        return logit, y

    # ------------------------------------------------------------------ (de)serialisation
    def _meta(self) -> dict:
        return {"key": self.key, "path_id": self.path_id, "direction": self.direction,
                "z_in_mm": self.z_in, "z_out_mm": self.z_out, "domain": self.domain.to_dict(),
                "input_norm": {"center": [float(v) for v in self.input_center],
                               "scale": [float(v) for v in self.input_scale]},
                "classifier": {"layers": _widths(self.classifier), "activation": self.classifier_activation},
                "regressor": {"layers": _widths(self.regressor), "activation": self.regressor_activation,
                              "outputs": list(OUTPUTS), "odd_y": bool(self.odd_y),
                              **({"position_cos": True} if self.position_cos else {})},
                "training": self.training, "metrics": self.metrics,
                **({"stop": self.stop_head.meta()} if self.stop_head is not None else {})}

    def _tensors(self) -> dict:
        t = {}
        for name, layers in (("classifier", self.classifier), ("regressor", self.regressor)):
            for i, (W, b) in enumerate(layers):
                t[f"{self.key}.{name}.{i}.weight"] = np.ascontiguousarray(W, np.float32)
                t[f"{self.key}.{name}.{i}.bias"] = np.ascontiguousarray(b, np.float32)
        t[f"{self.key}.regressor.skip.weight"] = np.ascontiguousarray(self.skip, np.float32)
        t[f"{self.key}.regressor.out_scale"] = np.ascontiguousarray(self.out_scale, np.float32)
        t[f"{self.key}.regressor.out_shift"] = np.ascontiguousarray(self.out_shift, np.float32)
        if self.stop_head is not None:
            t.update(self.stop_head.tensors(self.key))
        return t


#: :func:`position_cos` never divides by a |dz| below this (a ray within 0.06° of the output plane)
POSITION_COS_MIN = 1e-3


def position_cos(y: np.ndarray) -> np.ndarray:
    """Reduced-frame outputs ``y`` (N, 5+) with the exit position (columns 0, 1, on the output plane) times |dz| of
    the exit direction (columns 2, 3): what a map with ``position_cos`` regresses.  On a plane at distance h from
    where a ray at angle θ to the axis leaves the lens, the position grows like h·tan θ; times cos θ it is
    h·sin θ, and an error in it is, to first order, the ray's own offset across its direction — the error a
    render sees — however steep the ray.  The map divides by its own predicted |dz| again."""
    y = np.array(y, np.float64, copy=True)
    dz = np.sqrt(np.maximum(1.0 - y[:, 2] ** 2 - y[:, 3] ** 2, POSITION_COS_MIN ** 2))
    y[:, 0] *= dz
    y[:, 1] *= dz
    return y


def _widths(layers):
    return [int(np.shape(layers[0][0])[1])] + [int(np.shape(W)[0]) for W, _ in layers]


@dataclass
class NeuralLensModel:
    """All learned maps of one lens, plus where they live.  Load with :meth:`load`."""

    lens_name: str
    fingerprint: str
    z_front: float
    z_rear: float
    z_last_vertex: float
    sensor_distance_range: tuple
    maps: dict = field(default_factory=dict)          # key -> NeuralMap
    extra: dict = field(default_factory=dict)         # ghost_ranking, created, software, ...
    path: str | None = None

    # ------------------------------------------------------------------ access
    def map(self, path="transmit", direction: str = "backward") -> NeuralMap:
        pid = 0 if path == "transmit" else int(path)
        key = f"{direction}.{pid}"
        if key not in self.maps:
            raise ModelError(f"{self.path or 'model'}: no {direction} map for path {pid}; this model has "
                             f"{sorted(self.maps)}")
        return self.maps[key]

    def has(self, path="transmit", direction: str = "backward") -> bool:
        pid = 0 if path == "transmit" else int(path)
        return f"{direction}.{pid}" in self.maps

    @property
    def ghost_ids(self) -> list[int]:
        """Forward ghost paths with a map, in the order stored (largest energy first)."""
        return [m.path_id for m in self.maps.values() if m.direction == "forward" and m.path_id != 0]

    def check_sensor_distance(self, s_mm: float):
        lo, hi = self.sensor_distance_range
        if not (lo - 1e-9 <= s_mm <= hi + 1e-9):
            why = (f"a nearer focus than its training's close_focus_mm: retrain with a nearer one (`mi-neurallens "
                   f"train LENS --set close_focus_mm=MM`, mm in front of the first vertex)" if s_mm > hi
                   else "a focus beyond infinity")
            raise ModelError(f"{self.path or 'model'}: sensor distance {s_mm:.6g} mm is outside the range this "
                             f"model supports [{lo:.6g}, {hi:.6g}] mm behind the last vertex: {why}")

    # ------------------------------------------------------------------ I/O
    def metadata(self) -> dict:
        return {"format_version": FORMAT_VERSION,
                "lens": {"name": self.lens_name, "fingerprint": self.fingerprint},
                "planes": {"z_front_mm": self.z_front, "z_rear_mm": self.z_rear,
                           "z_last_vertex_mm": self.z_last_vertex},
                "sensor_distance_mm": [float(v) for v in self.sensor_distance_range],
                "maps": [m._meta() for m in self.maps.values()], **self.extra}

    def save(self, path) -> None:
        """Write atomically (temporary file in the same folder, then ``os.replace``)."""
        from safetensors.numpy import save_file
        path = os.fspath(path)
        tensors = {}
        for m in self.maps.values():
            tensors.update(m._tensors())
        meta = {"format": FORMAT, "format_version": str(FORMAT_VERSION),
                "model": json.dumps(jsonable(_thin_histories(self.metadata()), HISTORY_KEY_DIGITS), sort_keys=True)}
        from ..fileio import atomic_write
        atomic_write(path, lambda tmp: save_file(tensors, tmp, metadata=meta))

    @staticmethod
    def load(path, lens=None) -> "NeuralLensModel":
        """Read and validate a model file; with ``lens``, also check it was trained for that lens.
        Every problem raises :class:`~mi_neurallens.errors.ModelError` naming the file."""
        return load_model(path, lens)


def _read_header(path: str):
    try:
        size = os.path.getsize(path)
        with open(path, "rb") as f:
            head = f.read(8)
            if len(head) < 8:
                raise ModelError(f"{path}: not a model file: {size} bytes is too short for a safetensors header")
            (n,) = struct.unpack("<Q", head)
            if n > size - 8 or n > 100_000_000:
                raise ModelError(f"{path}: truncated or not a safetensors file (header claims {n} bytes, "
                                 f"file has {size - 8} after the length)")
            header = json.loads(f.read(n).decode("utf-8"))
    except FileNotFoundError:
        raise ModelError(f"{path}: model file not found") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ModelError(f"{path}: not a safetensors model file (unreadable header: {e})") from None
    end = max((int(v["data_offsets"][1]) for k, v in header.items() if k != "__metadata__"), default=0)
    if 8 + n + end > size:
        raise ModelError(f"{path}: truncated: the tensors need {8 + n + end} bytes, the file has {size}")
    return header


def load_model(path, lens=None) -> NeuralLensModel:
    path = os.fspath(path)
    header = _read_header(path)
    meta = header.get("__metadata__") or {}
    if meta.get("format") != FORMAT:
        raise ModelError(f"{path}: not a mi-neurallens model (metadata 'format' is {meta.get('format')!r}, "
                         f"expected {FORMAT!r})")
    ver = meta.get("format_version")
    if ver != str(FORMAT_VERSION):
        raise ModelError(f"{path}: unknown model format version {ver!r}; this mi-neurallens reads version "
                         f"{FORMAT_VERSION} (retrain with `mi-neurallens train`, or upgrade mi-neurallens)")
    try:
        doc = json.loads(meta["model"])
        lens_fp = doc["lens"]["fingerprint"]
        planes = doc["planes"]
        srange = tuple(float(v) for v in doc["sensor_distance_mm"])
        maps_meta = doc["maps"]
    except (KeyError, TypeError, json.JSONDecodeError) as e:
        raise ModelError(f"{path}: malformed model metadata ({type(e).__name__}: {e})") from None
    if lens is not None and lens.fingerprint() != lens_fp:
        raise ModelError(f"{path}: this model was trained for lens '{doc['lens'].get('name')}' (fingerprint "
                         f"{lens_fp}), not for '{lens.name}' (fingerprint {lens.fingerprint()}); train a model "
                         f"for this lens with `mi-neurallens train`")
    try:
        from safetensors.numpy import load_file
        tensors = load_file(path)
    except Exception as e:  # SafetensorError and friends
        raise ModelError(f"{path}: cannot read tensors ({e})") from None

    def get(name, shape):
        if name not in tensors:
            raise ModelError(f"{path}: missing tensor '{name}'")
        t = tensors[name]
        if tuple(t.shape) != tuple(shape):
            raise ModelError(f"{path}: tensor '{name}' has shape {tuple(t.shape)}, expected {tuple(shape)}")
        if not np.all(np.isfinite(t)):
            raise ModelError(f"{path}: tensor '{name}' contains NaN or infinity")
        return t.astype(np.float64)

    maps = {}
    for mm in maps_meta:
        try:
            key = mm["key"]
            wc, wr = mm["classifier"]["layers"], mm["regressor"]["layers"]
            ac, ar = mm["classifier"].get("activation", "tanh"), mm["regressor"].get("activation", "tanh")
            if ac not in ACTIVATIONS or ar not in ACTIVATIONS:
                raise ModelError(f"{path}: map {key}: unknown activation {ac!r}/{ar!r}; known: {ACTIVATIONS}")
            dom = Domain.from_dict(mm["domain"])
            n_in = dom.n_inputs
            if wc[0] != n_in or wr[0] != n_in or wc[-1] != 1 or wr[-1] != len(OUTPUTS):
                raise ModelError(f"{path}: map {key}: architecture {wc} / {wr} does not map {n_in} inputs to 1 logit "
                                 f"and {len(OUTPUTS)} outputs")
            cls = [(get(f"{key}.classifier.{i}.weight", (wc[i + 1], wc[i])), get(f"{key}.classifier.{i}.bias", (wc[i + 1],)))
                   for i in range(len(wc) - 1)]
            reg = [(get(f"{key}.regressor.{i}.weight", (wr[i + 1], wr[i])), get(f"{key}.regressor.{i}.bias", (wr[i + 1],)))
                   for i in range(len(wr) - 1)]
            tm = NeuralMap(
                path_id=int(mm["path_id"]), direction=str(mm["direction"]), z_in=float(mm["z_in_mm"]),
                z_out=float(mm["z_out_mm"]), domain=dom,
                input_center=np.asarray(mm["input_norm"]["center"], np.float64),
                input_scale=np.asarray(mm["input_norm"]["scale"], np.float64),
                classifier=cls, regressor=reg,
                skip=get(f"{key}.regressor.skip.weight", (len(OUTPUTS), n_in)),
                out_scale=get(f"{key}.regressor.out_scale", (len(OUTPUTS),)),
                out_shift=get(f"{key}.regressor.out_shift", (len(OUTPUTS),)),
                classifier_activation=ac, regressor_activation=ar,
                odd_y=bool(mm["regressor"].get("odd_y", False)),
                position_cos=bool(mm["regressor"].get("position_cos", False)),
                training=mm.get("training", {}), metrics=mm.get("metrics", {}),
                stop_head=_load_stop_head(path, key, mm.get("stop"), get, n_in))
            if tm.direction not in ("forward", "backward") or tm.key != key:
                raise ModelError(f"{path}: map {key}: inconsistent key/direction/path id")
            if tm.input_center.shape != (n_in,) or tm.input_scale.shape != (n_in,) or np.any(tm.input_scale == 0):
                raise ModelError(f"{path}: map {key}: input_norm must hold {n_in} centres and {n_in} non-zero scales")
        except (KeyError, TypeError, ValueError) as e:
            if isinstance(e, ModelError):
                raise
            raise ModelError(f"{path}: malformed map metadata ({type(e).__name__}: {e})") from None
        maps[key] = tm
    extra = {k: v for k, v in doc.items()
             if k not in ("format_version", "lens", "planes", "sensor_distance_mm", "maps")}
    return NeuralLensModel(lens_name=doc["lens"].get("name", "?"), fingerprint=lens_fp,
                           z_front=float(planes["z_front_mm"]), z_rear=float(planes["z_rear_mm"]),
                           z_last_vertex=float(planes.get("z_last_vertex_mm", math.nan)),
                           sensor_distance_range=srange, maps=maps, extra=extra, path=path)


def _load_stop_head(path, key, meta, get, n_in: int = 4):
    if meta is None:
        return None
    w, k = meta["layers"], int(meta["crossings"])
    act = meta.get("activation", "tanh")
    if act not in ACTIVATIONS:
        raise ModelError(f"{path}: map {key}: unknown stop-head activation {act!r}; known: {ACTIVATIONS}")
    if k < 1 or w[0] != n_in or w[-1] != 2 * k:
        raise ModelError(f"{path}: map {key}: stop head {w} does not map {n_in} inputs to 2 × {k} crossing coordinates")
    layers = [(get(f"{key}.stop.{i}.weight", (w[i + 1], w[i])), get(f"{key}.stop.{i}.bias", (w[i + 1],)))
              for i in range(len(w) - 1)]
    return StopHead(crossings=k, layers=layers, skip=get(f"{key}.stop.skip.weight", (2 * k, n_in)),
                    out_scale=get(f"{key}.stop.out_scale", (2 * k,)), out_shift=get(f"{key}.stop.out_shift", (2 * k,)),
                    activation=act, odd_y=bool(meta.get("odd_y", True)), training=meta.get("training", {}),
                    metrics=meta.get("metrics", {}))


def bundled_model_path(lens_name: str) -> str:
    """The model file of the lens ``lens_name``: ``models/<lens>.model.safetensors`` of the first lens library
    that has one (``$MI_NEURALLENS_LENSES``, then the bundled library; :mod:`mi_neurallens.resources`), else
    the path the bundled library would hold it at (which does not exist)."""
    from .. import resources
    found = resources.find_model(lens_name)
    return str(found if found is not None else resources.bundled_library().model(lens_name))
