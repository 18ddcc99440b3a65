"""Equal wall time, not equal samples: the error a user gets from ``realistic_lens`` and ``neural_lens``
in the same render time, per lens (issue 18).

    python benchmarks/equal_time.py [--lenses wide-22mm,ood-59mm,...] [--scene still_life]
                                    [--res 320x240] [--spp 4,16,64,256] [--reference-spp 1024]

Per lens: a converged reference (``realistic_lens`` at ``--reference-spp``, its own seed), then each sensor
at every ``--spp`` (same seeds for both, warm kernels, best of ``--repeats`` wall times, the two sensors
interleaved so drifts of the machine's speed hit both) and the MAPE of each render against the reference
(``mi_neurallens.metrics.mape``, the ``compare`` command's).  Each sensor's MAPE is interpolated in
log–log over its render times at the times ``realistic_lens`` needed for each spp: "in the time the exact
tracer renders N spp, the neural map reaches MAPE x".  The neural MAPE includes the map's own bias (the
reference is exact), so it flattens where noise falls below that bias.

Prints a markdown table and writes ``out/bench/equal_time.json``.
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

from mi_neurallens.fileio import atomic_write_json  # noqa: E402
from mi_neurallens.render_utils import add_variant_argument  # noqa: E402

SENSORS = ("realistic_lens", "neural_lens")


def interp_loglog(t, ts, ys):
    """``y`` at time ``t`` from samples (``ts`` ascending, ``ys``) by log–log linear interpolation,
    extrapolated with the slope of the nearest segment (None for fewer than two samples)."""
    ts, ys = np.log(np.asarray(ts, float)), np.log(np.maximum(np.asarray(ys, float), 1e-12))
    if len(ts) < 2:
        return None
    i = int(np.clip(np.searchsorted(ts, np.log(t)) - 1, 0, len(ts) - 2))
    s = (ys[i + 1] - ys[i]) / max(ts[i + 1] - ts[i], 1e-12)
    return float(np.exp(ys[i] + s * (np.log(t) - ts[i])))


def measure_lens(mi, dr, lens, a):
    from mi_neurallens.commands.render import load_scene
    from mi_neurallens.metrics import mape
    from mi_neurallens.neural.model import bundled_model_path
    if not os.path.exists(bundled_model_path(lens)):
        print(f"{lens}: no bundled model, skipped")
        return None
    scenes = {s: load_scene(a.scene, variant=a.variant, lens=lens, resolution=a.res, sensor_type=s,
                            sets=[f"model={lens}"] if s == "neural_lens" else [])
              for s in SENSORS}
    t0 = time.perf_counter()
    ref = np.array(mi.render(scenes["realistic_lens"], spp=a.reference_spp, seed=10_000))
    t_ref = time.perf_counter() - t0
    rows = {s: [] for s in SENSORS}
    for spp in a.spp:
        for s in SENSORS:                                   # warm-up: compile this spp's kernels
            dr.eval(mi.render(scenes[s], spp=spp, seed=0))
        dr.sync_thread()     # launches are asynchronous (CUDA): the first timed render must not inherit them
        best = {s: float("inf") for s in SENSORS}
        imgs = {}
        for r in range(a.repeats):
            for s in SENSORS:
                t0 = time.perf_counter()
                img = mi.render(scenes[s], spp=spp, seed=1 + r)
                dr.eval(img)
                dr.sync_thread()
                best[s] = min(best[s], time.perf_counter() - t0)
                if r == 0:
                    imgs[s] = np.array(img)
        for s in SENSORS:
            rows[s].append({"spp": spp, "seconds": best[s], "mape": mape(imgs[s], ref)})
    out = {"lens": lens, "reference_seconds": t_ref, "renders": rows, "equal_time": []}
    tr = [r["seconds"] for r in rows["realistic_lens"]]
    tn = [r["seconds"] for r in rows["neural_lens"]]
    mn = [r["mape"] for r in rows["neural_lens"]]
    for r, t_n in zip(rows["realistic_lens"], tn):      # both rendered the same spp list
        out["equal_time"].append({"spp_realistic": r["spp"], "seconds": r["seconds"], "mape_realistic": r["mape"],
                                  "mape_neural": interp_loglog(r["seconds"], tn, mn),
                                  "spp_neural": r["spp"] * r["seconds"] / t_n})
    out["time_per_spp_ratio"] = float(np.median(np.array(tn) / np.array(tr)))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lenses", default="wide-22mm,ood-59mm,canon-ef-24mm-f1.4l,dgauss-50mm,canon-rf-24mm-f1.4l-vcm")
    ap.add_argument("--scene", default="still_life")
    ap.add_argument("--res", default="320x240")
    ap.add_argument("--spp", default="4,16,64,256", help="spp list (the scenes' ldsampler needs powers of 4)")
    ap.add_argument("--reference-spp", type=int, default=1024)
    ap.add_argument("--repeats", type=int, default=2)
    add_variant_argument(ap)
    ap.add_argument("--out", default=os.path.join("out", "bench", "equal_time.json"))
    a = ap.parse_args(argv)
    a.res = tuple(int(v) for v in a.res.lower().split("x"))
    a.spp = [int(v) for v in a.spp.split(",")]
    import drjit as dr
    import mitsuba as mi
    mi.set_variant(a.variant)
    results = [r for r in (measure_lens(mi, dr, lens, a) for lens in a.lenses.split(",")) if r is not None]
    print(f"\n{a.scene} {a.res[0]}x{a.res[1]}, {a.variant}, {dr.thread_count()} threads; "
          f"reference realistic_lens {a.reference_spp} spp")
    print("| lens | neural / realistic time per spp | exact spp (s) | MAPE realistic | MAPE neural, same time "
          "| neural spp in that time |")
    print("|---|---|---|---|---|---|")
    for r in results:
        for e in r["equal_time"]:
            print(f"| {r['lens']} | {r['time_per_spp_ratio']:.2f} | {e['spp_realistic']} ({e['seconds']:.2f}) | "
                  f"{e['mape_realistic']:.4f} | {e['mape_neural']:.4f} | {e['spp_neural']:.1f} |")
    atomic_write_json(a.out, {"benchmark": "equal_time", "scene": a.scene,
                              "resolution": list(a.res), "variant": a.variant, "threads": dr.thread_count(),
                              "reference_spp": a.reference_spp, "machine": platform.processor() or platform.machine(),
                              "cpus": os.cpu_count(),
                              "command": "python benchmarks/equal_time.py " + " ".join(argv or sys.argv[1:]),
                              "lenses": results}, indent=2)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
