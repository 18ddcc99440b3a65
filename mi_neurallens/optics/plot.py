"""Lens layout drawings: the meridional (y–z) section of a lens with traced ray fans.

:func:`plot_lens` draws, in lens space (mm, z horizontal, object on the left):

* each element in its true shape: front and rear sag profiles out to their clear semi-diameters,
  a flat annulus out to the element's largest semi-diameter, and the edge joining them there;
  glass shaded by its index (darker = higher n_d); cemented interfaces are the shared boundary;
* the aperture stop as two blade marks, housing (baffle) radii as dark bars, the optical axis and
  the image plane (z = Σ thickness);
* for three fields (0, 0.7 and 1.0 of the half field of view, colour by field), meridional fans of
  rays from an object at infinity, one line style per wavelength, traced EXACTLY by
  :meth:`Lens.trace` (``record=True``).  The fan of each field and wavelength is real-ray aimed: it
  spans the rays that cross the stop plane between −0.999 and +0.999 of the stop radius, i.e. it
  fills the real entrance pupil at that field.  Rays that are blocked (vignetted by a rim,
  housing or the stop) end with a × where the tracer's record of them ends.

The half field of view (when ``fields_deg`` is not given) is the smaller of
(a) the largest field angle whose real chief ray still reaches the image plane, and
(b) the field angle whose real chief ray lands ``image_radius_mm`` from the axis
(default 21.6333 mm, the half diagonal of a 36 × 24 mm frame; a lens's ``metadata`` may set
``image_radius_mm``/``image_circle_radius_mm``, or give ``half_fov_deg``).

Matplotlib is used through the object API with the Agg canvas: no pyplot, no global state.
Files (PNG, SVG, PDF, … by extension) are written atomically (temporary file + ``os.replace``).
"""
from __future__ import annotations

import math
import os

import numpy as np

from ..constants import FULL_FRAME_HALF_DIAGONAL_MM, LAMBDA_C, LAMBDA_D, LAMBDA_F
from ..errors import LensError
from ..jit import from_numpy

FIELD_FRACTIONS = (0.0, 0.7, 1.0)
FIELD_COLORS = ("#1f6fb4", "#1a9850", "#d7301f")
PRIMARY_WAVELENGTH = LAMBDA_D
#: fans aim at ±this fraction of the stop radius (so edge rays are not lost to rounding at the stop)
STOP_FILL = 0.999


# ------------------------------------------------------------------------------ geometry helpers
def _n_d(medium) -> float:
    return float(medium.index(LAMBDA_D))


def _is_glass(medium) -> bool:
    return _n_d(medium) > 1.01


def _rim_z(lens, i) -> float:
    s = lens.surfaces[i]
    return float(lens.vertex_z[i] + s.sag(s.semi_diameter))


def _profile(lens, i, r_edge=None, n=121):
    """(z, y) of surface i from +sd to −sd; with ``r_edge`` extended flat (at the rim z) to ±r_edge."""
    s = lens.surfaces[i]
    sd = s.semi_diameter
    y = np.linspace(sd, -sd, n)
    z = lens.vertex_z[i] + s.sag(np.abs(y))
    if r_edge is not None and r_edge > sd * (1 + 1e-9):
        zr = _rim_z(lens, i)
        y = np.concatenate([[r_edge], y, [-r_edge]])
        z = np.concatenate([[zr], z, [zr]])
    return z, y


def _elements(lens):
    """Groups of surface indices [a, …, b] bounding consecutive glass slabs (cemented groups)."""
    groups, cur = [], None
    for i, s in enumerate(lens.surfaces):
        if s.is_stop:
            cur = None
            continue
        if _is_glass(s.medium):
            if cur is None:
                cur = [i]
                groups.append(cur)
            if i + 1 < len(lens.surfaces):
                cur.append(i + 1)
        else:
            cur = None
    return groups


