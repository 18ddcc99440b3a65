"""Training data for lens transport maps, streamed from the exact Dr.Jit tracer through the sampler of
:mod:`mi_neurallens.transport.sampling` (the reduced domain, rejection and Metropolis sampling):
:class:`RegressorStream` (valid rays for a regressor, refreshed as it trains) and :func:`classifier_samples`
(valid rays and perturbations across the boundary, for a classifier).
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import NeuralLensError
from ..transport.sampling import MCMCSampler, PathSampler, rejection_sample, valid_fraction


class RegressorStream:
    """Valid (x, y) training samples of one map: rejection sampling when the valid fraction is at
    least ``mcmc_threshold`` (inside pilot-traced :mod:`~mi_neurallens.transport.bounds` when
    ``bounded``), the Metropolis sampler otherwise.

    The tracer works in large launches (rejection sampling traces 2²¹ rays a chunk, a Metropolis step moves
    every chain), and the valid rays of a launch that a call does not take are kept, up to
    :attr:`KEEP` rows, for the next calls: the Levenberg–Marquardt finish asks for 8 192 rows an iteration,
    and tracing a whole chunk for each call cost 0.1 s an iteration on dgauss-50mm's ghosts.  The rows kept
    are untouched samples of the same distribution, so a call's rows are as fresh as before."""

    #: the most traced-but-unused valid rows kept for later calls (≈ 20 MB of float64 rows a map)
    KEEP = 1 << 18

    def __init__(self, ps: PathSampler, seed: int, mcmc_threshold: float = 0.02, n_chains: int = 1 << 16,
                 p_large: float = 0.3, sigma: float = 0.02, bounded: bool = True, like: "RegressorStream | None" = None):
        """``like``: a stream of the same map (path, planes, domain) whose sampler differs only in its output
        columns (e.g. without the stop-plane crossings): its valid fraction and pilot-traced bounds describe
        this stream's valid region too, so they are taken instead of traced again (a valid fraction's 2²⁰ rays
        and a pilot's 2²² a map; the Metropolis chains, which carry their own outputs, are started anew)."""
        self.ps = ps
        self.rng = np.random.default_rng(seed)
        if like is not None and (like.ps.path_id, like.ps.direction, like.ps.z_in, like.ps.z_out, like.ps.domain) != (
                ps.path_id, ps.direction, ps.z_in, ps.z_out, ps.domain):
            raise NeuralLensError(f"RegressorStream(like=…): the stream given samples {like.ps.direction}."
                                  f"{like.ps.path_id}, not this sampler's map {ps.direction}.{ps.path_id}")
        self.fraction = valid_fraction(ps, self.rng) if like is None else like.fraction
        self.mcmc = None
        self._u = np.zeros((0, ps.dims))
        self._y = np.zeros((0, ps.n_out))
        if self.fraction < mcmc_threshold:
            self.mcmc = MCMCSampler(ps, self.rng, n_chains=n_chains, p_large=p_large, sigma=sigma)
        elif bounded and like is not None:
            ps.bounds = like.ps.bounds
        elif bounded:
            ps.build_bounds(self.rng)

    def reseed(self, seed):
        """A new random stream (``np.random.default_rng(seed)``), without the rows kept from the old one (a
        resumed run's data depend only on its seed and step)."""
        self.rng = np.random.default_rng(seed)
        self._u, self._y = self._u[:0], self._y[:0]

    def sample(self, n: int):
        """``n`` valid samples (u (n, 4), x (n, 4), y (n, ``ps.n_out``)): the rows kept from earlier launches
        first, then new ones."""
        n = int(n)
        if len(self._u) < n:
            need = n - len(self._u)
            if self.mcmc is not None:
                u, _, y = self.mcmc.sample(need, whole_steps=True)
            else:
                u, _, y, _ = rejection_sample(self.ps, need, self.rng, whole_chunks=True, inputs=False)
            self._u, self._y = np.concatenate([self._u, u]), np.concatenate([self._y, y])
        u, y = self._u[:n], self._y[:n]
        self._u, self._y = self._u[n:n + self.KEEP].copy(), self._y[n:n + self.KEEP].copy()
        return u, self.ps.domain.u_to_x(u), y

    @property
    def method(self):
        if self.mcmc is not None:
            return "mcmc"
        return "rejection (bounded)" if self.ps.bounds is not None else "rejection"


def classifier_samples(ps: PathSampler, valid_u: np.ndarray, n: int, rng: np.random.Generator,
                       sigma_range=None, margin: bool = False):
    """A labelled set for the classifier: ⅓ uniform over the domain (natural labels), ⅓ valid samples
    (``valid_u``, e.g. from :class:`RegressorStream`) and ⅓ boundary samples: valid points perturbed by
    a Gaussian of log-uniform width in ``sigma_range`` (unit-cube units; default
    ``NetConfig.boundary_sigma``), labelled by the tracer.
    Returns (x (N, 4), label (N,) float32); with ``margin`` also the tracer's aperture margin (N,) and
    hard-failure mask (N,) of every sample (:meth:`PathSampler.margin_u`)."""
    if sigma_range is None:
        from .config import NetConfig
        sigma_range = NetConfig.boundary_sigma
    k = n // 3
    u_uni = rng.random((k, ps.dims))
    pick = valid_u[rng.integers(0, len(valid_u), n - 2 * k)]
    u_val = valid_u[rng.integers(0, len(valid_u), k)]
    sig = np.exp(rng.uniform(math.log(sigma_range[0]), math.log(sigma_range[1]), (len(pick), 1)))
    u_per = np.clip(pick + sig * rng.standard_normal(pick.shape), 0.0, 1.0 - 1e-7)
    perm = rng.permutation(n)
    if margin:
        u = np.concatenate([u_uni, u_per, u_val])[perm]
        lab, m, hard = ps.margin_u(u)
        return ps.domain.u_to_x(u), lab.astype(np.float32), m, hard
    u_lab = np.concatenate([u_uni, u_per])
    lab = ps.valid_u(u_lab)
    u = np.concatenate([u_lab, u_val])
    label = np.concatenate([lab, np.ones(len(u_val), dtype=bool)]).astype(np.float32)
    return ps.domain.u_to_x(u[perm]), label[perm]


# ----------------------------------------------------------------------------- optional disk cache
