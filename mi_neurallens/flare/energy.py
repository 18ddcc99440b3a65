"""Ghost energy ranking with the exact tracer (no Mitsuba needed).

:func:`ghost_energy_ranking` answers "which two-reflection paths of this lens matter?": for a
collimated bright light at several field angles across the film (0 … the film corner), rays are
sampled uniformly over the front aperture at CIE-weighted wavelengths, traced along every ghost
path, and the Fresnel-weighted flux that lands on the film is summed.  The result has the same
shape as the ranking a neural model file stores (``model.extra["ghost_ranking"]``): a list of dicts
``{"path_id", "surfaces": [a, b], "energy", "valid_fraction", "share", "cumulative_share",
"relative_to_transmit"}``, largest energy first.  ``energy`` is the flux on the film per unit
irradiance at the front (mm² of aperture, averaged over the field angles); ``relative_to_transmit``
divides it by the transmit path's flux for the same light.

:func:`select_ghosts` keeps the smallest strongest-first set that covers a fraction of the ghost
energy (default 99 %), at most ``max_ghosts`` (default 32).
"""
from __future__ import annotations

from functools import lru_cache
import math

import numpy as np

from ..constants import FULL_FRAME_MM
from ..jit import from_numpy
from ..transport.planning import select_ghosts  # noqa: F401 (the one selection rule, re-exported)


#: wavelength range used for ranking (nm); sampled ∝ the CIE Y curve (Gaussian fit)
RANK_LAMBDA = (380.0, 780.0)


def _cie_y_samples(rng, n):
    """Wavelengths ∝ a Gaussian fit of the CIE 1931 ȳ curve (peak 555 nm), clipped to RANK_LAMBDA."""
    lam = rng.normal(556.1, 46.0, n)
    return np.clip(lam, *RANK_LAMBDA)


def front_radius(lens, tan_theta: float, z_in: float) -> float:
    """Radius on the plane ``z_in`` that encloses every ray (slope ``tan_theta``) that can still hit
    the first optical surface within its clear aperture."""
    s = lens.surfaces[lens.optical_indices[0]]
    zs = lens.vertex_z[lens.optical_indices[0]]
    r = np.linspace(0.0, s.semi_diameter, 65)
    z = zs + np.nan_to_num(s.sag(r))
    return float(s.semi_diameter + max(float(z.max()) - z_in, 0.0) * abs(tan_theta)) * 1.02 + 1e-3


def input_plane(lens) -> float:
    """Lens-space plane (mm) in front of the whole first surface where forward rays are started."""
    s = lens.surfaces[0]
    sag = float(s.sag(s.semi_diameter)) if not s.is_stop else 0.0
    return min(0.0, sag if math.isfinite(sag) else 0.0)


def trivial_ghost(lens, a: int, b: int) -> bool:
    """True when one of the two reflecting surfaces separates identical media (R = 0 there)."""
    opt = lens.optical_indices
    for k in (a, b):
        i = opt[k]
        if lens.medium_before(i) == lens.surfaces[i].medium:
            return True
    return False


def ghost_energy_ranking(lens, *, sensor_width_mm: float = FULL_FRAME_MM[0],
                         sensor_height_mm: float = FULL_FRAME_MM[1],
                         fresnel: bool = True, n_rays: int = 1 << 14, n_angles: int = 5, seed: int = 0,
                         ghosts=None):
    """Rank the forward ghosts of ``lens`` (configured: its last thickness is the sensor distance)
    by the flux they put on the film.  See the module docstring.  Cached per arguments."""
    key = None if ghosts is None else tuple(int(g) for g in ghosts)
    return [dict(d) for d in _ranking_cached(lens, float(sensor_width_mm), float(sensor_height_mm),
                                             bool(fresnel), int(n_rays), int(n_angles), int(seed), key)]


def _ranking_rays(lens, w, h, n_rays, n_angles, rng):
    """The rays :func:`ghost_energy_ranking` traces through the configured ``lens`` (its own space, mm): numpy
    origins (x, y, z), directions (x, y, z), wavelengths (nm) and weights (flux per ray per unit irradiance: the
    projected sampled area over the ray count), collimated lights at ``n_angles`` field angles from the axis to the
    film corner of a ``w`` × ``h`` mm film, ``n_rays`` each over the front aperture."""
    efl = abs(lens.efl()) if hasattr(lens, "efl") else 50.0
    th_max = math.atan(0.5 * math.hypot(w, h) / efl)
    z_in = input_plane(lens)
    cols = [[] for _ in range(8)]
    for th in np.linspace(0.0, th_max, n_angles):
        R = front_radius(lens, math.tan(th), z_in)
        u = rng.random((n_rays, 2))
        rr, ph = R * np.sqrt(u[:, 0]), 2 * math.pi * u[:, 1]
        for c, v in zip(cols, (rr * np.cos(ph), rr * np.sin(ph), np.full(n_rays, z_in), np.full(n_rays, math.sin(th)),
                               np.zeros(n_rays), np.full(n_rays, math.cos(th)), _cie_y_samples(rng, n_rays),
                               np.full(n_rays, math.pi * R * R * math.cos(th) / n_rays / n_angles))):
            c.append(v)
    return [np.concatenate(c) for c in cols]


