"""The transport map: one interface for every way of sending a ray from one plane to another.

A **transport map** takes a ray crossing the input plane ``z = z_in`` (lens space, mm, +z toward the
sensor) to where it crosses the output plane ``z = z_out`` along one light path (transmit or a ghost)
in one direction (``forward`` = object → sensor, ``backward`` = sensor → object), valid or not, with
its Fresnel throughput.  The exact tracer, the learned maps and the polynomial baselines are all maps;
the sensors, the flare renderer, the training sampler and the accuracy tables consume this one
interface.

Evaluation (:meth:`TransportMap.eval_dr`) is written once, here:

1. **move** the ray along its direction to ``z_in`` (``o`` may be any point of the ray in the first
   medium);
2. **reject** rays heading the wrong way;
3. for maps that work in the symmetry-reduced frame (``reduced = True``, paper §4.1): **reduce**
   to ``(r, ωx, ωy, λ)`` (:mod:`mi_neurallens.trace.symmetry`) and **check the domain** the map was
   built for;
4. evaluate the map's **core** — the only thing a map provides (:meth:`TransportMap.core_dr` in lens
   space, or :meth:`TransportMap.core_reduced_dr` in the reduced frame);
5. **undo** the reduction and rebuild ``dz`` from the heading (when the core does not give it);
6. with an :attr:`TransportMap.iris` set (learned maps at render time), **test the iris** on every
   stop-plane crossing the core predicted (:mod:`mi_neurallens.trace.iris`).

:meth:`TransportMap.eval_np` is the numpy face of the same code: numpy in, Dr.Jit ``Float64`` on the
LLVM backend (independent of any Mitsuba variant, as :func:`mi_neurallens.trace.api.trace`), numpy
out — there are no numpy twins of the cores.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import NeuralLensError
from ..jit import from_numpy
from ..trace import symmetry


def heading_of(direction: str) -> int:
    """+1 for ``forward`` (toward +z, the sensor), −1 for ``backward``."""
    if direction not in ("forward", "backward"):
        raise NeuralLensError(f"direction must be 'forward' or 'backward', got {direction!r}")
    return 1 if direction == "forward" else -1


@dataclass
class MapResult:
    """What a transport map returns, in lens space (mm).

    From :meth:`TransportMap.eval_dr`: ``position``/``direction`` are ``(x, y, z)`` tuples of the
    input's Dr.Jit float type, ``throughput`` a float, ``valid`` a mask; nothing is evaluated.
    From :meth:`TransportMap.eval_np`: float64 numpy arrays ``position`` (N, 3), ``direction`` (N, 3)
    unit, ``throughput`` (N,), ``valid`` (N,) bool, ``stop`` (N, crossings, 2) or None.

    ``position`` lies on the map's output plane ``z_out``; ``direction`` is the exit direction (its z
    has the sign of the heading).  Values of invalid rays are unspecified.
    """

    valid: object
    position: object
    direction: object
    throughput: object
    #: learned maps: the classifier's logit (valid ⇔ in domain and logit > 0); None for other maps
    logit: object = None
    #: where the ray crosses the aperture-stop plane: a list of ``(x, y)`` in lens space (mm), one per
    #: crossing in path order, for maps that provide them (:attr:`TransportMap.stop_crossings`); else None
    stop: object = None


class TransportMap:
    """Base of every map.  A subclass sets ``method``, ``path_id``, ``direction``, ``z_in``, ``z_out``
    (and ``domain`` when ``reduced``) and implements one core:

    * ``reduced = False``: :meth:`core_dr` ``(p, d, lam, active)`` with ``p = (x, y)`` on ``z_in``
      and ``d`` the unit direction → ``(valid, (X, Y), (DX, DY, DZ or None), T)`` in lens space, or
      the same with a fifth item, the list of stop-plane crossings ``(x, y)``;
    * ``reduced = True``: :meth:`core_reduced_dr` ``(x, active)`` with ``x = (r, ωx, ωy, λ)`` →
      ``(valid, [X, Y, DX, DY, T, sx₁, sy₁, …], logit or None)`` in the reduced frame: the five
      outputs, then ``(sx, sy)`` of each stop-plane crossing the map provides.

    ``domain`` (a :class:`~mi_neurallens.transport.planning.Domain`, reduced maps only): rays
    outside it are invalid.  ``stop_crossings``: how many stop-plane crossings the core returns (0:
    none).  ``iris`` (an :class:`~mi_neurallens.trace.iris.Iris` or None): when set, a ray is valid only
    if every crossing passes it — how a map learned at the widest opening renders any smaller or
    bladed aperture.
    """

    method = "?"
    reduced = False
    stop_crossings = 0
    iris = None
    path_id: int
    direction: str
    z_in: float
    z_out: float

    # ------------------------------------------------------------------ identity
    @property
    def key(self) -> str:
        return f"{self.direction}.{self.path_id}"

    @property
    def heading(self) -> int:
        return heading_of(self.direction)

    def flops(self) -> int:
        """Floating-point operations per ray of the core (0: not counted, e.g. the tracer)."""
        return 0

    def number(self, key, value, like):
        """A number of this map (a plane, a domain bound) as it enters the kernel: a literal here; learned
        maps evaluated with ``mlp = "shared"`` return a kernel parameter instead
        (:class:`~mi_neurallens.neural.mlp.KernelParams`), so that maps of one architecture share a kernel."""
        return float(value)

    def describe(self) -> dict:
        return {"method": self.method, "path_id": self.path_id, "direction": self.direction,
                "z_in": self.z_in, "z_out": self.z_out, "flops_per_ray": self.flops()}

    # ------------------------------------------------------------------ cores (one per map)
    def core_dr(self, p, d, lam, active):  # pragma: no cover - provided by lens-space maps
        raise NotImplementedError

    def core_reduced_dr(self, x, active):  # pragma: no cover - provided by reduced maps
        raise NotImplementedError

    # ------------------------------------------------------------------ the one evaluation
    def eval_dr(self, o, d, lam_nm, active=True) -> MapResult:
        """Dr.Jit rays → :class:`MapResult` (see the module docstring for the steps).

        ``o``, ``d``: ``(x, y, z)`` tuples of Dr.Jit floats in lens space (mm; ``o`` any point of the
        ray in front of the map's first surface, ``d`` unit).  ``lam_nm``: Dr.Jit float or Python
        float (nm).  No ``dr.eval``: the map fuses into the caller's kernel."""
        import drjit as dr
        ox, oy, oz = o
        dx, dy, dz = d
        t = (self.number("z_in", self.z_in, oz) - oz) / dz
        px, py = dr.fma(t, dx, ox), dr.fma(t, dy, oy)
        lam = lam_nm if not isinstance(lam_nm, (int, float)) else px * 0.0 + float(lam_nm)
        ok = ((dz > 0.0) if self.heading > 0 else (dz < 0.0)) & active
        logit = None
        if self.reduced:
            (r, wx, wy), frame = symmetry.reduce(px, py, dx, dy)
            x = (r, wx, wy, lam)
            domain = getattr(self, "domain", None)
            if domain is not None:
                ok &= domain.contains_dr(x, self.number)
            valid, y, logit = self.core_reduced_dr(x, ok)
            X, Y, DX, DY = symmetry.undo(y[0], y[1], y[2], y[3], frame)
            T, DZ = y[4], None
            stop = [symmetry.undo_point(y[k], y[k + 1], frame) for k in range(5, len(y) - 1, 2)] or None
        else:
            valid, (X, Y), (DX, DY, DZ), T, *rest = self.core_dr((px, py), (dx, dy, dz), lam, ok)
            stop = rest[0] if rest else None
        if DZ is None:
            DZ = self.heading * dr.sqrt(dr.maximum(1.0 - dr.fma(DX, DX, DY * DY), 0.0))
        if self.iris is not None:
            if not stop:
                raise NeuralLensError(f"{self.method} map {self.key} gives no stop-plane crossing, so it "
                                      "cannot apply an iris")
            for sx, sy in stop:
                valid &= self.iris.contains_dr(sx, sy)
        return MapResult(valid, (X, Y, X * 0.0 + self.number("z_out", self.z_out, X)), (DX, DY, DZ), T, logit, stop)

    def eval_np(self, o, d, lam_nm) -> MapResult:
        """The same evaluation on numpy rays, in Dr.Jit ``Float64``: ``o``, ``d`` (N, 3), ``lam_nm``
        scalar or (N,) → :class:`MapResult` of float64 numpy arrays."""
        F = float64_type()
        o = np.asarray(o, np.float64)
        d = np.asarray(d, np.float64)
        n = len(o)
        lam = np.broadcast_to(np.asarray(lam_nm, np.float64), (n,))
        col = lambda a, i: from_numpy(F, a[:, i])
        res = self.eval_dr(tuple(col(o, i) for i in range(3)), tuple(col(d, i) for i in range(3)),
                           from_numpy(F, lam))
        return to_numpy(res, n)

    def core_reduced_np(self, x):
        """Reduced inputs (N, 4) numpy (a domain with configuration inputs: (N, 4 + their number)) →
        ``(valid, outputs (N, 5 + 2·crossings), logit or None)`` of the core in the reduced frame (float64; no
        domain check, no iris), through the same Dr.Jit code."""
        import drjit as dr
        F = float64_type()
        x = np.asarray(x, np.float64)
        xs = [from_numpy(F, x[:, i]) for i in range(x.shape[1])]
        valid, y, logit = self.core_reduced_dr(xs, True)
        arrays = list(y) + ([logit] if logit is not None else [])
        dr.eval(valid, arrays)
        out = np.stack([np.broadcast_to(a.numpy(), (len(x),)) for a in y], 1).astype(np.float64)
        v = np.broadcast_to(valid.numpy().astype(bool), (len(x),)).copy()
        return v, out, (None if logit is None else logit.numpy().astype(np.float64))


def float64_type():
    """The Dr.Jit float64 array type of the numpy faces (LLVM, or CUDA without LLVM)."""
    from ..trace.api import float_type
    return float_type("float64")


def to_numpy(res: MapResult, n: int) -> MapResult:
    """Evaluate a Dr.Jit :class:`MapResult` of ``n`` rays and return it as float64 numpy arrays."""
    import drjit as dr
    stop = [c for p in (res.stop or []) for c in p]
    arrays = [*res.position, *res.direction, res.throughput] + ([res.logit] if res.logit is not None else []) + stop
    dr.eval(res.valid, arrays)
    col = lambda a: np.broadcast_to(np.asarray(a.numpy(), np.float64), (n,))
    return MapResult(valid=np.broadcast_to(res.valid.numpy().astype(bool), (n,)).copy(),
                     position=np.stack([col(a) for a in res.position], 1),
                     direction=np.stack([col(a) for a in res.direction], 1),
                     throughput=col(res.throughput).copy(),
                     logit=None if res.logit is None else col(res.logit).copy(),
                     stop=None if not res.stop else np.stack([np.stack([col(x), col(y)], 1) for x, y in res.stop], 1))
