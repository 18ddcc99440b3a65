"""Rays/s of every method's ``eval_dr`` on the same rays, in one run: the exact tracer, the neural map
(when the bundled model has it), ABCD, Taylor degree 3/5 (with and without aperture polynomials) and the
fitted sparse polynomial.  LLVM backend, float32, rays uniform over the map's domain; best of 3 after a
warm-up (kernel compilation excluded).

    python benchmarks/bench_baselines.py [--lens wide-22mm] [--rays 1048576]

Writes out/bench/bench_baselines.json and prints a table.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np

from mi_neurallens.fileio import atomic_write_json


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lens", default="wide-22mm")
    ap.add_argument("--rays", type=int, default=1 << 20)
    ap.add_argument("--threads", type=int, default=2, help="Dr.Jit worker threads (default 2)")
    ap.add_argument("--out", default=os.path.join("out", "bench",
                                                  "bench_baselines.json"))
    args = ap.parse_args(argv)
    import drjit as dr
    from mi_neurallens import Lens
    from mi_neurallens.transport import ExactMap
    from mi_neurallens.baselines.accuracy import build_method, flops_of, pick_ghosts, rays_from_reduced, time_eval_dr
    from mi_neurallens.baselines.common import bundled_model, default_domain, default_map_planes
    dr.set_thread_count(args.threads)
    lens = Lens.load(args.lens)
    model = bundled_model(lens)
    _, short, long_ = pick_ghosts(lens, 2, model)
    cases = [(0, "backward"), (long_, "forward")]
    methods = ("neural", "abcd", "taylor3", "taylor5", "taylor5-ap", "fitted")
    rows = []
    for pid, direction in cases:
        zi, zo = default_map_planes(lens, direction, model)
        dom = default_domain(lens, pid, direction, model)
        rng = np.random.default_rng(0)
        x = dom.u_to_x(rng.random((args.rays, 4)))
        o, d, lam, _ = rays_from_reduced(x, zi, 1 if direction == "forward" else -1, rng)
        ex = ExactMap(lens, pid, direction, zi, zo)
        t_exact = time_eval_dr(ex, o, d, lam)
        rows.append({"path": f"{direction}.{pid}", "method": "exact", "rays_per_s": t_exact, "speedup": 1.0,
                     "flops_per_ray": None})
        print(f"{direction}.{pid} exact: {t_exact / 1e6:.2f} Mrays/s", flush=True)
        for name in methods:
            m = build_method(lens, name, pid, direction, zi, zo, dom, model)
            if m is None:
                continue
            rps = time_eval_dr(m, o, d, lam)
            rows.append({"path": f"{direction}.{pid}", "method": name, "rays_per_s": rps, "speedup": rps / t_exact,
                         "flops_per_ray": flops_of(m)})
            print(f"{direction}.{pid} {name}: {rps / 1e6:.2f} Mrays/s ({rps / t_exact:.2f}× exact)", flush=True)
    doc = {"lens": lens.name, "rays": args.rays, "threads": args.threads, "backend": "LLVM float32",
           "machine": f"{platform.machine()} {platform.processor() or ''} {os.cpu_count()} CPUs".strip(),
           "created": time.strftime("%Y-%m-%d %H:%M:%S"), "command": "python benchmarks/bench_baselines.py "
           + " ".join(argv if argv is not None else sys.argv[1:]), "rows": rows}
    atomic_write_json(args.out, doc, indent=1)
    print("\n| path | method | Mrays/s | × exact | FLOPs/ray |\n|---|---|---|---|---|")
    for r in rows:
        fl = "—" if r["flops_per_ray"] is None else str(r["flops_per_ray"])
        print(f"| {r['path']} | {r['method']} | {r['rays_per_s'] / 1e6:.2f} | {r['speedup']:.2f} | {fl} |")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
