"""Moving groups: a lens's zoom and its own focusing, as variable gaps between its surfaces.

Real lenses focus and zoom by moving groups of elements.  A prescription gives the gaps that change at a few
*positions*: zoom positions (a zoom lens's listed focal lengths) and, at each, the gaps at infinity focus and
at close focus.  :class:`MovingGroups` holds them and gives the gaps at any configuration:

* the **zoom parameter** ``t`` runs over the positions' indices, 0 … n−1 (0: the first listed position).  Between
  positions each gap follows a monotone piecewise cubic through its listed values (Fritsch–Carlson, as
  ``scipy.interpolate.PchipInterpolator``: smooth like a cam, without overshoot; a gap listed equal at two
  neighbouring positions stays constant between them);
* the **focus parameter** ``f`` moves every variable gap along the line from its infinity value (f = 0) to its
  close-focus value (f = 1) at the same zoom: ``d = d_inf(t) + f (d_close(t) − d_inf(t))``.

The last gap (the sensor distance) is variable where the prescription says so: a lens that focuses by moving as
a whole lists it alone, a rear-focusing lens lists it with the gap its rear group closes, an internally
focused one does not list it.  The sensor sits at the configured lens's image distance behind its last
vertex (lens space as everywhere: mm, first vertex at z = 0, +z toward the sensor), so the camera's origin
stays on the sensor as the groups move.

Requested as physical quantities (:func:`configure`): a focal length (mm; the EFL at infinity focus at
587.56 nm, the zoom parameter solved to match it) and a focus distance (mm from the sensor plane; the focus
parameter solved so that the object is imaged on the sensor — paraxially at 587.56 nm first, then at the real
rays' best focus (:func:`best_focus_offset`) — at every zoom: between the listed positions the interpolated gaps
leave a focus error, up to 4.7 mm for the EF 24-70, that ``f`` takes up, so the image stays on the sensor while
zooming).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import LensError

#: the focus parameter's search range: between listed zoom positions the interpolated gaps defocus the lens (the
#: EF 24-70's by up to 4.7 mm at infinity), which the focusing groups take up, beyond their listed travel (f from
#: −0.46 to 0.41 for infinity there); focusing nearer than the lens's close-focus distance is refused separately
FOCUS_RANGE = (-1.0, 2.0)
#: the paraxial wavelength of focal lengths and focus (the d line, nm)
WAVELENGTH_NM = 587.5618


def pchip(x, y, xq):
    """Fritsch–Carlson monotone piecewise-cubic interpolation of the points ``(x, y)`` (``x`` increasing) at
    ``xq`` (float or array): scipy's ``PchipInterpolator`` (tests/test_moving.py compares them), written out here
    because scipy is no runtime dependency.  Outside ``[x0, xn]``: the end cubics extended."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    n = len(x)
    if n == 1:
        return np.full_like(np.asarray(xq, np.float64), y[0])
    h = np.diff(x)
    delta = np.diff(y) / h
    m = np.zeros(n)
    if n == 2:
        m[:] = delta[0]
    else:
        for k in range(1, n - 1):
            if delta[k - 1] * delta[k] > 0:
                w1, w2 = 2 * h[k] + h[k - 1], h[k] + 2 * h[k - 1]
                m[k] = (w1 + w2) / (w1 / delta[k - 1] + w2 / delta[k])
        for k, (d0, d1, h0, h1) in ((0, (delta[0], delta[1], h[0], h[1])),
                                    (n - 1, (delta[-1], delta[-2], h[-1], h[-2]))):
            e = ((2 * h0 + h1) * d0 - h0 * d1) / (h0 + h1)      # the three-point end slope, shape-preserving
            if np.sign(e) != np.sign(d0):
                e = 0.0
            elif np.sign(d0) != np.sign(d1) and abs(e) > abs(3 * d0):
                e = 3 * d0
            m[k] = e
    xq = np.asarray(xq, np.float64)
    i = np.clip(np.searchsorted(x, xq, side="right") - 1, 0, n - 2)
    t = (xq - x[i]) / h[i]
    h00, h10 = (1 + 2 * t) * (1 - t) ** 2, t * (1 - t) ** 2
    h01, h11 = t * t * (3 - 2 * t), t * t * (t - 1)
    return h00 * y[i] + h10 * h[i] * m[i] + h01 * y[i + 1] + h11 * h[i] * m[i + 1]


