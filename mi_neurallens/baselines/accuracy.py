"""Accuracy and cost of every method against the exact tracer, and flare spot-diagram images.

:func:`evaluate_path` — per path and method, on rays over the neural map's own domain and planes:

* exit-position error (µm) and exit-direction error (arcsec), median and p99, on rays valid under
  BOTH the tracer and the method (held-out valid rays: uniform over the valid region, or the
  Metropolis sampler for rare ghosts — :func:`~mi_neurallens.transport.sampling.heldout_valid`), each
  rotated by a random angle about the axis so the lens-space (not only the reduced-frame) map is tested;
* relative throughput error |T − T_ref| / T_ref (median, p99);
* valid-mask agreement: IoU of the method's valid set with the tracer's on rays uniform over the whole
  domain (the natural mix), plus false-valid / false-blocked fractions;
* cost: rays/s of ``eval_dr`` (LLVM, float32, same rays for every method, best of 3, compile excluded) and
  a FLOP count per ray (polynomials: monomial products + 2 per term; MLPs: 2·in·out per layer + 17 per
  tanh, ``TANH_FLOPS``; the tracer: not counted).

:func:`flare_images` — a point light at infinity, spot diagrams on the sensor plane per method (box filter:
each ray adds its weight to the pixel it lands in), one channel per wavelength, and the flare MAPE against
the exact tracer (:func:`mi_neurallens.metrics.mape_masked`: luminance, over the pixels above 1 % of the
reference's peak — the plain MAPE of a mostly black image is dominated by empty pixels).  Every method
sees the same rays, so the error is the map's, not Monte Carlo noise.

These tables are measurements, never render time: :func:`evaluate_path` draws its held-out rays with the
training's sampler (:mod:`mi_neurallens.transport.sampling`), imported inside it only.
"""
from __future__ import annotations

import math
import time

import numpy as np

from ..constants import ARCSEC_PER_RAD, FULL_FRAME_HALF_DIAGONAL_MM
from ..jit import from_numpy
from ..metrics import mape_masked
from ..trace import symmetry
from .common import bundled_model, default_domain, default_map_planes

ARCSEC = ARCSEC_PER_RAD
#: the paper's image MAPE (flare renders, Fig. "light_tracing"): Poly (Taylor) vs neural
PAPER_MAPE = {"ood-59mm": {"all paths": {"poly": 0.148, "neural": 0.047},
                           "single path": {"poly": 0.027, "neural": 0.007, "path": "131092 (paper's id)"}},
              "wide-22mm": {"all paths": {"poly": 0.694, "neural": 0.032},
                            "single path": {"poly": 0.147, "neural": 0.002, "path": "65616 (paper's id)"}}}

DEFAULT_METHODS = ("abcd", "taylor3", "taylor5", "taylor5-ap", "fitted", "neural")


def build_method(lens, name: str, path_id: int, direction: str, z_in, z_out, domain, model, fitted_opts=None):
    """Method by table name: ``abcd``, ``taylor3``, ``taylor5``, ``taylor5-ap`` (aperture='all'),
    ``fitted``, ``neural``, ``exact``.  Returns None for ``neural`` without a bundled map."""
    from ..transport import make_map
    if name == "neural":
        if model is None or not model.has(path_id, direction):
            return None
        return model.map(path_id, direction)
    if name == "taylor5-ap":
        return make_map(lens, "taylor", path_id, direction, z_in, z_out, degree=5, aperture="all")
    if name == "taylor3-ap":
        return make_map(lens, "taylor", path_id, direction, z_in, z_out, degree=3, aperture="all")
    if name == "fitted":
        return make_map(lens, "fitted", path_id, direction, z_in, z_out, domain=domain, model=model,
                           **(fitted_opts or {}))
    return make_map(lens, name, path_id, direction, z_in, z_out)


def flops_of(m) -> int | None:
    """A map's operations per ray (None where not counted: the tracer)."""
    return int(m.flops()) or None


def _rotate(o, d, phi):
    c, s = np.cos(phi), np.sin(phi)
    o2 = np.stack([c * o[:, 0] - s * o[:, 1], s * o[:, 0] + c * o[:, 1], o[:, 2]], 1)
    d2 = np.stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1], d[:, 2]], 1)
    return o2, d2


def rays_from_reduced(x, z_in, heading, rng):
    """Reduced inputs (N, 4) → lens-space rays (o, d, λ) rotated by random angles, and the angles."""
    (px, py), (dx, dy, dz) = symmetry.reduced_ray(x[:, 0], x[:, 1], x[:, 2], heading)
    o = np.stack([px, py, np.full(len(px), z_in)], 1)
    d = np.stack([dx, dy, dz], 1)
    phi = rng.uniform(0, 2 * np.pi, len(x))
    o, d = _rotate(o, d, phi)
    return o, d, x[:, 3].copy(), phi


