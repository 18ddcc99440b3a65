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


@lru_cache(maxsize=16)
def _ranking_cached(lens, w, h, fresnel, n_rays, n_angles, seed, ghost_ids):
    import drjit as dr
    from ..trace.api import float_type, tracer_for
    F = float_type("float32")
    tr = tracer_for(lens, fresnel)
    efl = abs(lens.efl()) if hasattr(lens, "efl") else 50.0
    half_diag = 0.5 * math.hypot(w, h)
    th_max = math.atan(half_diag / efl)
    angles = np.linspace(0.0, th_max, n_angles)
    z_in = input_plane(lens)
    rng = np.random.default_rng(seed)
    ox, oy, dxs, dys, dzs, lams, wts = [], [], [], [], [], [], []
    for th in angles:
        R = front_radius(lens, math.tan(th), z_in)
        u = rng.random((n_rays, 2))
        rr = R * np.sqrt(u[:, 0])
        ph = 2 * math.pi * u[:, 1]
        ox.append(rr * np.cos(ph)); oy.append(rr * np.sin(ph))
        dxs.append(np.full(n_rays, math.sin(th))); dys.append(np.zeros(n_rays))
        dzs.append(np.full(n_rays, math.cos(th)))
        lams.append(_cie_y_samples(rng, n_rays))
        # flux per ray per unit irradiance: projected sampled area / n
        wts.append(np.full(n_rays, math.pi * R * R * math.cos(th) / n_rays / n_angles))
    cat = lambda xs: from_numpy(F, np.concatenate(xs))
    o = (cat(ox), cat(oy), cat([np.full(n_rays, z_in)] * n_angles))
    d = (cat(dxs), cat(dys), cat(dzs))
    lam = cat(lams)
    wt = np.concatenate(wts)

    def energy(pid):
        res = tr.trace(o, d, lam, pid, "forward")
        x, y = res.position[0], res.position[1]
        hit = res.valid & (dr.abs(x) <= 0.5 * w) & (dr.abs(y) <= 0.5 * h)
        T = dr.select(hit, res.throughput, 0.0)
        dr.eval(T, hit)
        hv = hit.numpy().astype(bool)
        return float((T.numpy() * wt).sum()), float(hv.mean())

    from ..trace.paths import rank_ghosts_by_energy
    return tuple(rank_ghosts_by_energy(lens, energy, ghost_ids, skip=lambda a, b: trivial_ghost(lens, a, b)))
