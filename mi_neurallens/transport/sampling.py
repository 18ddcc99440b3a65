"""Sampling the exact transport map over its reduced domain: where training data, held-out sets, the fitted
polynomial baseline's fit and the accuracy tables all get their rays (numpy and Dr.Jit; no torch).

Everything here works in the **reduced input domain** of :mod:`mi_neurallens.trace.symmetry`:
``(r, ωx, ωy, λ)`` with 0 ≤ r ≤ ``r_max`` on the input plane and (ωx, ωy) in the half disk
ωx² + ωy² ≤ ``s_max``², ωy ≥ 0.  A sample is addressed by a point ``u`` of the unit cube [0, 1)⁴:

* ``r = r_max·u0`` (uniform in r, as the paper: uniform over the reduced domain),
* ``(ωx, ωy) = s_max·√u1·(cos πu2, sin πu2)`` (uniform over the half disk's area),
* ``λ = CIE sample of u3`` (:func:`sample_cie_wavelength`, Mitsuba's ``sample_rgb_spectrum`` curve).

The map u → domain is measure preserving up to a constant, so a sampler that is uniform in u
(rejection sampling, or the Metropolis chain with symmetric proposals of :class:`MCMCSampler`) is
uniform over the valid region of the reduced domain and CIE-importance-sampled in λ.

Outputs (reduced frame, see :data:`OUTPUT_NAMES`): exit position (x, y) on the output plane (mm),
exit direction (dx, dy) (dz follows from the heading), Fresnel throughput T.
"""
from __future__ import annotations

import math
import time

import numpy as np

from ..errors import NeuralLensError
from ..jit import from_numpy
from .planning import Domain, sample_cie_wavelength

#: names of the reduced input and output columns
INPUT_NAMES = ("r", "wx", "wy", "lambda_nm")
OUTPUT_NAMES = ("x", "y", "dx", "dy", "throughput")

