"""Warm neural flare renders with literal (``fused``) vs parameter (``shared``) ghost kernels: what the shared
kernels cost per render once everything is compiled (issue 18, "one compilation").

    python benchmarks/warm_flare_kernels.py [--lens wide-22mm] [--ghosts 4] [--samples 22] [--json OUT]

``scenes/night_point.xml`` through the lens's ``neural_lens``, the model's first ``--ghosts`` ghost maps, every
ghost learned (``mode = "neural"``), 2^samples samples; one renderer per ``mlp``, interleaved, four renders each:
the first compiles (or reads the disk cache), the best of the other three is the warm time.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lens", default="wide-22mm")
    ap.add_argument("--ghosts", type=int, default=4)
    ap.add_argument("--samples", type=int, default=22)
    ap.add_argument("--json", help="write the result here")
    a = ap.parse_args(argv)
    sys.path.insert(0, ROOT)
    import drjit as dr
    import mitsuba as mi
    from mi_neurallens.render_utils import default_variant
    mi.set_variant(default_variant())
    from mi_neurallens.commands.render import load_scene
    from mi_neurallens.fileio import atomic_write_json
    from mi_neurallens.flare.render import FlareOptions, FlareRenderer
    from mi_neurallens.neural.model import bundled_model_path, load_model
    path = bundled_model_path(a.lens)
    m = load_model(path)
    ghosts = m.ghost_ids[:a.ghosts]
    scene = load_scene(os.path.join(ROOT, "scenes", "night_point.xml"), lens=a.lens, sensor_type="neural_lens",
                       sets=[f"model={path}"])
    frs = {k: FlareRenderer(scene, 0, FlareOptions(mode="neural", ghosts=ghosts, samples=1 << a.samples, model=m,
                                                   mlp=k)) for k in ("fused", "shared")}
    times = {k: [] for k in frs}
    for _ in range(4):
        for k, fr in frs.items():
            t0 = time.perf_counter()
            dr.eval(fr.render(seed=0).total)
            dr.sync_thread()
            times[k].append(time.perf_counter() - t0)
    best = {k: min(v[1:]) for k, v in times.items()}
    print(f"{a.lens}, {len(ghosts)} ghosts, 2^{a.samples} samples: first render fused {times['fused'][0]:.2f} s, "
          f"shared {times['shared'][0]:.2f} s; warm (best of 3) fused {best['fused']:.2f} s, shared "
          f"{best['shared']:.2f} s ({best['shared'] / best['fused']:.2f}x)")
    if a.json:
        atomic_write_json(a.json, {"benchmark": "warm_flare_kernels", "lens": a.lens, "ghosts": ghosts,
                                   "samples": 1 << a.samples, "seconds": times, "warm_best_of_3": best,
                                   "command": "python benchmarks/warm_flare_kernels.py " + " ".join(argv or sys.argv[1:])},
                          indent=2)


if __name__ == "__main__":
    main()