def ref_outputs(y, phi, z_out, heading):
    """Reduced-frame reference outputs (N, 5) → lens-space position, direction, throughput."""
    pos = np.stack([y[:, 0], y[:, 1], np.full(len(y), z_out)], 1)
    dz = heading * np.sqrt(np.maximum(1.0 - y[:, 2] ** 2 - y[:, 3] ** 2, 0.0))
    d = np.stack([y[:, 2], y[:, 3], dz], 1)
    pos, d = _rotate(pos, d, phi)
    return pos, d, y[:, 4]


def angle_arcsec(a, b):
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1)) * ARCSEC


def time_eval_dr(m, o, d, lam, repeats: int = 3) -> float:
    """Rays/s of ``m.eval_dr`` (float32 LLVM) on the given rays; best of ``repeats`` after a warm-up."""
    import drjit as dr
    from ..trace.api import float_type
    F = float_type("float32")
    O = tuple(from_numpy(F, o[:, i]) for i in range(3))
    D = tuple(from_numpy(F, d[:, i]) for i in range(3))
    L = from_numpy(F, lam)
    dr.eval(O, D, L)
    best = math.inf
    for k in range(repeats + 1):
        t0 = time.perf_counter()
        res = m.eval_dr(O, D, L)
        dr.eval(res.valid, res.position, res.direction, res.throughput)
        dr.sync_thread()
        dt = time.perf_counter() - t0
        if k > 0:
            best = min(best, dt)
    return len(o) / best


def evaluate_path(lens, path_id: int, direction: str, methods=DEFAULT_METHODS, n: int = 20000, seed: int = 4242,
                  time_rays: int = 1 << 18, model=None, fitted_opts=None, log=print) -> dict:
    """Every metric of every method on one path (see the module docstring)."""
    from ..transport.sampling import PathSampler, heldout_valid
    from ..transport import ExactMap
    model = bundled_model(lens) if model is None else model
    z_in, z_out = default_map_planes(lens, direction, model)
    dom = default_domain(lens, path_id, direction, model)
    heading = 1 if direction == "forward" else -1
    rng = np.random.default_rng(seed)
    x, y = heldout_valid(lens, (path_id, direction, z_in, z_out), dom, n, seed + 1)
    o, d, lam, phi = rays_from_reduced(x, z_in, heading, rng)
    pos_ref, dir_ref, T_ref = ref_outputs(y, phi, z_out, heading)
    ps = PathSampler(lens, path_id, direction, z_in, z_out, dom, precision="float64")
    xu = dom.u_to_x(rng.random((n, 4)))
    vu, _ = ps.trace_x(xu)
    ou, du, lu, _ = rays_from_reduced(xu, z_in, heading, rng)
    # timing rays: uniform over the domain
    xt = dom.u_to_x(rng.random((time_rays, 4)))
    ot, dt_, lt, _ = rays_from_reduced(xt, z_in, heading, rng)
    out = {"path_id": int(path_id), "direction": direction, "z_in": z_in, "z_out": z_out,
           "domain": dom.to_dict(), "steps": len(ps.tracer.path(path_id, direction).steps),
           "valid_fraction": float(vu.mean()), "n_valid_set": int(len(x)), "n_uniform_set": int(n),
           "methods": {}}
    ex = ExactMap(lens, path_id, direction, z_in, z_out)
    out["methods"]["exact"] = {"rays_per_s": time_eval_dr(ex, ot, dt_, lt), "flops_per_ray": None}
    for name in methods:
        t0 = time.perf_counter()
        m = build_method(lens, name, path_id, direction, z_in, z_out, dom, model, fitted_opts)
        if m is None:
            continue
        build_s = time.perf_counter() - t0
        r = m.eval_np(o, d, lam)
        both = r.valid
        e_pos = np.hypot(r.position[:, 0] - pos_ref[:, 0], r.position[:, 1] - pos_ref[:, 1]) * 1000.0
        e_dir = angle_arcsec(r.direction, dir_ref)
        e_T = np.abs(r.throughput - T_ref) / np.maximum(np.abs(T_ref), 1e-12)
        ru = m.eval_np(ou, du, lu)
        pv = ru.valid
        inter, union = int((pv & vu).sum()), int((pv | vu).sum())
        q = lambda a, p: float(np.percentile(a[both], p)) if both.any() else None
        row = {"build_s": build_s, "n_both": int(both.sum()), "valid_on_valid_set": float(both.mean()),
               "position_um_median": q(e_pos, 50), "position_um_p99": q(e_pos, 99),
               "direction_arcsec_median": q(e_dir, 50), "direction_arcsec_p99": q(e_dir, 99),
               "throughput_rel_median": q(e_T, 50), "throughput_rel_p99": q(e_T, 99),
               "iou": inter / max(union, 1), "false_valid": float((pv & ~vu).mean()),
               "false_blocked": float((~pv & vu).mean()),
               "rays_per_s": time_eval_dr(m, ot, dt_, lt), "flops_per_ray": flops_of(m)}
        if hasattr(m, "describe"):
            row["config"] = {k: v for k, v in m.describe().items() if k not in ("domain",)}
        out["methods"][name] = row
        if log:
            log(f"  {direction}.{path_id} {name:>10}: pos {_f(row['position_um_median'])}/{_f(row['position_um_p99'])} µm, "
                f"dir {_f(row['direction_arcsec_median'])}/{_f(row['direction_arcsec_p99'])}\", "
                f"T {_f(row['throughput_rel_median'])}, IoU {row['iou']:.3f}, {row['rays_per_s'] / 1e6:.1f} Mrays/s")
    out["methods"]["exact"]["speed_ratio_note"] = "reference"
    return out