# ----------------------------------------------------------------------------- one path's tracer
class PathSampler:
    """Traces unit-cube samples ``u`` of one (lens, path, direction) map from ``z_in`` to ``z_out``.

    ``precision``: ``"float32"`` for training data (≈ 0.01 µm / 0.02″ rounding), ``"float64"`` for
    held-out reference sets.  ``stops``: the outputs also hold the path's stop-plane crossings
    (sx, sy per crossing, reduced frame, mm) after the five of :data:`OUTPUT_NAMES`.
    """

    def __init__(self, lens, path_id: int, direction: str, z_in: float, z_out: float, domain: Domain,
                 fresnel: bool = True, precision: str = "float32", stops: bool = False):
        from ..trace.api import float_type
        from .exact import ExactMap
        self.lens, self.path_id, self.direction = lens, int(path_id), direction
        self.z_in, self.z_out, self.domain = float(z_in), float(z_out), domain
        #: the exact map whose reduced-frame core gives the data
        self.map = ExactMap(lens, self.path_id, direction, self.z_in, self.z_out, fresnel=fresnel, domain=domain)
        self.tracer = self.map.tracer
        self.heading = self.map.heading
        self.F = float_type(precision)
        self.rays_traced = 0
        #: optional :class:`~mi_neurallens.transport.bounds.ValidBounds` used by :meth:`random_valid`
        self.bounds = None
        #: output columns: the five, plus two per stop-plane crossing when ``stops``
        self.n_out = len(OUTPUT_NAMES) + (2 * self.map.stop_crossings if stops else 0)

    # -- Dr.Jit core ---------------------------------------------------------------------------
    @property
    def dims(self) -> int:
        """Columns of a sample's unit-cube address and inputs (:attr:`~mi_neurallens.transport.planning.Domain.dims`:
        4, plus the configuration inputs of a lens with moving groups)."""
        return self.domain.dims

    def u_to_x_dr(self, u):
        """Unit-cube components (:attr:`dims` Dr.Jit floats) → reduced inputs (r, ωx, ωy, λ (, zoom, focus)) in
        Dr.Jit (:meth:`~mi_neurallens.transport.planning.Domain.u_to_x_dr`)."""
        return self.domain.u_to_x_dr(u)

    def trace_dr(self, r, wx, wy, lam, *cond):
        """Reduced inputs (Dr.Jit) → (valid, [x, y, dx, dy, T (, sx, sy, …)]) (Dr.Jit, reduced frame): the exact
        map's reduced core, with rays whose outputs are not finite made invalid.  ``cond``: the configuration
        inputs of a lens with moving groups."""
        return self.map.core_reduced_finite_dr((r, wx, wy, lam) + tuple(cond), self.n_out)

    def _to_np(self, valid, outs, n):
        import drjit as dr
        dr.eval(outs, valid)
        self.rays_traced += n
        v = valid.numpy().astype(bool)
        y = np.empty((len(v), len(outs)))
        for i, o in enumerate(outs):          # column by column: one float32 -> float64 pass, no temporaries
            y[:, i] = o.numpy()
        y[~v] = np.nan
        return v, y

    def _columns(self, a: np.ndarray) -> list:
        """(N, :attr:`dims`) numpy → :attr:`dims` Dr.Jit arrays of this sampler's precision."""
        a = np.asarray(a)
        return [from_numpy(self.F, a[:, i]) for i in range(self.dims)]

    def trace_x(self, x: np.ndarray):
        """Reduced inputs (N, :attr:`dims`) → (valid (N,), outputs (N, :attr:`n_out`) float64, NaN where invalid)."""
        valid, outs = self.trace_dr(*self._columns(x))
        return self._to_np(valid, outs, len(x))

    def trace_u(self, u: np.ndarray):
        valid, outs = self.trace_dr(*self.u_to_x_dr(self._columns(u)))
        return self._to_np(valid, outs, len(u))

    def valid_u(self, u: np.ndarray) -> np.ndarray:
        return self.trace_u(u)[0]

    def margin_u(self, u: np.ndarray):
        """Unit-cube samples (N, :attr:`dims`) → (valid (N,), margin (N,) float64, hard_fail (N,)): the tracer's
        aperture margin (:attr:`~mi_neurallens.trace.tracer.TraceResult.margin`) and where the ray fails
        for another reason (then the margin says nothing).  ``valid == ~hard_fail & (margin >= 0)``."""
        import drjit as dr
        res = self.map.trace_reduced(self.u_to_x_dr(self._columns(u)), margin=True)
        hard = res.hard_fail | ~dr.isfinite(res.position[0]) | ~dr.isfinite(res.throughput)
        dr.eval(res.valid, res.margin, hard)
        self.rays_traced += len(u)
        hard = hard.numpy().astype(bool)
        valid = res.valid.numpy().astype(bool) & ~hard
        return valid, res.margin.numpy().astype(np.float64), hard

    def random_valid(self, n_rays: int, seed: int, bounds: bool = True):
        """Trace ``n_rays`` random samples drawn with Dr.Jit's PCG32 (stream ``seed``) and return only
        the valid ones, compacted inside Dr.Jit: (u (K, :attr:`dims`), y (K, :attr:`n_out`)), float64 arrays.

        Uniform over the unit cube, or, when :attr:`bounds` (a
        :class:`~mi_neurallens.transport.bounds.ValidBounds`) is set and ``bounds`` is true, uniform
        over its boxes: both are uniform over the valid region, the second wastes fewer rays.  ``u``
        is always the unit-cube address of the sample (:meth:`Domain.u_to_x` maps it to inputs)."""
        import drjit as dr
        from ..trace.api import float_type
        be = __import__(type(self.F(0)).__module__, fromlist=["PCG32"])
        rng = be.PCG32(n_rays, dr.opaque(be.UInt64, seed & 0xFFFFFFFFFFFF))  # opaque: no recompile per seed
        if self.F is float_type("float64"):
            u = [rng.next_float64() for _ in range(self.dims)]
        else:
            u = [rng.next_float32() for _ in range(self.dims)]
        if bounds and self.bounds is not None:
            d = self.domain
            r, wx, wy = self.bounds.sample_dr(self.F, u)
            lam, _ = sample_cie_wavelength(u[3])
            s2 = dr.fma(wx, wx, wy * wy)
            cond = d.conditions.u_to_tf_dr(u[4:]) if d.conditions is not None else []
            valid, outs = self.trace_dr(r, wx, wy, lam, *cond)
            valid &= s2 <= d.s_max * d.s_max
            u = [r / d.r_max, s2 / (d.s_max * d.s_max), dr.atan2(wy, wx) / math.pi, u[3]] + list(u[4:])
        else:
            valid, outs = self.trace_dr(*self.u_to_x_dr(u))
        # one kernel for the trace, then one for the compaction: compress() alone would evaluate only
        # ``valid`` and the gathers would re-trace every ray to get the outputs
        dr.eval(valid, u, outs)
        idx = dr.compress(valid)
        cols = [dr.gather(type(u[0]), a, idx) for a in u + outs]
        dr.eval(cols)
        self.rays_traced += n_rays
        k = dr.width(cols[0])
        nu = self.dims
        uo, yo = np.empty((k, nu)), np.empty((k, len(outs)))
        for i, c in enumerate(cols):          # column by column: one float32 -> float64 pass, no temporaries
            (uo[:, i] if i < nu else yo[:, i - nu])[:] = c.numpy()
        return uo, yo

    def build_bounds(self, rng: np.random.Generator, n_pilot: int = 1 << 22):
        """Pilot-trace :attr:`bounds` (see :mod:`mi_neurallens.transport.bounds`); returns them (or
        ``None`` when the valid region is too rare for a pilot to bound)."""
        from .bounds import ValidBounds
        self.bounds = ValidBounds.build(self, rng, n_pilot)
        return self.bounds


