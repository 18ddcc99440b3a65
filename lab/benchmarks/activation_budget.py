"""The accuracy budget of the activation (issue 18): how much cheaper tanh approximations, used at render
time in place of the 13/6 rational tanh the maps were trained with, change the maps' outputs, and what
they save.

    python lab/benchmarks/activation_budget.py [--maps wide-22mm:0,wide-22mm:2560,...] [--rays 20]

Per map (``LENS:PATH``, path 0 = the camera map, backward; another id = that ghost's forward map): rays
drawn uniformly over the map's reduced domain (as ``bench_mlp.py``), the float64 exact-tanh outputs as
the reference (``NeuralMap.eval_reduced_np``), and each candidate in float32 in the fused Dr.Jit kernel:
exit-position and direction deviations on the rays the reference calls valid (µm, arcsec: median, p99,
max), the fraction of rays whose validity flips, and the classifier + regressor rate (M rays/s, best of
``--repeats``, same run).  The candidates are odd Padé approximants of tanh with the input clamped where
they reach 1, and two minimax rationals of the same form (:func:`fit_minimax`, issue 55: on an AVX-512 Zen 5 the
activation is about half the cost of the EF 24-70's map: an identity activation evaluated it 1.8x as fast),
against Eigen's 13/6 rational (the training activation).  A map of a lens with moving groups is measured at its
first zoom position focused at infinity, as ``bench_mlp.py`` measures it.

    python lab/benchmarks/activation_budget.py --maps wide-22mm:0,canon-ef-24mm-f1.4l:0,wide-22mm:2560 --repeats 10

Prints a markdown table and writes ``out/lab/activation_budget.json``.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from mi_neurallens.constants import ARCSEC_PER_RAD  # noqa: E402
from mi_neurallens.fileio import atomic_write_json  # noqa: E402
from mi_neurallens.render_utils import default_variant  # noqa: E402

#: odd Padé approximants of tanh: x·N(x²)/D(x²), coefficients in ascending powers of x²; then minimax rationals
#: of the same form (``fit_minimax(4, 4, 7.0)``, ``fit_minimax(5, 4, 8.0)``) with the clamp they were fitted for:
#: 6 and 7 multiply-adds against Eigen's 9, max error 9e-7 and 4e-7 (float32) against its 2.6e-7
PADE = {
    "pade 7/6": ((135135.0, 17325.0, 378.0, 1.0), (135135.0, 62370.0, 3150.0, 28.0)),
    "pade 5/4": ((945.0, 105.0, 1.0), (945.0, 420.0, 15.0)),
    "pade 3/2": ((15.0, 1.0), (15.0, 6.0)),
    "minimax 7/6": ((0.9999956876832581, 0.12302166530294488, 0.0022769744824863852, 3.929948006950457e-06),
                    (1.0, 0.45634014989381044, 0.021072111668128765, 0.00014234931101998402), 7.0),
    "minimax 9/6": ((0.9999990649921883, 0.1269977626271506, 0.0026844895826633832, 7.083406587349902e-06,
                     -6.01991512194644e-09),
                    (1.0, 0.4603276898015696, 0.02279736659263781, 0.00019529834569501504), 8.0),
}


def fit_minimax(n_num: int, n_den: int, clamp: float, iters: int = 400):
    """A minimax fit of tanh(x) ≈ x·N(x²)/D(x²) on [0, clamp] (``n_num``, ``n_den`` coefficients, D's first 1):
    Loeb's linearised least squares (the last D as weight), with Lawson's weights moving toward the largest
    errors.  Returns (max error, N, D) of the best iterate."""
    x = np.unique(np.concatenate([np.linspace(0, clamp, 20000),
                                  clamp * (1 - np.cos(np.linspace(0, np.pi / 2, 20000)))]))
    t, u = np.tanh(x), x * x
    A = np.concatenate([np.stack([x * u ** k for k in range(n_num)], 1),
                        np.stack([-t * u ** k for k in range(1, n_den)], 1)], 1)
    w, q_prev, best = np.ones_like(x) / len(x), np.ones_like(x), None
    for _ in range(iters):
        W = np.sqrt(w) / q_prev
        sol = np.linalg.lstsq(A * W[:, None], t * W, rcond=None)[0]
        num, den = sol[:n_num], np.concatenate([[1.0], sol[n_num:]])
        q = _poly(den, u)
        err = x * _poly(num, u) / q - t
        if best is None or np.max(np.abs(err)) < best[0]:
            best = (float(np.max(np.abs(err))), num.tolist(), den.tolist())
        q_prev, w = np.abs(q), w * np.abs(err)
        w /= w.sum()
    return best


def _poly(c, t):
    p = c[-1]
    for a in reversed(c[:-1]):
        p = p * t + a
    return p


def clamp_point(num, den):
    """Where x·N(x²)/D(x²) first reaches 1 (it then grows without bound): clamping the input there keeps it
    continuous and monotone, with a small slope step (render time needs no gradient)."""
    x = np.linspace(1e-3, 20.0, 400_001)
    f = x * _poly(num, x * x) / _poly(den, x * x)
    i = int(np.argmax(f >= 1.0)) if np.any(f >= 1.0) else int(np.argmax(f))
    return float(x[i]), float(f[i])


def max_error(fn_np):
    x = np.linspace(0.0, 12.0, 200_001)
    return float(np.max(np.abs(fn_np(x) - np.tanh(x))))


def make_pade(num, den, xc=None):
    """(Dr.Jit activation, numpy twin, clamp point) of the clamped Padé approximant (clamped at ``xc`` where given)."""
    if xc is None:
        xc, _ = clamp_point(num, den)

    def act_dr(v):
        import drjit as dr
        if dr.type_v(v) == dr.VarType.Float64:
            return dr.tanh(v)
        v = dr.clip(v, -xc, xc)
        t = v * v
        n = dr.fma(t, num[-1], num[-2])
        for a in reversed(num[:-2]):
            n = dr.fma(t, n, a)
        d = dr.fma(t, den[-1], den[-2])
        for a in reversed(den[:-2]):
            d = dr.fma(t, d, a)
        return v * n / d

    def act_np(x):
        x = np.clip(x, -xc, xc)
        return x * _poly(num, x * x) / _poly(den, x * x)
    return act_dr, act_np, xc


def sample_inputs(tm, n, seed):
    d = tm.domain.to_dict()
    rng = np.random.default_rng(seed)
    return np.stack([rng.uniform(0, d["r_max_mm"], n), rng.uniform(-d["s_max"], d["s_max"], n) * 0.7,
                     rng.uniform(0, d["s_max"], n) * 0.7,
                     rng.uniform(d["lambda_min_nm"], d["lambda_max_nm"], n)], 1)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--maps", default="wide-22mm:0,canon-rf-24mm-f1.4l-vcm:0,wide-22mm:2560,ood-59mm:10240")
    ap.add_argument("--rays", type=int, default=20, help="log2 rays per map")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(ROOT), "out", "lab", "activation_budget.json"))
    a = ap.parse_args(argv)
    import drjit as dr
    import mitsuba as mi
    mi.set_variant(default_variant())
    import mi_neurallens.neural.mlp as mlp
    from mi_neurallens import Lens
    from mi_neurallens.neural.model import bundled_model_path, load_model

    cands = {"eigen 13/6 (trained)": (mlp.tanh_eigen, None, mlp.TANH_CLAMP)}
    for name, spec in PADE.items():
        cands[name] = make_pade(*spec)
    errs = {"eigen 13/6 (trained)": max_error(lambda x: mlp.tanh_eigen(x))}
    errs.update({k: max_error(v[1]) for k, v in cands.items() if v[1] is not None})
    trained = mlp._tanh
    rows = []
    n = 1 << a.rays
    for spec in a.maps.split(","):
        lens_name, pid = spec.split(":")
        pid = int(pid)
        lens = Lens.load(lens_name)
        model = load_model(bundled_model_path(lens_name), lens)
        tm = model.map("transmit" if pid == 0 else pid, "backward" if pid == 0 else "forward")
        cond = getattr(tm.domain, "conditions", None)
        if cond is not None:    # moving groups: configured as bench_mlp.py does (the first position, infinity)
            import math
            from mi_neurallens.optics import moving as mv
            lens, t, f = mv.configure(lens, None, math.inf)
            tm = cond.configure_map(tm, lens.image_z, t, f)
        tm.stop_head = None                                # the camera path at the trained aperture
        x = sample_inputs(tm, n, seed=pid + 7)
        logit_ref, y_ref = tm.eval_reduced_np(x)
        valid = logit_ref > 0
        X = [mi.Float(x[:, i].astype(np.float32)) for i in range(4)]
        dr.eval(X)
        for name, (act, _, xc) in cands.items():
            # the activation mlp_dr applies (restored below); a candidate replaces it in either style
            mlp._tanh = lambda x, style=None, f=act: f(x)
            try:
                def run():
                    logit, y = tm.eval_reduced_dr(X, mlp="fused")
                    out = [logit] + list(y)
                    dr.eval(out)
                    dr.sync_thread()
                    return out
                t0 = time.perf_counter()
                out = run()
                first = time.perf_counter() - t0
                best = float("inf")
                for _ in range(a.repeats):
                    t0 = time.perf_counter()
                    run()
                    best = min(best, time.perf_counter() - t0)
            finally:
                mlp._tanh = trained
            o = np.stack([v.numpy() for v in out], 1).astype(np.float64)
            dpos = 1e3 * np.hypot(o[valid, 1] - y_ref[valid, 0], o[valid, 2] - y_ref[valid, 1])
            ddir = ARCSEC_PER_RAD * np.hypot(o[valid, 3] - y_ref[valid, 2], o[valid, 4] - y_ref[valid, 3])
            row = {"map": spec, "activation": name, "clamp": xc, "max_abs_error_vs_tanh": errs[name],
                   "pos_um": [float(np.median(dpos)), float(np.percentile(dpos, 99)), float(dpos.max())],
                   "dir_arcsec": [float(np.median(ddir)), float(np.percentile(ddir, 99)), float(ddir.max())],
                   "validity_flips": float(np.mean((o[:, 0] > 0) != valid)),
                   "mrays_per_s": n / best / 1e6, "first_call_s": first,
                   "map_error": tm.metrics.get("held_out", tm.metrics)}
            rows.append(row)
            print(f"{spec:28s} {name:22s} pos {row['pos_um'][0]:.3g}/{row['pos_um'][1]:.3g}/{row['pos_um'][2]:.3g} µm "
                  f"dir {row['dir_arcsec'][0]:.3g}/{row['dir_arcsec'][1]:.3g} ″ flips {row['validity_flips']:.2e} "
                  f"{row['mrays_per_s']:.2f} M rays/s", flush=True)
    print(f"\n2^{a.rays} rays per map, {default_variant()}, {dr.thread_count()} threads; deviation from the float64 "
          "exact-tanh outputs on valid rays")
    print("| map | activation | max \\|error\\| vs tanh | pos µm med / p99 / max | dir ″ med / p99 | validity flips | M rays/s |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['map']} | {r['activation']} | {r['max_abs_error_vs_tanh']:.1e} | "
              f"{r['pos_um'][0]:.3g} / {r['pos_um'][1]:.3g} / {r['pos_um'][2]:.3g} | "
              f"{r['dir_arcsec'][0]:.3g} / {r['dir_arcsec'][1]:.3g} | {r['validity_flips']:.1e} | {r['mrays_per_s']:.2f} |")
    atomic_write_json(a.out, {"benchmark": "activation_budget", "rays": n, "variant": default_variant(),
                              "threads": dr.thread_count(), "machine": platform.processor() or platform.machine(),
                              "command": "python benchmarks/activation_budget.py " + " ".join(argv or sys.argv[1:]),
                              "rows": rows}, indent=2)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