# ------------------------------------------------------------------------------ tracing
# Every trace below is batched over (field, wavelength) pairs and never uses a single ray: Dr.Jit
# bakes width-1 arrays into the kernel as literals, which would compile a new kernel per call.
def _rays(theta_deg, heights, z0):
    """Parallel rays at field angles θ (object above the axis: the rays head down, −y), passing
    height ``h`` at the first vertex plane z = 0, started on the plane z = z0 < 0.
    ``theta_deg`` and ``heights`` broadcast together; returns flat (N, 3) origins and directions."""
    t, h = np.broadcast_arrays(np.radians(np.asarray(theta_deg, dtype=np.float64)),
                               np.asarray(heights, dtype=np.float64))
    t, h = t.ravel(), h.ravel()
    d = np.stack([np.zeros_like(t), -np.sin(t), np.cos(t)], 1)
    o = np.stack([np.zeros_like(h), h + z0 / d[:, 2] * d[:, 1], np.full_like(h, z0)], 1)
    return o, d


def _pad(*arrays):
    """Pad (N, …) arrays to at least 2 rows (see the note above); returns (arrays, N)."""
    n = len(arrays[0])
    if n >= 2:
        return arrays, n
    return tuple(np.concatenate([a, a[:1].repeat(2 - n, 0)]) for a in arrays), n


def _raw_points(lens, o, d, wl):
    """Every recorded hit of the transmit path, also those after a ray is blocked (which
    ``Lens.trace(record=True)`` hides): ray aiming needs the stop heights of vignetted rays."""
    from ..trace.api import float_type, tracer_for
    wl = np.broadcast_to(np.asarray(wl, dtype=np.float64), (len(o),))
    (o, d, wl), n = _pad(o, d, wl)
    F = float_type("float64")
    col = lambda a, k: from_numpy(F, a[:, k])
    res = tracer_for(lens, False).trace(tuple(col(o, k) for k in range(3)),
                                        tuple(col(d, k) for k in range(3)),
                                        from_numpy(F, wl), "transmit", "forward", record=True)
    pts = np.stack([np.stack([c.numpy() for c in p], 1) for p in res.points], 1).astype(np.float64)
    return pts[:n]


def _on_surface(lens, i, p):
    """Rays whose recorded hit ``p`` (N, 3) really lies on surface i (not a missed-root artefact)."""
    s = lens.surfaces[i]
    with np.errstate(invalid="ignore"):
        r = np.hypot(p[:, 0], p[:, 1])
        rmax = s.max_semi_diameter()
        sag = np.nan_to_num(s.sag(np.minimum(r, rmax)))
        return (r <= rmax) & (np.abs(p[:, 2] - lens.vertex_z[i] - sag) <= 1e-6 * (1 + abs(lens.vertex_z[i])))


def _trace_fans(lens, thetas, heights, wls, z0):
    """Trace rays (one per entry of the broadcast ``thetas``/``heights``/``wls``) exactly.

    Returns (points (N, M, 3), NaN after the point where a blocked ray dies, valid (N,)).
    """
    o, d = _rays(thetas, heights, z0)
    wl = np.broadcast_to(np.asarray(wls, dtype=np.float64), np.broadcast_shapes(
        np.shape(thetas), np.shape(heights), np.shape(wls))).ravel()
    (o, d, wl), n = _pad(o, d, wl)
    res = lens.trace(o, d, wl, record=True, fresnel=False, precision="float64")
    return res.points[:n], res.valid[:n]


def _stop_heights(lens, thetas, wls, z0, h):
    """Stop-plane crossing heights (K, n) of the rays at launch heights ``h`` (K, n) for each
    (θ_k, λ_k), ignoring apertures; NaN where a ray cannot reach the stop (misses a surface)."""
    K, n = h.shape
    th = np.repeat(np.asarray(thetas, dtype=np.float64), n)
    wl = np.repeat(np.asarray(wls, dtype=np.float64), n)
    o, d = _rays(th, h.ravel(), z0)
    raw = _raw_points(lens, o, d, wl)
    ks = lens.stop_index + 1
    ok = np.all(np.isfinite(raw[:, : ks + 1]), axis=(1, 2))
    with np.errstate(invalid="ignore"):
        for i in range(lens.stop_index):
            ok &= _on_surface(lens, i, raw[:, i + 1])
            ok &= raw[:, i + 2, 2] >= raw[:, i + 1, 2] - 1e-9
    return np.where(ok, raw[:, ks, 1], np.nan).reshape(K, n)