def _f(v, fmt="{:.3g}"):
    return "—" if v is None else fmt.format(v)


# ----------------------------------------------------------------------------------- ghosts
def ghost_ranking(lens, model=None, n_rays: int = 1 << 14):
    """Ghosts by energy: the bundled model's stored ranking, or the render-time one
    (:func:`~mi_neurallens.flare.energy.ghost_energy_ranking`, ``n_rays`` per field angle)."""
    model = bundled_model(lens) if model is None else model
    if model is not None and model.extra.get("ghost_ranking"):
        return model.extra["ghost_ranking"]
    from ..flare.energy import ghost_energy_ranking
    return ghost_energy_ranking(lens, n_rays=n_rays)


def pick_ghosts(lens, k: int, model=None):
    """The ``k`` most energetic ghosts (ids), plus the shortest and longest of the top 2k by step count
    (so a short and a long ghost are always present)."""
    from ..trace.paths import resolve_path
    rk = [g for g in ghost_ranking(lens, model) if g["energy"] > 0]
    top = [g["path_id"] for g in rk[:k]]
    pool = [g["path_id"] for g in rk[:max(2 * k, 8)]]
    steps = {p: len(resolve_path(lens, p, "forward").steps) for p in pool}
    short, long_ = min(pool, key=lambda p: steps[p]), max(pool, key=lambda p: steps[p])
    out = list(dict.fromkeys(top + [short, long_]))
    return out, short, long_


# ----------------------------------------------------------------------------------- flare images
def flare_rays(lens, domain, z_in, field_deg: float, n: int, rng):
    """A point light at infinity ``field_deg`` off axis (in the x–z plane): parallel rays through a disk
    of radius r_max on ``z_in``."""
    th = math.radians(field_deg)
    rr = domain.r_max * np.sqrt(rng.random(n))
    a = rng.uniform(0, 2 * np.pi, n)
    o = np.stack([rr * np.cos(a), rr * np.sin(a), np.full(n, z_in)], 1)
    d = np.tile([math.sin(th), 0.0, math.cos(th)], (n, 1))
    return o, d


def splat(res, sensor_z, half_extent, px_res, weights):
    """Box-filtered spot diagram: (H, W) image of the rays' sensor-plane hits."""
    p, dvec, v = res.position, res.direction, res.valid
    with np.errstate(all="ignore"):
        t = (sensor_z - p[:, 2]) / dvec[:, 2]
        x = p[:, 0] + t * dvec[:, 0]
        y = p[:, 1] + t * dvec[:, 1]
    ok = v & np.isfinite(x) & np.isfinite(y)
    w = np.where(ok, weights, 0.0)
    H, _, _ = np.histogram2d(y[ok], x[ok], bins=px_res, range=[[-half_extent, half_extent]] * 2, weights=w[ok])
    return H


