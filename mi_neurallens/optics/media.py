"""Optical media: refractive index as a function of wavelength.

A :class:`Medium` is an immutable description of n(λ) by a closed *formula* and a tuple of
*coefficients*.  The same object evaluates

* in numpy (float64), :meth:`Medium.index`, for paraxial optics and tests, and
* inside Dr.Jit kernels, :meth:`Medium.dr_index`, with the coefficients baked in as literals
  (no catalog lookups, no gathers), for the exact tracer.

Wavelengths are in **nanometres** in the public API.  Catalog formulas are written with λ in
micrometres, as the vendors publish them; the conversion happens inside the formula.

Formulas (λ in µm inside the formula):

``constant``      n = c0
``sellmeier``     n² = 1 + Σ_i B_i λ² / (λ² − C_i)          coefficients (B1, C1, B2, C2, ...)
``power_n2``      n² = Σ_i a_i λ^(p_i)                       coefficients (p1, a1, p2, a2, ...)
``table``         linear interpolation in (λ_nm, n) pairs, linear extrapolation from the end
                  segments (what Open Optical Designer does); coefficients (λ1, n1, λ2, n2, ...)
``buchdahl``      n = n0 + ν1 ω + ν2 ω² + ν3 ω³,  ω = (λ − λ0)/(1 + 2.5 (λ − λ0)) (λ, λ0 in µm);
                  coefficients (λ0_µm, n0, ν1, ν2, ν3); used for model glasses from (nd, Vd)

Where media come from (all return a :class:`Medium`; file readers call
:func:`mi_neurallens.optics.glass.resolve_medium`; :func:`catalog_glass` and :func:`ood_material` live in
:mod:`mi_neurallens.optics.catalogs`):

:func:`catalog_glass`   a vendor glass from the ``opticalglass`` spreadsheets (imported lazily).
                        Schott, Ohara (3-term Sellmeier, ``coefs`` = B1 B2 B3 C1 C2 C3) →
                        ``sellmeier``; Hoya, CDGM, Sumita (n² = A0 + A1λ² + A2λ⁻² … A5λ⁻⁸) and
                        Hikari (n² = A0 + A1λ² + A2λ⁴ + A3λ⁻² … A8λ⁻¹²) → ``power_n2``.
:func:`model_glass`     (nd, Vd) only → quadratic ``buchdahl``.  ν1, ν2 are fixed by nF − nC =
                        (nd − 1)/Vd and by ng − nF = P_gF(Vd)·(nF − nC), where P_gF(Vd) is a normal
                        glass line fitted to the catalogs (see :data:`NORMAL_LINE_PGF`).  nd, nF − nC
                        exact; always strictly decreasing on 360–830 nm; Vd → ∞ gives a flat index.
                        ``model="opticalglass"`` reproduces ``opticalglass.modelglass.ModelGlass``.
:func:`lines_glass`     patent line indices (C, d, F [, g] [, e]) → ``power_n2`` interpolating every
                        given line exactly (with only C, d, F, ng is first imputed from P_gF(Vd)).
:func:`table_glass`     (λ_nm, n) pairs → ``table``.
:func:`ood_material`    the material table of Open Optical Designer (``data/ood-materials.json``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
import math
import numbers

import numpy as np

from ..constants import LAMBDA_C, LAMBDA_D, LAMBDA_E, LAMBDA_F, VISIBLE_RANGE_NM
from ..errors import GlassError

FORMULAS = ("constant", "sellmeier", "power_n2", "table", "buchdahl")


@dataclass(frozen=True)
class Medium:
    """n(λ) of one medium.  Hashable; two media with equal formula and coefficients are equal."""

    name: str
    formula: str
    coefficients: tuple[float, ...]
    #: where the data came from, e.g. ``{"catalog": "Ohara", "glass": "S-LAL14"}``; informative only
    source: dict = field(default_factory=dict, compare=False, hash=False)

    def __post_init__(self):
        if self.formula not in FORMULAS:
            raise GlassError(f"medium '{self.name}': unknown formula '{self.formula}'; "
                             f"valid: {', '.join(FORMULAS)}")
        c = tuple(float(v) for v in self.coefficients)
        if not all(math.isfinite(v) for v in c):
            raise GlassError(f"medium '{self.name}': non-finite dispersion coefficient in {c}")
        object.__setattr__(self, "coefficients", c)

    # ------------------------------------------------------------------ evaluation
    def index(self, wavelength_nm):
        """Refractive index at ``wavelength_nm`` (float or numpy array, nm), float64 numpy."""
        lam = np.asarray(wavelength_nm, dtype=np.float64)
        return self._eval(lam, np, np.sqrt)

    def dr_index(self, lam_nm):
        """Refractive index inside a Dr.Jit kernel.

        ``lam_nm`` is any Dr.Jit float array (``mi.Float``, ``Float64``, ...) of wavelengths in nm.
        Coefficients enter as Python floats, i.e. literals in the generated kernel.
        """
        import drjit as dr
        return self._eval(lam_nm, None, dr.sqrt)

    @property
    def is_constant(self) -> bool:
        return self.formula == "constant"

    def _eval(self, lam_nm, xp, sqrt):
        f, c = self.formula, self.coefficients
        if f == "constant":
            return lam_nm * 0.0 + c[0]
        if f == "table":
            return _table_eval(lam_nm, c, xp)
        lam = lam_nm * 1e-3  # µm
        if f == "sellmeier":
            l2 = lam * lam
            n2 = 1.0
            for b, cc in zip(c[0::2], c[1::2]):
                n2 = n2 + b * l2 / (l2 - cc)
            return sqrt(n2)
        if f == "power_n2":
            n2 = 0.0
            for p, a in zip(c[0::2], c[1::2]):
                n2 = n2 + a * _pow_int(lam, int(round(p)))
            return sqrt(n2)
        if f == "buchdahl":
            l0, n0, v1, v2, v3 = c
            dl = lam - l0
            w = dl / (1.0 + 2.5 * dl)
            return n0 + w * (v1 + w * (v2 + w * v3))
        raise AssertionError(f)

    # ------------------------------------------------------------------ derived numbers
    @property
    def nd(self) -> float:
        return float(self.index(LAMBDA_D))

    @property
    def vd(self) -> float:
        """Abbe number (nd − 1)/(nF − nC); ``inf`` for a dispersion-free medium."""
        dn = float(self.index(LAMBDA_F) - self.index(LAMBDA_C))
        return math.inf if dn == 0 else (self.nd - 1.0) / dn

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict:
        d = {"name": self.name, "formula": self.formula, "coefficients": list(self.coefficients)}
        if self.source:
            d["source"] = dict(self.source)
        return d

    @staticmethod
    def from_dict(d: dict) -> "Medium":
        return Medium(str(d["name"]), str(d["formula"]), tuple(d["coefficients"]),
                      dict(d.get("source", {})))

    def __repr__(self) -> str:
        if self.formula == "constant":
            return f"Medium({self.name!r}, n={self.coefficients[0]:.6g})"
        return f"Medium({self.name!r}, {self.formula}, nd={self.nd:.6f}, vd={self.vd:.2f})"


def _pow_int(x, p: int):
    if p == 0:
        return x * 0.0 + 1.0
    if p < 0:
        return 1.0 / _pow_int(x, -p)
    r = x
    for _ in range(p - 1):
        r = r * x
    return r


def _table_eval(lam_nm, c, xp):
    ls, ns = c[0::2], c[1::2]
    if len(ls) == 1:
        return lam_nm * 0.0 + ns[0]

    def seg(k):
        s = (ns[k + 1] - ns[k]) / (ls[k + 1] - ls[k])
        return ns[k] + (lam_nm - ls[k]) * s

    # Piecewise-linear, written as a chain of selects so it works on numpy and Dr.Jit arrays.
    out = seg(0)
    for k in range(1, len(ls) - 1):
        if xp is not None:
            out = xp.where(lam_nm >= ls[k], seg(k), out)
        else:
            import drjit as dr
            out = dr.select(lam_nm >= ls[k], seg(k), out)
    return out


def constant(n: float, name: str | None = None) -> Medium:
    """A dispersion-free medium of index ``n``."""
    return Medium(name or ("air" if n == 1.0 else f"n={n:g}"), "constant", (float(n),))


AIR = constant(1.0, "air")


# ====================================================================== plausibility checks
#: Wavelength range (nm) over which model, line and table glasses must be physically plausible.
CHECK_RANGE_NM = VISIBLE_RANGE_NM


def _implausibility(m: Medium, strict: bool = True) -> str | None:
    """Why ``m`` is not a normal-dispersion glass on :data:`CHECK_RANGE_NM` (None if it is):
    finite, n ≥ 1, strictly decreasing (non-increasing unless ``strict``)."""
    lam = np.linspace(CHECK_RANGE_NM[0], CHECK_RANGE_NM[1], 941)  # 0.5 nm steps
    with np.errstate(all="ignore"):
        n = m.index(lam)
    if not np.all(np.isfinite(n)):
        k = int(np.argmin(np.isfinite(n)))
        return f"n is undefined at {lam[k]:g} nm"
    if np.min(n) < 1.0:
        k = int(np.argmin(n))
        return f"n = {n[k]:.6f} < 1 at {lam[k]:g} nm"
    d = np.diff(n)
    if not np.all(d < 0 if strict else d <= 0):
        k = int(np.argmax(d >= 0))
        return (f"n is not strictly decreasing with wavelength: n({lam[k]:g} nm) = {n[k]:.7f}, "
                f"n({lam[k + 1]:g} nm) = {n[k + 1]:.7f}")
    return None


def _real(x, what: str) -> float:
    """``x`` as a finite float; bools, strings, NaN and infinities raise GlassError."""
    if isinstance(x, bool) or not isinstance(x, numbers.Real):
        raise GlassError(f"{what} must be a number, got {x!r} ({type(x).__name__})")
    v = float(x)
    if not math.isfinite(v):
        raise GlassError(f"{what} must be finite, got {x!r}")
    return v


# ====================================================================== model glasses
#: Normal line of the relative partial dispersion P_gF = (ng − nF)/(nF − nC) as a function of Vd:
#: P_gF = c0 + c1·Vd + c2·Vd², Vd clamped to ``vd_range``.  Least-squares fit over the 983 glasses
#: of the six opticalglass 1.1.1 catalogs (rms 0.0042; a straight line leaves rms 0.0113).
NORMAL_LINE_PGF = {"c": (7.221e-1, -5.002e-3, 3.302e-5), "vd_range": (16.5, 101.0)}

# opticalglass' Buchdahl2 normal line ν1 = b + m ν2.
_OG_MODEL_B, _OG_MODEL_M = -0.064667, -1.604048

_L0_UM = LAMBDA_D * 1e-3
LAMBDA_G = 435.8343


def _omega(lam_nm: float) -> float:
    dl = lam_nm * 1e-3 - _L0_UM  # same arithmetic as Medium._eval
    return dl / (1.0 + 2.5 * dl)


def _pgf_normal(vd: float) -> float:
    lo, hi = NORMAL_LINE_PGF["vd_range"]
    c0, c1, c2 = NORMAL_LINE_PGF["c"]
    v = min(max(vd, lo), hi)
    return c0 + v * (c1 + v * c2)


def model_glass(nd: float, vd: float, name: str | None = None, *, model: str = "normal-line"
                ) -> Medium:
    """A model glass from nd and the Abbe number Vd only (formula ``buchdahl``, quadratic).

    n(587.5618 nm) = nd and nF − nC = (nd − 1)/Vd exactly.  The second constraint comes from the
    partial-dispersion normal line :data:`NORMAL_LINE_PGF` (ng − nF = P_gF(Vd)·(nF − nC)), so the
    curve is a fixed shape scaled by nF − nC: strictly decreasing on 360–830 nm for any Vd > 0
    and flat for Vd = inf.  Against the 983 catalog glasses it is within 1.4e-4 (median) /
    6e-4 (95th percentile) of the real index on 400–700 nm.

    ``model="opticalglass"`` instead reproduces opticalglass 1.1.1's ``ModelGlass`` (Buchdahl2,
    ν1 = b + m ν2), for cross-checks against rayoptics.  Caveats of that model: its nF − nC is
    *not* (nd − 1)/Vd (Buchdahl2.update divides by m·δω − δω² where the constraint needs
    m·δω + δω²: Vd 30 comes out as 29.27), it is not monotonic for low-dispersion glass
    (nd 1.45, Vd 90) and it is not flat for large Vd.  Only nd is checked for it.
    """
    nd = _real(nd, "model glass nd")
    if isinstance(vd, bool) or not isinstance(vd, numbers.Real) or math.isnan(float(vd)):
        raise GlassError(f"model glass Vd must be a number, got {vd!r}")
    vd = float(vd)
    if not nd > 1.0:
        raise GlassError(f"model glass nd must be > 1, got {nd!r}")
    if not vd > 0.0:
        raise GlassError(f"model glass Vd must be > 0 (or inf for no dispersion), got {vd!r}")
    dfc = 0.0 if math.isinf(vd) else (nd - 1.0) / vd
    wF, wC, wg = _omega(LAMBDA_F), _omega(LAMBDA_C), _omega(LAMBDA_G)
    if model == "normal-line":
        a11, a12 = wF - wC, wF * wF - wC * wC
        a21, a22 = wg - wF, wg * wg - wF * wF
        r1, r2 = dfc, _pgf_normal(vd) * dfc
        det = a11 * a22 - a12 * a21
        v1 = (r1 * a22 - a12 * r2) / det
        v2 = (a11 * r2 - a21 * r1) / det
    elif model == "opticalglass":
        dw, dw2 = wF - wC, wF * wF - wC * wC
        v2 = (dfc - _OG_MODEL_B * dw) / (_OG_MODEL_M * dw - dw2)
        v1 = _OG_MODEL_B + _OG_MODEL_M * v2
    else:
        raise GlassError(f"unknown model glass model {model!r}; valid: 'normal-line', 'opticalglass'")
    label = name or f"model nd={nd:.6g} vd={vd:.6g}"
    m = Medium(label, "buchdahl", (_L0_UM, nd, v1, v2, 0.0),
               {"model": model, "nd": nd, "vd": vd})
    if model == "normal-line":
        why = _implausibility(m, strict=dfc > 0.0)
        if why:
            raise GlassError(f"model glass nd={nd!r}, Vd={vd!r} is not a plausible glass "
                             f"({why}); Vd is usually 15–100")
    return m


# ====================================================================== line glasses
LINES_NM = {"C": LAMBDA_C, "d": LAMBDA_D, "F": LAMBDA_F, "g": LAMBDA_G, "e": LAMBDA_E}

# Powers of λ (µm) in n² = Σ a_i λ^p_i, by number of lines (C, d, F [+ g imputed] / + g / + e).
_LINE_POWERS = {4: (0, -2, -4, -6), 5: (2, 0, -2, -4, -6)}


def lines_glass(nd: float, nC: float, nF: float, ng: float | None = None, ne: float | None = None,
                name: str | None = None) -> Medium:
    """A glass from patent line indices (formula ``power_n2``), exact at every given line.

    Lines: C 656.2725, d 587.5618, F 486.1327, g 435.8343, e 546.074 nm.  n² is interpolated in
    powers of λ (µm): four lines → λ⁰, λ⁻², λ⁻⁴, λ⁻⁶; five (g and e) → λ², λ⁰, λ⁻², λ⁻⁴, λ⁻⁶.
    With only C, d, F the g index is imputed from the normal line :data:`NORMAL_LINE_PGF`
    (a plain 3-term Cauchy fit through C, d, F is ~4× further from real glasses).  Raises
    :class:`GlassError` unless n is ≥ 1 and strictly decreasing on 360–830 nm.
    """
    vals = {"d": _real(nd, "nd"), "C": _real(nC, "nC"), "F": _real(nF, "nF")}
    if ng is not None:
        vals["g"] = _real(ng, "ng")
    if ne is not None:
        vals["e"] = _real(ne, "ne")
    for k, v in vals.items():
        if not v >= 1.0:
            raise GlassError(f"line index n{k} must be ≥ 1, got {v!r}")
    if not vals["F"] > vals["d"] > vals["C"]:
        raise GlassError(f"line indices must satisfy nF > nd > nC (normal dispersion), got "
                         f"nC={vals['C']!r}, nd={vals['d']!r}, nF={vals['F']!r}")
    source = {"lines": dict(vals)}
    fit = dict(vals)
    if len(vals) == 3:
        dfc = vals["F"] - vals["C"]
        fit["g"] = vals["F"] + _pgf_normal((vals["d"] - 1.0) / dfc) * dfc
        source["imputed"] = {"g": fit["g"]}
    powers = _LINE_POWERS[len(fit)]
    keys = [k for k in ("C", "d", "e", "F", "g") if k in fit]
    lam = np.array([LINES_NM[k] * 1e-3 for k in keys])
    A = np.array([[_pow_int(l, p) for p in powers] for l in lam])
    b = np.array([fit[k] ** 2 for k in keys])
    a = np.linalg.solve(A, b)
    a = a + np.linalg.solve(A, b - A @ a)  # one step of iterative refinement
    coefs = []
    for p, ai in zip(powers, a):
        coefs += [float(p), float(ai)]
    label = name or f"lines nd={vals['d']:.6g}"
    m = Medium(label, "power_n2", tuple(coefs), source)
    why = _implausibility(m)
    if why:
        given = ", ".join(f"n{k}={v!r}" for k, v in vals.items())
        raise GlassError(f"line indices {given} do not describe a normal glass on "
                         f"{CHECK_RANGE_NM[0]:g}–{CHECK_RANGE_NM[1]:g} nm ({why})")
    return m


# ====================================================================== tables
def table_glass(pairs_nm_n, name: str) -> Medium:
    """A tabulated medium from ``[(λ_nm, n), ...]``: linear interpolation, linear extrapolation
    from the end segments (what Open Optical Designer does).  One pair gives a constant index."""
    if isinstance(pairs_nm_n, (str, bytes, dict)) or not hasattr(pairs_nm_n, "__len__"):
        raise GlassError(f"table must be a list of [wavelength_nm, n] pairs, got {pairs_nm_n!r}")
    if len(pairs_nm_n) < 1:
        raise GlassError("table must hold at least one [wavelength_nm, n] pair, got none")
    coefs = []
    prev = -math.inf
    for i, pair in enumerate(pairs_nm_n):
        if isinstance(pair, (str, bytes, dict)) or not hasattr(pair, "__len__") or len(pair) != 2:
            raise GlassError(f"table entry {i} must be a [wavelength_nm, n] pair, got {pair!r}")
        lam = _real(pair[0], f"table entry {i} wavelength")
        n = _real(pair[1], f"table entry {i} index")
        if not lam > 0:
            raise GlassError(f"table entry {i}: wavelength must be > 0 nm, got {pair[0]!r}")
        if not n > 0:
            raise GlassError(f"table entry {i}: index must be > 0, got {pair[1]!r}")
        if not lam > prev:
            raise GlassError(f"table wavelengths must be strictly increasing; entry {i} "
                             f"({lam:g} nm) follows {prev:g} nm")
        prev = lam
        coefs += [lam, n]
    if not isinstance(name, str) or not name:
        raise GlassError(f"table medium needs a non-empty name, got {name!r}")
    return Medium(name, "table", tuple(coefs), {"table": True})