@dataclass(frozen=True)
class MovingGroups:
    """The variable gaps of a lens (see the module docstring).

    ``gaps``: surface index → one ``(d_infinity, d_close)`` pair (mm) per position, the gap after that surface
    (the last surface's gap is the sensor distance).  ``zoom_efl_mm``: the focal length listed for each position
    (mm; None for a prime, which has one position).  ``close_focus_mm``: the close-focus distance the
    close-focus gaps are for (mm from the sensor plane), or None.  ``close_gaps``: where the close-focus gaps
    come from: ``"published"`` (the prescription's), ``"modelled"`` (solved here, e.g. paraxially for the
    close distance), or None without close focus data (``d_close = d_infinity``: zoom only).
    ``focus_label``: a note on how the lens focuses (free text, not part of the fingerprint).
    ``stop_semi_diameters``: the stop's radius (mm) at each position, where the prescription gives one per
    position (a Zemax file's per-configuration aperture), interpolated like the gaps; None: the stop stays."""

    gaps: dict
    zoom_efl_mm: tuple | None = None
    close_focus_mm: float | None = None
    close_gaps: str | None = "published"
    focus_label: str = field(default="", compare=False)
    stop_semi_diameters: tuple | None = None

    def __post_init__(self):
        gaps = {int(k): tuple((float(a), float(b)) for a, b in v) for k, v in dict(self.gaps).items()}
        object.__setattr__(self, "gaps", dict(sorted(gaps.items())))
        if self.zoom_efl_mm is not None:
            object.__setattr__(self, "zoom_efl_mm", tuple(float(v) for v in self.zoom_efl_mm))
        if self.stop_semi_diameters is not None:
            object.__setattr__(self, "stop_semi_diameters", tuple(float(v) for v in self.stop_semi_diameters))
            if len(self.stop_semi_diameters) != len(next(iter(gaps.values()), ())) or \
                    any(not v > 0 for v in self.stop_semi_diameters):
                raise LensError(f"moving groups: one stop semi-diameter > 0 per position, got {self.stop_semi_diameters}")
        n = {len(v) for v in gaps.values()}
        if not gaps:
            raise LensError("moving groups: no variable gap")
        if len(n) != 1:
            raise LensError(f"moving groups: every variable gap must list the same number of positions, got {sorted(n)}")
        if self.zoom_efl_mm is not None and len(self.zoom_efl_mm) != n.pop():
            raise LensError(f"moving groups: {len(self.zoom_efl_mm)} zoom focal lengths for "
                            f"{len(next(iter(gaps.values())))} positions of the gaps")
        for i, v in gaps.items():
            if any(not (a > 0 and b > 0) for a, b in v):
                raise LensError(f"moving groups: the gap after surface {i} must be > 0 mm at every position, got {v}")

    # ------------------------------------------------------------------ structure
    @property
    def positions(self) -> int:
        """Number of listed positions (1 for a prime)."""
        return len(next(iter(self.gaps.values())))

    @property
    def is_zoom(self) -> bool:
        return self.positions > 1

    @property
    def focuses(self) -> bool:
        """Whether the groups move to focus (any gap differs between infinity and close focus)."""
        return any(a != b for v in self.gaps.values() for a, b in v)

    @property
    def zoom_range(self) -> tuple:
        """(0, n−1): the zoom parameter's range."""
        return 0.0, float(self.positions - 1)

    def gaps_at(self, zoom: float = 0.0, focus: float = 0.0) -> dict:
        """Surface index → gap (mm) at zoom parameter ``zoom`` and focus parameter ``focus``."""
        lo, hi = self.zoom_range
        if not (lo - 1e-9 <= zoom <= hi + 1e-9):
            raise LensError(f"zoom parameter {zoom:g} outside [{lo:g}, {hi:g}]")
        x = np.arange(self.positions, dtype=np.float64)
        out = {}
        for i, v in self.gaps.items():
            a = np.array(v, np.float64)
            d_inf, d_close = float(pchip(x, a[:, 0], zoom)), float(pchip(x, a[:, 1], zoom))
            out[i] = d_inf + focus * (d_close - d_inf)
        return out

    def stop_at(self, zoom: float) -> float | None:
        """The stop's semi-diameter (mm) at zoom parameter ``zoom``, or None where the stop does not change."""
        if self.stop_semi_diameters is None:
            return None
        return float(pchip(np.arange(self.positions, dtype=np.float64), self.stop_semi_diameters, zoom))

    # ------------------------------------------------------------------ identity and file form
    def key(self) -> list:
        """What the lens fingerprint covers: the gaps, the zoom focal lengths, the close-focus distance."""
        r = lambda v: None if v is None else float(f"{float(v):.12g}")
        key = [[[i, [[r(a), r(b)] for a, b in v]] for i, v in self.gaps.items()],
               None if self.zoom_efl_mm is None else [r(v) for v in self.zoom_efl_mm], r(self.close_focus_mm)]
        if self.stop_semi_diameters is not None:
            key.append([r(v) for v in self.stop_semi_diameters])
        return key

    def to_dict(self) -> dict:
        d = {"gaps": {str(i): [[a, b] for a, b in v] for i, v in self.gaps.items()}}
        if self.zoom_efl_mm is not None:
            d["zoom_focal_lengths_mm"] = list(self.zoom_efl_mm)
        if self.close_focus_mm is not None:
            d["close_focus_mm"] = self.close_focus_mm
        if self.close_gaps is not None:
            d["close_gaps"] = self.close_gaps
        if self.stop_semi_diameters is not None:
            d["stop_semi_diameters_mm"] = list(self.stop_semi_diameters)
        if self.focus_label:
            d["note"] = self.focus_label
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "MovingGroups":
        return cls(gaps={int(k): v for k, v in d["gaps"].items()}, zoom_efl_mm=d.get("zoom_focal_lengths_mm"),
                   close_focus_mm=d.get("close_focus_mm"), close_gaps=d.get("close_gaps", "published"),
                   focus_label=d.get("note", ""), stop_semi_diameters=d.get("stop_semi_diameters_mm"))


