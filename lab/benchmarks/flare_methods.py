"""Flare image MAPE of every ghost evaluator (neural map, fitted/Taylor/ABCD polynomials) against the
exact tracer, per shipped ghost and for all shipped ghosts combined — the paper's flare comparison
(and the goals of docs/flares.md), with Fresnel throughput on and off.

    python benchmarks/flare_methods.py [--samples 22] [--reference-samples 25] [--lenses wide-22mm,ood-59mm]

scenes/night_point.xml (one point light at (0.9, 0.45, 5) m, 240×160), ``neural_lens`` sensor of the
bundled model; the ghosts are the ones the model has maps for.  MAPE =
``mi_neurallens.metrics.mape_masked`` (luminance, pixels above 1 % of the reference maximum, ε = 0.1 %
of it).  Three measurements per method, all with the same per-ghost sample budget (2^samples on
average):

* ``independent``: the method's render (seed 1) against an exact reference with 2^reference-samples
  per ghost (seed 101).  Includes the Monte Carlo noise of both; the ``exact`` row (exact at the test
  budget against the reference) is that noise floor.
* ``paired``: the method's render against the exact render *with the same samples* (``pilot_with =
  "exact"``, same seed: common random numbers).  Monte Carlo noise cancels between the two, so this is
  the map's own error; it is reported at two budgets (2^samples and 4× that) to show it has converged.

Writes benchmarks/results/flare_methods.json and prints markdown tables.
"""
from __future__ import annotations

import argparse
import os
import time

from mi_neurallens.fileio import atomic_write_json
from mi_neurallens.render_utils import default_variant

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
METHODS = ("exact", "neural", "fitted", "taylor5", "taylor3", "abcd")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=22, help="log2 flare samples per ghost (test renders)")
    ap.add_argument("--reference-samples", type=int, default=25, help="log2 samples per ghost of the reference")
    ap.add_argument("--lenses", default="wide-22mm,ood-59mm")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--fresnel", default="on,off", help="on, off or both (on,off)")
    ap.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "flare_methods.json"))
    a = ap.parse_args(argv)
    import mitsuba as mi
    mi.set_variant(default_variant())
    from mi_neurallens.commands.render import load_scene
    from mi_neurallens.flare.render import render_flare
    from mi_neurallens.metrics import mape_masked
    from mi_neurallens.neural.model import bundled_model_path, load_model
    methods = [m for m in a.methods.split(",") if m]
    doc = {"samples_log2": a.samples, "reference_samples_log2": a.reference_samples,
           "scene": "scenes/night_point.xml", "rows": {}}
    t_all = time.perf_counter()
    for lens in [x for x in a.lenses.split(",") if x]:
        ghosts = load_model(bundled_model_path(lens)).ghost_ids
        n = len(ghosts)
        for fres in [x for x in a.fresnel.split(",") if x]:
            scene = load_scene(os.path.join(ROOT, "scenes", "night_point.xml"), variant=default_variant(), lens=lens,
                               sensor_type="neural_lens",
                               sets=[f"model={lens}", f"fresnel={'true' if fres == 'on' else 'false'}"])
            t0 = time.perf_counter()
            ref = render_flare(scene, seed=101, per_ghost=True, mode="exact", ghosts=ghosts,
                               samples=n << a.reference_samples)
            t_ref = time.perf_counter() - t0
            exact_at = {}
            for k in (a.samples, a.samples + 2):
                exact_at[k] = render_flare(scene, seed=1, per_ghost=True, mode="exact", ghosts=ghosts,
                                           samples=n << k)

            def row(img, ref_img):
                out = {"all": mape_masked(img.total, ref_img.total)}
                for g in ghosts:   # a map that blocks every ray leaves no image: all light missing
                    out[str(g)] = mape_masked(img.ghosts.get(g, 0.0 * ref_img.ghosts[g]), ref_img.ghosts[g])
                return out

            res = {"reference_seconds": t_ref, "ghosts": ghosts}
            for method in methods:
                t0 = time.perf_counter()
                r = exact_at[a.samples] if method == "exact" else render_flare(
                    scene, seed=1, per_ghost=True, mode=method, ghosts=ghosts, samples=n << a.samples)
                dt = time.perf_counter() - t0
                entry = {"independent": row(r, ref), "seconds": dt}
                if method != "exact":
                    for k in (a.samples, a.samples + 2):
                        rp = render_flare(scene, seed=1, per_ghost=True, mode=method, ghosts=ghosts,
                                          samples=n << k, pilot_with="exact")
                        entry[f"paired_2^{k}"] = row(rp, exact_at[k])
                res[method] = entry
                print(lens, f"fresnel {fres}", method,
                      {kk: (round(v["all"], 4) if isinstance(v, dict) else round(v, 2)) for kk, v in entry.items()},
                      flush=True)
            doc["rows"].setdefault(lens, {})[f"fresnel_{fres}"] = res
    doc["seconds"] = time.perf_counter() - t_all
    print_tables(doc)
    atomic_write_json(a.out, doc, indent=1)


def print_tables(doc):
    s = doc["samples_log2"]
    for lens, per_f in doc["rows"].items():
        for fk, res in per_f.items():
            ghosts = res["ghosts"]
            meths = [m for m in METHODS if m in res]
            print(f"\n{lens}, {fk.replace('_', ' ')}: MAPE independent (vs 2^{doc['reference_samples_log2']}-sample "
                  f"reference) / paired 2^{s} / paired 2^{s + 2}")
            print("| ghost | " + " | ".join(meths) + " |")
            print("|---|" + "---|" * len(meths))
            for key in ["all"] + [str(g) for g in ghosts]:
                cells = []
                for m in meths:
                    e = res[m]
                    if m == "exact":
                        cells.append(f"{e['independent'][key]:.3f} (noise)")
                    else:
                        cells.append(f"{e['independent'][key]:.3f} / {e[f'paired_2^{s}'][key]:.4f} / "
                                     f"{e[f'paired_2^{s + 2}'][key]:.4f}")
                print(f"| {key} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
