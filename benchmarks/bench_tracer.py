"""Exact-tracer throughput: rays/s of the Dr.Jit tracer (float32, Fresnel on, per-ray wavelength)
for the transmit path and a few ghosts of the bundled lenses, against optiland's own tracer on
the same rays, measured in the same run.

    python benchmarks/bench_tracer.py [--rays 22] [--ref-rays 16] [--repeats 5]

Prints a markdown table and writes out/bench/bench_tracer.json.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import time

import numpy as np

import drjit as dr  # noqa: E402

from mi_neurallens import Lens  # noqa: E402
from mi_neurallens.optics.glass import model_glass  # noqa: E402
from mi_neurallens.trace.api import float_type  # noqa: E402
from mi_neurallens.trace.paths import ghost_id  # noqa: E402
from mi_neurallens.trace.tracer import LensTracer  # noqa: E402
from mi_neurallens.fileio import atomic_write_json  # noqa: E402


def object_rays(lens, n, rng, lam_range=(400.0, 700.0)):
    """Object-space rays toward the first surface covering the lens's field (many pass, some don't)."""
    r0 = lens.surfaces[0].semi_diameter
    half_fov = np.arctan(21.6 / lens.efl())
    th = half_fov * np.sqrt(rng.uniform(0, 1, n))
    az = rng.uniform(0, 2 * np.pi, n)
    d = np.stack([np.sin(th) * np.cos(az), np.sin(th) * np.sin(az), np.cos(th)], 1)
    rr = r0 * np.sqrt(rng.uniform(0, 1, n))
    b = rng.uniform(0, 2 * np.pi, n)
    p = np.stack([rr * np.cos(b), rr * np.sin(b), np.zeros(n)], 1)
    z0 = min(0.0, float(lens.surfaces[0].sag(r0))) - 5.0
    o = p + d * ((z0 - p[:, 2:3]) / d[:, 2:3])
    lam = rng.uniform(*lam_range, n)
    return o, d, lam


def time_ours(lens, path, o, d, lam, repeats):
    F = float_type("float32")
    tr = LensTracer(lens, fresnel=True)
    O = tuple(F(o[:, i].astype(np.float32)) for i in range(3))
    D = tuple(F(d[:, i].astype(np.float32)) for i in range(3))
    L = F(lam.astype(np.float32))
    dr.eval(O, D, L)
    best, valid = float("inf"), 0.0
    for _ in range(repeats + 1):  # first run compiles (or loads the kernel cache)
        dr.sync_thread()
        t0 = time.perf_counter()
        r = tr.trace(O, D, L, path)
        dr.eval(r.position, r.direction, r.throughput, r.valid)
        dr.sync_thread()
        best = min(best, time.perf_counter() - t0) if _ > 0 else best
        valid = float(dr.mean(F(r.valid))[0] if hasattr(dr.mean(F(r.valid)), "__len__") else dr.mean(F(r.valid)))
    return len(o) / best, valid


def time_optiland(lens, o, d, lam_nm, repeats):
    from mi_neurallens.optics.interop import optiland_optic
    from optiland.rays import RealRays
    optic = optiland_optic(lens, lam_nm)
    group = optic.surfaces if hasattr(optic.surfaces, "trace") else optic.surface_group
    n = len(o)
    best = float("inf")
    for _ in range(repeats):
        rays = RealRays(o[:, 0].copy(), o[:, 1].copy(), o[:, 2].copy(), d[:, 0].copy(), d[:, 1].copy(),
                        d[:, 2].copy(), np.ones(n), np.full(n, lam_nm * 1e-3))
        t0 = time.perf_counter()
        group.trace(rays, skip=1, record=False)
        best = min(best, time.perf_counter() - t0)
    return n / best


def with_model_dispersion(lens, vd=50.0):
    """The same lens with each constant-index glass replaced by a model glass (nd = n, Vd = vd)."""
    def m(x):
        return model_glass(x.coefficients[0], vd) if x.is_constant and x.coefficients[0] > 1.0 else x
    return lens.replace(name=lens.name + f"+disp(Vd={vd:g})",
                        surfaces=tuple(dataclasses.replace(s, medium=m(s.medium)) for s in lens.surfaces))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, default=22, help="log2 of rays per measurement (ours)")
    ap.add_argument("--ref-rays", type=int, default=16, help="log2 of rays for optiland")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=os.path.join("out", "bench", "bench_tracer.json"))
    a = ap.parse_args(argv)
    import warnings
    warnings.filterwarnings("ignore")
    rng = np.random.default_rng(0)
    n, nref = 1 << a.rays, 1 << a.ref_rays
    w22 = Lens.load("wide-22mm")
    cases = [
        (w22, "transmit", True),
        (with_model_dispersion(w22), "transmit", True),
        (w22, ghost_id(1, 0), False),
        (w22, ghost_id(6, 3), False),
        (w22, ghost_id(11, 9), False),
        (Lens.load("canon-ef-24mm-f1.4l"), "transmit", True),
        (Lens.load("ood-59mm"), "transmit", True),
        (Lens.load("dgauss-50mm"), "transmit", True),
    ]
    rows = []
    for lens, path, ref in cases:
        o, d, lam = object_rays(lens, n, rng)
        ours, frac = time_ours(lens, path, o, d, lam, a.repeats)
        row = {"lens": lens.name, "surfaces": len(lens.optical_indices),
               "path": path if isinstance(path, str) else f"ghost id {path}",
               "mrays_per_s": ours / 1e6, "valid_fraction": frac}
        if ref:
            k = min(nref, n)
            theirs = time_optiland(lens, o[:k], d[:k], 550.0, max(1, a.repeats // 2))
            row["optiland_mrays_per_s"] = theirs / 1e6
            row["speedup"] = ours / theirs
        rows.append(row)
        print(f"  {row['lens']:<34} {row['path']:<16} {ours / 1e6:7.1f} Mrays/s", flush=True)

    info = {"machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
            "drjit_threads": dr.thread_count(), "rays": n, "optiland_rays": nref,
            "precision": "float32", "fresnel": True, "wavelength": "per ray, uniform 400-700 nm"}
    print()
    print("| lens | optical surfaces | path | ours (Mrays/s) | valid | optiland (Mrays/s) | speed-up |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        ol = f"{r['optiland_mrays_per_s']:.3f}" if "optiland_mrays_per_s" in r else "n/a (no ghosts)"
        sp = f"{r['speedup']:.0f}×" if "speedup" in r else ""
        print(f"| {r['lens']} | {r['surfaces']} | {r['path']} | {r['mrays_per_s']:.1f} | "
              f"{r['valid_fraction']:.2f} | {ol} | {sp} |")
    atomic_write_json(a.out, {"info": info, "rows": rows}, indent=2)
    print(f"\nwrote {a.out}")


if __name__ == "__main__":
    main()