# ---------------------------------------------------------------------------------------------- configurations
def at(lens, zoom: float = 0.0, focus: float = 0.0, *, check: bool = True):
    """``lens`` (with :attr:`~mi_neurallens.optics.prescription.Lens.moving`) as one fixed configuration: its
    variable gaps at ``zoom`` and ``focus``, without moving groups (metadata ``configuration`` records the two
    parameters).  ``check=False``: not validated (the searches below; only the gaps are checked positive)."""
    mg = lens.moving
    if mg is None:
        raise LensError(f"lens '{lens.name}' has no moving groups", file=lens.path)
    surfaces = list(lens.surfaces)
    for i, d in mg.gaps_at(zoom, focus).items():
        if not d > 0:
            raise LensError(f"lens '{lens.name}' at zoom {zoom:.4g}, focus {focus:.4g}: the gap after surface {i} "
                            f"closes ({d:.4g} mm)", file=lens.path)
        surfaces[i] = dataclasses.replace(surfaces[i], thickness=float(d))
    r = mg.stop_at(zoom)
    if r is not None:
        k = lens.stop_index
        surfaces[k] = dataclasses.replace(surfaces[k], semi_diameter=r)
    meta = dict(lens.metadata)
    meta["configuration"] = {"zoom": float(zoom), "focus": float(focus)}
    if not check:
        return lens.unchecked(surfaces=tuple(surfaces), moving=None, metadata=meta)
    try:
        return lens.replace(surfaces=tuple(surfaces), moving=None, metadata=meta)
    except LensError as e:
        raise LensError(f"lens '{lens.name}' at zoom {zoom:.4g}, focus {focus:.4g} is no valid lens (its groups "
                        f"collide): {e}", file=lens.path) from e


def _secant(fn, x0: float, x1: float, lo: float, hi: float, tol: float, iters: int = 40):
    """A root of ``fn`` (nearly linear) by the secant method from ``x0``, ``x1``, kept within [lo, hi]; None when it
    does not converge."""
    f0, f1 = fn(x0), fn(x1)
    for _ in range(iters):
        if not (math.isfinite(f0) and math.isfinite(f1)):
            return None
        if abs(f1) <= tol:
            return x1
        if f1 == f0:
            return None
        x2 = min(max(x1 - f1 * (x1 - x0) / (f1 - f0), lo), hi)
        x0, f0, x1, f1 = x1, f1, x2, fn(x2)
    return None


def focus_error(lens, zoom: float, focus: float, distance_mm: float) -> float:
    """Paraxial defocus (mm, image distance − sensor distance, behind the last vertex) of an object
    ``distance_mm`` from the sensor plane (``inf``: at infinity) at configuration (``zoom``, ``focus``); NaN where
    the configuration has a closed gap or the object lies in front of the lens's front focal point."""
    try:
        L = at(lens, zoom, focus, check=False)
        px = L.paraxial(WAVELENGTH_NM)
        s = L.surfaces[-1].thickness
        if math.isinf(distance_mm):
            return float(px.bfl) - s
        obj = distance_mm - L.total_track - s          # in front of the first vertex
        return float(px.image_distance(obj)) - s if obj > 0 else math.nan
    except LensError:
        return math.nan


