"""Multivariate polynomials for the polynomial-optics baselines.

Two classes:

* :class:`TPS` — a *truncated power series* (dense truncated multivariate polynomial) in ``nv``
  variables up to total degree ``D``: ``+ − × ÷``, ``sqrt``, ``cos`` (series about the constant term),
  :func:`compose` with truncation.  Exact Taylor arithmetic ("differential algebra"): running the
  exact ray-surface formulas on TPS arguments yields the degree-D Taylor expansion of the map.
* :class:`SparsePoly` — a list of monomials with coefficients for several outputs, evaluated in numpy
  (float64) and fused into Dr.Jit kernels with the coefficients as Python-float literals; monomials are
  shared between outputs and built by one multiply each from a parent monomial (a product tree).
  Inputs are normalised inside: ``v_i = (x_i − center_i) / scale_i``.

Monomial order: graded (total degree), then lexicographic; exponent tuples index the basis.
"""
from __future__ import annotations

from functools import lru_cache
from itertools import combinations_with_replacement
import math

import numpy as np


# ----------------------------------------------------------------------------------- basis
class Basis:
    """All monomials of ``nv`` variables with total degree ≤ ``D`` and the product table."""

    def __init__(self, nv: int, D: int):
        self.nv, self.D = nv, D
        exps = []
        for d in range(D + 1):
            block = []
            for combo in combinations_with_replacement(range(nv), d):
                e = [0] * nv
                for i in combo:
                    e[i] += 1
                block.append(tuple(e))
            exps += sorted(block, reverse=True)
        self.exps = np.array(exps, dtype=np.int64).reshape(-1, nv)
        self.index = {e: i for i, e in enumerate(exps)}
        self.deg = self.exps.sum(1)
        self.M = len(exps)
        I, J, K = [], [], []
        for i in range(self.M):
            for j in range(self.M):
                if self.deg[i] + self.deg[j] <= D:
                    I.append(i)
                    J.append(j)
                    K.append(self.index[tuple(self.exps[i] + self.exps[j])])
        self.I, self.J, self.K = (np.array(v, dtype=np.int64) for v in (I, J, K))


@lru_cache(maxsize=None)
def basis(nv: int, D: int) -> Basis:
    return Basis(nv, D)


