"""Held-out accuracy of learned maps against the exact tracer (float64 reference).

Regressor (on valid rays, uniform over the valid region, or MCMC for rare paths): exit-position error
on the output plane (µm), exit-direction error (arcsec), relative throughput error.  Classifier (on rays
uniform over the whole reduced domain, i.e. the natural mix): misclassification rate, false-valid and
false-blocked rates (fractions of all rays), and for each misclassified ray the distance to the true
boundary (in normalised input units, 1 = half the domain's width): the smallest radius at which one of
32 random perturbations changes the true label.
"""
from __future__ import annotations

import numpy as np

from ..constants import ARCSEC_PER_RAD
from ..transport.sampling import PathSampler, heldout_valid

ARCSEC = ARCSEC_PER_RAD


def map_outputs_np(tm, x):
    """(logit (N,), outputs (N, 5 + 2k)) of the learned map ``tm`` on reduced inputs ``x`` (N, 4), float64,
    through the Dr.Jit core with the map's numbers as kernel parameters (``mlp = "shared"``): every map of
    one architecture then runs one compiled kernel, where literals compiled one per map and per weight set
    (the calibration's shifted bias is another) — 1.7 s of LLVM compilation a ghost, 48 s of a lens's 28
    forward maps on a 2-core CPU.  The arithmetic is the literals' own."""
    import dataclasses
    if getattr(tm, "mlp", "shared") != "shared":
        tm = dataclasses.replace(tm, mlp="shared")
    return tm.eval_reduced_np(x)


def regression_errors(y_pred: np.ndarray, y_true: np.ndarray, heading: int) -> dict:
    """Per-sample errors → summary dict.  Columns (x, y, dx, dy, T) in the reduced frame."""
    pos = np.hypot(y_pred[:, 0] - y_true[:, 0], y_pred[:, 1] - y_true[:, 1]) * 1000.0  # µm

    def d3(y):
        dz = heading * np.sqrt(np.maximum(1.0 - y[:, 2] ** 2 - y[:, 3] ** 2, 0.0))
        v = np.stack([y[:, 2], y[:, 3], dz], 1)
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    a, b = d3(y_pred), d3(y_true)
    cross = np.linalg.norm(np.cross(a, b), axis=1)
    ang = np.arctan2(cross, np.sum(a * b, axis=1)) * ARCSEC
    rel = np.abs(y_pred[:, 4] - y_true[:, 4]) / np.maximum(np.abs(y_true[:, 4]), 1e-12)
    q = lambda v, p: float(np.percentile(v, p))
    return {"n": int(len(pos)),
            "position_um_median": q(pos, 50), "position_um_p99": q(pos, 99), "position_um_max": float(pos.max()),
            "direction_arcsec_median": q(ang, 50), "direction_arcsec_p99": q(ang, 99),
            "direction_arcsec_max": float(ang.max()),
            "throughput_rel_median": q(rel, 50), "throughput_rel_p99": q(rel, 99)}


def stop_errors(s_pred: np.ndarray, s_true: np.ndarray) -> dict:
    """Stop-plane crossing errors (µm): per ray the largest over its crossings; columns (sx, sy, …)."""
    k = s_true.shape[1] // 2
    e = np.max([np.hypot(s_pred[:, 2 * i] - s_true[:, 2 * i], s_pred[:, 2 * i + 1] - s_true[:, 2 * i + 1])
                for i in range(k)], axis=0) * 1000.0
    return {"n": int(len(e)), "crossings": int(k), "stop_um_median": float(np.median(e)),
            "stop_um_p99": float(np.percentile(e, 99)), "stop_um_max": float(e.max())}