def _film_energy(tr, o, d, lam, wt, pid, w, h, z_out=None, groups=None):
    """(energy, valid fraction) of path ``pid`` traced by ``tr``: the weights ``wt`` (numpy) of the rays that land
    on the ``w`` × ``h`` mm film (on the plane ``z_out``; default the tracer's image plane) times their
    throughput; with ``groups`` (one group index per ray) the energy is each group's (an array)."""
    import drjit as dr
    res = tr.trace(o, d, lam, pid, "forward", z_out=z_out)
    x, y = res.position[0], res.position[1]
    hit = res.valid & (dr.abs(x) <= 0.5 * w) & (dr.abs(y) <= 0.5 * h)
    T = dr.select(hit, res.throughput, 0.0)
    dr.eval(T, hit)
    e = T.numpy() * wt
    frac = float(hit.numpy().astype(bool).mean())
    return (float(e.sum()) if groups is None else np.bincount(groups, e)), frac


@lru_cache(maxsize=16)
def _ranking_cached(lens, w, h, fresnel, n_rays, n_angles, seed, ghost_ids):
    from ..trace.api import float_type
    from ..trace.parameters import LiveGeometry
    from ..trace.tracer import LensTracer
    F = float_type("float32")
    # the configuration's numbers as kernel inputs: the 435 ghosts of a 30-surface zoom rank at another focal
    # length, focus or f-number with the kernels compiled for the first (≈ 100 s of compiling on 2 cores)
    tr = LensTracer(lens, fresnel, geometry=LiveGeometry.configuration(lens, F))
    ox, oy, oz, dx, dy, dz, lam, wt = _ranking_rays(lens, w, h, n_rays, n_angles, np.random.default_rng(seed))
    o, d = tuple(from_numpy(F, a) for a in (ox, oy, oz)), tuple(from_numpy(F, a) for a in (dx, dy, dz))
    lam_dr = from_numpy(F, lam)

    def energy(pid):
        return _film_energy(tr, o, d, lam_dr, wt, pid, w, h)

    from ..trace.paths import rank_ghosts_by_energy
    return tuple(rank_ghosts_by_energy(lens, energy, ghost_ids, skip=lambda a, b: trivial_ghost(lens, a, b)))


#: zoom positions (evenly over the zoom range) at which :func:`moving_ghost_ranking` ranks a lens with moving groups
RANK_ZOOMS = 5


def moving_ghost_ranking(configs, *, sensor_width_mm: float = FULL_FRAME_MM[0],
                         sensor_height_mm: float = FULL_FRAME_MM[1], fresnel: bool = True, zooms: int = RANK_ZOOMS,
                         n_rays: int = 1 << 13, n_angles: int = 5, seed: int = 0, ghosts=None):
    """The ghost ranking of a lens with moving groups over the configurations its maps learn
    (:class:`~mi_neurallens.transport.configurations.Configurations`): the rays of :func:`ghost_energy_ranking` at
    ``zooms`` zoom positions, each at both ends of its focus band, all traced in one kernel per ghost (each ray in
    its own configuration, :meth:`~mi_neurallens.transport.configurations.Configurations.geometry`, in the
    configurations' frame); a ghost's ``energy`` is its largest over the configurations (a ghost strong at one end
    of the zoom counts, though faint at the other), ``valid_fraction`` its mean, ``relative_to_transmit`` against
    the transmit path's largest; the same entries as :func:`ghost_energy_ranking`'s.  Each configuration's rays are
    :func:`ghost_energy_ranking`'s for that configuration (the same ``seed``), so a ghost's energy is the largest of
    that function's over the configurations.  ``ghosts``: only these path ids.  One kernel per ghost for every
    configuration: the 24-70 mm's 435 ghosts rank in about 5 min on a 2-core CPU, once per training."""
    import drjit as dr
    from ..optics import moving as mv
    from ..trace.api import float_type
    from ..trace.paths import rank_ghosts_by_energy
    from ..trace.tracer import LensTracer
    F = float_type("float32")
    w, h = float(sensor_width_mm), float(sensor_height_mm)
    ts = np.linspace(*configs.zoom_range, zooms if len(configs.band_t) > 1 else 1)
    pairs = [(float(t), float(f)) for t in ts for f in configs.band(float(t))]
    cols, groups, cond = [], [], []
    for k, (t, f) in enumerate(pairs):
        ln = mv.at(configs.lens, t, f, check=False)
        rays = _ranking_rays(ln, w, h, n_rays, n_angles, np.random.default_rng(seed))
        rays[2] = rays[2] - configs.shift_of(ln.image_z)            # into the configurations' frame
        cols.append(rays)
        groups.append(np.full(len(rays[0]), k))
        cond.append(np.array([[t, f]] * len(rays[0])))
    ox, oy, oz, dx, dy, dz, lam, wt = (np.concatenate([c[i] for c in cols]) for i in range(8))
    groups, cond = np.concatenate(groups), np.concatenate(cond)
    values = [from_numpy(F, cond[:, 0 if n == "zoom" else 1]) for n in configs.names]
    tr = LensTracer(configs.lens, fresnel=fresnel, geometry=configs.geometry(F, values, configs.lens))
    o, d = tuple(from_numpy(F, a) for a in (ox, oy, oz)), tuple(from_numpy(F, a) for a in (dx, dy, dz))
    lam_dr = from_numpy(F, lam)
    dr.eval(o, d, lam_dr)

    def energy(pid):
        e, frac = _film_energy(tr, o, d, lam_dr, wt, pid, w, h, float(configs.z_sensor), groups)
        return float(np.max(e)), frac

    ids = None if ghosts is None else tuple(int(g) for g in ghosts)
    out = rank_ghosts_by_energy(configs.lens, energy, ids, skip=lambda a, b: trivial_ghost(configs.lens, a, b))
    for d_ in out:
        d_["configurations"] = len(pairs)
    return out