def _solve_heights(h, ys, targets):
    """Launch heights whose stop heights equal ``targets`` on the monotone branch through the chief
    ray (ys = 0), clipped to the branch; and the branch's (h_lo, h_hi).  None if no ray reaches the
    stop centre."""
    good = np.isfinite(ys)
    sign = np.sign(ys)
    cross = np.nonzero(good[:-1] & good[1:] & (sign[:-1] * sign[1:] <= 0) & (ys[:-1] != ys[1:]))[0]
    if cross.size == 0:
        return None
    c = cross[np.argmin(np.abs(h[cross]))]
    slope = np.sign(ys[c + 1] - ys[c])
    a = c
    while a > 0 and good[a - 1] and np.sign(ys[a] - ys[a - 1]) == slope:
        a -= 1
    b = c + 1
    while b < len(h) - 1 and good[b + 1] and np.sign(ys[b + 1] - ys[b]) == slope:
        b += 1
    hb, yb = h[a:b + 1], ys[a:b + 1]
    if slope < 0:
        hb, yb = hb[::-1], yb[::-1]
    t = np.clip(np.asarray(targets, dtype=np.float64), yb[0], yb[-1])
    return np.interp(t, yb, hb), (min(hb[0], hb[-1]), max(hb[0], hb[-1]))


def _aim(lens, thetas, wls, z0, targets, n_scan=1001):
    """Real-ray aiming.  For each pair (θ_k, λ_k): the launch heights (at z = 0) of the rays that
    cross the stop plane at ``targets`` (mm).  Returns (K, len(targets)), NaN rows where no ray
    reaches the stop centre.  Two batched passes: a coarse scan, then a fine one on the branch."""
    thetas = np.atleast_1d(np.asarray(thetas, dtype=np.float64))
    wls = np.broadcast_to(np.asarray(wls, dtype=np.float64), thetas.shape)
    K = len(thetas)
    tan = np.tan(np.radians(np.minimum(thetas, 89.0)))
    sd_max = max(s.semi_diameter for s in lens.surfaces)
    H = 2.0 * sd_max * (1.0 + tan) + abs(lens.vertex_z[lens.stop_index]) * tan
    u = np.linspace(-1.0, 1.0, n_scan)
    h = H[:, None] * u[None, :]
    out = np.full((K, len(np.atleast_1d(targets))), np.nan)
    ys = _stop_heights(lens, thetas, wls, z0, h)
    lo, hi = np.zeros(K), np.zeros(K)
    found = np.zeros(K, dtype=bool)
    for k in range(K):
        sol = _solve_heights(h[k], ys[k], targets)
        if sol is not None:
            step = h[k, 1] - h[k, 0]
            lo[k], hi[k] = sol[1][0] - 2 * step, sol[1][1] + 2 * step
            found[k] = True
    if not found.any():
        return out
    u = np.linspace(0.0, 1.0, n_scan)
    h = lo[:, None] + (hi - lo)[:, None] * u[None, :]
    ys = _stop_heights(lens, thetas, wls, z0, h)
    for k in np.nonzero(found)[0]:
        sol = _solve_heights(h[k], ys[k], targets)
        if sol is not None:
            out[k] = sol[0]
    return out


def _start_z(lens) -> float:
    z = lens.vertex_z
    zmin = min(min(_rim_z(lens, i), z[i]) for i in range(len(lens.surfaces)))
    return float(zmin - 0.05 * (lens.image_z - zmin) - 1.0)


def _metadata_float(lens, *keys):
    md = lens.metadata or {}
    for k in keys:
        v = md.get(k)
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0:
            return float(v)
    return None


