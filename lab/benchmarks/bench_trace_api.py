"""``Lens.trace`` (numpy in, numpy out) against the Dr.Jit kernel it wraps, in one run.

    python benchmarks/bench_trace_api.py [--lens wide-22mm] [--log2n 22]

Forward transmit rays of ``bench_tracer.py`` (object-space rays over the lens's field toward its first
surface, 400–700 nm).  Rows: the tracer kernel on Dr.Jit arrays already in place (what a renderer pays); ``Lens.trace``
with float64 numpy arrays (inputs read and results returned as float64); ``Lens.trace`` with float32
arrays (float32 end to end).  Best of 3 after a warm-up that compiles the kernel.  Issue 18's goal:
≥ 25 M rays/s through the numpy API.  Writes ``benchmarks/results/trace_api.json``.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from mi_neurallens import Lens  # noqa: E402
from mi_neurallens.trace.api import float_type, tracer_for  # noqa: E402
from bench_tracer import object_rays  # noqa: E402  (the tracer benchmark's rays: its kernel figure)


def best(fn, k=3):
    import drjit as dr
    fn()
    ts = []
    for _ in range(k):
        dr.sync_thread()
        t = time.perf_counter()
        fn()
        dr.sync_thread()
        ts.append(time.perf_counter() - t)
    return min(ts)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lens", default="wide-22mm")
    ap.add_argument("--log2n", type=int, default=22)
    a = ap.parse_args()
    import drjit as dr
    lens = Lens.load(a.lens)
    n = 1 << a.log2n
    o, d, lam = object_rays(lens, n, np.random.default_rng(1))
    F = float_type("float32")
    cols = lambda x: tuple(F(np.ascontiguousarray(x[:, i], np.float32)) for i in range(3))
    O, D, L = cols(o), cols(d), F(lam.astype(np.float32))
    tr = tracer_for(lens)

    def kernel():
        res = tr.trace(O, D, L, "transmit", "forward")
        dr.eval(res.position, res.direction, res.throughput, res.valid)

    o32, d32, lam32 = o.astype(np.float32), d.astype(np.float32), lam.astype(np.float32)
    rows = {"kernel (Dr.Jit arrays in place)": best(kernel),
            "Lens.trace, float64 arrays": best(lambda: lens.trace(o, d, lam)),
            "Lens.trace, float32 arrays": best(lambda: lens.trace(o32, d32, lam32))}
    out = {"machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
           "command": " ".join(sys.argv), "lens": a.lens, "rays": n,
           "rows": {k: {"seconds": v, "rays_per_s": n / v} for k, v in rows.items()}}
    for k, v in rows.items():
        print(f"{k:34s} {n / v / 1e6:6.1f} M rays/s")
    os.makedirs(os.path.join(ROOT, "benchmarks", "results"), exist_ok=True)
    with open(os.path.join(ROOT, "benchmarks", "results", "trace_api.json"), "w") as f:
        json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
