"""Cost against error of a ghost map's network size: the curve a flare's architecture is chosen from.

    python benchmarks/ghost_sizes.py LENS --models LABEL=FILE [LABEL=FILE ...] [--ghosts 12,320]
                                    [--samples 22] [--reference 26] [--scene scenes/night_point.xml]
                                    [--json OUT]

Each model holds maps of the same ghosts trained at one network size (``mi-neurallens train LENS --paths
GHOSTS --set forward_regressor.hidden=3 --set forward_regressor.width=16 …``).  For every ghost, in one
run: the exact flare's rate (forward samples/s, best of 3 after compiling) and its MAPE against an
independent exact reference of 2^``reference`` samples (the noise floor at 2^``samples``); then per model
the map's architecture and multiply-adds per sample (classifier + regressor), its held-out exit-position
error, the neural flare's rate, the **paired** MAPE against the exact flare with the same samples (common
random numbers: the map's own error, the ``flare_edges.py`` protocol) and the **equal-time** MAPE against
the reference (the neural flare given the exact one's wall time: the number a user decides by).  Machine
noise: the rates of one run are comparable, not those of two.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _best_time(fr, seeds=(1, 2, 3)):
    import drjit as dr
    fr.render(seed=0)                                  # compile
    best, res = 1e30, None
    for s in seeds:
        t0 = time.perf_counter()
        res = fr.render(seed=s)
        dr.sync_thread()
        best = min(best, time.perf_counter() - t0)
    return best, res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("lens")
    ap.add_argument("--models", nargs="+", required=True, metavar="LABEL=FILE")
    ap.add_argument("--ghosts", help="comma list of ghost ids (default: those of the first model)")
    ap.add_argument("--samples", type=int, default=22, help="log2 forward samples of the timed renders")
    ap.add_argument("--reference", type=int, default=26, help="log2 samples of the independent exact reference")
    ap.add_argument("--scene", default=os.path.join(ROOT, "scenes", "night_point.xml"))
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    import mitsuba as mi
    sys.path.insert(0, ROOT)
    from mi_neurallens.render_utils import default_variant
    mi.set_variant(default_variant())
    from mi_neurallens.commands.render import load_scene
    from mi_neurallens.fileio import atomic_write_json
    from mi_neurallens.flare.render import FlareOptions, FlareRenderer
    from mi_neurallens.metrics import mape_masked
    from mi_neurallens.neural.mlp import mlp_cost
    from mi_neurallens.neural.model import load_model
    models = dict(m.split("=", 1) for m in a.models)
    loaded = {k: load_model(v) for k, v in models.items()}
    first = next(iter(loaded.values()))
    ghosts = [int(g) for g in a.ghosts.split(",")] if a.ghosts else list(first.ghost_ids)
    scene = load_scene(a.scene, variant=default_variant(), lens=a.lens, sensor_type="realistic_lens")
    n = 1 << a.samples
    rows = []
    for g in ghosts:
        ref = FlareRenderer(scene, 0, FlareOptions(mode="exact", ghosts=[g], samples=1 << a.reference)).render(seed=101).total
        t_ex, r_ex = _best_time(FlareRenderer(scene, 0, FlareOptions(mode="exact", ghosts=[g], samples=n)))
        ex_paired = FlareRenderer(scene, 0, FlareOptions(mode="exact", ghosts=[g], samples=n)).render(seed=1).total
        row = dict(ghost=g, exact=dict(seconds=t_ex, samples_per_s=n / t_ex, floor=float(mape_masked(r_ex.total, ref))),
                   models={})
        print(f"ghost {g}: exact {n / t_ex / 1e6:.2f} M samples/s, MAPE vs the 2^{a.reference} reference "
              f"{row['exact']['floor']:.4f}", flush=True)
        for label, path in models.items():
            tm = loaded[label].map(g, "forward")
            if tm is None:
                continue
            cost_r, act_r = mlp_cost(tm.regressor)
            cost_c, act_c = mlp_cost(tm.classifier)
            arch = (f"{len(tm.regressor) - 1}x{tm.regressor[0][1].shape[0]} + "
                    f"{len(tm.classifier) - 1}x{tm.classifier[0][1].shape[0]}")   # hidden layers x width
            opts = dict(mode="neural", ghosts=[g], model=path)
            t_ne, _ = _best_time(FlareRenderer(scene, 0, FlareOptions(samples=n, **opts)))
            paired = FlareRenderer(scene, 0, FlareOptions(samples=n, pilot_with="exact", **opts)).render(seed=1).total
            n_eq = max(int(n * t_ex / t_ne) // 256 * 256, 256)
            eq = FlareRenderer(scene, 0, FlareOptions(samples=n_eq, **opts)).render(seed=1).total
            reg, cls = (tm.metrics or {}).get("regressor", {}), (tm.metrics or {}).get("classifier", {})
            m = dict(architecture=arch, fma=cost_r + cost_c, activations=act_r + act_c,
                     position_um=reg.get("position_um_median"), position_p99_um=reg.get("position_um_p99"),
                     misclassification=cls.get("misclassification"),
                     seconds=t_ne, samples_per_s=n / t_ne, rate_vs_exact=t_ex / t_ne,
                     paired=float(mape_masked(paired, ex_paired)), equal_time_samples=n_eq,
                     equal_time=float(mape_masked(eq, ref)))
            row["models"][label] = m
            pos = "?" if m["position_um"] is None else f"{m['position_um']:.1f} um"
            print(f"  {label:>6} {arch:>15} {m['fma']:5d} FMA  held-out {pos}  {m['samples_per_s'] / 1e6:.2f} M/s "
                  f"({m['rate_vs_exact']:.2f}x exact)  paired {m['paired']:.4f}  equal time {m['equal_time']:.4f} "
                  f"({n_eq} samples; exact {row['exact']['floor']:.4f})", flush=True)
        rows.append(row)
    if a.json:
        atomic_write_json(a.json, dict(lens=a.lens, models={k: os.path.relpath(v, ROOT) for k, v in models.items()},
                                       log2_samples=a.samples, reference_log2_samples=a.reference,
                                       machine=platform.processor() or platform.machine(), rows=rows,
                                       command="python " + " ".join([os.path.relpath(__file__, ROOT)]
                                                                    + (argv or sys.argv[1:]))), indent=1)


if __name__ == "__main__":
    main()