#: real-ray focusing: rays per trace (on axis, over the entrance pupil) and the tolerance on the best focus (mm)
BEST_FOCUS_RAYS = 4096
BEST_FOCUS_TOL_MM = 1e-4


def best_focus_offset(lens, distance_mm: float) -> float:
    """Where the real rays from an on-axis object ``distance_mm`` from the sensor plane (``inf``: infinity) focus
    best, relative to the sensor (mm along the axis, + behind it): the plane of the smallest RMS spot of rays over
    the whole entrance pupil at 587.56 nm (its closed form: the spot's radius is quadratic in the plane's offset),
    traced through ``lens`` (a fixed configuration) in float64.  NaN when too few rays pass."""
    px = lens.paraxial(WAVELENGTH_NM)
    n = BEST_FOCUS_RAYS
    k = np.arange(n) + 0.5                               # a Fermat spiral over the pupil: even, deterministic
    r = px.entrance_pupil_radius * 0.999 * np.sqrt(k / n)
    a = k * (math.pi * (3.0 - math.sqrt(5.0)))
    pupil = np.stack([r * np.cos(a), r * np.sin(a), np.full(n, px.entrance_pupil_z)], 1)
    if math.isinf(distance_mm):
        d = np.tile([0.0, 0.0, 1.0], (n, 1))
        o = pupil - d * (pupil[:, 2:3] + 10.0)
    else:
        o = np.tile([0.0, 0.0, lens.image_z - distance_mm], (n, 1))
        d = pupil - o
        d /= np.linalg.norm(d, axis=1, keepdims=True)
    res = lens.trace(o, d, WAVELENGTH_NM, precision="float64", opaque=True, fresnel=False)
    v = res.valid
    if v.sum() < 16:
        return math.nan
    P, D = res.position[v], res.direction[v]
    u, w = D[:, 0] / D[:, 2], D[:, 1] / D[:, 2]            # lateral change per mm along the axis
    return float(-np.sum(P[:, 0] * u + P[:, 1] * w) / np.sum(u * u + w * w))


def focus_parameter(lens, zoom: float, distance_mm: float, real_rays: bool = False) -> float:
    """The focus parameter that images an object ``distance_mm`` from the sensor plane (``inf``: infinity) on the
    sensor at ``zoom``: paraxially (d line, to 1e-9 mm), or with ``real_rays`` at the real rays' best focus
    (:func:`best_focus_offset`, to :data:`BEST_FOCUS_TOL_MM`, from the paraxial solution); nearer than the lens's
    close focus, or beyond what its groups reach, a :class:`LensError` naming the distances."""
    f = _paraxial_focus_parameter(lens, zoom, distance_mm)
    if not real_rays or not lens.moving.focuses:
        return f
    g = lambda x: best_focus_offset(at(lens, zoom, x), distance_mm)
    lo, hi = FOCUS_RANGE
    step = 0.01 if f < hi - 0.01 else -0.01
    real = _secant(g, f, f + step, lo, hi, BEST_FOCUS_TOL_MM, iters=12)
    if real is None:
        raise LensError(f"lens '{lens.name}': no focus of its groups puts the real rays' best focus of an object "
                        f"{distance_mm / 1000:.4g} m away on the sensor at zoom {zoom:.4g}", file=lens.path)
    return real


def _paraxial_focus_parameter(lens, zoom: float, distance_mm: float) -> float:
    """:func:`focus_parameter`, paraxially."""
    mg = lens.moving
    if mg.close_focus_mm is not None and distance_mm < mg.close_focus_mm * (1.0 - 1e-9):
        raise LensError(f"lens '{lens.name}' focuses no nearer than {mg.close_focus_mm / 1000:.4g} m from the sensor "
                        f"(its close focus), asked for {distance_mm / 1000:.4g} m", file=lens.path)
    if not mg.focuses:
        if math.isinf(distance_mm):
            return 0.0
        raise LensError(f"lens '{lens.name}' lists no focusing movement (its variable gaps are the same at "
                        "infinity and close focus): it is focused at infinity only", file=lens.path)
    lo, hi = FOCUS_RANGE
    err = lambda f: focus_error(lens, zoom, f, distance_mm)
    f = _secant(err, 0.0, 1.0, lo, hi, 1e-9)
    if f is None:                            # not near-linear here: bracket on a grid, then bisect
        grid = np.linspace(lo, hi, 31)
        errs = [err(g) for g in grid]
        for k in range(len(grid) - 1):
            a, b = errs[k], errs[k + 1]
            if np.isfinite(a) and np.isfinite(b) and (a > 0) != (b > 0):
                f = _bisect(err, float(grid[k]), float(grid[k + 1]))
                break
    if f is None:
        raise LensError(f"lens '{lens.name}' cannot focus {distance_mm / 1000:.4g} m from the sensor at zoom "
                        f"{zoom:.4g}: its focusing groups do not reach it"
                        + (f" (its close focus: {mg.close_focus_mm / 1000:.4g} m)" if mg.close_focus_mm else ""),
                        file=lens.path)
    return f