def half_field_deg(lens, wavelength_nm: float = LAMBDA_D, image_radius_mm: float | None = None):
    """The half field of view (degrees) used by :func:`plot_lens` when no fields are given: the
    smaller of the largest angle whose real chief ray reaches the image plane and the angle whose
    real chief ray lands ``image_radius_mm`` off axis (see the module docstring)."""
    v = _metadata_float(lens, "half_fov_deg", "half_field_deg")
    if v is not None:
        return min(v, 89.0)
    rimg = image_radius_mm or _metadata_float(lens, "image_radius_mm", "image_circle_radius_mm") \
        or FULL_FRAME_HALF_DIAGONAL_MM
    z0 = _start_z(lens)
    thetas = np.concatenate([np.arange(0.5, 10.0, 0.5), np.arange(10.0, 89.01, 1.0)])
    hs = _aim(lens, thetas, wavelength_nm, z0, [0.0], n_scan=401)[:, 0]
    ok = np.isfinite(hs)
    pts, valid = _trace_fans(lens, thetas[ok], hs[ok], wavelength_nm, z0)
    alive = np.zeros(len(thetas), dtype=bool)
    alive[ok] = valid
    y = np.full(len(thetas), np.nan)
    y[ok] = np.abs(pts[:, -1, 1])
    n_alive = len(thetas) if alive.all() else int(np.argmin(alive))   # contiguous run from 0°
    if n_alive == 0:                # no real chief ray at all: paraxial estimate
        p = lens.paraxial(wavelength_nm)
        return float(math.degrees(math.atan(rimg / abs(p.efl))))
    t_run, y_run = np.concatenate([[0.0], thetas[:n_alive]]), np.concatenate([[0.0], y[:n_alive]])
    over = np.nonzero(y_run >= rimg)[0]
    if over.size:                   # the angle where the chief ray reaches the image radius
        j = int(over[0])
        return float(t_run[j - 1] + (t_run[j] - t_run[j - 1]) * (rimg - y_run[j - 1])
                     / (y_run[j] - y_run[j - 1]))
    return float(t_run[-1])


# ------------------------------------------------------------------------------ drawing
def _glass_color(n):
    t = float(np.clip((n - 1.45) / 0.5, 0.0, 1.0))
    light, dark = np.array([0.80, 0.89, 0.97]), np.array([0.42, 0.60, 0.80])
    return tuple(light + (dark - light) * t)


def _line_styles(wavelengths):
    styles = ["-", "--", ":", "-."]
    prim = int(np.argmin([abs(w - LAMBDA_D) for w in wavelengths]))
    out, k = {}, 1
    for i, w in enumerate(wavelengths):
        if i == prim:
            out[w] = "-"
        else:
            out[w] = styles[k % len(styles)]
            k += 1
    return out


def _stop_extent(stop, sgn) -> float:
    """Opening of the stop along +y (sgn = 1) or −y: its radius, or for a bladed polygon (blade k
    at normal angle rot + 2πk/B, inscribed radius r) the distance to the nearest blade line."""
    r = stop.semi_diameter
    if not stop.blades:
        return r
    phi = sgn * math.pi / 2
    c = [math.cos(phi - math.radians(stop.blade_rotation_deg) - 2 * math.pi * k / stop.blades)
         for k in range(stop.blades)]
    return min(r / v for v in c if v > 1e-12)


def _free_blade_length(lens, groups, r0, length) -> float:
    """Shorten the stop's blade marks so they stop where a neighbouring element's drawn outline
    (surface profile, then the flat annulus out to the element edge) reaches the stop plane."""
    k = lens.stop_index
    zs = float(lens.vertex_z[k])
    r = np.linspace(r0, r0 + length, 200)
    free = np.ones_like(r, dtype=bool)
    for g in groups:
        edge = max(lens.surfaces[i].semi_diameter for i in g)
        for i, sgn in ((k - 1, 1.0), (k + 1, -1.0)):
            if i in g:
                s = lens.surfaces[i]
                z = lens.vertex_z[i] + s.sag(np.minimum(r, s.semi_diameter))
                # the glass lies behind the previous surface (sgn 1) / in front of the next (−1)
                free &= ~((r <= edge) & (sgn * (z - zs) >= 0))
    if free.all():
        return length
    stop_at = int(np.argmin(free))
    return max(float(r[stop_at] - r0), 0.45 * length)   # keep the mark visible