# ----------------------------------------------------------------------------------- TPS
class TPS:
    """Truncated power series: coefficients ``c`` over :class:`Basis` ``(nv, D)``."""

    __slots__ = ("b", "c")

    def __init__(self, b: Basis, c):
        self.b = b
        self.c = np.asarray(c, dtype=np.float64)

    # constructors
    @staticmethod
    def const(b: Basis, v: float) -> "TPS":
        c = np.zeros(b.M)
        c[0] = v
        return TPS(b, c)

    @staticmethod
    def var(b: Basis, i: int, v0: float = 0.0) -> "TPS":
        c = np.zeros(b.M)
        c[0] = v0
        if b.D >= 1:
            e = [0] * b.nv
            e[i] = 1
            c[b.index[tuple(e)]] = 1.0
        return TPS(b, c)

    @property
    def c0(self) -> float:
        return float(self.c[0])

    def coef(self, e) -> float:
        return float(self.c[self.b.index[tuple(e)]])

    def truncate(self, d: int) -> "TPS":
        c = self.c.copy()
        c[self.b.deg > d] = 0.0
        return TPS(self.b, c)

    # arithmetic
    def _lift(self, o):
        return o if isinstance(o, TPS) else TPS.const(self.b, float(o))

    def __add__(self, o):
        if isinstance(o, TPS):
            return TPS(self.b, self.c + o.c)
        c = self.c.copy()
        c[0] += float(o)
        return TPS(self.b, c)

    __radd__ = __add__

    def __neg__(self):
        return TPS(self.b, -self.c)

    def __sub__(self, o):
        return self + (-o)

    def __rsub__(self, o):
        return (-self) + o

    def __mul__(self, o):
        if not isinstance(o, TPS):
            return TPS(self.b, self.c * float(o))
        b = self.b
        w = self.c[b.I] * o.c[b.J]
        return TPS(b, np.bincount(b.K, weights=w, minlength=b.M))

    __rmul__ = __mul__

    def __truediv__(self, o):
        if not isinstance(o, TPS):
            return TPS(self.b, self.c / float(o))
        return self * o.recip()

    def __rtruediv__(self, o):
        return self.recip() * float(o)

    def _series(self, coeffs) -> "TPS":
        """Σ coeffs[k] h^k with h = self − c0 (nilpotent beyond degree D), Horner."""
        h = self - self.c0
        out = TPS.const(self.b, coeffs[-1])
        for a in reversed(coeffs[:-1]):
            out = out * h + a
        return out

    def recip(self) -> "TPS":
        a0 = self.c0
        if a0 == 0.0:
            raise ZeroDivisionError("TPS reciprocal of a series with zero constant term")
        return self._series([(-1.0) ** k * a0 ** (-1 - k) for k in range(self.b.D + 1)])

    def sqrt(self) -> "TPS":
        a0 = self.c0
        if not a0 > 0.0:
            raise ValueError(f"TPS sqrt of a series with constant term {a0} ≤ 0")
        co, binom = [], 1.0
        for k in range(self.b.D + 1):
            co.append(binom * a0 ** (0.5 - k))
            binom *= (0.5 - k) / (k + 1)
        return self._series(co)

    def cos(self) -> "TPS":
        a0 = self.c0
        cyc = (math.cos(a0), -math.sin(a0), -math.cos(a0), math.sin(a0))
        return self._series([cyc[k % 4] / math.factorial(k) for k in range(self.b.D + 1)])

    def sin(self) -> "TPS":
        a0 = self.c0
        cyc = (math.sin(a0), math.cos(a0), -math.sin(a0), -math.cos(a0))
        return self._series([cyc[k % 4] / math.factorial(k) for k in range(self.b.D + 1)])

    def __call__(self, *args):
        return compose([self], list(args))[0]

    def eval_np(self, *xs) -> np.ndarray:
        """Evaluate at numpy points (each ``xs[i]`` an array)."""
        return SparsePoly.from_tps([self]).eval_np(np.stack(np.broadcast_arrays(*map(np.asarray, xs)), -1))[..., 0]

    def __repr__(self):
        nz = np.nonzero(self.c)[0]
        return "TPS(" + " + ".join(f"{self.c[i]:.6g}·{tuple(int(v) for v in self.b.exps[i])}" for i in nz[:8]) + \
            (" + …" if len(nz) > 8 else "") + ")"


def tps_vars(nv: int, D: int, values=None):
    b = basis(nv, D)
    values = values or [0.0] * nv
    return [TPS.var(b, i, values[i]) for i in range(nv)]


def compose(P, args):
    """``P`` (list of TPS in n variables) evaluated at ``args`` (n TPS over a common basis B2),
    truncated to B2's degree.  Exact truncated composition when every argument has a zero constant
    term (expansion about a fixed point, e.g. the optical axis)."""
    b1 = P[0].b
    b2 = args[0].b
    if len(args) != b1.nv:
        raise ValueError(f"compose: {b1.nv} arguments needed, got {len(args)}")
    mono = {tuple([0] * b1.nv): TPS.const(b2, 1.0)}
    outs = [TPS(b2, np.zeros(b2.M)) for _ in P]
    used = np.zeros(b1.M, dtype=bool)
    for p in P:
        used |= p.c != 0.0
    for m in range(b1.M):
        if not used[m]:
            continue
        e = tuple(int(v) for v in b1.exps[m])
        val = _mono_tps(e, mono, args)
        for o, p in zip(outs, P):
            if p.c[m] != 0.0:
                o.c += p.c[m] * val.c
    return outs


def _mono_tps(e, memo, args):
    if e in memo:
        return memo[e]
    i = max(k for k in range(len(e)) if e[k] > 0)
    parent = list(e)
    parent[i] -= 1
    v = _mono_tps(tuple(parent), memo, args) * args[i]
    memo[e] = v
    return v