def boundary_distance(ps: PathSampler, xn_wrong: np.ndarray, label_true: np.ndarray, center, scale,
                      rng, n_dir: int = 32, radii=None) -> np.ndarray:
    """For each point (normalised coordinates), the smallest radius at which a random perturbation has
    the opposite true label (inf when none within the largest radius)."""
    if radii is None:
        radii = np.geomspace(1e-4, 0.5, 24)
    out = np.full(len(xn_wrong), np.inf)
    if len(xn_wrong) == 0:
        return out
    for r in radii:
        todo = ~np.isfinite(out)
        if not todo.any():
            break
        pts = xn_wrong[todo]
        k = xn_wrong.shape[1]
        d = rng.standard_normal((len(pts), n_dir, k))
        d /= np.linalg.norm(d, axis=2, keepdims=True)
        q = (pts[:, None, :] + r * d).reshape(-1, k)
        x = q * scale + center
        x[:, 0] = np.abs(x[:, 0])               # r ≥ 0 (mirror image is the same ray family)
        x[:, 2] = np.abs(x[:, 2])               # ωy ≥ 0 (mirror symmetry)
        v, _ = ps.trace_x(x)
        flip = (v.reshape(len(pts), n_dir) != label_true[todo][:, None]).any(1)
        idx = np.nonzero(todo)[0][flip]
        out[idx] = r
    return out


def evaluate_map(lens, tm, n: int = 200_000, seed: int = 999, mcmc_threshold: float = 0.02,
                 fresnel: bool = True, boundary: bool = True, reg_data=None) -> dict:
    """Every metric of one :class:`~mi_neurallens.neural.model.NeuralMap`."""
    from ..transport.planning import Domain
    dom = Domain.from_dict(tm.domain)
    rng = np.random.default_rng(seed)
    k = tm.stop_crossings
    if reg_data is None:
        reg_data = heldout_valid(lens, (tm.path_id, tm.direction, tm.z_in, tm.z_out), dom, n, seed + 1,
                                 mcmc_threshold, fresnel, stops=k > 0)
    x, y = reg_data
    _, yp = map_outputs_np(tm, x)
    if getattr(tm, "position_cos", False):     # compared as the map regresses them: a ray's offset, not a plane's
        from ..neural.model import position_cos
        yp, y = position_cos(yp), position_cos(y)          # columns 0, 1 only: the stop crossings stay
    m = {"regressor": regression_errors(yp[:, :5], y[:, :5], tm.heading)}
    if k and y.shape[1] >= 5 + 2 * k:
        m["stop"] = stop_errors(yp[:, 5:5 + 2 * k], y[:, 5:5 + 2 * k])
    # classifier on the natural (uniform-domain) mix
    ps = PathSampler(lens, tm.path_id, tm.direction, tm.z_in, tm.z_out, dom, fresnel=fresnel, precision="float64")
    xu = dom.u_to_x(rng.random((n, dom.dims)))
    v, _ = ps.trace_x(xu)
    logit, _ = map_outputs_np(tm, xu)
    pv = logit > 0
    wrong = pv != v
    c = {"n": int(n), "valid_fraction": float(v.mean()), "misclassification": float(wrong.mean()),
         "false_valid": float((pv & ~v).mean()), "false_blocked": float((~pv & v).mean()),
         "false_valid_of_invalid": float((pv & ~v).sum() / max((~v).sum(), 1)),
         "false_blocked_of_valid": float((~pv & v).sum() / max(v.sum(), 1))}
    # classifier on truly-valid regressor samples (important for rare ghosts, where the natural mix is
    # almost all invalid)
    lv, _ = map_outputs_np(tm, x)
    c["false_blocked_on_valid_set"] = float((lv <= 0).mean())
    if boundary and wrong.any():
        idx = np.nonzero(wrong)[0][:2000]
        xn = tm.normalise_np(xu[idx])
        dist = boundary_distance(ps, xn, v[idx], tm.input_center, tm.input_scale, rng)
        fin = dist[np.isfinite(dist)]
        c["wrong_boundary_distance_median"] = float(np.median(fin)) if len(fin) else None
        c["wrong_boundary_distance_p99"] = float(np.percentile(fin, 99)) if len(fin) else None
        c["wrong_boundary_distance_units"] = "normalised input (1 = half the domain width)"
        c["wrong_far_from_boundary"] = int((~np.isfinite(dist)).sum())
    m["classifier"] = c
    if dom.conditions is not None:
        m["cells"] = cell_errors(dom.conditions, x, y, yp, tm.heading, xu, wrong)
    return m


