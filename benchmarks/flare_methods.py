"""Flare image MAPE of every ghost evaluator (neural map, fitted/Taylor/ABCD polynomials) against the
exact tracer, for the ghosts that have a shipped neural map — the paper's flare comparison, limited to
the ghosts we ship maps for.

    python benchmarks/flare_methods.py [--samples 22] [--reference-samples 24]

scenes/night_point.xml (one point light at (0.9, 0.45, 5) m), 240×160, sensor as the neural model's
lens, ``neural_lens`` sensor. MAPE = ``mi_neurallens.metrics.mape_masked`` (luminance, pixels above
1 % of the reference maximum, ε = 0.1 % of it). The reference is exact with 4× more samples and other
seeds; "exact" at the test sample count gives the Monte Carlo noise floor. Writes
benchmarks/results/flare_methods.json and prints a markdown table.
"""
from __future__ import annotations

import argparse
import json
import os

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=22, help="log2 flare samples per ghost")
    ap.add_argument("--reference-samples", type=int, default=24)
    ap.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "flare_methods.json"))
    a = ap.parse_args(argv)
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    from mi_neurallens.commands.render import load_scene
    from mi_neurallens.flare.render import render_flare
    from mi_neurallens.metrics import mape_masked
    from mi_neurallens.neural.model import bundled_model_path, load_model
    rows = {}
    for lens in ("wide-22mm", "ood-59mm"):
        ghosts = load_model(bundled_model_path(lens)).ghost_ids
        scene = load_scene(os.path.join(ROOT, "scenes", "night_point.xml"), variant="llvm_ad_rgb", lens=lens,
                           sensor_type="neural_lens", sets=[f"model={lens}"])
        n = len(ghosts)
        ref = render_flare(scene, seed=101, per_ghost=True, mode="exact", ghosts=ghosts,
                           samples=n << a.reference_samples)
        for method in ("exact", "neural", "fitted", "taylor5", "taylor3", "abcd"):
            r = render_flare(scene, seed=1, per_ghost=True, mode=method, ghosts=ghosts, samples=n << a.samples)
            row = {"all": mape_masked(r.total, ref.total)}
            for g in ghosts:   # a map that blocks every ray leaves no image: all light missing
                row[str(g)] = mape_masked(r.ghosts.get(g, 0.0 * ref.ghosts[g]), ref.ghosts[g])
            rows.setdefault(lens, {})[method] = row
            print(lens, method, {k: round(v, 4) for k, v in row.items()}, flush=True)
    print("\n| lens | ghost | " + " | ".join(rows["wide-22mm"]) + " |")
    print("|---|---|" + "---|" * len(rows["wide-22mm"]))
    for lens, per in rows.items():
        for key in next(iter(per.values())):
            print(f"| {lens} | {key} | " + " | ".join(f"{per[m][key]:.3f}" for m in per) + " |")
    os.makedirs(os.path.dirname(a.out), exist_ok=True)
    with open(a.out + ".tmp", "w") as f:
        json.dump({"samples_log2": a.samples, "reference_samples_log2": a.reference_samples, "rows": rows}, f,
                  indent=2)
    os.replace(a.out + ".tmp", a.out)


if __name__ == "__main__":
    main()
