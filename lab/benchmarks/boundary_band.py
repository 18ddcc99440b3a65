"""What tracing a learned ghost's edges buys: the flare's ``boundary_band`` swept on chosen ghosts.

    python benchmarks/boundary_band.py LENS GHOST[,GHOST...] [--bands 0,0.1,0.3,1] [--samples 24]
                                       [--light 0.9:0.45] [--json OUT]

Each ghost alone (``mi_neurallens.flare.verify``'s scene: night_point, 240×160, the light at ``--light`` m, 5 m
away), rendered by the tracer and by its learned map with each band *on the same samples* (``pilot_with =
"exact"``, seed 1): the paired MAPE (the map's own error, noise mostly cancelled) and the share of the ghost's
samples the band left to the tracer.  Band 0 is the learned map alone.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("lens")
    ap.add_argument("ghosts", help="comma-separated ghost path ids")
    ap.add_argument("--bands", default="0,0.1,0.3,1")
    ap.add_argument("--samples", type=int, default=24, help="log2 samples per render")
    ap.add_argument("--light", default="0.9:0.45", help="x:y of the point light (m, at z = 5 m)")
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    sys.path.insert(0, ROOT)
    import mitsuba as mi
    from mi_neurallens.render_utils import default_variant
    mi.set_variant(default_variant())
    from mi_neurallens.flare.render import render_flare
    from mi_neurallens.flare.verify import verification_scene
    from mi_neurallens.metrics import flare_error_map
    from mi_neurallens.neural.model import bundled_model_path

    light = tuple(float(v) for v in a.light.split(":"))
    scene = verification_scene(a.lens, bundled_model_path(a.lens), light)
    n = 1 << a.samples
    rows = []
    for pid in (int(v) for v in a.ghosts.split(",")):
        ex = render_flare(scene, 0, seed=1, ghosts=[pid], samples=n, mode="exact").total
        for band in (float(v) for v in a.bands.split(",")):
            t0 = time.perf_counter()
            r = render_flare(scene, 0, seed=1, ghosts=[pid], samples=n, mode="neural", pilot_with="exact",
                             boundary_band=band)
            dt = time.perf_counter() - t0
            rel, mask = flare_error_map(r.total, ex)
            st = next(s for s in r.stats if s.path_id == pid)
            row = {"ghost": pid, "band": band, "paired_mape": float(rel[mask].mean()), "pixels": int(mask.sum()),
                   "traced_fraction": st.traced / max(st.samples, 1), "samples": st.samples, "seconds": dt}
            rows.append(row)
            print(f"ghost {pid} band {band:g}: paired MAPE {row['paired_mape']:.4f} over {row['pixels']} px, "
                  f"traced {100 * row['traced_fraction']:.1f} % of {st.samples} samples ({dt:.1f} s, first render "
                  "of a kernel included)", flush=True)
    if a.json:
        os.makedirs(os.path.dirname(os.path.abspath(a.json)), exist_ok=True)
        with open(a.json, "w") as f:
            json.dump({"lens": a.lens, "light_m": [*light, 5.0], "log2_samples": a.samples, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
