"""What differentiating a lens costs: the still life through ``realistic_lens`` (or ``neural_lens``), rendered
(one process, warm-up excluded, ``dr.sync_thread()``, best of ``--repeats``):

* ``primal``: the ``path`` render of the loaded scene (nothing differentiated: the literal kernel);
* ``primal, live lens``: the same after ``params.update()`` made the differentiated parameters kernel inputs (no
  gradients);
* ``lens_ad primal``: ``lens_ad``'s primal (a nested ``path``);
* ``lens_ad primal + reverse``: ``mi.render`` and ``dr.backward`` of the image's mean with the parameters
  gradient-enabled — what one step of an optimisation costs.

The parameters: every curvature of the lens (``realistic_lens``), or the sensor distance and every weight of
the camera map's regressor (``neural_lens``).

    python benchmarks/bench_differentiable.py [--res 160x120] [--spp 16] [--repeats 3] [--lens wide-22mm]
                                              [--sensor realistic_lens|neural_lens]

Prints the times and their ratios to ``primal`` and writes ``out/bench/bench_differentiable.json``.  The bar: a
differentiable render at most 3x the primal at the same spp.
"""
from __future__ import annotations

import argparse
import os
import platform
import time

from mi_neurallens.fileio import atomic_write_json

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--res", default="160x120")
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--lens", default="wide-22mm")
    ap.add_argument("--sensor", default="realistic_lens", choices=("realistic_lens", "neural_lens"))
    ap.add_argument("--out", default=None, help="(default: out/bench/bench_differentiable[_neural].json)")
    args = ap.parse_args(argv)
    if args.out is None:
        args.out = os.path.join(ROOT, "out", "bench", "bench_differentiable" + (
            "_neural" if args.sensor == "neural_lens" else "") + ".json")
    import drjit as dr
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    import mi_neurallens
    mi_neurallens.register()
    from mi_neurallens.commands.render import load_scene
    from mi_neurallens.resources import scene_path
    from mi_neurallens.trace import parameters as lp
    w, h = (int(x) for x in args.res.split("x"))

    def scene():
        return load_scene(str(scene_path("still_life")), variant="llvm_ad_rgb", lens=args.lens, resolution=(w, h),
                          spp=args.spp, sets=[], sensor_type=args.sensor)

    def differentiated(p):
        if args.sensor == "neural_lens":
            return [k for k in p.keys() if k.endswith(".sensor_distance") or ".regressor_" in k]
        return [k for k in p.keys() if lp.parse(k) and lp.parse(k)[1] == lp.CURVATURE]

    def best(fn):
        fn()                                   # warm-up: compiles
        ts = []
        for _ in range(args.repeats):
            dr.sync_thread()
            t = time.perf_counter()
            fn()
            dr.sync_thread()
            ts.append(time.perf_counter() - t)
        return min(ts)

    rows = {}
    sc = scene()
    rows["primal"] = best(lambda: dr.eval(mi.render(sc, spp=args.spp, seed=1)))
    p = mi.traverse(sc)
    for k in differentiated(p):
        p[k] = p[k] * (1 + 1e-7)
    p.update()
    rows["primal, live lens"] = best(lambda: dr.eval(mi.render(sc, spp=args.spp, seed=1)))

    ad, lens_ad = scene(), mi.load_dict({"type": "lens_ad", "max_depth": 6})
    rows["lens_ad primal"] = best(lambda: dr.eval(mi.render(ad, integrator=lens_ad, spp=args.spp, seed=1)))
    pa = mi.traverse(ad)
    keys = differentiated(pa)
    for k in keys:
        dr.enable_grad(pa[k])
    pa.update()

    def step():
        img = mi.render(ad, pa, integrator=lens_ad, spp=args.spp, seed=1)
        dr.backward(dr.mean(img, axis=None))
        dr.eval([dr.grad(pa[k]) for k in keys])
    rows["lens_ad primal + reverse"] = best(step)
    base = rows["primal"]
    print(f"still life {w}x{h}, {args.spp} spp, {args.sensor} {args.lens}, {len(keys)} parameters differentiated "
          f"({', '.join(k.split('.')[-1] for k in keys[:3])}{', ...' if len(keys) > 3 else ''})")
    for k, v in rows.items():
        print(f"  {k:28s} {v:7.3f} s   {v / base:5.2f}x")
    atomic_write_json(args.out, {"machine": platform.processor() or platform.machine(), "res": [w, h],
                                 "spp": args.spp, "lens": args.lens, "sensor": args.sensor, "seconds": rows,
                                 "ratio_to_primal": {k: v / base for k, v in rows.items()}})


if __name__ == "__main__":
    main()