def flare_images(lens, paths, methods=("abcd", "taylor3", "taylor5", "fitted", "neural"), field_deg=None,
                 wavelengths=(450.0, 550.0, 650.0), n: int = 200_000, px_res: int = 192, half_extent=None,
                 seed: int = 11, model=None, built=None, fitted_opts=None):
    """Per path and method an (H, W, 3) spot-diagram image (one channel per wavelength, weights = Fresnel
    throughput, and a second set with weights 1 — the paper's protocol, Fresnel off), normalised by a common
    factor (the reference's 99.5th percentile of non-empty pixels = 1), and MAPE vs exact.

    Returns {"images": {path: {method: img}}, "images_geometric": …, "mape": {path: {method: v}},
    "mape_geometric": …, "all": {method: mape of the sum over paths}, "all_geometric": …}."""
    from ..transport import ExactMap
    model = bundled_model(lens) if model is None else model
    zf, zr = default_map_planes(lens, "forward", model)
    dom = default_domain(lens, 0, "forward", model)
    if field_deg is None:
        from ..transport.planes import default_field_half_angle
        field_deg = 0.5 * default_field_half_angle(lens)
    if half_extent is None:
        half_extent = FULL_FRAME_HALF_DIAGONAL_MM
    sensor_z = lens.image_z
    rng = np.random.default_rng(seed)
    o, d = flare_rays(lens, dom, zf, field_deg, n, rng)
    built = built if built is not None else {}
    imgs = {"throughput": {}, "geometric": {}}
    for pid in paths:
        for kind in imgs:
            imgs[kind][pid] = {}
        for name in ("exact",) + tuple(methods):
            key = (pid, name)
            if key not in built:
                built[key] = ExactMap(lens, pid, "forward", zf, zr) if name == "exact" else \
                    build_method(lens, name, pid, "forward", zf, zr, dom, model, fitted_opts)
            m = built[key]
            if m is None:
                continue
            chans_T, chans_G = [], []
            for lam in wavelengths:
                r = m.eval_np(o, d, np.full(n, lam))
                chans_T.append(splat(r, sensor_z, half_extent, px_res, r.throughput) / n)
                chans_G.append(splat(r, sensor_z, half_extent, px_res, np.ones(n)) / n)
            imgs["throughput"][pid][name] = np.stack(chans_T, -1)
            imgs["geometric"][pid][name] = np.stack(chans_G, -1)
    result = {"field_deg": field_deg, "sensor_z": sensor_z, "half_extent_mm": half_extent, "n_rays": n,
              "wavelengths": list(wavelengths), "paths": list(paths)}
    for kind in imgs:
        mp, allm = {}, {}
        per = imgs[kind]
        names = [nm for nm in ("exact",) + tuple(methods) if all(nm in per[p] for p in paths)]
        # all paths: the sum of the un-normalised images (each ghost weighted by its energy)
        raw = {nm: sum(per[p][nm] for p in paths) for nm in names}
        for pid in paths:
            s = _norm(per[pid]["exact"])
            for name, im in per[pid].items():
                per[pid][name] = im * s
            mp[pid] = {name: mape_masked(im, per[pid]["exact"]) for name, im in per[pid].items() if name != "exact"}
        s = _norm(raw["exact"])
        allm = {nm: mape_masked(raw[nm], raw["exact"]) for nm in names if nm != "exact"}
        result["mape" if kind == "throughput" else "mape_geometric"] = mp
        result["all" if kind == "throughput" else "all_geometric"] = allm
        result["images" if kind == "throughput" else "images_geometric"] = per
        result["all_images" if kind == "throughput" else "all_images_geometric"] = {nm: raw[nm] * s for nm in names}
    return result


def _norm(ref):
    nz = ref[ref > 0]
    return 1.0 / float(np.percentile(nz, 99.5)) if nz.size else 1.0


def save_flare_figure(result, lens_name, short_id, long_id, path, methods):
    """Rows: a short and a long ghost (geometric weights, the paper's protocol); columns: exact, methods;
    log tone mapping; MAPE in each title."""
    from matplotlib.figure import Figure
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    names = ["exact"] + [m for m in methods if m in result["images_geometric"][short_id]]
    rows = [short_id, long_id]
    fig = Figure(figsize=(2.3 * len(names), 2.5 * len(rows) + 0.3), dpi=110)
    FigureCanvasAgg(fig)
    he = result["half_extent_mm"]
    for i, pid in enumerate(rows):
        for j, nm in enumerate(names):
            ax = fig.add_subplot(len(rows), len(names), i * len(names) + j + 1)
            im = result["images_geometric"][pid].get(nm)
            if im is None:
                ax.axis("off")
                continue
            disp = np.clip(np.log10(1.0 + 200.0 * np.clip(im[..., ::-1], 0, None)) / np.log10(201.0), 0, 1)
            ax.imshow(disp, origin="lower", extent=[-he, he, -he, he], interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            t = nm if nm == "exact" else f"{nm}\nMAPE {result['mape_geometric'][pid][nm]:.3f}"
            ax.set_title(t, fontsize=8)
            if j == 0:
                kind = "short" if pid == short_id else "long"
                ax.set_ylabel(f"{kind} ghost {pid}", fontsize=8)
    fig.suptitle(f"{lens_name}: ghost spot diagrams, point light {result['field_deg']:.1f}° off axis "
                 "(650/550/450 nm as R/G/B, log scale)", fontsize=9)
    fig.tight_layout()
    from ..fileio import atomic_write
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png"))
    return path
