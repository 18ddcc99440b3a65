"""Pilot-traced bounds of a map's valid region, for rejection sampling that wastes few rays.

The reduced input domain ``(r, ωx, ωy, λ)`` of :mod:`mi_neurallens.transport.sampling` is much larger
than the set of rays that pass the lens: for a camera-ray (backward) map, only directions that aim
at the exit pupil pass, and which ones depends on r.  Uniform rejection sampling over the whole
domain accepts about 12 % of the rays on the 22 mm lens.

:class:`ValidBounds` splits ``[0, r_max]`` into bins and keeps, per bin, an axis-aligned box in
(ωx, ωy) that encloses every valid pilot ray of that bin *and of its two neighbours*, widened by a
margin.  Sampling picks a bin with probability ∝ (bin width × box area), r uniform in the bin and
(ωx, ωy) uniform in the box: the density is the same constant everywhere inside the union of boxes,
so after rejecting the invalid rays the samples are still **uniform over the valid region** (the
distribution the regressor is trained on), provided the valid region lies inside the union.  That
is checked, not assumed: :meth:`ValidBounds.build` re-traces an independent uniform pilot and
reports the fraction of its valid rays that fall outside (``missed``; 0 in every bundled map), and
sampling falls back to the whole domain when that fraction exceeds 10⁻⁴ or the pilot finds too few
valid rays to trust.

Units: r in mm on the input plane, ω as direction cosines (unitless), λ untouched (CIE-sampled).
"""
from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np


@dataclass
class ValidBounds:
    """Per-r-bin direction boxes (see the module docstring).  Arrays have one entry per bin."""

    r_edges: np.ndarray        # (B+1,) mm, 0 .. r_max
    wx_lo: np.ndarray          # (B,) direction-cosine box per bin
    wx_hi: np.ndarray
    wy_lo: np.ndarray          # ≥ 0 (reduced domain)
    wy_hi: np.ndarray
    missed: float = 0.0        # fraction of an independent pilot's valid rays outside the boxes

    @property
    def weights(self) -> np.ndarray:
        """Unnormalised selection probability of each bin: bin width × box area."""
        return (np.diff(self.r_edges) * np.maximum(self.wx_hi - self.wx_lo, 0.0)
                * np.maximum(self.wy_hi - self.wy_lo, 0.0))

    def volume_fraction(self, domain) -> float:
        """Volume of the union of boxes relative to the full (r, half-disk) domain: the expected
        speed-up of rejection sampling is about 1 / this."""
        return float(self.weights.sum() / (domain.r_max * 0.5 * math.pi * domain.s_max ** 2))

    def contains(self, x: np.ndarray) -> np.ndarray:
        """(N, 4) reduced inputs → bool (N,): inside the union of boxes (numpy)."""
        j = np.clip(np.searchsorted(self.r_edges, x[:, 0], side="right") - 1, 0, len(self.wx_lo) - 1)
        return ((x[:, 0] <= self.r_edges[-1]) & (x[:, 1] >= self.wx_lo[j]) & (x[:, 1] <= self.wx_hi[j])
                & (x[:, 2] >= self.wy_lo[j]) & (x[:, 2] <= self.wy_hi[j]))

    # -- construction ---------------------------------------------------------------------------
    @staticmethod
    def from_valid(x: np.ndarray, domain, bins: int = 48, margin: float = 0.04):
        """Boxes around the valid reduced inputs ``x`` (N, 4): per bin, the extent of the valid rays of
        the bin and its two neighbours, widened by ``margin``·s_max each side and clipped to the
        domain.  Empty bins (and their neighbours' reach) get no box."""
        edges = np.linspace(0.0, domain.r_max, bins + 1)
        j = np.clip((x[:, 0] / domain.r_max * bins).astype(int), 0, bins - 1)
        lo = np.full((bins, 2), np.inf)
        hi = np.full((bins, 2), -np.inf)
        np.minimum.at(lo, j, x[:, 1:3])
        np.maximum.at(hi, j, x[:, 1:3])
        lo2, hi2 = lo.copy(), hi.copy()
        for s in (-1, 1):                                   # dilate by one bin either side
            src = slice(max(-s, 0), bins - max(s, 0))
            dst = slice(max(s, 0), bins - max(-s, 0))
            lo2[dst] = np.minimum(lo2[dst], lo[src])
            hi2[dst] = np.maximum(hi2[dst], hi[src])
        m = margin * domain.s_max
        empty = ~np.isfinite(lo2[:, 0])
        lo2, hi2 = np.where(empty[:, None], 0.0, lo2 - m), np.where(empty[:, None], 0.0, hi2 + m)
        s = domain.s_max
        return ValidBounds(edges, np.clip(lo2[:, 0], -s, s), np.clip(hi2[:, 0], -s, s),
                           np.clip(lo2[:, 1], 0.0, s), np.clip(hi2[:, 1], 0.0, s))

    @staticmethod
    def build(ps, rng: np.random.Generator, n_pilot: int = 1 << 22, min_valid: int = 20_000,
              max_missed: float = 1e-4, **kw):
        """Bounds for the :class:`~mi_neurallens.transport.sampling.PathSampler` ``ps`` from a uniform pilot
        of ``n_pilot`` rays, checked on a second independent pilot.  Returns ``None`` (sample the whole
        domain) when the pilot finds fewer than ``min_valid`` valid rays, or when more than
        ``max_missed`` of the second pilot's valid rays fall outside the boxes (the bounds would bias
        the training distribution)."""
        u1, _ = ps.random_valid(n_pilot, int(rng.integers(0, 2**47)), bounds=False)
        if len(u1) < min_valid:
            return None
        b = ValidBounds.from_valid(ps.domain.u_to_x(u1), ps.domain, **kw)
        u2, _ = ps.random_valid(n_pilot, int(rng.integers(0, 2**47)), bounds=False)
        b.missed = float(1.0 - b.contains(ps.domain.u_to_x(u2)).mean()) if len(u2) else 0.0
        return b if b.missed <= max_missed else None

    # -- Dr.Jit sampling ------------------------------------------------------------------------
    def sample_dr(self, F, u):
        """Unit-cube components ``u`` (4 Dr.Jit floats of type ``F``) → reduced inputs
        (r, ωx, ωy) uniform over the union of boxes (λ is left to the caller)."""
        import drjit as dr
        w = self.weights
        cdf = np.concatenate([[0.0], np.cumsum(w) / w.sum()])
        cdf[-1] = 1.0
        n = len(w)
        cdf_d = F(cdf)
        j = dr.binary_search(0, n - 1, lambda i: dr.gather(F, cdf_d, i + 1) <= u[0])
        c0, c1 = dr.gather(F, cdf_d, j), dr.gather(F, cdf_d, j + 1)
        t = dr.clip((u[0] - c0) / dr.maximum(c1 - c0, 1e-30), 0.0, 1.0)

        def g(a):
            return dr.gather(F, F(a), j)
        r = g(self.r_edges[:-1]) + t * g(np.diff(self.r_edges))
        wx = g(self.wx_lo) + u[1] * g(self.wx_hi - self.wx_lo)
        wy = g(self.wy_lo) + u[2] * g(self.wy_hi - self.wy_lo)
        return r, wx, wy

    def to_dict(self) -> dict:
        return {"bins": int(len(self.wx_lo)), "missed": self.missed}