# ----------------------------------------------------------------------------- samplers
def rejection_sample(ps: PathSampler, n: int, rng: np.random.Generator, chunk: int = 1 << 21,
                     max_rays: int | None = None, whole_chunks: bool = False, inputs: bool = True):
    """Up to ``n`` valid samples uniform over the valid region: returns (u, x, y, stats).
    Random numbers come from Dr.Jit's PCG32 (streams seeded from ``rng``) and the valid rays are
    compacted inside Dr.Jit.  Stops early (returning fewer) after ``max_rays`` traced rays.
    ``whole_chunks``: return every valid ray of the chunks traced (at least ``n``), not the first ``n``.
    ``inputs``: also map ``u`` to the inputs ``x`` (else x is None: a caller that keeps only ``u`` saves a
    pass over millions of rows)."""
    us, ys, got, traced = [], [], 0, 0
    t0 = time.perf_counter()
    while got < n and (max_rays is None or traced < max_rays):
        u, y = ps.random_valid(chunk, int(rng.integers(0, 2**47)))
        traced += chunk
        us.append(u)
        ys.append(y)
        got += len(u)
    keep = slice(None) if whole_chunks else slice(n)
    u = np.concatenate(us)[keep] if us else np.zeros((0, ps.dims))
    y = np.concatenate(ys)[keep] if ys else np.zeros((0, ps.n_out))
    dt = time.perf_counter() - t0
    stats = {"rays": traced, "valid": int(got), "acceptance": got / max(traced, 1), "seconds": dt,
             "valid_per_s": got / max(dt, 1e-9), "rays_per_s": traced / max(dt, 1e-9)}
    return u, (ps.domain.u_to_x(u) if inputs else None), y, stats


