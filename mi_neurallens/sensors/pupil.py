"""Where to aim camera rays: rear-element and exit-pupil sampling bounds (shared by the lens sensors).

A camera ray starts at a sensor point ``f`` (lens space, z = z_img) and is aimed at a point ``P``
sampled uniformly on a region of the **sampling plane** z = z_s (the plane of the last vertex).  Its
measure is ``dω = cos³θ dA / Δz²`` (Δz = z_img − z_s), so the estimate of the sensor-plane
irradiance ``∫ L cosθ dω`` has weight ``L · cos⁴θ · A / Δz²`` with ``A`` the region's area.

Regions, always expressed in the **rotated frame** of the film point (the film point on the +x
axis at radius r; mirror symmetry makes every region symmetric in y) and rotated back to the film
point's azimuth:

* ``rear_element``: the disk centred on the axis that contains every crossing, with the sampling
  plane, of a line from the film point to any point of the last surface inside its clear
  semi-diameter (the surface has sag, so this radius grows slightly with r).  Exactly conservative.
* ``exit_pupil`` (default): an ellipse (centre ``cx(r)`` on the radial line, semi-axes ``ax(r)``,
  ``ay(r)``) bounding the rays that actually pass, precomputed numerically: for 4·K+1 film radii, a
  coarse grid over the rear-element disk and then a fine grid over the coarse bounding box are
  traced at 360, 550 and 830 nm; every passing grid cell (its far corner) is enclosed.  Node k
  (radius k·Δ) encloses the passing cells of all film radii within ±Δ, and the bounds are linearly
  interpolated in r between nodes, so they vary continuously with the film radius (no radial-bin
  rings as in pbrt) and overlap their neighbours' range, which keeps them conservative between the
  sampled radii; 1 % is added on top (``margin``).  A polygonal (bladed) stop is bounded by its circumscribed
  circle.  Tests compare the result with ``rear_element`` sampling (they must agree within noise).
"""
from __future__ import annotations

import math

import numpy as np

from ..jit import from_numpy
from .common import LensSetup

EXIT_PUPIL, REAR_ELEMENT = "exit_pupil", "rear_element"
MODES = (EXIT_PUPIL, REAR_ELEMENT)

#: wavelengths (nm) whose passing rays are enclosed by the exit-pupil bounds
BOUND_WAVELENGTHS_NM = (360.0, 550.0, 830.0)


def _concentric(u1, u2):
    """Shirley–Chiu concentric square → unit disk (numpy), the same map as Mitsuba's."""
    a = 2.0 * u1 - 1.0
    b = 2.0 * u2 - 1.0
    big = np.abs(a) > np.abs(b)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(big, a, b)
        phi = np.where(big, (np.pi / 4) * (b / a), (np.pi / 2) - (np.pi / 4) * (a / b))
    phi = np.where((a == 0) & (b == 0), 0.0, phi)
    return r * np.cos(phi), r * np.sin(phi)


