"""Fitted sparse polynomials (Hanika & Dachsbacher 2014 / Schrade et al. 2016 style, as in lentil).

Inputs: the neural maps' reduced inputs (r, ωx, ωy, λ) on ``z_in`` (:mod:`mi_neurallens.trace.symmetry`),
normalised to [−1, 1] as ``(2r/r_max − 1, ωx/s_max, ωy/s_max, (λ − λ_c)/λ_h)`` over the map's domain
(λ_c, λ_h: centre and half width of its λ range).  Outputs, in the reduced frame: exit position (x, y) on ``z_out``, exit
direction cosines (dx, dy), Fresnel throughput T — the same as the neural regressor.

Data: valid rays traced exactly (float64) over the domain the neural map uses, with the training data's
sampler (uniform over the valid region by rejection, or the Metropolis sampler for rare paths:
:func:`mi_neurallens.transport.sampling.heldout_valid`), ``n_samples`` of them (default 20 000; lentil
uses 15 000).  The sampler is imported inside the fit (:class:`FittedMap`'s constructor) only: a fitted map is
fitted when it is built.

Term selection: per output, **orthogonal matching pursuit** over the template of all monomials of total
degree ≤ ``degree`` (default 11, like lentil) that have the output's parity in ωy (mirror symmetry makes
x, dx, T even and y, dy odd in ωy), up to ``terms`` terms (default 28, lentil's default): repeatedly add
the monomial most correlated with the current residual, then re-solve least squares on the chosen set.

Validity (``valid=``):

* ``"classifier"`` — the bundled neural model's classifier of the same map (the paper's factorisation,
  polynomial regressor);
* ``"aperture"`` — *aperture polynomials*: for each step of the path that clips rays (stop, clear
  apertures), a sparse polynomial (same template/OMP/budget) of r² = x² + y² of the hit point, fitted to
  rays that reach that step, tested against the aperture radius², plus the domain;
* ``"all"`` — every ray in the domain is valid;
* ``"auto"`` (default) — ``"classifier"`` when a bundled map exists, else ``"aperture"``.
"""
from __future__ import annotations

import numpy as np

from .common import BaselineMap, bundled_model, default_domain
from .poly import SparsePoly, design_matrix, monomial_template, omp

#: ωy parity of each output (x, y, dx, dy, T): 0 even, 1 odd
PARITY = (0, 1, 0, 1, 0)


def fit_sparse(V, Y, degree: int, terms: int, parities, tol: float = 0.0) -> SparsePoly:
    """OMP fit of each column of ``Y`` (N, k) on normalised inputs ``V`` (N, 4); ``parities[j]``: ωy parity
    of output j (None: no constraint).  Returns one SparsePoly (normalised variables) with k outputs."""
    polys, cache = [], {}
    for j in range(Y.shape[1]):
        par = parities[j]
        if par not in cache:
            ex = monomial_template(V.shape[1], degree, None if par is None else (2, par))
            cache[par] = (ex, design_matrix(V, ex))
        ex, A = cache[par]
        always = [0] if par == 0 else []
        idx, coef = omp(A, Y[:, j], terms, always=always, tol=tol)
        polys.append(SparsePoly(ex[idx], coef[:, None]))
    return SparsePoly.stack(polys)


