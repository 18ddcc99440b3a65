"""Training-pipeline benchmark: data generation, training speed, time to the accuracy goals, memory, ablations.

    python benchmarks/bench_training.py                 # throughput + goals + memory (≈ 2 min)
    python benchmarks/bench_training.py --ablations     # + tanh/ReLU, symmetry, schedule (≈ +8 min)

Writes ``benchmarks/results/bench_training.json`` and prints a table; with ``--ablations`` also the
figures ``docs/training/*.png``.  Bars (docs/training.md): ≥ 10 M valid transmit samples/s, a transmit
map reaching its goals in ≤ 20 min, peak memory ≤ 4 GB.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from mi_neurallens.flare.energy import ghost_energy_ranking  # noqa: E402
from mi_neurallens import Lens  # noqa: E402
from mi_neurallens.training import data, plan  # noqa: E402
from mi_neurallens.training.evaluate import GOALS, regression_errors  # noqa: E402
from mi_neurallens.fileio import atomic_write_json  # noqa: E402

LENS = "wide-22mm"
STEPS = 0          # --ablation-steps: equal step budgets instead of equal wall-clock budgets


def setup(lens):
    s0, _ = plan.sensor_distance_range(lens, 300.0)
    zf, zr = plan.planes(lens, s0)
    return zf, zr


def peak_rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


# ----------------------------------------------------------------------------- data generation
def bench_generation(lens, zf, zr, seconds=6.0):
    rows = {}
    rng = np.random.default_rng(0)
    bdom = plan.backward_domain(lens, 0, zr, zf, rng, n=1 << 20)
    fdom = plan.forward_domain(lens, zf, plan.default_field_half_angle(lens))
    for name, pid, d, zi, zo, dom in (("backward transmit", 0, "backward", zr, zf, bdom),
                                      ("forward transmit", 0, "forward", zf, zr, fdom)):
        ps = data.PathSampler(lens, pid, d, zi, zo, dom)
        t0 = time.perf_counter()
        b = ps.build_bounds(rng)
        t_bounds = time.perf_counter() - t0
        for bounded, label in ((False, " (plain)"), (True, "")):
            ps.random_valid(1 << 22, 1, bounds=bounded)                      # compile
            t0, got, rays = time.perf_counter(), 0, 0
            while time.perf_counter() - t0 < seconds:
                u, _ = ps.random_valid(1 << 22, int(rng.integers(1 << 40)), bounds=bounded)
                got += len(u)
                rays += 1 << 22
            dt = time.perf_counter() - t0
            rows[name + label] = {
                "method": "rejection inside pilot bounds (Dr.Jit PCG32 + compaction)" if bounded
                else "rejection over the whole reduced domain (Dr.Jit PCG32 + compaction)",
                "valid_per_s": got / dt, "rays_per_s": rays / dt, "acceptance": got / rays}
            if bounded:
                rows[name + label].update(bounds_seconds=t_bounds, bounds_missed=b.missed,
                                          bounds_volume_fraction=b.volume_fraction(dom))
    # a rare ghost: the least-often-valid ghost that still reaches the film
    ranking = ghost_energy_ranking(lens)
    rare = [g for g in ranking if 0 < g["valid_fraction"] < 0.01 and g["energy"] > 0]
    g = min(rare, key=lambda g: g["valid_fraction"]) if rare else ranking[-1]
    ps = data.PathSampler(lens, g["path_id"], "forward", zf, zr, fdom)
    u, _, _, st = data.rejection_sample(ps, 1 << 30, rng, chunk=1 << 22, max_rays=1 << 25)
    rej = st["valid_per_s"]
    m = data.MCMCSampler(ps, rng, n_chains=1 << 20, p_large=0.3, sigma=0.02, seed_rays=1 << 24)
    m.step()
    m.proposed = m.accepted = m.proposed_large = m.accepted_large = 0
    t0, got = time.perf_counter(), 0
    uu = []
    while time.perf_counter() - t0 < seconds:
        u, _ = m.step()
        got += len(u)
        uu.append(u[:4096])
    dt = time.perf_counter() - t0
    uu = np.concatenate(uu)
    distinct = len(np.unique(uu, axis=0)) / len(uu)
    rows["rare ghost"] = {"path_id": g["path_id"], "surfaces": g["surfaces"], "valid_fraction": st["acceptance"],
                          "rejection_valid_per_s": rej, "mcmc_valid_per_s": got / dt,
                          "mcmc_distinct_fraction": distinct, "mcmc_stats": m.stats(),
                          "speedup": (got / dt) / max(rej, 1e-9),
                          "speedup_distinct": (got / dt * distinct) / max(rej, 1e-9)}
    return rows


# ----------------------------------------------------------------------------- training speed
def bench_training_speed(batch=8192, steps=150):
    import torch
    from mi_neurallens.training.nets import make_net
    torch.set_num_threads(2)
    out = {}
    for kind, hidden, n_out in (("regressor 5x32", 5, 5), ("classifier 2x32", 2, 1)):
        net = make_net(torch, 4, n_out, hidden, 32, "tanh")
        opt = torch.optim.Adam(net.parameters(), 1e-3)
        X, Y = torch.randn(1 << 20, 4), torch.randn(1 << 20, n_out)
        for i in range(steps + 20):
            if i == 20:
                t0 = time.perf_counter()
            bi = torch.randint(0, len(X), (batch,))
            loss = ((net(X[bi]) - Y[bi]) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        dt = time.perf_counter() - t0
        out[kind] = {"batch": batch, "steps_per_s": steps / dt, "samples_per_s": steps * batch / dt}
    return out


def time_to_goals():
    """From the shipped models' training histories: wall seconds until the regressor's validation met
    each goal (validation = 20k held-out rays during training)."""
    from mi_neurallens.neural import bundled_model_path, load_model
    out = {}
    for name in ("wide-22mm", "ood-59mm", "canon-ef-24mm-f1.4l"):
        p = bundled_model_path(name)
        if not os.path.exists(p):
            continue
        m = load_model(p)
        for key, tm in m.maps.items():
            if key != "backward.0":
                continue
            work = p + ".work"
            hist = tm.training.get("regressor_history") or []
            jp = os.path.join(work, f"{key}.regressor.ckpt.json")
            if not hist and os.path.exists(jp):
                hist = json.load(open(jp)).get("history", [])
            first = {}
            for goal, hkey in (("position_um_median", "pos_um_med"), ("position_um_p99", "pos_um_p99"),
                               ("direction_arcsec_median", "dir_as_med"), ("direction_arcsec_p99", "dir_as_p99"),
                               ("throughput_rel_median", "T_rel_med")):
                hit = [h["seconds"] for h in hist if h[hkey] <= GOALS[goal]]
                first[goal] = min(hit) if hit else None
            out[f"{name} {key}"] = {"regressor_seconds": tm.training.get("regressor_seconds"),
                                    "classifier_seconds": tm.training.get("classifier_seconds"),
                                    "first_seconds_meeting_goal": first,
                                    "all_regressor_goals_met_at_end": all(
                                        tm.metrics["regressor"][g] <= GOALS[g] for g in first),
                                    "final": {g: tm.metrics["regressor"][g] for g in first} |
                                             {"misclassification": tm.metrics["classifier"]["misclassification"]}}
    return out


def train_log_peak_rss():
    out = {}
    for name in ("wide-22mm", "ood-59mm", "canon-ef-24mm-f1.4l"):
        p = os.path.join(ROOT, "training", "logs", f"{name}.train.log")
        if os.path.exists(p):
            for line in open(p, errors="replace"):
                if "Maximum resident set size" in line:
                    out[name] = int(line.split(":")[1]) / 1024.0
                if "Elapsed (wall clock)" in line:
                    out[name + " wall"] = line.split("):", 1)[1].strip() if "):" in line else line.strip()
                if "User time" in line:
                    out[name + " user_s"] = float(line.split(":")[1])
    return out


# ----------------------------------------------------------------------------- ablations
def _budget_regressor(stream, val, heading, center, scale, seconds, s_max=None, **over):
    from mi_neurallens.training.config import NetConfig, PAPER
    from mi_neurallens.training.regressor import train_regressor
    d = dict(max_minutes=seconds / 60.0, max_steps=10 ** 7, eval_every=100, patience=10 ** 6, pool=500_000)
    if STEPS:
        d.update(max_minutes=1e9, max_steps=STEPS)
    if over.get("schedule") == "paper":
        d.update(PAPER)
    d.update(over)
    nc = NetConfig(**d)
    res = train_regressor(stream, val, nc, heading=heading, center=center, scale_in=scale, seed=7, ckpt=None,
                          progress=False, s_max=s_max)
    res["s_max"] = s_max
    return res, nc


def _eval_reduced(res, x, center, scale, activation="tanh"):
    from mi_neurallens.neural.mlp import mlp_np
    from mi_neurallens.training.outputs import odd_factor
    xn = (x - center) / scale
    M = odd_factor(x[:, 2], res["s_max"] if res.get("odd_y") else None)
    return M * (mlp_np(xn, res["layers"], activation) * res["out_scale"] + res["out_shift"] + xn @ res["skip"].T)


def ablations(lens, zf, zr, seconds=75.0, figdir=None):
    out = {}
    rng = np.random.default_rng(1)
    fdom = plan.forward_domain(lens, zf, plan.default_field_half_angle(lens))
    bdom = plan.backward_domain(lens, 0, zr, zf, rng, n=1 << 20)
    # --- tanh vs ReLU on the brightest ghost (a flare), same budget
    ranking = ghost_energy_ranking(lens)
    gid = ranking[0]["path_id"]
    ps = data.PathSampler(lens, gid, "forward", zf, zr, fdom)
    stream = data.RegressorStream(ps, 3)
    c, s = fdom.norm_center_scale()
    from mi_neurallens.training.evaluate import heldout_valid
    val = heldout_valid(lens, (gid, "forward", zf, zr), fdom, 20000, 5)
    res = {}
    for act in ("tanh", "relu"):
        r, _ = _budget_regressor(stream, val, 1, c, s, seconds, s_max=fdom.s_max, activation=act)
        test = heldout_valid(lens, (gid, "forward", zf, zr), fdom, 100000, 6)
        e = regression_errors(_eval_reduced(r, test[0], c, s, act), test[1], 1)
        res[act] = r
        out[f"ghost {gid} {act}"] = {k: e[k] for k in ("position_um_median", "position_um_p99",
                                                       "direction_arcsec_median", "direction_arcsec_p99",
                                                       "throughput_rel_median")} | {"steps": r["state"]["step"]}
    if figdir:
        flare_figure(lens, gid, zf, zr, fdom, res, c, s, os.path.join(figdir, "tanh-vs-relu-ghost.png"))
    # --- symmetry reduction vs full 5-D inputs, backward transmit, same budget
    out.update(symmetry_ablation(lens, zf, zr, bdom, seconds))
    # --- paper schedule vs ours (backward transmit), same budget
    ps = data.PathSampler(lens, 0, "backward", zr, zf, bdom)
    stream = data.RegressorStream(ps, 4)
    c, s = bdom.norm_center_scale()
    val = heldout_valid(lens, (0, "backward", zr, zf), bdom, 20000, 8)
    test = heldout_valid(lens, (0, "backward", zr, zf), bdom, 100000, 9)
    for name, over in (("fast (default)", {}), ("paper schedule", {"schedule": "paper"}),
                       ("fast, no linear residual", {"residual": "none"})):
        r, _ = _budget_regressor(stream, val, -1, c, s, seconds, s_max=bdom.s_max, **over)
        e = regression_errors(_eval_reduced(r, test[0], c, s), test[1], -1)
        out[f"backward transmit, {name}"] = {k: e[k] for k in ("position_um_median", "position_um_p99",
                                                               "direction_arcsec_median", "direction_arcsec_p99",
                                                               "throughput_rel_median")} | {"steps": r["state"]["step"]}
    out["budget_seconds_each"] = None if STEPS else seconds
    out["budget_steps_each"] = STEPS or None
    return out


def symmetry_ablation(lens, zf, zr, dom, seconds):
    """Same network, data budget and time: reduced inputs (r, ωx, ωy, λ) vs full (x, y, dx, dy, λ)."""
    import torch
    from mi_neurallens.trace import symmetry
    from mi_neurallens.training.nets import make_net
    from mi_neurallens.training.outputs import fit_output_transform
    torch.set_num_threads(2)
    rng = np.random.default_rng(11)

    def full_rays(n):
        """Uniform over the position disk (area) × direction disk, CIE λ: returns full inputs + outputs."""
        xs, ys = [], []
        got = 0
        while got < n:
            m = 1 << 21
            r = dom.r_max * np.sqrt(rng.random(m))
            a = 2 * np.pi * rng.random(m)
            rho = dom.s_max * np.sqrt(rng.random(m))
            b = 2 * np.pi * rng.random(m)
            lam, _ = data.sample_cie_wavelength(rng.random(m))
            x = np.stack([r * np.cos(a), r * np.sin(a), rho * np.cos(b), rho * np.sin(b), lam], 1)
            o = np.stack([x[:, 0], x[:, 1], np.full(m, zr)], 1)
            d = np.stack([x[:, 2], x[:, 3], -np.sqrt(1 - rho ** 2)], 1)
            rb = lens.trace(o, d, lam, direction="backward", z_out=zf)
            v = rb.valid
            xs.append(x[v])
            ys.append(np.concatenate([rb.position[v, :2], rb.direction[v, :2], rb.throughput[v, None]], 1))
            got += int(v.sum())
        return np.concatenate(xs)[:n], np.concatenate(ys)[:n]

    Xf, Yf = full_rays(1_000_000)
    Xt, Yt = full_rays(100_000)
    out = {}
    for mode in ("reduced", "full"):
        if mode == "reduced":
            def feats(X):
                (r, wx, wy), fr = symmetry.reduce(X[:, 0], X[:, 1], X[:, 2], X[:, 3])
                c, s = dom.norm_center_scale()
                return (np.stack([r, wx, wy, X[:, 4]], 1) - c) / s, fr

            def targets(X, Y):
                _, fr = symmetry.reduce(X[:, 0], X[:, 1], X[:, 2], X[:, 3])
                c_, s_, g = fr
                # inverse of undo: rotate by −φ then reflect
                x = c_ * Y[:, 0] + s_ * Y[:, 1]
                y = (-s_ * Y[:, 0] + c_ * Y[:, 1]) * g
                dx = c_ * Y[:, 2] + s_ * Y[:, 3]
                dy = (-s_ * Y[:, 2] + c_ * Y[:, 3]) * g
                return np.stack([x, y, dx, dy, Y[:, 4]], 1)
        else:
            def feats(X):
                c = np.array([0, 0, 0, 0, 595.0])
                s = np.array([dom.r_max, dom.r_max, dom.s_max, dom.s_max, 235.0])
                return (X - c) / s, None

            def targets(X, Y):
                return Y
        xn, _ = feats(Xf)
        T = targets(Xf, Yf)
        skip, shift, sc = fit_output_transform(xn, T, "linear")
        net = make_net(torch, xn.shape[1], 5, 5, 32, "tanh")
        opt = torch.optim.Adam(net.parameters(), 3e-3)
        Xt_ = torch.as_tensor(xn, dtype=torch.float32)
        Yt_ = torch.as_tensor((T - shift - xn @ skip.T) / sc, dtype=torch.float32)
        t0, step = time.perf_counter(), 0
        while (step < STEPS) if STEPS else (time.perf_counter() - t0 < seconds):
            frac = step / STEPS if STEPS else (time.perf_counter() - t0) / seconds
            for g in opt.param_groups:
                g["lr"] = 1e-6 + 0.5 * (3e-3 - 1e-6) * (1 + np.cos(np.pi * min(frac, 1)))
            bi = torch.randint(0, len(Xt_), (8192,))
            loss = ((net(Xt_[bi]) - Yt_[bi]) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            step += 1
        xq, fr = feats(Xt)
        with torch.no_grad():
            p = net(torch.as_tensor(xq, dtype=torch.float32)).double().numpy() * sc + shift + xq @ skip.T
        if mode == "reduced":
            X, Y, DX, DY = symmetry.undo(p[:, 0], p[:, 1], p[:, 2], p[:, 3], fr)
            p = np.stack([X, Y, DX, DY, p[:, 4]], 1)
        e = regression_errors(p, Yt, -1)
        out[f"backward transmit, symmetry {mode}"] = {k: e[k] for k in (
            "position_um_median", "position_um_p99", "direction_arcsec_median", "direction_arcsec_p99",
            "throughput_rel_median")} | {"steps": step, "inputs": int(xn.shape[1])}
    return out


def flare_figure(lens, gid, zf, zr, dom, res, c, s, path, field_deg=12.0, n=1 << 21):
    """A flare-like picture of one ghost: a point light at ``field_deg``; rays uniform over the front plane;
    exact validity (so only the regressors differ); splat at the sensor plane."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mi_neurallens.trace import symmetry
    rng = np.random.default_rng(2)
    r = dom.r_max * np.sqrt(rng.random(n))
    a = 2 * np.pi * rng.random(n)
    th = np.radians(field_deg)
    o = np.stack([r * np.cos(a), r * np.sin(a), np.full(n, zf)], 1)
    d = np.tile([np.sin(th), 0.0, np.cos(th)], (n, 1))
    zs = lens.total_track + lens.surfaces[-1].thickness
    ex = lens.trace(o, d, 550.0, direction="forward", path=gid, z_out=zr)
    v = ex.valid
    (rr, wx, wy), fr = symmetry.reduce(o[v, 0], o[v, 1], d[v, 0], d[v, 1])
    x = np.stack([rr, wx, wy, np.full(len(rr), 550.0)], 1)
    imgs = {"exact tracer": None}

    def splat(pos, dirn, T):
        t = (zs - zr) / dirn[:, 2]
        X, Y = pos[:, 0] + t * dirn[:, 0], pos[:, 1] + t * dirn[:, 1]
        return X, Y, T

    imgs["exact tracer"] = splat(ex.position[v], ex.direction[v], ex.throughput[v])
    for act in ("tanh", "relu"):
        y = _eval_reduced(res[act], x, c, s, act)
        X, Y, DX, DY = symmetry.undo(y[:, 0], y[:, 1], y[:, 2], y[:, 3], fr)
        dz = np.sqrt(np.maximum(1 - DX ** 2 - DY ** 2, 0))
        imgs[f"{act} MLP"] = splat(np.stack([X, Y], 1), np.stack([DX, DY, dz], 1), y[:, 4])
    X0, Y0, _ = imgs["exact tracer"]
    cx, cy = np.median(X0), np.median(Y0)
    half = max(np.percentile(np.abs(X0 - cx), 99.5), np.percentile(np.abs(Y0 - cy), 99.5)) * 1.15
    fig, ax = plt.subplots(1, 3, figsize=(12, 4.2))
    for k, (name, (X, Y, T)) in enumerate(imgs.items()):
        h, _, _ = np.histogram2d(Y, X, 320, [[cy - half, cy + half], [cx - half, cx + half]], weights=T)
        ax[k].imshow(h ** 0.5, cmap="inferno", origin="lower", extent=[cx - half, cx + half, cy - half, cy + half])
        ax[k].set_title(name)
        ax[k].set_xlabel("sensor x (mm)")
    fig.suptitle(f"{lens.name}: ghost {gid}, point light at {field_deg}°, same training budget")
    fig.tight_layout()
    os.makedirs(os.path.dirname(path), exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--ablations", action="store_true")
    ap.add_argument("--ablation-seconds", type=float, default=75.0)
    ap.add_argument("--ablation-steps", type=int, default=0,
                    help="give every ablation variant this many steps (fair on a shared machine) instead of seconds")
    ap.add_argument("--only-ablations", action="store_true",
                    help="run only the ablations and update them in an existing JSON")
    ap.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "bench_training.json"))
    args = ap.parse_args()
    global STEPS
    STEPS = args.ablation_steps
    import drjit as dr
    lens = Lens.load(LENS)
    zf, zr = setup(lens)
    t0 = time.perf_counter()
    res = {"info": {"machine": f"{platform.machine()}, {os.cpu_count()} cores", "drjit_threads": dr.thread_count(),
                    "lens": LENS, "python": platform.python_version(),
                    "load_average_at_start": os.getloadavg()[0]}}
    if args.only_ablations:
        abl = ablations(lens, zf, zr, args.ablation_seconds, os.path.join(ROOT, "docs", "training"))
        res = json.load(open(args.out)) if os.path.exists(args.out) else res   # read last: keep others' updates
        res["ablations"] = abl
        res["ablations_peak_rss_mb"] = peak_rss_mb()
        atomic_write_json(args.out, res, indent=1)
        for k, v in res["ablations"].items():
            print(k, v)
        return
    res["generation"] = bench_generation(lens, zf, zr)
    res["training_speed"] = bench_training_speed()
    res["time_to_goals"] = time_to_goals()
    res["training_runs"] = train_log_peak_rss()
    if args.ablations:
        res["ablations"] = ablations(lens, zf, zr, args.ablation_seconds, os.path.join(ROOT, "docs", "training"))
    elif os.path.exists(args.out):                      # keep the ablations of an earlier run
        old = json.load(open(args.out))
        for k in ("ablations", "ablations_peak_rss_mb"):
            if k in old:
                res[k] = old[k]
    res["peak_rss_mb_this_process"] = peak_rss_mb()
    res["seconds"] = time.perf_counter() - t0
    atomic_write_json(args.out, res, indent=1)
    g = res["generation"]
    print(f"\n{'measure':<46} {'value':>14}")
    for k in ("backward transmit (plain)", "backward transmit", "forward transmit (plain)", "forward transmit"):
        print(f"{'valid samples/s, ' + k:<46} {g[k]['valid_per_s'] / 1e6:>12.2f} M  (acceptance {g[k]['acceptance']:.3f})")
    rg = g["rare ghost"]
    print(f"{'rare ghost ' + str(rg['path_id']) + ' valid fraction':<46} {rg['valid_fraction']:>14.5f}")
    print(f"{'  rejection valid samples/s':<46} {rg['rejection_valid_per_s'] / 1e6:>12.3f} M")
    print(f"{'  MCMC valid samples/s (acceptance)':<46} {rg['mcmc_valid_per_s'] / 1e6:>12.3f} M  "
          f"({rg['mcmc_stats']['acceptance']:.3f})")
    print(f"{'  MCMC speed-up (all / distinct samples)':<46} {rg['speedup']:>10.1f}x / {rg['speedup_distinct']:.1f}x")
    for k, v in res["training_speed"].items():
        print(f"{'training samples/s, ' + k:<46} {v['samples_per_s'] / 1e6:>12.3f} M")
    for k, v in res["time_to_goals"].items():
        print(f"{'time to goals ' + k:<46} {json.dumps(v['first_seconds_meeting_goal'])}")
    for k, v in res["training_runs"].items():
        print(f"{'training run ' + k:<46} {v}")
    for k, v in res.get("ablations", {}).items():
        if isinstance(v, dict):
            print(f"{'ablation ' + k:<46} pos {v['position_um_median']:.3g}/{v['position_um_p99']:.3g} µm, "
                  f"dir {v['direction_arcsec_median']:.3g}/{v['direction_arcsec_p99']:.3g}\", "
                  f"T {100 * v['throughput_rel_median']:.3g}%  ({v['steps']} steps)")
    print(f"{'peak RSS this process (MB)':<46} {res['peak_rss_mb_this_process']:>14.0f}")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