class PupilBounds:
    """Sampling regions on the plane of the last vertex as a function of film radius.

    ``setup``: a :class:`~mi_neurallens.sensors.common.LensSetup`; ``mode``: ``exit_pupil`` or
    ``rear_element``; ``nodes``: K, the number of radial intervals of the table; ``opaque``: trace the bounds
    with the surfaces' numbers as kernel inputs (:func:`mi_neurallens.trace.api.trace`); ``margin``: the factor
    the exit-pupil ellipses grow beyond the passing cells (1 % for a loaded lens).
    """

    def __init__(self, setup: LensSetup, mode: str = EXIT_PUPIL, nodes: int = 32,
                 coarse: int = 128, fine: int = 64, opaque: bool = False, margin: float = 1.01):
        if mode not in MODES:
            raise ValueError(f"pupil sampling mode must be one of {MODES}, got {mode!r}")
        self.setup, self.mode, self.K = setup, mode, int(nodes)
        #: trace with the surfaces' numbers as kernel inputs (a lens being optimised: one kernel for every step)
        self.opaque = bool(opaque)
        #: the exit-pupil ellipses' axes are grown by this factor beyond the traced cells
        self.margin = float(margin)
        lens = setup.lens
        self.lens = lens
        self.z_img = float(lens.image_z)
        self.z_s = float(lens.vertex_z[-1])
        self.dz = self.z_img - self.z_s
        self.r_max = 1.05 * setup.film_half_diagonal_mm + 1e-3
        self.delta = self.r_max / self.K
        rear = lens.surfaces[-1]
        self.rear_radius = float(rear.semi_diameter)
        rr = np.linspace(0.0, self.rear_radius, 257)
        sag = np.nan_to_num(rear.sag(rr)) if not rear.is_stop else np.zeros_like(rr)
        smin, smax = min(0.0, float(sag.min())), max(0.0, float(sag.max()))
        self.alpha_lo = self.dz / (self.dz - smin)
        self.alpha_hi = self.dz / (self.dz - smax)
        self.node_r = np.arange(self.K + 1) * self.delta
        self.build_stats = {}
        naive = self._naive_radius(self.node_r)
        if mode == REAR_ELEMENT:
            self.cx, self.ax, self.ay = np.zeros_like(naive), naive.copy(), naive.copy()
        else:
            self.cx, self.ax, self.ay = self._build_exit_pupil(coarse, fine)
        self._dr = None

    # ------------------------------------------------------------------ construction
    def _naive_radius(self, r):
        R, lo, hi = self.rear_radius, self.alpha_lo, self.alpha_hi
        r = np.asarray(r, dtype=np.float64)
        return 1.001 * np.maximum((1.0 - lo) * r + lo * R, (hi - 1.0) * r + hi * R)

    def _passes(self, r, x, y, lams):
        """Valid mask of backward rays from film points (r, 0) to plane points (x, y) at any λ."""
        lens = self.lens
        stop = lens.stop
        if stop.blades:
            lens = lens.with_surface(lens.stop_index, blades=0,
                                     semi_diameter=stop.semi_diameter / math.cos(math.pi / stop.blades))
        n = r.size
        o = np.stack([r, np.zeros(n), np.full(n, self.z_img)], 1)
        d = np.stack([x - r, y, np.full(n, -self.dz)], 1)
        ok = np.zeros(n, bool)
        for lam in lams:
            res = lens.trace(o, d, lam, direction="backward", fresnel=False, opaque=self.opaque)
            ok |= res.valid
        return ok

    def _build_exit_pupil(self, nc: int, nf: int):
        """The exit-pupil table (cx, ax, ay) at the :attr:`node_r` film radii (mm, sampling plane, rotated frame):
        passing rays found on a coarse grid over the rear-element disk (:meth:`_coarse_boxes`), then on a fine
        grid over each radius's box (:meth:`_fine_cells`), enclosed node by node (:meth:`_node_ellipses`) and
        grown until the interpolated ellipses enclose them (:meth:`_enclose`), plus 1 %."""
        lams = BOUND_WAVELENGTHS_NM if self.setup.lambda_dependent else (550.0,)
        sub = 4
        rj = np.arange(self.K * sub + 1) * (self.delta / sub)
        box, n_coarse = self._coarse_boxes(rj, nc, lams)
        pts, n_fine = self._fine_cells(rj, box, nf, lams)
        cx, ax, ay = self._node_ellipses(pts, rj.size, sub)
        self._enclose(pts, rj, sub, cx, ax, ay)
        ax *= self.margin
        ay *= self.margin
        self.build_stats = {"film_radii": int(rj.size), "rays_traced": int(n_coarse * len(lams) + n_fine * len(lams)),
                            "wavelengths_nm": list(lams)}
        return cx, ax, ay

    def _coarse_boxes(self, rj, nc: int, lams):
        """Coarse pass over the rear-element disk (half plane y >= 0) of each film radius ``rj`` (mm), an
        ``nc`` × ``nc``/2 grid: per radius the box (x0, x1, y1) of its passing points, 1.5 cells wider (NaN where
        none passes), and the number of grid points traced per wavelength."""
        J = rj.size
        rho = self._naive_radius(rj)
        gx = (np.arange(nc) + 0.5) / nc * 2.0 - 1.0
        gy = (np.arange(nc // 2) + 0.5) / (nc // 2)
        GX, GY = np.meshgrid(gx, gy, indexing="ij")
        GX, GY = GX.ravel(), GY.ravel()
        keep = GX ** 2 + GY ** 2 <= (1.0 + 2.0 / nc) ** 2
        GX, GY = GX[keep], GY[keep]
        m = GX.size
        R = np.repeat(rj, m)
        X = (rho[:, None] * GX[None, :]).ravel()
        Y = (rho[:, None] * GY[None, :]).ravel()
        ok = self._passes(R, X, Y, lams).reshape(J, m)
        hc = 2.0 * rho / nc  # coarse cell size per radius
        box = np.full((J, 3), np.nan)  # x0, x1, y1
        for j in range(J):
            if ok[j].any():
                xs, ys = X.reshape(J, m)[j][ok[j]], Y.reshape(J, m)[j][ok[j]]
                box[j] = [xs.min() - 1.5 * hc[j], xs.max() + 1.5 * hc[j], ys.max() + 1.5 * hc[j]]
        if np.isnan(box[:, 0]).all():
            from ..errors import NeuralLensError
            raise NeuralLensError(f"lens '{self.lens.name}': no ray from the sensor passes through the lens "
                                  "(check fstop, focus and sensor size)")
        return box, ok.size

    def _fine_cells(self, rj, box, nf: int, lams):
        """Fine pass over each coarse ``box`` (an ``nf`` × ``nf``/2 grid): ``{j: (x, y, hx, hy)}``, the passing
        points of film radius ``rj[j]`` and the fine cell's size (mm), and the number of points traced per
        wavelength."""
        have = ~np.isnan(box[:, 0])
        fx = (np.arange(nf) + 0.5) / nf
        fy = (np.arange(nf // 2) + 0.5) / (nf // 2)
        FX, FY = np.meshgrid(fx, fy, indexing="ij")
        FX, FY = FX.ravel(), FY.ravel()
        mf = FX.size
        idx = np.nonzero(have)[0]
        x0, x1, y1 = box[idx, 0], box[idx, 1], box[idx, 2]
        Xf = (x0[:, None] + (x1 - x0)[:, None] * FX[None, :])
        Yf = (y1[:, None] * FY[None, :])
        okf = self._passes(np.repeat(rj[idx], mf), Xf.ravel(), Yf.ravel(), lams).reshape(idx.size, mf)
        hx = (x1 - x0) / nf
        hy = y1 / (nf // 2)
        pts = {}
        for a, j in enumerate(idx):
            if okf[a].any():
                pts[j] = (Xf[a][okf[a]], Yf[a][okf[a]], hx[a], hy[a])
        return pts, okf.size

    def _node_ellipses(self, pts, J: int, sub: int):
        """Each node's own ellipse (cx, ax, ay): the passing cells (:meth:`_fine_cells`, expanded to their far
        corner) of the ``J`` film radii within one sub-step (of ``sub`` per node) of it; an empty node copies the
        nearest non-empty one (rays there then fail)."""
        K = self.K
        cx, ax, ay = np.full(K + 1, np.nan), np.full(K + 1, np.nan), np.full(K + 1, np.nan)
        for k in range(K + 1):
            js = [j for j in range(max(0, sub * k - 1), min(J, sub * k + 2)) if j in pts]
            if not js:
                continue
            lo = min((pts[j][0] - pts[j][2]).min() for j in js)
            hi = max((pts[j][0] + pts[j][2]).max() for j in js)
            top = max((pts[j][1] + pts[j][3]).max() for j in js)
            cx[k], ax[k], ay[k] = 0.5 * (lo + hi), 0.5 * (hi - lo), top
        good = ~np.isnan(cx)
        gi = np.nonzero(good)[0]
        for k in range(K + 1):
            if not good[k]:
                n = gi[np.argmin(np.abs(gi - k))]
                cx[k], ax[k], ay[k] = cx[n], ax[n], ay[n]
        return cx, ax, ay

    def _enclose(self, pts, rj, sub: int, cx, ax, ay):
        """Grow the axes ``ax``, ``ay`` (in place) until the INTERPOLATED ellipse at every traced film radius
        ``rj`` encloses all of that radius's passing cells ``pts``, so the bounds are conservative where they are
        used."""
        K = self.K
        hr = self.delta / sub
        for _ in range(4):
            grow = np.ones(K + 1)
            for j, (px, py, hxj, hyj) in pts.items():
                # the cells of radius r_j must also fit the bounds half a sub-step either side, where
                # the linear interpolation is least constrained
                for re in (rj[j] - 0.5 * hr, rj[j], rj[j] + 0.5 * hr):
                    re = min(max(re, 0.0), self.node_r[-1])
                    c_, a_, b_ = (np.interp(re, self.node_r, t) for t in (cx, ax, ay))
                    q = float(np.sqrt((((np.abs(px - c_) + hxj) / a_) ** 2 + ((py + hyj) / b_) ** 2).max()))
                    k = min(int(re / self.delta), K - 1)
                    grow[k] = max(grow[k], q)
                    grow[k + 1] = max(grow[k + 1], q)
            ax *= grow
            ay *= grow
            if grow.max() <= 1.0:
                break

    # ------------------------------------------------------------------ evaluation
    def params_np(self, r):
        """(cx, ax, ay) at film radii ``r`` (numpy), linearly interpolated."""
        r = np.clip(np.asarray(r, dtype=np.float64), 0.0, self.r_max)
        return (np.interp(r, self.node_r, self.cx), np.interp(r, self.node_r, self.ax),
                np.interp(r, self.node_r, self.ay))

    def sample_np(self, fx, fy, u1, u2):
        """Numpy twin of :meth:`sample`: plane points (X, Y) and region areas for film points."""
        r = np.hypot(fx, fy)
        c = np.where(r > 0, fx / np.where(r > 0, r, 1), 1.0)
        s = np.where(r > 0, fy / np.where(r > 0, r, 1), 0.0)
        cx, ax, ay = self.params_np(r)
        dx, dy = _concentric(u1, u2)
        lx, ly = cx + ax * dx, ay * dy
        return c * lx - s * ly, s * lx + c * ly, np.pi * ax * ay

    def contains_np(self, fx, fy, X, Y):
        """Whether plane points (X, Y) lie inside the region of film points (fx, fy) (numpy)."""
        r = np.hypot(fx, fy)
        c = np.where(r > 0, fx / np.where(r > 0, r, 1), 1.0)
        s = np.where(r > 0, fy / np.where(r > 0, r, 1), 0.0)
        lx, ly = c * X + s * Y, -s * X + c * Y
        cx, ax, ay = self.params_np(r)
        return ((lx - cx) / ax) ** 2 + (ly / ay) ** 2 <= 1.0

    def _tables(self, mi):
        if self._dr is None:
            self._dr = tuple(from_numpy(mi.Float, a) for a in (self.cx, self.ax, self.ay))
        return self._dr

    def sample(self, mi, dr, fx, fy, u):
        """Dr.Jit: plane point (X, Y) (lens space, z = :attr:`z_s`) and region area (mm²) for film
        points (fx, fy) and a 2-D sample ``u``."""
        tcx, tax, tay = self._tables(mi)
        r2 = dr.fma(fx, fx, fy * fy)
        r = dr.sqrt(r2)
        pos = r2 > 0.0
        inv_r = dr.select(pos, dr.rcp(r), 0.0)
        c = dr.select(pos, fx * inv_r, 1.0)
        s = fy * inv_r
        t = dr.minimum(r * (1.0 / self.delta), float(self.K))
        i = mi.UInt32(dr.minimum(mi.UInt32(t), self.K - 1))
        f = t - mi.Float(i)
        g = lambda tab: dr.lerp(dr.gather(mi.Float, tab, i), dr.gather(mi.Float, tab, i + 1), f)
        cx, ax, ay = g(tcx), g(tax), g(tay)
        d = mi.warp.square_to_uniform_disk_concentric(u)
        lx = dr.fma(ax, d.x, cx)
        ly = ay * d.y
        X = dr.fma(c, lx, -s * ly)
        Y = dr.fma(s, lx, c * ly)
        return X, Y, (math.pi * ax) * ay


def measure_pass_fraction(bounds: PupilBounds, n: int = 1 << 18, wavelength_nm: float = 550.0,
                          seed: int = 0) -> float:
    """Fraction of camera rays (uniform film points over the sensor, region samples) that pass the
    lens: the sampling efficiency of ``bounds``."""
    rng = np.random.default_rng(seed)
    st = bounds.setup
    fx = (rng.random(n) - 0.5) * st.sensor_width_mm
    fy = (rng.random(n) - 0.5) * st.sensor_height_mm
    X, Y, _ = bounds.sample_np(fx, fy, rng.random(n), rng.random(n))
    o = np.stack([fx, fy, np.full(n, bounds.z_img)], 1)
    d = np.stack([X - fx, Y - fy, np.full(n, -bounds.dz)], 1)
    res = bounds.lens.trace(o, d, wavelength_nm, direction="backward", fresnel=False)
    return float(res.valid.mean())