class FittedMap(BaselineMap):
    """A sparse polynomial fit of one map (see the module docstring)."""

    method = "fitted"
    reduced = True

    def __init__(self, lens, path="transmit", direction="forward", z_in=None, z_out=None, *,
                 domain=None, degree: int = 11, terms: int = 28, n_samples: int = 20000,
                 valid: str = "auto", seed: int = 7, model=None, data=None, fresnel: bool = True):
        super().__init__(lens, path, direction, z_in, z_out)
        if valid not in ("auto", "classifier", "aperture", "all"):
            raise ValueError(f"fitted valid must be 'auto', 'classifier', 'aperture' or 'all', got {valid!r}")
        self.degree, self.terms = int(degree), int(terms)
        model = bundled_model(lens) if model is None else model
        self.domain = default_domain(lens, self.path_id, direction, model) if domain is None else domain
        d = self.domain
        # every input to [-1, 1] (r centred: powers of a centred variable are far less correlated, which
        # greedy selection needs); ωy is not centred so that the mirror parity in ωy stays a parity
        self.in_center = np.array([0.5 * d.r_max, 0.0, 0.0, 0.5 * (d.lam_min + d.lam_max)])
        self.in_scale = np.array([0.5 * d.r_max, d.s_max, d.s_max, 0.5 * (d.lam_max - d.lam_min)])
        self.tm = None
        if valid in ("auto", "classifier"):
            if model is not None and model.has(self.path_id, direction):
                self.tm = model.map(self.path_id, direction)
                valid = "classifier"
            elif valid == "classifier":
                from ..errors import ModelError
                raise ModelError(f"fitted valid='classifier': no bundled neural map {self.key} for lens "
                                 f"'{lens.name}'; use valid='aperture' or 'all'")
            else:
                valid = "aperture"
        self.valid_mode = valid
        # --- regressor data and fit
        if data is None:                # the fit's data: the training's held-out sampler
            from ..transport.sampling import heldout_valid
            data = heldout_valid(lens, (self.path_id, direction, self.z_in, self.z_out), d, n_samples, seed,
                                 fresnel=fresnel)
        x, y = data
        self.n_fit = len(x)
        V = (x - self.in_center) / self.in_scale
        reg = fit_sparse(V, y, self.degree, self.terms, PARITY)
        # --- aperture polynomials
        self.ap_radii2 = []
        polys = [reg]
        if valid == "aperture":
            ap, r2 = self._fit_apertures(seed + 101)
            if ap is not None:
                polys.append(ap)
                self.ap_radii2 = r2
        sp = SparsePoly.stack(polys)
        self.core = SparsePoly(sp.exps, sp.coefs, self.in_center, self.in_scale)
        self.train_rms = np.sqrt(np.mean((reg.eval_np(V) - y) ** 2, axis=0))

    def _fit_apertures(self, seed, n: int = 1 << 19, n_fit: int = 10000):
        """Fit r² of the hit point of every clipping step on rays that reach it (float64 tracer)."""
        from ..trace.api import float_type
        from ..trace.tracer import LensTracer
        import drjit as dr
        lens, d = self.lens, self.domain
        rng = np.random.default_rng(seed)
        u = rng.random((n, 4))
        x = d.u_to_x(u)
        F = float_type("float64")
        tr = LensTracer(lens)
        dz = self.heading * np.sqrt(np.maximum(1.0 - x[:, 1] ** 2 - x[:, 2] ** 2, 0.0))
        z = np.zeros(n)
        res = tr.trace((F(x[:, 0]), F(z), F(z + self.z_in)), (F(x[:, 1]), F(x[:, 2]), F(dz)), F(x[:, 3]),
                       self.path_id, self.direction, z_out=self.z_out, record=True)
        dr.eval(res.points, res.alive)
        V = (x - self.in_center) / self.in_scale
        cols, radii2 = [], []
        for k, st in enumerate(self.spec.steps):
            px, py, _ = (np.asarray(c.numpy(), np.float64) for c in res.points[k + 1])
            reach = np.broadcast_to(res.alive[k + 1].numpy().astype(bool), (n,))
            R = st.clear_radius
            r2 = px * px + py * py
            ok = reach & np.isfinite(r2)
            if ok.sum() < 50 or not np.any(r2[ok] > R * R):
                continue                          # this step never clips a ray that reaches it
            idx = np.nonzero(ok)[0]
            if len(idx) > n_fit:
                idx = rng.choice(idx, n_fit, replace=False)
            cols.append((V[idx], r2[idx] / (R * R)))
            radii2.append(1.0)
        if not cols:
            return None, []
        polys = []
        for Vk, yk in cols:
            polys.append(fit_sparse(Vk, yk[:, None], self.degree, self.terms, (0,)))
        return SparsePoly.stack(polys), radii2

    # ------------------------------------------------------------------ evaluation
    def flops(self) -> int:
        f = self.core.flops() + 40          # symmetry reduce/undo, domain test, dz
        if self.tm is not None:
            f += sum(2 * W.shape[0] * W.shape[1] + 12 * W.shape[0] for W, _ in self.tm.classifier)
        return f

    def core_reduced_dr(self, x, active):
        import drjit as dr
        from ..neural.mlp import mlp_dr
        y = self.core.eval_dr(list(x))
        valid = active
        for k, R2 in enumerate(self.ap_radii2):
            valid &= y[5 + k] <= R2
        logit = None
        if self.tm is not None:
            tm = self.tm
            xn = [dr.fma(v, 1.0 / float(s), -float(c) / float(s))
                  for v, c, s in zip(x, tm.input_center, tm.input_scale)]
            logit = mlp_dr(xn, tm.classifier, tm.classifier_activation)[0]
            valid &= logit > 0.0
        valid &= dr.fma(y[2], y[2], y[3] * y[3]) < 1.0     # a unit exit direction (rotation invariant)
        return valid, y[:5], logit

    def describe(self) -> dict:
        return {**super().describe(), "degree": self.degree, "terms_per_output": self.terms,
                "valid": self.valid_mode, "n_fit": self.n_fit, "aperture_polynomials": len(self.ap_radii2),
                "domain": self.domain.to_dict(),
                "train_rms": {k: float(v) for k, v in zip(("x", "y", "dx", "dy", "T"), self.train_rms)}}