def _draw_lens(ax, lens):
    from matplotlib.patches import Polygon
    surfs = lens.surfaces
    groups = _elements(lens)
    edge = "#16324f"
    for g in groups:
        R = max(surfs[i].semi_diameter for i in g)
        for a, b in zip(g[:-1], g[1:]):
            zf, yf = _profile(lens, a, R)
            zb, yb = _profile(lens, b, R)
            poly = np.concatenate([np.stack([zf, yf], 1), np.stack([zb[::-1], yb[::-1]], 1)])
            ax.add_patch(Polygon(poly, closed=True, facecolor=_glass_color(_n_d(surfs[a].medium)),
                                 edgecolor=edge, linewidth=1.0, joinstyle="round", zorder=2))
    # a surface between two gaps (a dummy or flare-cut surface, not the stop) still clips at its
    # semi-diameter: thin grey profile, plus grey aperture ticks beyond it
    in_glass = {i for g in groups for i in g}
    r_max = max(s.semi_diameter for s in surfs)
    for i, s in enumerate(surfs):
        if not s.is_stop and i not in in_glass:
            z, y = _profile(lens, i)
            ax.plot(z, y, color="#888888", lw=0.7, ls=(0, (4, 2)), zorder=2)
            zr = _rim_z(lens, i)
            for sgn in (1, -1):
                ax.plot([zr, zr], [sgn * s.semi_diameter, sgn * (s.semi_diameter + 0.05 * r_max)],
                        color="#666666", lw=1.8, solid_capstyle="butt", zorder=4)
    # housings: dark bars from the housing radius outward at the rim plane
    outer = 1.12 * max(max(s.semi_diameter for s in surfs),
                       max((s.housing_radius or 0.0) for s in surfs))
    for i, s in enumerate(surfs):
        if s.housing_radius is not None and s.housing_radius < outer:
            z = _rim_z(lens, i)
            for sgn in (1, -1):
                ax.plot([z, z], [sgn * s.housing_radius, sgn * max(outer, s.housing_radius * 1.05)],
                        color="#444444", lw=2.2, solid_capstyle="butt", zorder=4)
    # stop: two blade marks
    st, zs = lens.stop, float(lens.vertex_z[lens.stop_index])
    blade = max(0.18 * st.semi_diameter, 0.06 * max(s.semi_diameter for s in surfs), 1.0)
    blade = _free_blade_length(lens, groups, _stop_extent(st, 1), blade)
    for sgn in (1, -1):
        r0 = _stop_extent(st, sgn)
        ax.plot([zs, zs], [sgn * r0, sgn * (r0 + blade)], color="black",
                lw=2.6, solid_capstyle="butt", zorder=5)
    ax.annotate("stop", (zs, _stop_extent(st, 1) + blade), xytext=(0, 3), textcoords="offset points",
                ha="center", va="bottom", fontsize=8, color="black", zorder=6)
    return outer