# ----------------------------------------------------------------------------------- sparse evaluation
class SparsePoly:
    """Several polynomials sharing one monomial list, in normalised variables.

    ``exps`` (T, nv) int, ``coefs`` (T, n_out) float64, ``center``/``scale`` (nv,): the polynomial of
    output j is ``Σ_t coefs[t, j] Π_i ((x_i − center_i)/scale_i)^exps[t, i]``.
    """

    def __init__(self, exps, coefs, center=None, scale=None):
        self.exps = np.asarray(exps, dtype=np.int64).reshape(len(exps), -1)
        self.coefs = np.asarray(coefs, dtype=np.float64).reshape(len(self.exps), -1)
        nv = self.exps.shape[1]
        self.center = np.zeros(nv) if center is None else np.asarray(center, np.float64)
        self.scale = np.ones(nv) if scale is None else np.asarray(scale, np.float64)

    @property
    def nv(self):
        return self.exps.shape[1]

    @property
    def n_out(self):
        return self.coefs.shape[1]

    @staticmethod
    def from_tps(polys, drop: float = 0.0) -> "SparsePoly":
        b = polys[0].b
        C = np.stack([p.c for p in polys], 1)
        keep = np.any(np.abs(C) > drop, axis=1)
        keep[0] = True
        return SparsePoly(b.exps[keep], C[keep])

    def rescaled(self, center, scale) -> "SparsePoly":
        """The same polynomials expressed in variables normalised by ``scale`` (centre must be 0)."""
        if np.any(np.asarray(center) != 0) or np.any(self.center != 0):
            raise ValueError("rescaled: only zero centres are supported")
        s = np.asarray(scale, np.float64) / self.scale
        f = np.prod(s[None, :] ** self.exps, axis=1)
        return SparsePoly(self.exps, self.coefs * f[:, None], np.zeros(self.nv), np.asarray(scale, np.float64))

    def pruned(self, rel: float = 0.0) -> "SparsePoly":
        keep = np.any(np.abs(self.coefs) > rel * np.abs(self.coefs).max(initial=0.0), axis=1)
        return SparsePoly(self.exps[keep], self.coefs[keep], self.center, self.scale)

    def output(self, j) -> "SparsePoly":
        js = [j] if isinstance(j, int) else list(j)
        C = self.coefs[:, js]
        keep = np.any(C != 0.0, axis=1)
        return SparsePoly(self.exps[keep], C[keep], self.center, self.scale)

    @staticmethod
    def stack(polys) -> "SparsePoly":
        """Union of the monomials of several SparsePolys (same nv, centre and scale) → one multi-output."""
        p0 = polys[0]
        idx, rows = {}, []
        for p in polys:
            for e in map(tuple, p.exps):
                if e not in idx:
                    idx[e] = len(rows)
                    rows.append(e)
        C = np.zeros((len(rows), sum(p.n_out for p in polys)))
        j = 0
        for p in polys:
            for t, e in enumerate(map(tuple, p.exps)):
                C[idx[e], j:j + p.n_out] = p.coefs[t]
            j += p.n_out
        return SparsePoly(np.array(rows).reshape(len(rows), p0.nv), C, p0.center, p0.scale)

    # ---- monomial plan: each monomial of degree ≥ 2 = parent monomial × one variable
    def _plan(self):
        if getattr(self, "_plan_cache", None) is None:
            nv = self.nv
            order, have = [], {tuple([0] * nv)}
            for i in range(nv):
                e = [0] * nv
                e[i] = 1
                have.add(tuple(e))

            def need(e):
                if e in have:
                    return
                i = max(k for k in range(nv) if e[k] > 0)
                p = list(e)
                p[i] -= 1
                p = tuple(p)
                need(p)
                order.append((e, p, i))
                have.add(e)

            for e in map(tuple, self.exps):
                need(e)
            self._plan_cache = order
        return self._plan_cache

    def flops(self) -> int:
        """Multiplies for the monomials + 2 per term and output (fma) + 2 per input normalisation."""
        nz = int(np.count_nonzero(self.coefs))
        return len(self._plan()) + 2 * nz + 2 * self.nv

    def eval_np(self, X) -> np.ndarray:
        """X (N, nv) → (N, n_out), float64."""
        X = (np.asarray(X, np.float64) - self.center) / self.scale
        nv = self.nv
        mono = {tuple([0] * nv): np.ones(X.shape[:-1])}
        for i in range(nv):
            e = [0] * nv
            e[i] = 1
            mono[tuple(e)] = X[..., i]
        for e, p, i in self._plan():
            mono[e] = mono[p] * X[..., i]
        out = np.zeros(X.shape[:-1] + (self.n_out,))
        for t, e in enumerate(map(tuple, self.exps)):
            c = self.coefs[t]
            nzj = np.nonzero(c)[0]
            for j in nzj:
                out[..., j] += c[j] * mono[e]
        return out

    def eval_dr(self, xs):
        """xs: list of nv Dr.Jit floats → list of n_out Dr.Jit floats (literal coefficients)."""
        import drjit as dr
        nv = self.nv
        v = [dr.fma(x, 1.0 / float(s), -float(c) / float(s)) if (c != 0.0 or s != 1.0) else x
             for x, c, s in zip(xs, self.center, self.scale)]
        mono = {}
        for i in range(nv):
            e = [0] * nv
            e[i] = 1
            mono[tuple(e)] = v[i]
        for e, p, i in self._plan():
            mono[e] = mono[p] * v[i]
        zero_e = tuple([0] * nv)
        outs = []
        for j in range(self.n_out):
            c0, terms = 0.0, []
            for t, e in enumerate(map(tuple, self.exps)):
                cj = float(self.coefs[t, j])
                if cj == 0.0:
                    continue
                if e == zero_e:
                    c0 += cj
                else:
                    terms.append((e, cj))
            if not terms:
                outs.append(v[0] * 0.0 + c0)
                continue
            e, cj = terms[0]
            acc = dr.fma(mono[e], cj, c0)
            for e, cj in terms[1:]:
                acc = dr.fma(mono[e], cj, acc)
            outs.append(acc)
        return outs


