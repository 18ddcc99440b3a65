"""Standalone evaluation speed of a learned lens map: classifier + regressor on 2^k rays, fused with
literal weights (the default, in the backend's evaluation style and in the other one: neural/mlp.py
``MLP_STYLES``) vs Dr.Jit cooperative vectors (``drjit.nn``), beside the exact tracer on the same rays, in
one run; each neural path's outputs against the CPU style's, and the default's against the float64
reference with the exact tanh (what the float32 kernel and its tanh approximation add to the map's own
error).  Also the kernel compile time of each (cold,
in-process).  A lens with moving groups: its first position, focused at infinity (the map's folded configuration).

    python benchmarks/bench_mlp.py [--lens wide-22mm] [--model FILE] [--rays 22] [--repeats 5]

Prints a markdown table and writes out/bench/bench_mlp.json.  The bar (issue 5):
>= 10 M rays/s for classifier + regressor on this 2-core CPU.
"""
from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np

from mi_neurallens.fileio import atomic_write_json
from mi_neurallens.render_utils import default_variant

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lens", default="wide-22mm")
    ap.add_argument("--model", help="model file (default: the bundled model of --lens)")
    ap.add_argument("--without-stop-head", action="store_true",
                    help="leave the stop head out (the sensor at the trained aperture does not evaluate it)")
    ap.add_argument("--rays", type=int, default=22)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=os.path.join("out", "bench", "bench_mlp.json"))
    a = ap.parse_args(argv)
    import drjit as dr
    import mitsuba as mi
    mi.set_variant(default_variant())
    from mi_neurallens import Lens
    from mi_neurallens.neural.mlp import forced_style, mlp_style
    from mi_neurallens.neural.model import bundled_model_path, load_model
    from mi_neurallens.trace.tracer import LensTracer

    lens = Lens.load(a.lens)
    model = load_model(a.model or bundled_model_path(a.lens), lens)
    tm = model.map("transmit", "backward")
    cond = getattr(tm.domain, "conditions", None)
    if cond is not None:        # moving groups: the map and the tracer at the first position, focused at infinity
        import math
        from mi_neurallens.optics import moving as mv
        lens, t, f = mv.configure(lens, None, math.inf)
        tm = cond.configure_map(tm, lens.image_z, t, f)
    if a.without_stop_head:
        tm.stop_head = None
    n = 1 << a.rays
    rng = np.random.default_rng(0)
    d = tm.domain if isinstance(tm.domain, dict) else tm.domain.to_dict()   # a Domain since the transport spine
    x_np = [rng.uniform(0, d["r_max_mm"], n), rng.uniform(-d["s_max"], d["s_max"], n) * 0.7,
            rng.uniform(0, d["s_max"], n) * 0.7, rng.uniform(d["lambda_min_nm"], d["lambda_max_nm"], n)]
    X = [mi.Float(v.astype(np.float32)) for v in x_np]
    dr.eval(X)

    def fused():
        logit, y = tm.eval_reduced_dr(X, mlp="fused")
        return [logit] + list(y)

    def styled(style):          # the fused literals in one evaluation style (neural/mlp.py MLP_STYLES)
        def fn():
            with forced_style(style):
                return fused()
        return fn

    def coop():
        logit, y = tm.eval_reduced_dr(X, mlp="coopvec")
        return [logit] + list(y)

    # the exact tracer on rays from the same sensor-side plane (backward transmit)
    tr = LensTracer(lens)
    zi = float(lens.image_z)
    ox, oy = mi.Float(x_np[0].astype(np.float32)), mi.Float(np.zeros(n, np.float32))
    dxn, dyn = mi.Float(x_np[1].astype(np.float32)), mi.Float(x_np[2].astype(np.float32))
    dzn = -dr.sqrt(dr.maximum(1.0 - dxn * dxn - dyn * dyn, 0.0))
    lam = X[3]
    dr.eval(ox, oy, dxn, dyn, dzn)

    def exact():
        r = tr.trace((ox, oy, ox * 0 + zi), (dxn, dyn, dzn), lam, "transmit", "backward")
        return [*r.position, *r.direction, r.throughput, r.valid]

    default_style = mlp_style(X[0])
    other = "gpu" if default_style == "cpu" else "cpu"
    FUSED, OTHER, COOP = ("neural, fused literals (default)", f"neural, fused literals, {other} style",
                          "neural, cooperative vectors")
    runs = {"exact tracer": exact, FUSED: styled(default_style), OTHER: styled(other), COOP: coop}
    rows = {}
    for name, fn in runs.items():
        t0 = time.perf_counter()
        out = fn()
        dr.eval(out)
        dr.sync_thread()
        first = time.perf_counter() - t0
        best = float("inf")
        for _ in range(a.repeats):
            t0 = time.perf_counter()
            out = fn()
            dr.eval(out)
            dr.sync_thread()
            best = min(best, time.perf_counter() - t0)
        rows[name] = {"mrays_per_s": n / best / 1e6, "first_call_s": first, "best_s": best}
    # agreement of the neural paths with the fused literals in the CPU style (the minimax rational tanh, within
    # 1.2e-6 of tanh), per output, on the rays the reference classifier passes (logit: all rays); outputs in the
    # map's units (positions mm, direction cosines, throughput): fp16 on CUDA is where they part
    from mi_neurallens.neural.model import OUTPUTS
    ref = np.stack([v.numpy() for v in styled("cpu")()], 1)
    names = ["logit"] + list(OUTPUTS) + [f"stop{i}" for i in range(ref.shape[1] - 1 - len(OUTPUTS))]
    ok = ref[:, 0] > 0
    for name in (FUSED, OTHER, COOP):
        f = np.stack([v.numpy() for v in runs[name]()], 1)
        per = {}
        for i, nm in enumerate(names):
            d = np.abs(f[slice(None) if i == 0 else ok, i] - ref[slice(None) if i == 0 else ok, i])
            per[nm] = {"max": float(d.max()) if d.size else 0.0,
                       "p99": float(np.percentile(d, 99)) if d.size else 0.0}
        rows[name]["max_abs_diff_vs_cpu_style"] = float(np.abs(f - ref).max())
        rows[name]["diff_vs_cpu_style_per_output"] = per
        rows[name]["validity_flips"] = float(np.mean((f[:, 0] > 0) != ok))
    # what the float32 kernel adds to the map's own error: the default style's outputs (its tanh approximation,
    # float32 arithmetic) against the float64 reference with the exact tanh, on the first 2^18 rays
    from mi_neurallens.constants import ARCSEC_PER_RAD
    m = min(n, 1 << 18)
    logit_ref, y_ref = tm.eval_reduced_np(np.stack([v.numpy()[:m].astype(np.float64) for v in X], 1))
    out = runs[FUSED]()
    dr.eval(out)                # one kernel for all outputs, then each read back
    f = np.stack([v.numpy()[:m] for v in out], 1).astype(np.float64)
    passing = logit_ref > 0
    dpos = 1e3 * np.hypot(f[passing, 1] - y_ref[passing, 0], f[passing, 2] - y_ref[passing, 1])
    ddir = ARCSEC_PER_RAD * np.hypot(f[passing, 3] - y_ref[passing, 2], f[passing, 4] - y_ref[passing, 3])
    vs64 = {"rays": m, "validity_flips": float(np.mean((f[:, 0] > 0) != passing))}
    for key, d in (("position_um", dpos), ("direction_arcsec", ddir)):
        vs64[key] = {"median": float(np.median(d)), "p99": float(np.percentile(d, 99)), "max": float(d.max())}
    rows[FUSED]["vs_float64_exact_tanh"] = vs64
    widths = [[np.shape(W)[0] for W, _ in net][:-1] for net in (tm.classifier, tm.regressor)]
    print(f"{a.lens}, backward transmit map (classifier {widths[0]}, regressor {widths[1]}, tanh"
          f"{', stop head' if tm.stop_head is not None else ''}), 2^{a.rays} rays, "
          f"{dr.thread_count()} threads, best of {a.repeats}")
    print("| evaluation | Mrays/s | first call incl. compile (s) |")
    print("|---|---|---|")
    for k, r in rows.items():
        print(f"| {k} | {r['mrays_per_s']:.1f} | {r['first_call_s']:.2f} |")
    for name in (OTHER, COOP) if default_style == "cpu" else (FUSED, COOP):
        cv = rows[name]
        print(f"{name} vs the CPU style: max |diff| = {cv['max_abs_diff_vs_cpu_style']:.2e}; validity flips "
              f"{cv['validity_flips']:.2e}; per output max / p99 (passing rays): "
              + ", ".join(f"{k} {v['max']:.2e} / {v['p99']:.2e}"
                          for k, v in cv["diff_vs_cpu_style_per_output"].items()))
    print(f"{FUSED} vs float64 with the exact tanh ({m} rays): exit position µm median / max "
          f"{vs64['position_um']['median']:.2g} / {vs64['position_um']['max']:.2g}, direction ″ "
          f"{vs64['direction_arcsec']['median']:.2g} / {vs64['direction_arcsec']['max']:.2g}, validity flips "
          f"{vs64['validity_flips']:.1e}")
    res = {"lens": a.lens, "model": a.model or "bundled", "hidden_widths": widths, "rays": n,
           "variant": mi.variant(), "default_style": default_style,
           "threads": dr.thread_count(), "machine": platform.processor() or platform.machine(),
           "cpus": os.cpu_count(), "rows": rows}
    atomic_write_json(a.out, res, indent=2)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
