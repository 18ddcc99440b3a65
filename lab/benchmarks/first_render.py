"""The first flare render on a fresh kernel cache vs a warm one (issue 18's "one compilation" goal:
first full-flare neural render on a fresh cache ≤ 2× a warm one).

    python benchmarks/first_render.py [--lens wide-22mm] [--samples 20] [--modes exact,neural:fused,neural:shared]
                                      [--model LABEL=FILE ...]

Each mode runs in child processes whose ``HOME`` is a new empty folder, so Dr.Jit's kernel cache
(``~/.drjit``) starts empty: process 1 times its first render (every kernel compiled) and its second
of the same seed (in-memory cache: the warm time); process 2, same folder, times its first render (kernels
from the disk cache).  The flare: ``scenes/night_point.xml`` through the lens's neural sensor, every ghost
the model has a map for, 2^samples forward samples in all.  A mode ``neural:M`` sets the flare's ``mlp`` to M
(``fused``: weights as kernel literals, a kernel per ghost map; ``shared``: kernel parameters, one kernel per
architecture; plain ``neural``: the flare's default, ``auto``).  ``--model LABEL=FILE`` (repeatable) runs
the modes for each model file in turn (rows "LABEL mode"); default: the lens's bundled model.  Prints a markdown table and writes ``benchmarks/results/first_render.json``.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

CHILD = r"""
import json, os, sys, time
sys.path.insert(0, {root!r})
import drjit as dr, mitsuba as mi
from mi_neurallens.render_utils import default_variant
mi.set_variant(default_variant())
from mi_neurallens.commands.render import load_scene
from mi_neurallens.flare.render import FlareOptions, FlareRenderer
from mi_neurallens.neural.model import bundled_model_path, load_model
model = {model!r} or bundled_model_path({lens!r})
ghosts = load_model(model).ghost_ids
scene = load_scene(os.path.join({root!r}, "scenes", "night_point.xml"), lens={lens!r}, sensor_type="neural_lens",
                   sets=[f"model={{model}}"])
fr = FlareRenderer(scene, 0, FlareOptions(mode={mode!r}, ghosts=ghosts, samples=1 << {samples}, model=model,
                                          mlp={mlp!r}))
times = []
for k in range(2):                       # the same seed twice: the second render compiles nothing
    t0 = time.perf_counter(); r = fr.render(seed=0); dr.eval(r.total); dr.sync_thread()
    times.append(time.perf_counter() - t0)
print(json.dumps({{"ghosts": len(ghosts), "first": times[0], "second": times[1], "mlp": fr.learned_mlp()}}))
"""


def child(home, lens, mode, samples, model=None):
    env = dict(os.environ, HOME=home)
    mode, _, mlp = mode.partition(":")
    code = CHILD.format(root=ROOT, lens=lens, mode=mode, samples=samples, mlp=mlp or "auto",
                        model=os.path.abspath(model) if model else None)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lens", default="wide-22mm")
    ap.add_argument("--samples", type=int, default=20, help="log2 forward samples (split over the ghosts)")
    ap.add_argument("--modes", default="exact,neural:fused,neural:shared")
    ap.add_argument("--model", action="append", default=[], metavar="LABEL=FILE",
                    help="run the modes with this model file (repeatable; default: the bundled model)")
    ap.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "first_render.json"))
    a = ap.parse_args(argv)
    from mi_neurallens.fileio import atomic_write_json
    models = [m.split("=", 1) for m in a.model] or [("", None)]
    rows = {}
    for label, model in models:
        for mode in a.modes.split(","):
            with tempfile.TemporaryDirectory() as home:
                cold = child(home, a.lens, mode, a.samples, model)
                disk = child(home, a.lens, mode, a.samples, model)
            rows[f"{label} {mode}".strip()] = {
                "ghosts": cold["ghosts"], "mlp": cold["mlp"], "model": model, "fresh_cache_first_s": cold["first"],
                "warm_s": cold["second"], "disk_cache_first_s": disk["first"],
                "fresh_over_warm": cold["first"] / cold["second"], "disk_over_warm": disk["first"] / cold["second"]}
    print(f"{a.lens}, night_point.xml, 2^{a.samples} samples over the ghosts")
    print("| mode | ghosts | first render, fresh cache (s) | first, disk cache (s) | warm (s) | fresh / warm | disk / warm |")
    print("|---|---|---|---|---|---|---|")
    for mode, r in rows.items():
        print(f"| {mode} | {r['ghosts']} | {r['fresh_cache_first_s']:.2f} | {r['disk_cache_first_s']:.2f} | "
              f"{r['warm_s']:.2f} | {r['fresh_over_warm']:.1f} | {r['disk_over_warm']:.1f} |")
    atomic_write_json(a.out, {"benchmark": "first_render", "lens": a.lens, "samples": 1 << a.samples,
                              "command": "python benchmarks/first_render.py " + " ".join(argv or sys.argv[1:]),
                              "rows": rows}, indent=2)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
