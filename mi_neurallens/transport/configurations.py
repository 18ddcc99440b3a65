"""A lens's moving groups as inputs of one learned map: zoom and focus beside the ray.

A zoom lens, or one that focuses by moving groups of its elements (:mod:`mi_neurallens.optics.moving`), is a
family of lenses: one per configuration (zoom parameter ``t``, focus parameter ``f``).  One learned map serves the
whole family when the configuration is an input of its networks, beside the reduced ray ``(r, ωx, ωy, λ)``:
:class:`Configurations` says which parameters are inputs (``"zoom"`` for a zoom lens, ``"focus"`` for a lens whose
groups focus), over which range they were learned, and gives the tracer the geometry of a configuration **per
ray**, so that one kernel traces training rays of many configurations at once.

* **Range.**  ``t`` over the listed positions, ``[0, n−1]``; ``f`` at each ``t`` over the *focus band*: from the
  focus parameter that images infinity on the sensor to the one that images the close-focus distance, each both
  paraxially (d line) and where the real rays focus best (:func:`mi_neurallens.optics.moving.focus_parameter`; the
  sensors focus there: :func:`~mi_neurallens.optics.moving.configure`), widened by :data:`FOCUS_MARGIN` of its
  width on each side, since a network errs most at the edge of what it learned.  Tabulated at :data:`BAND_GRID`
  zoom parameters, linear between them.
* **Sampling.**  A training sample's two extra unit-cube coordinates ``(u4, u5)`` give
  ``t = t0 + w_a(u4) (t1 − t0)`` and ``f = f_lo(t) + w_b(u5) (f_hi(t) − f_lo(t))``, where the warp
  ``w_a(u) = u − a sin(2πu) / 2π`` (:func:`end_warp`) draws a range's ends 1/(1 − a) times as densely as uniform
  and its middle 1/(1 + a) times: a network's error grows toward the edges of what it learned, and the ends are
  what users ask for most — the listed zoom positions, infinity focus — and the close focus.  ``a`` is
  :data:`ZOOM_END_WEIGHT` for the zoom, ``b`` :data:`FOCUS_END_WEIGHT` for the focus (:attr:`Configurations.end_weights`,
  kept in the model file so that its held-out rays are drawn as its training rays were).  With a
  :attr:`Configurations.zoom_margin` ``m`` the zoom is drawn over ``[t0 − m (t1 − t0), t1 + m (t1 − t0)]`` instead
  (:attr:`Configurations.sampled_zoom_range`): the gaps' end cubics continued, the focus band held at its end
  values, so that the listed ends are learned as inner points; sensors still take only ``[t0, t1]``.  With
  :attr:`Configurations.zoom_periods` ``p`` the zoom's warp is ``w_a`` with ``p`` periods (:func:`end_warp`): densest
  at every listed position for ``p = n − 1`` (exactly, without a margin), where the gaps' cubics join.
* **Frame.**  The configurations differ in their gaps, so their vertices move relative to each other: the map's
  planes are fixed relative to the **sensor**, which does not move.  The map works in the lens space of the
  configuration whose image plane lies farthest behind its first vertex, every other configuration shifted along
  the axis so that its sensor plane lies on the same :attr:`Configurations.z_sensor` (mm).  A renderer holding a
  configured lens (first vertex at z = 0) moves the map's planes by ``image_z − z_sensor``
  (:meth:`Configurations.shift_of`).
* **Product inputs** (:attr:`Configurations.monomials`).  Across a zoom range the map's linear part — the paraxial
  map of each configuration — changes several-fold, and a tanh network represents a product of its inputs only
  approximately.  So the map also takes the products of the ray's r, ωx, ωy with a few monomials of (t, f)
  (:data:`MONOMIALS`) as inputs: the regressor's linear skip over them spans a paraxial map whose coefficients are
  cubic in the configuration, and the networks learn what is left (the aberrations).  A zoom listed at more than
  two positions adds the truncated powers (t − k)₊², (t − k)₊³ of each inner position ``k``
  (:func:`knot_monomials`): the gaps' cubics join there with continuous slope but not curvature, so the lens is a
  smooth function of t only together with them; without them a smooth network rounds the join off (the EF
  24-70's map erred 1.4–1.7× as much 0.02 in t on either side of its 35.13 mm position as at it).  They are computed from the
  other inputs, never sampled (:meth:`Configurations.products_np`, :meth:`Configurations.products_dr`).
* **Geometry per ray** (:meth:`Configurations.geometry`): the variable gaps as the prescription's monotone cubics
  in ``t`` (the same Fritsch–Carlson cubics as :func:`mi_neurallens.optics.moving.pchip`, as per-interval
  polynomials) plus ``f`` times the close-focus offset; each vertex's z counted back from the sensor; the stop's
  radius where it changes with zoom.

Units: mm, lens space (+z toward the sensor).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..errors import LensError, NeuralLensError

#: the map inputs a lens's moving groups can give, in this order
CONDITION_NAMES = ("zoom", "focus")
#: zoom parameters at which the focus band is tabulated (linear between)
BAND_GRID = 17
#: the focus band's widening on each side beyond the paraxial and the real-ray focus of infinity and of the close
#: focus, as a fraction of its width.  The band once spanned the paraxial solutions alone, widened by this margin to
#: reach the real rays' best focus, where the sensors focus: at 45-57 mm the EF 24-70's real-ray infinity focus lies
#: 0.068 (8 % of the band) beyond the paraxial one, so the margin was used up there (45 mm at infinity was its map's
#: worst configuration) and, at 47-57 mm, exceeded by up to 0.65 % (:data:`BAND_TOLERANCE`)
FOCUS_MARGIN = 0.08
#: the monomials t^a f^b (a, b) whose products with the ray's r, ωx, ωy are inputs too, per set of configuration
#: inputs (see the module docstring): the paraxial map's coefficients as cubics in the zoom, quadratics in the focus
MONOMIALS = {("zoom", "focus"): ((1, 0), (0, 1), (2, 0), (1, 1), (0, 2), (3, 0), (2, 1)),
             ("zoom",): ((1, 0), (2, 0), (3, 0)), ("focus",): ((0, 1), (0, 2))}
#: the truncated powers (t − k)₊^a of each inner listed zoom position k that multiply r, ωx, ωy too (a, as the
#: monomials' (a, 0, k); :func:`knot_monomials`): the join of two of the gaps' cubics, exactly in their basis
KNOT_POWERS = (2, 3)
#: the ray's inputs that the monomials multiply: r, ωx, ωy (not λ)
PRODUCT_RAY_COLUMNS = (0, 1, 2)
#: a in the zoom sampling's warp (:func:`end_warp`; module docstring, "Sampling"): 0 is uniform; 0.5 draws the zoom
#: range's ends twice, its middle 2/3 times as densely as uniform
ZOOM_END_WEIGHT = 0.5
#: the same for the focus band: its ends are infinity (the focus most renders use) and the close focus, where the
#: 24-70's map erred 1.5-2x as much as in the band's middle (bench_zoom at 45 mm: 5.6" at infinity, 2.7" at 0.5 m)
FOCUS_END_WEIGHT = 0.5
#: the fraction of the zoom range that training draws beyond each of its ends (:attr:`Configurations.zoom_margin`;
#: the module docstring, "Sampling"); 0: the listed range only
ZOOM_MARGIN = 0.0
#: how far beyond its learned focus band, as a fraction of the band's width, a map is still evaluated
#: (:meth:`Configurations.check`): models trained before the band held the real-ray focus (:data:`FOCUS_MARGIN`) end
#: up to 0.65 % of it short of the real rays' infinity focus (the bundled EF 24-70's at 47-57 mm), where its map errs
#: no more than inside (docs/neural_lens.md, "Zoom and internal focusing")
BAND_TOLERANCE = 0.01
#: the outer fraction of the zoom range and of the focus band that :meth:`Configurations.cells` counts as an end
CELL_EDGES = {"zoom": 0.1, "focus": 0.2}
#: the outer fraction of each that a corner cell spans (:meth:`Configurations.cells` with ``corners``): inside an end
#: cell, where the range's extreme configuration errs most and the end cell's median hides it.  The focus band
#: reaches :data:`FOCUS_MARGIN` beyond the focus of infinity and of the close focus (0.08 / 1.16 = 6.9 % of it), so
#: its outer 12 % are that margin and the renderable band's outer 5 %
CORNER_EDGES = {"zoom": 0.03, "focus": 0.12}
#: the fewest held-out rays a cell's median is taken over (:meth:`Configurations.cells`)
CELL_MIN_RAYS = 400
#: the end weights of a model file that records none: the zoom's warp, a uniform focus (as models were trained
#: before the focus warp)
LEGACY_END_WEIGHTS = (ZOOM_END_WEIGHT, 0.0)


def knot_monomials(positions: int) -> tuple:
    """The product monomials (a, 0, k) of a zoom listed at ``positions`` zoom positions: (t − k)₊^a for each inner
    position k = 1 … positions − 2 and a in :data:`KNOT_POWERS` (none for two positions: one cubic, no join)."""
    return tuple((a, 0, k) for k in range(1, int(positions) - 1) for a in KNOT_POWERS)


def end_warp(u, a: float, periods: int = 1):
    """w(u) = u − a sin(2πpu) / 2πp, ``0 ≤ a < 1``, ``p = periods``: [0, 1] onto itself, monotone, ends fixed,
    sample density 1 / w'(u) = 1 / (1 − a cos 2πpu): densest at u = k/p (k = 0 … p).  numpy arrays or Dr.Jit
    floats."""
    c = 2 * math.pi * int(periods)
    if isinstance(u, np.ndarray) or np.isscalar(u):
        return u - a / c * np.sin(c * np.asarray(u, np.float64))
    import drjit as dr
    return u - (a / c) * dr.sin(c * u)


def end_unwarp(w, a: float, periods: int = 1) -> np.ndarray:
    """:func:`end_warp`'s inverse (numpy, float64; Newton from w, converged to 1e-15: w' ≥ 1 − a > 0)."""
    w = np.asarray(w, np.float64)
    u = w.copy()
    for _ in range(50):
        step = (end_warp(u, a, periods) - w) / (1.0 - a * np.cos(2 * math.pi * int(periods) * u))
        u -= step
        if np.all(np.abs(step) < 1e-15):
            break
    return u


def _cubic_pieces(x, y) -> np.ndarray:
    """(n−1, 4) coefficients ``c`` of :func:`~mi_neurallens.optics.moving.pchip` through ``(x, y)``
    (``x = 0, 1, …, n−1``) on each interval ``k``: ``y(k + s) = c0 + c1 s + c2 s² + c3 s³`` for s in [0, 1]
    (each interval's cubic, solved from four of its values: exact to rounding)."""
    from ..optics.moving import pchip
    n = len(x)
    if n == 1:
        return np.array([[float(y[0]), 0.0, 0.0, 0.0]])
    s = np.array([0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0])
    V = np.vander(s, 4, increasing=True)
    out = np.empty((n - 1, 4))
    for k in range(n - 1):
        out[k] = np.linalg.solve(V, pchip(x, y, k + s))
    return out


@dataclasses.dataclass(eq=False)
class Configurations:
    """Which of a lens's moving-group parameters a map takes as inputs, over which range, in which frame (see
    the module docstring).  ``names``: a tuple of :data:`CONDITION_NAMES`; ``zoom_range``: (t0, t1);
    ``band_t``, ``band_lo``, ``band_hi``: the focus band (zoom parameters, lowest and highest focus parameter);
    ``z_sensor``: the frame's sensor plane (mm).  ``lens``: the prescription with its moving groups, needed for
    :meth:`geometry` (training), not stored in a model file."""

    names: tuple
    zoom_range: tuple
    band_t: np.ndarray
    band_lo: np.ndarray
    band_hi: np.ndarray
    z_sensor: float
    lens: object = dataclasses.field(default=None, compare=False, repr=False)
    #: the (a, b) of the monomials t^a f^b whose products with r, ωx, ωy are inputs (:data:`MONOMIALS`; () none),
    #: or (a, b, k): (t − k)₊^a f^b, a truncated power at the listed zoom position k (:func:`knot_monomials`)
    monomials: tuple = ()
    #: the sampling warps' end weights (zoom, focus) (:func:`end_warp`; module docstring, "Sampling")
    end_weights: tuple = (ZOOM_END_WEIGHT, FOCUS_END_WEIGHT)
    #: the fraction of the zoom range the training rays reach beyond each of its ends (module docstring,
    #: "Sampling"); what sensors may ask for stays :attr:`zoom_range`
    zoom_margin: float = ZOOM_MARGIN
    #: the zoom warp's periods over the sampled range: 1 draws its ends densest, the number of listed intervals every
    #: listed position (where the gaps' cubics join, and what users ask for); module docstring, "Sampling"
    zoom_periods: int = 1

    def __eq__(self, other) -> bool:
        return isinstance(other, Configurations) and self.to_dict() == other.to_dict()

    __hash__ = None

    # ------------------------------------------------------------------ construction
    @classmethod
    def of_lens(cls, lens, close_focus_mm: float | None = None) -> "Configurations":
        """The configurations of ``lens`` (with :attr:`~mi_neurallens.optics.prescription.Lens.moving`) over its
        whole zoom range and, where its groups focus, from infinity to ``close_focus_mm`` (mm from the sensor;
        default: the prescription's close focus)."""
        from ..optics import moving as mv
        mg = getattr(lens, "moving", None)
        if mg is None:
            raise NeuralLensError(f"lens '{lens.name}' has no moving groups: it has one configuration")
        names = tuple(n for n, on in zip(CONDITION_NAMES, (mg.is_zoom, mg.focuses)) if on)
        if not names:
            raise NeuralLensError(f"lens '{lens.name}': its moving groups neither zoom nor focus")
        t0, t1 = mg.zoom_range
        grid = np.linspace(t0, t1, BAND_GRID if mg.is_zoom else 1)
        lo, hi = np.zeros(len(grid)), np.zeros(len(grid))
        if mg.focuses:
            close = float(close_focus_mm if close_focus_mm is not None else mg.close_focus_mm)
            for i, t in enumerate(grid):
                try:
                    ends = [mv.focus_parameter(lens, float(t), d, real_rays=r)
                            for d in (math.inf, close) for r in (False, True)]
                except LensError as e:
                    raise NeuralLensError(f"lens '{lens.name}': no focus band at zoom parameter {t:.4g}: {e}") from e
                a, b = min(ends), max(ends)
                w = b - a
                lo[i], hi[i] = a - FOCUS_MARGIN * w, b + FOCUS_MARGIN * w
        monomials = MONOMIALS[names] + (knot_monomials(mg.positions) if mg.is_zoom else ())
        out = cls(names, (float(t0), float(t1)), grid, lo, hi, 0.0, lens, monomials)
        out.z_sensor = max(mv.at(lens, float(t), float(f), check=False).image_z
                           for t, f in out.corner_configurations())
        return out

    def corner_configurations(self, per_interval: int = 4):
        """(t, f) pairs along the band's edges, ``per_interval`` per grid interval and the ends: where a
        configuration's extremes (its track, its rear-most surface) lie."""
        ts = np.linspace(*self.zoom_range, max((len(self.band_t) - 1) * per_interval + 1, 1))
        return [(float(t), float(f)) for t in ts for f in self.band(t)]

    # ------------------------------------------------------------------ ranges
    @property
    def dims(self) -> int:
        """How many sampled inputs the configurations add to a map (1 or 2): the unit cube's extra columns."""
        return len(self.names)

    @property
    def n_products(self) -> int:
        """How many product inputs follow them (:attr:`monomials` × the ray's r, ωx, ωy)."""
        return len(self.monomials) * len(PRODUCT_RAY_COLUMNS)

    @staticmethod
    def _monomial(t, f, a: int, b: int, knot=None):
        """t^a f^b, or with ``knot`` k (t − k)₊^a f^b; numpy arrays, Python floats or Dr.Jit floats."""
        if knot is not None:
            if isinstance(t, np.ndarray):
                t = np.maximum(t - knot, 0.0)
            elif isinstance(t, (float, int)):
                t = max(float(t) - knot, 0.0)
            else:
                import drjit as dr
                t = dr.maximum(t - float(knot), 0.0)
        out = None
        for v, k in ((t, a), (f, b)):
            for _ in range(k):
                out = v if out is None else out * v
        return out

    def products_np(self, x: np.ndarray) -> np.ndarray:
        """The product inputs (N, :attr:`n_products`) of the reduced inputs ``x`` (N, 4 + :attr:`dims`)."""
        t, f = self.split([x[:, 4 + j] for j in range(self.dims)])
        cols = []
        for mono in self.monomials:
            m = self._monomial(np.asarray(t, np.float64), np.asarray(f, np.float64), *mono)
            cols += [x[:, j] * m for j in PRODUCT_RAY_COLUMNS]
        return np.stack(cols, 1) if cols else np.zeros((len(x), 0))

    def products_dr(self, x) -> list:
        """:meth:`products_np` in Dr.Jit: ``x`` the 4 + :attr:`dims` reduced inputs (the configuration's may be
        scalars of width 1: the monomials are then computed once)."""
        t, f = self.split(list(x[4:4 + self.dims]))
        out = []
        for mono in self.monomials:
            m = self._monomial(t, f, *mono)
            out += [x[j] * m for j in PRODUCT_RAY_COLUMNS]
        return out

    def products_center_scale(self, ray_scale) -> tuple:
        """Centre 0 and half-range of each product input (``ray_scale``: the largest |r|, |ωx|, |ωy| of the
        domain), the monomial's largest magnitude over the learned range."""
        t = np.linspace(*self.zoom_range, 33)
        fs = np.linspace(float(self.band_lo.min()), float(self.band_hi.max()), 33)
        T, Fo = np.meshgrid(t, fs)
        s = []
        for mono in self.monomials:
            m = float(np.abs(self._monomial(T, Fo, *mono)).max()) or 1.0
            s += [max(float(ray_scale[j]) * m, 1e-6) for j in PRODUCT_RAY_COLUMNS]
        return np.zeros(len(s)), np.array(s)

    def band(self, t: float) -> tuple:
        """(lowest, highest) focus parameter learned at zoom parameter ``t``."""
        return tuple(float(v) for v in self._band_np(t))

    def check(self, zoom: float, focus: float) -> None:
        """A :class:`~mi_neurallens.errors.NeuralLensError` when (``zoom``, ``focus``) lies outside what the map
        learned (the focus band widened by :data:`BAND_TOLERANCE` of its width), naming the range."""
        t0, t1 = self.zoom_range
        if "zoom" in self.names and not (t0 - 1e-9 <= zoom <= t1 + 1e-9):
            raise NeuralLensError(f"zoom parameter {zoom:.4g} is outside the learned range [{t0:g}, {t1:g}]")
        lo, hi = self.band(zoom)
        tol = BAND_TOLERANCE * (hi - lo) + 1e-9
        if "focus" in self.names and not (lo - tol <= focus <= hi + tol):
            raise NeuralLensError(f"focus parameter {focus:.4g} at zoom parameter {zoom:.4g} is outside the learned "
                                  f"band [{lo:.4g}, {hi:.4g}] (infinity to the close focus the map was trained for)")

    def values(self, zoom: float, focus: float) -> tuple:
        """The map's condition inputs of a configuration, in :attr:`names` order."""
        return tuple(float(zoom) if n == "zoom" else float(focus) for n in self.names)

    def configure_map(self, tm, image_z: float, zoom: float, focus: float):
        """The learned map ``tm`` (over these configurations) at one configuration: its condition inputs set, its
        planes moved from the configurations' frame into the space of the configured lens whose sensor lies at
        ``image_z`` (mm); outside the learned range a :class:`~mi_neurallens.errors.NeuralLensError`."""
        import dataclasses as dc
        self.check(zoom, focus)
        shift = self.shift_of(image_z)
        return dc.replace(tm, z_in=tm.z_in + shift, z_out=tm.z_out + shift, condition_values=self.values(zoom, focus))

    def shift_of(self, image_z: float) -> float:
        """How far a configured lens's lens space (first vertex at 0, sensor at ``image_z``) lies along +z from
        this frame: a plane at ``z`` here is at ``z + shift_of(image_z)`` there."""
        return float(image_z) - self.z_sensor

    # ------------------------------------------------------------------ unit cube ↔ (t, f)
    def _band_np(self, t):
        """The band's edges at ``t`` (float or array): linear between the tabulated zoom parameters."""
        return np.interp(t, self.band_t, self.band_lo), np.interp(t, self.band_t, self.band_hi)

    @property
    def sampled_zoom_range(self) -> tuple:
        """(t0, t1) the training rays are drawn over: :attr:`zoom_range` widened by :attr:`zoom_margin` of its
        width on each side."""
        t0, t1 = self.zoom_range
        m = float(self.zoom_margin) * (t1 - t0)
        return t0 - m, t1 + m

    def u_to_tf(self, u: np.ndarray):
        """The extra unit-cube columns (N, :attr:`dims`) → (t, f) (N,) each, float64."""
        u = np.asarray(u, np.float64)
        t0, t1 = self.sampled_zoom_range
        j = 0
        t = np.full(len(u), t0)
        if "zoom" in self.names:
            t = t0 + end_warp(u[:, j], self.end_weights[0], self.zoom_periods) * (t1 - t0)
            j += 1
        lo, hi = self._band_np(t)
        f = lo + end_warp(u[:, j], self.end_weights[1]) * (hi - lo) if "focus" in self.names else np.zeros(len(u))
        return t, f

    def tf_to_u(self, t, f) -> np.ndarray:
        t0, t1 = self.sampled_zoom_range
        cols = []
        if "zoom" in self.names:
            cols.append(end_unwarp((np.asarray(t, np.float64) - t0) / max(t1 - t0, 1e-30), self.end_weights[0],
                                   self.zoom_periods))
        if "focus" in self.names:
            lo, hi = self._band_np(t)
            cols.append(end_unwarp((np.asarray(f, np.float64) - lo) / np.maximum(hi - lo, 1e-30),
                                   self.end_weights[1]))
        return np.stack(cols, 1)

    def u_to_tf_dr(self, u):
        """:meth:`u_to_tf` in Dr.Jit: the extra unit-cube components (a list of :attr:`dims` Dr.Jit floats) → the
        map's condition inputs in :attr:`names` order."""
        import drjit as dr
        t0, t1 = self.sampled_zoom_range
        out, j = [], 0
        t = u[0] * 0.0 + t0
        if "zoom" in self.names:
            t = dr.fma(end_warp(u[j], self.end_weights[0], self.zoom_periods), t1 - t0, t0)
            out.append(t)
            j += 1
        if "focus" in self.names:
            lo, hi = self._band_dr(t)
            out.append(dr.fma(end_warp(u[j], self.end_weights[1]), hi - lo, lo))
        return out

    def _band_dr(self, t):
        import drjit as dr
        from ..jit import from_numpy
        F = type(t)
        n = len(self.band_t)
        if n == 1:
            return t * 0.0 + float(self.band_lo[0]), t * 0.0 + float(self.band_hi[0])
        g0, g1 = float(self.band_t[0]), float(self.band_t[-1])
        x = dr.clip((t - g0) * ((n - 1) / (g1 - g0)), 0.0, n - 1.0)
        k = dr.minimum(dr.uint32_array_t(F)(dr.floor(x)), n - 2)
        s = x - F(k)
        lo, hi = from_numpy(F, self.band_lo), from_numpy(F, self.band_hi)
        a0, a1 = dr.gather(F, lo, k), dr.gather(F, lo, k + 1)
        b0, b1 = dr.gather(F, hi, k), dr.gather(F, hi, k + 1)
        return dr.fma(s, a1 - a0, a0), dr.fma(s, b1 - b0, b0)

    def split(self, cond) -> tuple:
        """(t, f) from the condition inputs (Dr.Jit or floats) in :attr:`names` order (a parameter that is no
        input is 0)."""
        d = dict(zip(self.names, cond))
        return d.get("zoom", 0.0), d.get("focus", 0.0)

    def cells(self, x: np.ndarray, min_rays: int = CELL_MIN_RAYS, margin: bool = False,
              corners: bool = False) -> dict:
        """The rays ``x`` (N, inputs; the map's inputs, configuration columns at 4, 5) grouped by where their
        configuration lies in the learned range: the zoom range's outer :data:`CELL_EDGES` fraction at each end
        ("wide", "tele"), the focus band's at each end ("infinity", "close"), the rest ("mid").  Returns
        {name: boolean mask (N,)} of the cells holding at least ``min_rays`` rays, e.g. ``"tele, infinity"``: what a
        conditioned map's goals are checked on, since its error grows toward the range's ends and corners, which an
        all-ray median averages away (the goals hold per configuration).

        The rays of the :attr:`zoom_margin` (zooms beyond the listed range, which training draws and no sensor
        renders) are in no cell, so the goals are checked on renderable configurations only; with ``margin`` they
        are in the end cells beside them (what the finish's row weights need: a weight for every row).

        With ``corners``, also the range's corners: the outer :data:`CORNER_EDGES` fraction of every axis at each
        of its ends, e.g. ``"tele, close, corner"`` (for one axis, ``"close, corner"``), the configurations the range
        ends at (the shortest close focus at the longest focal length) and a map errs most at, which the end cells
        around them average with milder ones.  A corner's rays are in its end cell too."""
        x = np.asarray(x, dtype=np.float64)
        t, f = self.split([x[:, 4 + j] for j in range(self.dims)])
        t = np.broadcast_to(np.asarray(t, np.float64), (len(x),))
        f = np.broadcast_to(np.asarray(f, np.float64), (len(x),))
        parts, ends = [], []          # per axis: its three cells; its two corner ranges
        if "zoom" in self.names:
            t0, t1 = self.zoom_range
            a = (t - t0) / max(t1 - t0, 1e-30)
            e, c = CELL_EDGES["zoom"], CORNER_EDGES["zoom"]
            inside = np.ones(len(x), bool) if margin else (a >= -1e-6) & (a <= 1.0 + 1e-6)   # float32 inputs too
            parts.append((("wide", (a < e) & inside), ("mid", (a >= e) & (a <= 1 - e)), ("tele", (a > 1 - e) & inside)))
            ends.append((("wide", (a < c) & inside), ("tele", (a > 1 - c) & inside)))
        if "focus" in self.names:
            lo, hi = self._band_np(t)
            b = (f - lo) / np.maximum(hi - lo, 1e-30)
            # the focus parameter is 0 at the infinity gaps: the band's end nearer 0 is infinity
            inf_lo = abs(float(np.median(self.band_lo))) <= abs(float(np.median(self.band_hi)))
            e, c = CELL_EDGES["focus"], CORNER_EDGES["focus"]
            low, high = (("infinity", "close") if inf_lo else ("close", "infinity"))
            parts.append(((low, b < e), ("mid", (b >= e) & (b <= 1 - e)), (high, b > 1 - e)))
            ends.append(((low, b < c), (high, b > 1 - c)))

        def products(axes):
            out = {"": np.ones(len(x), bool)}
            for part in axes:
                out = {(f"{k}, {n}" if k else n): m & c for k, m in out.items() for n, c in part}
            return out
        out = products(parts)
        if corners and ends:
            out.update({f"{k}, corner": m for k, m in products(ends).items()})
        return {k: m for k, m in out.items() if m.sum() >= min_rays}

    # ------------------------------------------------------------------ normalisation and file form
    def norm_center_scale(self):
        """Centre and half-range of each condition input (the networks see them in about [−1, 1])."""
        c, s = [], []
        for n in self.names:
            lo, hi = (self.zoom_range if n == "zoom" else (float(self.band_lo.min()), float(self.band_hi.max())))
            c.append(0.5 * (lo + hi))
            s.append(max(0.5 * (hi - lo), 1e-6))
        return np.array(c), np.array(s)

    def to_dict(self) -> dict:
        return {"names": list(self.names), "zoom_range": list(self.zoom_range),
                "band": {"zoom": [float(v) for v in self.band_t], "focus_lo": [float(v) for v in self.band_lo],
                         "focus_hi": [float(v) for v in self.band_hi]},
                "z_sensor_mm": float(self.z_sensor), "product_monomials": [list(m) for m in self.monomials],
                "end_weights": [float(v) for v in self.end_weights], "zoom_margin": float(self.zoom_margin),
                "zoom_periods": int(self.zoom_periods)}

    @classmethod
    def from_dict(cls, d, lens=None) -> "Configurations":
        if isinstance(d, Configurations):
            return d if lens is None else dataclasses.replace(d, lens=lens)
        b = d["band"]
        return cls(tuple(d["names"]), tuple(float(v) for v in d["zoom_range"]), np.asarray(b["zoom"], np.float64),
                   np.asarray(b["focus_lo"], np.float64), np.asarray(b["focus_hi"], np.float64),
                   float(d["z_sensor_mm"]), lens, tuple(tuple(int(v) for v in m) for m in d.get("product_monomials", ())),
                   tuple(float(v) for v in d.get("end_weights", LEGACY_END_WEIGHTS)), float(d.get("zoom_margin", 0.0)),
                   int(d.get("zoom_periods", 1)))

    # ------------------------------------------------------------------ the tracer's geometry, per ray
    def geometry(self, float_type, cond, lens=None):
        """The tracer's view (:class:`ConfigurationGeometry`) of the configurations ``cond`` (Dr.Jit arrays, one
        value per ray, in :attr:`names` order) of ``lens`` (default :attr:`lens`; the prescription with its moving
        groups): per-ray vertex positions in this frame and stop radius."""
        lens = lens if lens is not None else self.lens
        if lens is None:
            raise NeuralLensError("Configurations.geometry: no lens (pass one, or Configurations.from_dict(d, lens))")
        return ConfigurationGeometry(self, lens, float_type, *self.split(cond))

    def pieces(self, lens):
        """The moving groups of ``lens`` as cubics: per variable gap ``i``, the (n−1, 4) interval cubics of its
        infinity gap and the close-focus cubic minus it (:func:`_cubic_pieces`: each gap's own monotone cubic through
        its infinity and through its close values, as :meth:`~mi_neurallens.optics.moving.MovingGroups.gaps_at`);
        and the stop radius's, or None.  Cached per lens."""
        cache = self.__dict__.setdefault("_pieces", {})
        if id(lens) not in cache:
            mg = lens.moving
            x = np.arange(mg.positions, dtype=np.float64)
            gaps = {}
            for i, v in mg.gaps.items():
                a = np.asarray(v, np.float64)
                inf, close = _cubic_pieces(x, a[:, 0]), _cubic_pieces(x, a[:, 1])
                gaps[i] = (inf, close - inf)        # the cubics are linear in their coefficients
            stop = None if mg.stop_semi_diameters is None else _cubic_pieces(x, np.asarray(mg.stop_semi_diameters))
            cache[id(lens)] = (lens, (gaps, stop))      # the lens kept: its id stays its own
        return cache[id(lens)][1]


def _eval_pieces(coef: np.ndarray, k, s, F):
    """The interval cubics ``coef`` (n−1, 4) at interval ``k`` (Dr.Jit uint), offset ``s`` (Dr.Jit float)."""
    import drjit as dr
    if len(coef) == 1:
        c = [float(v) for v in coef[0]]
        return dr.fma(dr.fma(dr.fma(s, c[3], c[2]), s, c[1]), s, c[0])
    from ..jit import from_numpy
    c = [dr.gather(F, from_numpy(F, coef[:, j]), k) for j in range(4)]
    return dr.fma(dr.fma(dr.fma(s, c[3], c[2]), s, c[1]), s, c[0])


class ConfigurationGeometry:
    """What :class:`~mi_neurallens.trace.tracer.LensTracer` reads of a live geometry
    (:class:`~mi_neurallens.trace.parameters.LiveGeometry`'s interface), for a configuration per ray: each vertex's
    z (Dr.Jit, per ray) in the configurations' frame, the sensor plane (:attr:`Configurations.z_sensor`, a
    literal), the stop's radius (per ray where it changes with zoom, else None: the lens's)."""

    def __init__(self, configs: Configurations, lens, F, t, f):
        import drjit as dr
        gaps, stop = configs.pieces(lens)
        n = lens.moving.positions
        if not isinstance(t, (int, float)):
            k = dr.minimum(dr.uint32_array_t(F)(dr.clip(dr.floor(t), 0.0, float(max(n - 2, 0)))), max(n - 2, 0))
            s = t - F(k)
        else:
            k, s = None, None
        if k is None:                                   # zoom is no input: position 0
            k = dr.zeros(dr.uint32_array_t(F), 1)
            s = dr.zeros(F, 1)
        d = [float(x.thickness) for x in lens.surfaces]
        live = {i: _eval_pieces(a, k, s, F) + f * _eval_pieces(b, k, s, F) for i, (a, b) in gaps.items()}
        z, acc = [], float(configs.z_sensor)
        for i in reversed(range(len(lens.surfaces))):
            acc = acc - (live[i] if i in live else d[i])
            z.append(acc)
        self._z = list(reversed(z))
        self.image_z = float(configs.z_sensor)
        self.stop_radius = None if stop is None else _eval_pieces(stop, k, s, F)

    def _packed(self):
        return None

    def surfaces(self, n: int | None = None) -> list[dict]:
        """Per surface, the ``live`` dict :class:`~mi_neurallens.trace.surfaces.SurfaceGeometry` takes: its z."""
        return [{"z": z} for z in self._z]