def plot_lens(lens, path_or_ax, fields_deg=None, wavelengths_nm=(LAMBDA_F, LAMBDA_D, LAMBDA_C),
              rays_per_fan=11, title=None, *, image_radius_mm=None, dpi=150):
    """Draw ``lens`` (y–z section, traced fans) to a file or into a matplotlib ``Axes``.

    ``path_or_ax``: a path (PNG/SVG/PDF/… by extension; written atomically) or an ``Axes``.
    ``fields_deg``: field angles (degrees) of the fans; default 0, 0.7 and 1.0 × the half field of
    view (:func:`half_field_deg`).  ``wavelengths_nm``: one line style each (the one nearest the
    d line solid).  ``rays_per_fan``: rays per field and wavelength across the real pupil.
    Returns the path written, or the ``Axes``.
    """
    rays_per_fan = int(rays_per_fan)
    if rays_per_fan < 1:
        raise LensError(f"rays_per_fan must be ≥ 1, got {rays_per_fan}")
    wavelengths = [float(w) for w in (wavelengths_nm or (LAMBDA_D,))]
    if any(not (math.isfinite(w) and w > 0) for w in wavelengths):
        raise LensError(f"wavelengths must be positive numbers of nm, got {list(wavelengths_nm)}")
    wl_prim = wavelengths[int(np.argmin([abs(w - LAMBDA_D) for w in wavelengths]))]
    par = lens.paraxial(wl_prim)
    fields, labels, hf = _fields(lens, fields_deg, wl_prim, image_radius_mm)
    colors = _field_colors(len(fields))
    styles = _line_styles(wavelengths)

    own_fig = not hasattr(path_or_ax, "plot")
    if own_fig:
        _image_format(path_or_ax)          # fail before tracing on an unknown extension
    z0 = _start_z(lens)
    track = lens.image_z - z0
    stub = 0.10 * track
    polylines, deaths, y_img = _fan_polylines(lens, fields, wavelengths, rays_per_fan, z0, stub, colors, styles)

    # ---------------------------------------------------------------- limits and figure
    r_lens = max(s.semi_diameter for s in lens.surfaces)
    zi = lens.image_z
    h_plane = max(max(y_img, default=0.0) * 1.12, 0.35 * r_lens)
    zmin = min([z0 - stub] + [float(np.nanmin(z)) for z, *_ in polylines])
    xlim = (zmin - 0.02 * track, zi + 0.04 * track)
    y_rays = max([float(np.nanmax(np.abs(y))) for _, y, *_ in polylines], default=0.0)
    ymax = max(r_lens * 1.25, h_plane * 1.1, min(y_rays * 1.04, 1.6 * r_lens),
               max((s.housing_radius or 0.0) for s in lens.surfaces) * 1.15)
    if own_fig:
        fig, ax, ymax = _new_figure(xlim, ymax, title, dpi)
    else:
        ax = path_or_ax
        fig = None

    _draw_lens(ax, lens)
    _draw_rays(ax, polylines, deaths)
    _draw_axis(ax, par, zi, h_plane, zmin, track)
    _frame_axes(ax, xlim, ymax)
    _title(ax, lens, par, title, hf, fields_deg is None, wl_prim)
    _legend(ax, fig, fields, labels, colors, wavelengths, styles, bool(deaths))

    if not own_fig:
        return ax
    return _save(fig, path_or_ax)


def _fields(lens, fields_deg, wl_prim, image_radius_mm):
    """The fans' field angles (degrees), their legend labels and the half field (or the largest angle given)."""
    if fields_deg is None:
        hf = half_field_deg(lens, wl_prim, image_radius_mm)
        return [f * hf for f in FIELD_FRACTIONS], ["on axis", "0.7 field", "full field"], hf
    fields = [float(f) for f in fields_deg]
    if any(not (math.isfinite(f) and 0 <= abs(f) < 90) for f in fields):
        raise LensError(f"field angles must be in (−90°, 90°), got {list(fields_deg)}")
    return fields, [""] * len(fields), (max(abs(f) for f in fields) if fields else 0.0)


def _field_colors(n: int) -> list:
    """One colour per field: :data:`FIELD_COLORS` for up to three, else a viridis ramp."""
    if n <= 3:
        return [FIELD_COLORS[k] for k in range(n)]
    import matplotlib
    cmap = matplotlib.colormaps["viridis"]
    return [cmap(k / max(1, n - 1)) for k in range(n)]