def _bisect(fn, lo: float, hi: float, iters: int = 60) -> float:
    """The root of ``fn`` (a sign change between ``lo`` and ``hi``) by bisection."""
    flo = fn(lo)
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        fm = fn(mid)
        if (fm > 0) == (flo > 0):
            lo, flo = mid, fm
        else:
            hi = mid
    return 0.5 * (lo + hi)


def focal_length(lens, zoom: float) -> float:
    """The EFL (mm, d line) at zoom parameter ``zoom``, focused at infinity."""
    f = focus_parameter(lens, zoom, math.inf) if lens.moving.focuses else 0.0
    return float(at(lens, zoom, f, check=False).paraxial(WAVELENGTH_NM).efl)


def focal_length_range(lens) -> tuple:
    """(EFL at the first position, EFL at the last), mm."""
    lo, hi = lens.moving.zoom_range
    return focal_length(lens, lo), focal_length(lens, hi)


def zoom_parameter(lens, efl_mm: float) -> float:
    """The zoom parameter whose infinity-focus EFL is ``efl_mm`` (to 1e-9 relative); outside the lens's range a
    :class:`LensError` naming it (the range the prescription lists, where it lists one)."""
    mg = lens.moving
    lo, hi = mg.zoom_range
    if not mg.is_zoom:
        raise LensError(f"lens '{lens.name}' is not a zoom lens: it has one focal length", file=lens.path)
    f_lo, f_hi = focal_length(lens, lo), focal_length(lens, hi)
    a, b = min(f_lo, f_hi), max(f_lo, f_hi)
    # the range as the prescription lists it (its positions' nominal focal lengths), within which a request
    # beyond the computed end (68.14 listed, 68.127 computed for the EF 24-70's tele end) is that end
    listed = sorted(mg.zoom_efl_mm[k] for k in (0, -1)) if mg.zoom_efl_mm else [a, b]
    lo_ok, hi_ok = min(a, listed[0]), max(b, listed[1])
    if not (lo_ok * (1 - 1e-9) <= efl_mm <= hi_ok * (1 + 1e-9)):
        raise LensError(f"focal length {efl_mm:g} mm is outside lens '{lens.name}''s range "
                        f"{listed[0]:.6g}-{listed[1]:.6g} mm", file=lens.path)
    if efl_mm <= a:
        return lo if f_lo <= f_hi else hi
    if efl_mm >= b:
        return hi if f_lo <= f_hi else lo
    # the listed positions bracket it: the secant method within the bracketing interval
    x = np.arange(mg.positions, dtype=np.float64)
    efls = [f_lo] + [focal_length(lens, float(k)) for k in x[1:-1]] + [f_hi]
    k = next(k for k in range(len(efls) - 1) if min(efls[k], efls[k + 1]) <= efl_mm <= max(efls[k], efls[k + 1]))
    fn = lambda t: focal_length(lens, t) - efl_mm
    t = _secant(fn, float(k), float(k + 1), float(k), float(k + 1), 1e-9 * efl_mm)
    return t if t is not None else _bisect(fn, float(k), float(k + 1), iters=50)


def configure(lens, focal_length_mm: float | None = None, focus_distance_mm: float = math.inf,
              real_rays: bool = True):
    """``lens`` at a focal length (mm; None: the first listed position) focused at ``focus_distance_mm`` (from
    the sensor plane; ``inf``) — by default where the real rays focus best (``real_rays``; the zoom parameter is
    solved paraxially): ``(configured lens, zoom parameter, focus parameter)``, the lens validated."""
    mg = lens.moving
    t = 0.0 if focal_length_mm is None else zoom_parameter(lens, float(focal_length_mm))
    f = focus_parameter(lens, t, float(focus_distance_mm), real_rays) \
        if (mg.focuses or not math.isinf(focus_distance_mm)) else 0.0
    return at(lens, t, f), t, f