def cell_errors(conf, x, y, yp, heading, xu, wrong) -> dict:
    """A map over moving groups, cell by cell of its configurations and at its range's corners
    (:meth:`~mi_neurallens.transport.configurations.Configurations.cells`): {cell: position µm and direction ″
    medians of the held-out rays ``x`` (outputs ``y``, predicted ``yp``), misclassification of the natural-mix rays
    ``xu`` (``wrong``: where the classifier erred)}."""
    out = {}
    reg, cls = conf.cells(x, corners=True), conf.cells(xu, corners=True)
    for k in sorted(set(reg) | set(cls)):
        r = regression_errors(yp[reg[k], :5], y[reg[k], :5], heading) if k in reg else {}
        out[k] = {"position_um_median": r.get("position_um_median"), "direction_arcsec_median":
                  r.get("direction_arcsec_median"), "misclassification": float(wrong[cls[k]].mean()) if k in cls else None}
    return out


def worst_cells(m: dict) -> str:
    """The worst configuration cell of each figure in a map's metrics ``m`` (:func:`cell_errors`) as a line of
    text; "" for a map without cells."""
    cells = m.get("cells") or {}
    parts = []
    for key, what, fmt in (("position_um_median", "position", "{:.3g} µm"), ("direction_arcsec_median", "direction",
                                                                              "{:.3g}″"),
                           ("misclassification", "misclassified", "{:.3%}")):
        got = {k: v[key] for k, v in cells.items() if v.get(key) is not None}
        if got:
            w = max(got, key=got.get)
            parts.append(f"{what} {fmt.format(got[w])} ({w})")
    return ", ".join(parts)


GOALS = {"position_um_median": 2.0, "position_um_p99": 20.0, "direction_arcsec_median": 5.0,
         "direction_arcsec_p99": 40.0, "throughput_rel_median": 0.005, "misclassification": 0.005}


def meets_goals(m: dict) -> dict:
    r, c = m["regressor"], m["classifier"]
    vals = {**{k: r[k] for k in GOALS if k in r}, "misclassification": c["misclassification"]}
    return {k: bool(vals[k] <= g) for k, g in GOALS.items()}


def markdown_table(model, rows) -> str:
    """The held-out metrics of ``rows`` ((key, metrics) pairs) as a markdown table; a "flare" column per
    ``boundary_band`` a verified paired flare MAPE was recorded with (:func:`~mi_neurallens.flare.verify.
    flare_records`), when any row has one."""
    from ..flare.verify import flare_records, record_band
    bands = sorted({record_band(r) for _, m in rows for r in flare_records(m)})
    hdr = ("| map | path | pos µm med | pos µm p99 | dir ″ med | dir ″ p99 | T rel med | misclass | "
           "false-valid | false-blocked | wrong: boundary dist med | stop µm med | stop µm p99 |"
           + "".join(" flare, paired MAPE |" if b == 0 else f" flare, band {b:g} |" for b in bands) + "\n"
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|" + "---|" * len(bands) + "\n")
    lines = []
    for key, m in rows:
        r, c, st = m["regressor"], m["classifier"], m.get("stop")
        bd = c.get("wrong_boundary_distance_median")
        stop = (f"{st['stop_um_median']:.3g} | {st['stop_um_p99']:.3g}" if st else "— | —")
        got = {record_band(x): x.get("paired_mape") for x in flare_records(m)}
        fl = "".join(f" {'—' if got.get(b) is None else f'{got[b]:.4f}'} |" for b in bands)
        lines.append(f"| {key} | {m.get('describe', '')} | {r['position_um_median']:.3g} | {r['position_um_p99']:.3g} | "
                     f"{r['direction_arcsec_median']:.3g} | {r['direction_arcsec_p99']:.3g} | "
                     f"{100 * r['throughput_rel_median']:.3g}% | {100 * c['misclassification']:.3g}% | "
                     f"{100 * c['false_valid']:.3g}% | {100 * c['false_blocked']:.3g}% | "
                     f"{'—' if bd is None else f'{bd:.3g}'} | {stop} |{fl}")
    worst = [f"* {key}, worst configuration cell (median): {worst_cells(m)}" for key, m in rows if worst_cells(m)]
    return hdr + "\n".join(lines) + "\n" + ("\n" + "\n".join(worst) + "\n" if worst else "")