def _fan_polylines(lens, fields, wavelengths, rays_per_fan, z0, stub, colors, styles):
    """The traced fans as drawn: ``polylines`` [(z, y, colour, line style)] (mm; each with a short incoming stub
    of length ``stub`` before the first surface), ``deaths`` [(z, y, colour)] where blocked rays end, and
    ``y_img``, the image heights |y| (mm) of the rays that pass."""
    polylines, deaths, y_img = [], [], []
    targets = np.linspace(-STOP_FILL, STOP_FILL, rays_per_fan) * lens.stop.semi_diameter \
        if rays_per_fan > 1 else np.zeros(1)
    pairs = [(fi, w) for fi in range(len(fields)) for w in wavelengths]
    th_pairs = np.array([abs(fields[fi]) for fi, _ in pairs])
    wl_pairs = np.array([w for _, w in pairs])
    hs = _aim(lens, th_pairs, wl_pairs, z0, targets) if pairs else np.zeros((0, len(targets)))
    keep = np.all(np.isfinite(hs), axis=1)
    if not keep.any():
        return polylines, deaths, y_img
    pts, valid = _trace_fans(lens, th_pairs[keep][:, None], hs[keep],
                             wl_pairs[keep][:, None], z0)
    pts = pts.reshape(int(keep.sum()), len(targets), *pts.shape[1:])
    valid = valid.reshape(int(keep.sum()), len(targets))
    for kk, k in enumerate(np.nonzero(keep)[0]):
        fi, w = pairs[k]
        sgn = 1.0 if fields[fi] >= 0 else -1.0
        for j in range(len(targets)):
            p = pts[kk, j]
            p = p[np.all(np.isfinite(p), axis=1)].copy()
            if len(p) < 2:
                continue
            p[:, 1] *= sgn
            d0 = p[1] - p[0]
            p[0] = p[1] - d0 / (np.linalg.norm(d0) or 1.0) * stub     # a short incoming stub
            polylines.append((p[:, 2], p[:, 1], colors[fi], styles[w]))
            if valid[kk, j]:
                y_img.append(abs(p[-1, 1]))
            else:
                deaths.append((p[-1, 2], p[-1, 1], colors[fi]))
    return polylines, deaths, y_img


def _new_figure(xlim, ymax, title, dpi):
    """A figure sized to the drawing's aspect (z range ``xlim``, y range ±``ymax``, mm): ``(fig, ax, ymax)``, the
    y range widened for a long, slim lens."""
    from matplotlib.figure import Figure
    xspan = xlim[1] - xlim[0]
    w_in = 12.0
    ax_w = w_in - 1.0
    ax_h = ax_w * 2 * ymax / xspan
    if ax_h < 3.0:            # long, slim lenses: show more y rather than a sliver
        ax_h = 3.0
        ymax = 0.5 * ax_h * xspan / ax_w
    if ax_h > 7.5:            # short, fat lenses: narrow the figure instead of padding it
        ax_h = 7.5
        w_in = max(7.0, 1.0 + ax_h * xspan / (2 * ymax))
    n_title = 2 + (1 if title else 0)
    fig = Figure(figsize=(w_in, ax_h + 1.3 + 0.2 * n_title + (0.25 if w_in < 11 else 0.0)),
                 dpi=dpi, layout="constrained")
    return fig, fig.add_subplot(1, 1, 1), ymax


def _draw_rays(ax, polylines, deaths):
    """The fans' polylines, and a × where each blocked ray ends."""
    for z, y, c, ls in polylines:
        ax.plot(z, y, color=c, ls=ls, lw=0.75 if ls == "-" else 0.7, alpha=0.9 if ls == "-" else 0.75,
                zorder=3, solid_capstyle="round")
    if deaths:
        dz, dy, dc = zip(*deaths)
        ax.scatter(dz, dy, marker="x", s=16, c=list(dc), linewidths=1.1, zorder=7)


def _draw_axis(ax, par, zi, h_plane, zmin, track):
    """The image plane at ``zi`` (±``h_plane``, mm), the optical axis and the paraxial cardinal marks on it
    (entrance and exit pupils, rear focal point) that lie in the drawing."""
    ax.plot([zi, zi], [-h_plane, h_plane], color="#333333", lw=1.6, zorder=5)
    ax.annotate("image plane", (zi, h_plane), xytext=(-3, 3), textcoords="offset points", ha="right",
                va="bottom", fontsize=8, zorder=6)
    ax.axhline(0.0, color="#777777", lw=0.6, ls=(0, (8, 3, 2, 3)), zorder=1)
    # paraxial cardinal marks on the axis
    marks = [(par.entrance_pupil_z, "EP"), (par.exit_pupil_z, "XP"), (par.rear_focal_z, "F′")]
    for z, lab in marks:
        if math.isfinite(z) and zmin <= z <= zi + 0.1 * track:
            ax.plot([z], [0.0], marker="|", ms=9, mew=1.2, color="#555555", zorder=6)
            ax.annotate(lab, (z, 0.0), xytext=(0, -10), textcoords="offset points", ha="center",
                        va="top", fontsize=7, color="#555555", zorder=6)