# ----------------------------------------------------------------------------------- fitting helpers
def monomial_template(nv: int, D: int, parity=None):
    """Exponents of every monomial of total degree ≤ D (graded order).  ``parity``: optional
    ``(var, p)``: keep only monomials whose exponent of ``var`` has parity p (0 even, 1 odd)."""
    e = basis(nv, D).exps if D <= 12 and nv <= 5 else None
    if e is None:  # pragma: no cover
        raise ValueError("template too large")
    if parity is not None:
        var, p = parity
        e = e[(e[:, var] % 2) == p]
    return e


def design_matrix(V, exps) -> np.ndarray:
    """V (N, nv) normalised inputs → (N, T) monomial values."""
    V = np.asarray(V, np.float64)
    exps = np.asarray(exps)
    maxe = int(exps.max(initial=0))
    A = None
    for i in range(V.shape[1]):
        P = np.empty((V.shape[0], maxe + 1))
        P[:, 0] = 1.0
        for k in range(1, maxe + 1):
            P[:, k] = P[:, k - 1] * V[:, i]
        cols = P[:, exps[:, i]]
        A = cols if A is None else np.multiply(A, cols, out=A)
    return A


def omp(A, y, n_terms: int, always=(), tol: float = 0.0):
    """Orthogonal matching pursuit: greedily pick up to ``n_terms`` columns of ``A`` (the one most
    correlated with the residual, columns normalised), re-solving least squares on the picked set after
    each pick (Gram-Schmidt, so each step is O(N·T)).  ``always``: column indices picked first.
    Returns (indices, coefficients)."""
    A = np.asarray(A, np.float64)
    y = np.asarray(y, np.float64)
    N, T = A.shape
    norms = np.sqrt(np.einsum("ij,ij->j", A, A))
    norms[norms == 0] = 1.0
    Q = np.zeros((N, min(n_terms, T)))
    nq_used = 0
    picked = []
    r = y.copy()
    avail = np.ones(T, dtype=bool)
    ynorm = np.linalg.norm(y) + 1e-300
    for step in range(min(n_terms, T)):
        if step < len(always):
            k = int(always[step])
        else:
            corr = np.abs(A.T @ r) / norms
            corr[~avail] = -1.0
            k = int(np.argmax(corr))
            if corr[k] <= 0:
                break
        avail[k] = False
        Qu = Q[:, :nq_used]
        q = A[:, k] / norms[k]
        q = q - Qu @ (Qu.T @ q)
        q = q - Qu @ (Qu.T @ q)                 # re-orthogonalise (numerical safety)
        nq = np.linalg.norm(q)
        if nq < 1e-10:
            continue
        q /= nq
        Q[:, nq_used] = q
        nq_used += 1
        picked.append(k)
        r = r - q * (q @ r)
        if np.linalg.norm(r) <= tol * ynorm:
            break
    idx = np.array(picked, dtype=np.int64)
    if len(idx) == 0:
        return idx, np.zeros(0)
    coef, *_ = np.linalg.lstsq(A[:, idx], y, rcond=None)
    return idx, coef