class MCMCSampler:
    """Metropolis sampler of the uniform distribution over a path's valid region (binary visibility
    target, Hachisuka & Jensen 2011 style).

    ``n_chains`` independent chains in the unit cube run in lock-step (one traced ray per chain per
    step).  Each step proposes, per chain, with probability ``p_large`` an independent uniform point
    (a *large step*) and otherwise a Gaussian mutation of width ``sigma`` (wrapped into the cube).
    Both proposals are symmetric and the target is the indicator of validity, so a proposal is
    accepted iff it is valid; every chain's state after each step is one (correlated) valid sample.
    Chains start from valid seeds found by rejection sampling (replicated if few) plus ``burn_in``
    steps.
    """

    def __init__(self, ps: PathSampler, rng: np.random.Generator, n_chains: int = 1 << 16,
                 p_large: float = 0.3, sigma: float = 0.02, burn_in: int = 16,
                 seed_rays: int = 1 << 24):
        self.ps, self.rng = ps, rng
        self.p_large, self.sigma = float(p_large), float(sigma)
        u, _, y, st = rejection_sample(ps, n_chains, rng, chunk=1 << 20, max_rays=seed_rays, inputs=False)
        if len(u) == 0:
            raise NeuralLensError(f"path {ps.path_id} ({ps.direction}): no valid ray in {st['rays']} random "
                                  "rays; the path carries no light in this domain")
        idx = rng.integers(0, len(u), n_chains) if len(u) < n_chains else np.arange(n_chains)
        self.u, self.y = u[idx].copy(), y[idx].copy()
        self.proposed = self.accepted = 0
        self.proposed_large = self.accepted_large = 0
        for _ in range(int(burn_in) if len(u) < n_chains else 0):
            self.step()
        self.proposed = self.accepted = self.proposed_large = self.accepted_large = 0

    def step(self):
        n = len(self.u)
        large = self.rng.random(n) < self.p_large
        k = self.ps.dims
        prop = np.where(large[:, None], self.rng.random((n, k)),
                        np.mod(self.u + self.sigma * self.rng.standard_normal((n, k)), 1.0))
        v, y = self.ps.trace_u(prop)
        self.u[v] = prop[v]
        self.y[v] = y[v]
        self.proposed += n
        self.accepted += int(v.sum())
        self.proposed_large += int(large.sum())
        self.accepted_large += int((v & large).sum())
        return self.u.copy(), self.y.copy()

    def sample(self, n: int, whole_steps: bool = False):
        """``n`` valid samples (from whole steps; ``whole_steps``: all of their samples, at least ``n``):
        (u, x, y)."""
        us, ys = [], []
        while sum(len(a) for a in us) < n:
            u, y = self.step()
            us.append(u)
            ys.append(y)
        keep = slice(None) if whole_steps else slice(n)
        u = np.concatenate(us)[keep]
        return u, self.ps.domain.u_to_x(u), np.concatenate(ys)[keep]

    @property
    def acceptance(self) -> float:
        return self.accepted / max(self.proposed, 1)

    def stats(self) -> dict:
        return {"acceptance": self.acceptance, "p_large": self.p_large, "sigma": self.sigma,
                "acceptance_large": self.accepted_large / max(self.proposed_large, 1),
                "acceptance_small": (self.accepted - self.accepted_large)
                / max(self.proposed - self.proposed_large, 1)}


def valid_fraction(ps: PathSampler, rng: np.random.Generator, n: int = 1 << 20) -> float:
    return float(ps.valid_u(rng.random((n, ps.dims))).mean())


def heldout_valid(lens, tm_or_spec, domain, n: int, seed: int, mcmc_threshold: float = 0.02,
                  fresnel: bool = True, stops: bool = False):
    """(x, y) float64 valid held-out samples of a map (independent seed); ``stops``: y also holds the
    stop-plane crossings (:class:`~mi_neurallens.transport.sampling.PathSampler`)."""
    path_id, direction, z_in, z_out = tm_or_spec
    ps = PathSampler(lens, path_id, direction, z_in, z_out, domain, fresnel=fresnel, precision="float64",
                     stops=stops)
    rng = np.random.default_rng(seed)
    if valid_fraction(ps, rng, 1 << 18) >= mcmc_threshold:
        _, x, y, _ = rejection_sample(ps, n, rng)
    else:
        m = MCMCSampler(ps, rng, n_chains=min(n, 1 << 14), burn_in=32)
        # thin the chain (every 4th step) to reduce correlation in the held-out set
        xs, ys = [], []
        while sum(len(a) for a in xs) < n:
            for _ in range(3):
                m.step()
            u, yy = m.step()
            xs.append(ps.domain.u_to_x(u))
            ys.append(yy)
        x, y = np.concatenate(xs)[:n], np.concatenate(ys)[:n]
    return x, y
