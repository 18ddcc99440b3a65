"""The exact map: the Dr.Jit tracer behind the transport-map interface.

The ground truth of every other map: ``realistic_lens`` renders with it, the flare renderer traces
ghosts with it, and the training sampler draws its data from its reduced-frame core.
"""
from __future__ import annotations

from ..trace import symmetry
from .base import TransportMap


class ExactMap(TransportMap):
    """Exact tracing of ``path`` (``"transmit"``, an id or a ghost ``(a, b)``) in ``direction`` from the
    plane ``z_in`` to ``z_out`` (lens space, mm).  ``fresnel``: Fresnel (and coating) throughput, else 1.
    ``tracer``: share an existing :class:`~mi_neurallens.trace.tracer.LensTracer` of the same lens.
    ``numbers``: ``{"z_in": …, "z_out": …}`` as Dr.Jit arrays (kernel inputs, possibly attached), used in place
    of the literal planes by :meth:`eval_dr` (a sensor whose lens is being optimised).

    The tracer is frame independent, so :meth:`eval_dr` traces in lens space; :meth:`core_reduced_dr`
    traces the reduced ray (position (r, 0), direction (ωx, ωy)) for samplers that work in the reduced
    frame.  ``domain``: optional, the reduced domain for :meth:`core_reduced_dr`'s callers; its film reach
    (:class:`~mi_neurallens.transport.planning.Reach`), when it has one, blocks the reduced-frame rays that
    land outside it (a forward map's training data), not :meth:`eval_dr`'s (flares test the film).  Both give
    the path's stop-plane crossings too (:attr:`stop_crossings` of them); the iris itself is the lens's
    stop, tested by the tracer.
    """

    method = "exact"

    def __init__(self, lens, path, direction: str, z_in: float,
                 z_out: float | None = None, *, fresnel: bool = True, tracer=None, domain=None, numbers=None):
        from ..trace.tracer import LensTracer
        self.lens = lens
        self.tracer = tracer if tracer is not None else LensTracer(lens, fresnel=fresnel)
        self.spec = self.tracer.path(path, direction)
        self.path_id = self.spec.id
        self.direction = direction
        self.z_in = float(z_in)
        self.z_out = float(self.tracer.default_output_z(direction) if z_out is None else z_out)
        self.domain = domain
        #: planes as Dr.Jit arrays instead of literals (``"z_in"``, ``"z_out"``): a sensor's live geometry
        self.numbers = dict(numbers or {})
        #: stop-plane crossings of this path (the steps through the stop surface)
        self.stop_crossings = sum(1 for st in self.spec.steps if st.kind == "stop")

    def number(self, key, value, like):
        return self.numbers[key] if key in self.numbers else float(value)

    def kernel_inputs(self, float_t=None) -> list:
        """The Dr.Jit arrays its kernels read besides the rays (the tracer's live geometry, the planes in
        :attr:`numbers`): a frozen function's inputs.  ``float_t``: unused (the interface of the learned maps')."""
        import drjit as dr
        return self.tracer.kernel_inputs() + [v for v in self.numbers.values() if dr.is_array_v(v)]

    @property
    def fresnel(self) -> bool:
        return self.tracer.fresnel

    def core_dr(self, p, d, lam, active):
        px, py = p
        res = self.tracer.trace((px, py, px * 0.0 + self.number("z_in", self.z_in, px)), d, lam, self.spec,
                                self.direction, z_out=self.number("z_out", self.z_out, px), active=active)
        X, Y, _ = res.position
        return res.valid, (X, Y), res.direction, res.throughput, res.stop_points

    def trace_reduced(self, x, margin: bool = False, active=True):
        """Reduced inputs ``x = (r, ωx, ωy, λ)`` → the tracer's
        :class:`~mi_neurallens.trace.tracer.TraceResult` (reduced frame; ``margin`` as the tracer's).  A domain with
        configuration inputs (:class:`~mi_neurallens.transport.configurations.Configurations`) takes them after λ,
        one configuration per ray, traced in the configurations' frame."""
        import dataclasses
        import drjit as dr
        r, wx, wy, lam = x[:4]
        tracer = self.tracer
        cond = getattr(self.domain, "conditions", None)
        if cond is not None:
            from ..trace.tracer import LensTracer
            if len(x) < 4 + cond.dims:
                raise ValueError(f"exact map {self.key}: {len(x)} reduced inputs, its domain has {4 + cond.dims}")
            tracer = LensTracer(self.lens, fresnel=self.fresnel,
                                geometry=cond.geometry(type(r), x[4:4 + cond.dims], self.lens))
        (px, py), d = symmetry.reduced_ray(r, wx, wy, self.heading)
        res = tracer.trace((px, py, px * 0.0 + self.z_in), d, lam, self.spec, self.direction,
                           z_out=self.z_out, margin=margin, active=active)
        reach = getattr(self.domain, "reach", None)
        if reach is None:
            return res
        m = reach.margin_dr(res.position, res.direction)
        return dataclasses.replace(res, valid=res.valid & (m >= 0.0),
                                   margin=dr.minimum(res.margin, m) if margin else res.margin)

    def core_reduced_finite_dr(self, x, n_out: int, active=True):
        """Reduced inputs ``x = (r, ωx, ωy, λ)`` (Dr.Jit) → (valid, the first ``n_out`` outputs of
        :meth:`core_reduced_dr`: [x, y, dx, dy, T (, sx, sy, …)], reduced frame, mm), with the rays whose outputs
        are not all finite made invalid: what a sampler of the map's data keeps (the training's
        :class:`~mi_neurallens.transport.sampling.PathSampler`, the backward domain's pilot,
        :func:`~mi_neurallens.transport.planes.backward_domain`)."""
        import drjit as dr
        valid, outs, _ = self.core_reduced_dr(x, active)
        outs = outs[:n_out]
        for o in outs:
            valid &= dr.isfinite(o)
        return valid, outs

    def core_reduced_dr(self, x, active):
        res = self.trace_reduced(x, active=active)
        return res.valid, [res.position[0], res.position[1], res.direction[0], res.direction[1],
                           res.throughput] + [c for p in res.stop_points for c in p], None
