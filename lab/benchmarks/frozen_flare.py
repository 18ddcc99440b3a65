"""Frozen flare kernels (``FlareOptions.freeze``, ``dr.freeze``) against traced ones: what a flare render costs
beyond its samples (issue 18: "≈ 20 ms per learned ghost and render").

    python benchmarks/frozen_flare.py [--lens ood-59mm] [--samples 16,20,24] [--modes exact,neural] [--repeat 3]

One process, kernels already compiled (a throwaway render first).  For each mode (``exact`` or ``neural``: every
ghost of the lens's bundled model, ``mlp`` as the flare's default) and budget 2^s (all ghosts together, the
night scene's point light), with ``freeze`` off and on:

* ``new``: the first render of a new :class:`~mi_neurallens.flare.render.FlareRenderer` (what ``lens_flare``, the
  CLI and ``render_flare`` do for every render): frozen, its kernels are recorded, once per signature;
* ``again``: the best of ``--repeat`` later renders of that renderer (other seeds): frozen, they replay.

A linear fit of time against samples over the budgets splits each into a fixed part (per render) and a rate.
Prints a markdown table and writes ``benchmarks/results/frozen_flare_<lens>.json``.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def main(argv=None):
    p = argparse.ArgumentParser()
    p.add_argument("--lens", default="ood-59mm")
    p.add_argument("--samples", default="16,20,24", help="log2 budgets, comma list")
    p.add_argument("--modes", default="exact,neural")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)
    import numpy as np
    import drjit as dr
    import mitsuba as mi
    from mi_neurallens.render_utils import default_variant
    mi.set_variant(default_variant())
    from mi_neurallens.commands.render import load_scene
    from mi_neurallens.fileio import atomic_write_json
    from mi_neurallens.flare.render import FlareOptions, FlareRenderer
    from mi_neurallens.neural.model import bundled_model_path, load_model
    model = bundled_model_path(a.lens)
    ghosts = load_model(model).ghost_ids
    scene = load_scene(os.path.join(ROOT, "scenes", "night_point.xml"), lens=a.lens, sensor_type="neural_lens",
                       sets=[f"model={model}"])
    budgets = [int(s) for s in a.samples.split(",")]

    def renderer(mode, freeze, s):
        return FlareRenderer(scene, 0, FlareOptions(mode=mode, ghosts=ghosts, samples=1 << s, model=model,
                                                    freeze=freeze))

    def timed(fr, seed):
        t0 = time.perf_counter()
        r = fr.render(seed=seed)
        dr.eval(r.total)
        dr.sync_thread()
        return time.perf_counter() - t0

    rows = []
    for mode in a.modes.split(","):
        for freeze in (False, True):
            renderer(mode, freeze, budgets[0]).render(seed=0)          # compile (and fill the caches)
            for s in budgets:
                fr = renderer(mode, freeze, s)
                new = timed(fr, 1)
                again = min(timed(fr, 2 + k) for k in range(a.repeat))
                rows.append({"mode": mode, "freeze": freeze, "log2_samples": s, "new_s": new, "again_s": again,
                             "learned": sum(1 for st in fr.render(seed=0, samples=1 << 12).stats
                                            if st.evaluator == "neural"),
                             "recordings": {k: f.n_recordings for k, f in fr.kernels.frozen.items()},
                             "unfrozen": len(fr.kernels.unfrozen)})
                print(f"{mode:6s} freeze={freeze!s:5s} 2^{s}: new {new:.3f} s, again {again:.3f} s "
                      f"recordings {rows[-1]['recordings']}", flush=True)
    fits = []
    for mode in a.modes.split(","):
        for freeze in (False, True):
            rs = [r for r in rows if r["mode"] == mode and r["freeze"] == freeze]
            n = np.array([2.0 ** r["log2_samples"] for r in rs])
            for col in ("new_s", "again_s"):
                slope, fixed = np.polyfit(n, np.array([r[col] for r in rs]), 1)
                fits.append({"mode": mode, "freeze": freeze, "render": col[:-2], "fixed_s": float(fixed),
                             "samples_per_s": float(1.0 / slope) if slope > 0 else None})
    print(f"\n{a.lens}: {len(ghosts)} ghosts, night_point.xml, {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} threads\n")
    print("| mode | freeze | render | " + " | ".join(f"2^{s} (s)" for s in budgets) + " | fixed (s) | M samples/s |")
    print("|---|---|---|" + "---|" * (len(budgets) + 2))
    for f in fits:
        ts = [r[f["render"] + "_s"] for r in rows if r["mode"] == f["mode"] and r["freeze"] == f["freeze"]]
        rate = f["samples_per_s"]
        print(f"| {f['mode']} | {'on' if f['freeze'] else 'off'} | {f['render']} | "
              + " | ".join(f"{t:.3f}" for t in ts) + f" | {f['fixed_s']:.3f} | "
              + (f"{rate / 1e6:.1f}" if rate else "—") + " |")
    out = a.out or os.path.join(ROOT, "benchmarks", "results", f"frozen_flare_{a.lens}.json")
    atomic_write_json(out, {"lens": a.lens, "ghosts": len(ghosts), "rows": rows, "fits": fits,
                            "command": "python benchmarks/frozen_flare.py " + " ".join(argv or sys.argv[1:]),
                            "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} threads"})


if __name__ == "__main__":
    main()