def _frame_axes(ax, xlim, ymax):
    """Limits (mm), equal aspect, labels and a light grid."""
    ax.set_xlim(*xlim)
    ax.set_ylim(-ymax, ymax)
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("z (mm)  — object space on the left, sensor on the right")
    ax.set_ylabel("y (mm)")
    ax.grid(True, color="#e6e6e6", lw=0.5, zorder=0)
    ax.set_axisbelow(True)
    for side in ("top", "right"):
        ax.spines[side].set_visible(False)


def _title(ax, lens, par, title, hf, half_field: bool, wl_prim):
    """The title: ``title`` (if any), the lens's EFL and f-number, then its paraxial data and focus and the
    half field ``hf`` (degrees; ``half_field`` False: the largest field given)."""
    zi = lens.image_z
    head = f"{lens.name}: EFL {par.efl:.2f} mm, f/{par.fnumber:.2f}"
    try:
        fd = par.focus_distance_for(par.sensor_distance)
        focus = "focused at ∞" if math.isinf(fd) else f"focused at {fd / 1000:.3g} m"
    except LensError:
        focus = f"image plane {par.bfl - par.sensor_distance:.2f} mm in front of F′"
    sub = (f"BFL {par.bfl:.2f} mm · track {lens.total_track:.2f} mm · image plane z = {zi:.2f} mm, "
           f"{focus} · "
           + (f"half field {hf:.1f}°" if half_field else f"max field {hf:.1f}°")
           + f" · paraxial at {wl_prim:g} nm")
    ax.set_title((title + "\n" if title else "") + head + "\n" + sub, fontsize=10, loc="left")


def _legend(ax, fig, fields, labels, colors, wavelengths, styles, blocked: bool):
    """One entry per field and per wavelength (and for the blocked rays' ×): below the axes of our own figure
    ``fig``, else inside ``ax``."""
    from matplotlib.lines import Line2D
    handles = []
    for fi, th in enumerate(fields):
        lab = f"{abs(th):.1f}°" + (f" ({labels[fi]})" if labels[fi] else "")
        handles.append(Line2D([], [], color=colors[fi], lw=2, label=lab))
    for w in wavelengths:
        handles.append(Line2D([], [], color="#444444", ls=styles[w], lw=1.0, label=f"{w:g} nm"))
    if blocked:
        handles.append(Line2D([], [], color="#444444", marker="x", ls="", label="ray blocked"))
    if fig is not None:     # below the axes, in the space constrained layout reserves for it
        ncol = len(handles) if fig.get_figwidth() >= 11 else (len(handles) + 1) // 2
        fig.legend(handles=handles, loc="outside lower center", fontsize=8, ncol=ncol, frameon=False,
                   handlelength=2.6, columnspacing=1.4)
    else:
        ax.legend(handles=handles, loc="best", fontsize=7, ncol=2, framealpha=0.85)


def _image_format(path) -> str:
    """The file format from ``path``'s extension (``png`` when it has none); LensError if unknown."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower().lstrip(".") or "png"
    types = FigureCanvasAgg.get_supported_filetypes()
    if ext not in types:
        raise LensError(f"cannot write '{path}': unknown image format '.{ext}'; valid: "
                        + ", ".join(sorted("." + e for e in types)))
    return ext


def _save(fig, path) -> str:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    FigureCanvasAgg(fig)
    path = os.fspath(path)
    ext = _image_format(path)
    from ..fileio import atomic_write
    atomic_write(path, lambda tmp: fig.savefig(tmp, format=ext))
    return path
