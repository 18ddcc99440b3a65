"""A ghost path's transport map continued to the film: :class:`GhostEvaluator`, what the flare's kernels call.

An evaluator takes lens-space rays on the flare's input plane (mm, +z toward the sensor) and answers where they
land on the sensor plane and with what Fresnel throughput.  Learned evaluators may leave some samples to the
tracer (``near``): those whose classifier has not decided (``boundary_band``) and, through an iris other than the
trained one, those whose predicted stop-plane crossing lies at the iris's edge (``iris_band``,
:func:`iris_band_mm`).  The renderer (:mod:`mi_neurallens.flare.render`) chooses each ghost's evaluator; the
kernels (:mod:`mi_neurallens.flare.kernels`) call it.
"""
from __future__ import annotations


#: a learned ghost rendered through an iris other than the one it was trained with tests its predicted stop-plane
#: crossings against that iris (:mod:`mi_neurallens.trace.iris`); with an iris band b > 0, a sample whose predicted
#: crossing lies within b × this × the stop head's held-out p99 crossing error (``metrics["stop"]``) of the iris's
#: edge is traced instead, as the classifier's undecided samples are (docs/flares.md, "Exact edges")
IRIS_BAND_P99 = 3.0
#: the p99 crossing error assumed (µm) for a stop head without recorded metrics: the aperture issue's goal
IRIS_BAND_DEFAULT_P99_UM = 20.0


def iris_band_mm(tmap, band: float) -> float:
    """Half-width (mm, stop plane) of the band around the iris's edge whose samples a learned map with iris band
    ``band`` leaves to the tracer: 0 without a band or without an iris tested at render time
    (:data:`IRIS_BAND_P99`)."""
    if not band > 0.0 or getattr(tmap, "iris", None) is None:
        return 0.0
    p99 = ((getattr(tmap, "metrics", None) or {}).get("stop") or {}).get("stop_um_p99")
    return float(band) * IRIS_BAND_P99 * float(p99 if p99 is not None else IRIS_BAND_DEFAULT_P99_UM) * 1e-3


class GhostEvaluator:
    """One path's transport map (exact, learned or a baseline), from the flare's input plane, continued
    straight to the sensor plane ``z_sensor``: ``(o, d, lam, active)`` → ``(valid, x, y, T, near)`` on the
    sensor (lens space, mm).  ``fresnel = False``: T = 1.  ``band`` > 0 (a learned map with a classifier):
    ``near`` marks the samples whose classifier logit is within ±``band`` of its decision; ``iris_band`` > 0
    (default: ``band``; a learned map with an iris tested at render time): also those whose predicted stop-plane
    crossing lies within :func:`iris_band_mm` of the iris's edge.  The map leaves ``near`` out (``valid`` is
    false there) for the tracer to take (:meth:`~mi_neurallens.flare.render.FlareRenderer.splat`); without a
    band ``near`` is None.  ``z_var``: the sensor plane as the kernel reads it, a width-1 Dr.Jit array (a kernel
    input: another zoom or focus compiles no new kernel); None: ``z_sensor`` as a literal."""

    def __init__(self, tmap, z_sensor, fresnel=True, band=0.0, iris_band=None, z_var=None):
        self.map, self.z, self.fresnel, self.z_var = tmap, float(z_sensor), fresnel, z_var
        #: ``exact`` for the tracer, ``neural`` for every other map (the learned ones and the baselines)
        self.kind = "exact" if tmap.method == "exact" else "neural"
        self.band = float(band) if self.kind == "neural" and getattr(tmap, "use_classifier", False) else 0.0
        ib = band if iris_band is None else iris_band
        #: the iris band's half-width (mm; 0: the iris's edge is learned)
        self.iris_mm = iris_band_mm(tmap, ib) if self.kind == "neural" else 0.0
        self._iris_vars = {}

    @property
    def pid(self) -> int:
        return self.map.path_id

    @property
    def shared_numbers(self) -> bool:
        """Whether the map's numbers are kernel inputs (``mlp`` shared or coopvec): then so is the iris band."""
        tm = self.map
        return hasattr(tm, "kernel_signature") and tm.kernel_signature() is not None

    def _iris_width(self, float_t):
        """The iris band's half-width as the kernel reads it: an opaque variable (a kernel input, one per float
        type, created before any recording) where the map's numbers are inputs, else a literal."""
        if not self.shared_numbers:
            return self.iris_mm
        import drjit as dr
        v = self._iris_vars.get(float_t)
        if v is None:
            v = self._iris_vars[float_t] = dr.opaque(float_t, self.iris_mm)
        return v

    def freeze_key(self, float_t):
        """``(signature, inputs)`` for the renderer's frozen kernels: a learned map whose numbers are kernel
        inputs (``mlp`` shared or coopvec) shares its signature with every map of its architecture and hands
        its numbers and packed networks (``inputs``, Dr.Jit variables); any other map (the tracer, literals, a
        baseline) has a signature of its own, and hands what it reads besides literals (the tracer's configuration
        numbers, a configured learned map's folded layers and planes: ``kernel_inputs``).  With :attr:`z_var`
        the sensor plane is an input too."""
        tm = self.map
        sig = tm.kernel_signature() if hasattr(tm, "kernel_signature") else None
        z, zs = (self.z, []) if self.z_var is None else ("input", [self.z_var])
        if sig is None:
            # the tracer's live geometry and planes, a configured learned map's folded numbers and planes: inputs
            inputs = tm.kernel_inputs(float_t) if hasattr(tm, "kernel_inputs") else []
            return ("map", tm.method, tm.key, z, self.fresnel, self.band, self.iris_mm), inputs + zs
        extra = [self._iris_width(float_t)] if self.iris_mm > 0.0 else []
        return (sig, z, self.fresnel, self.band, self.iris_mm > 0.0), tm.kernel_inputs(float_t) + extra + zs

    def __call__(self, o, d, lam, active):
        import drjit as dr
        res = self.map.eval_dr(o, d, lam, active)
        (px, py, pz), (dx, dy, dz) = res.position, res.direction
        t = ((self.z if self.z_var is None else self.z_var) - pz) / dz
        x, y = dr.fma(t, dx, px), dr.fma(t, dy, py)
        T = res.throughput if self.fresnel else res.throughput * 0.0 + 1.0
        valid = res.valid & (dz > 0.0)
        near = None
        if self.band > 0.0 and res.logit is not None:
            near = active & (dr.abs(res.logit) < self.band)
        if self.iris_mm > 0.0 and res.stop:
            # the iris decides only where the classifier lets the ray through (or has not decided)
            cand = active if res.logit is None else active & (res.logit > -self.band)
            w = self._iris_width(type(x))
            for sx, sy in res.stop:
                at = cand & (dr.abs(self.map.iris.edge_distance_dr(sx, sy)) < w)
                near = at if near is None else near | at
        if near is not None:
            valid &= ~near
        return valid, x, y, T, near
