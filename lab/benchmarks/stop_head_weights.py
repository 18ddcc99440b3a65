"""How a stop head's loss weighs its crossing columns: the same heads trained with each rule, side by side.

    python benchmarks/stop_head_weights.py LENS KEY[,KEY...] [--modes uniform,goals,square] [--lm-minutes 1.5]
                                           [--json OUT]

For each rule the maps ``KEY`` of the bundled model get new stop heads, trained as one stack with the lens's
own stop settings (its recipe's ``[stop]`` / ``[forward_stop]``, or the defaults) and ``--lm-minutes`` of the
finish, then measured on 200 000 held-out valid rays (the seed ``--keep both`` uses), beside the shipped head.
Rules: ``uniform`` (every standardised column alike), ``goals`` (∝ the column's spread, the default:
``mi_neurallens.training.stop_head.stop_loss_weights``), ``square`` (∝ spread², the squared error in mm).
Error per ray: the largest over its crossings (µm); goal median ≤ 2, p99 ≤ 20.  Nothing is written to the model.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("lens")
    ap.add_argument("keys", help="comma-separated map keys, e.g. forward.278528,forward.67174400")
    ap.add_argument("--modes", default="uniform,goals,square")
    ap.add_argument("--lm-minutes", type=float, default=1.5)
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    sys.path.insert(0, ROOT)
    import mitsuba as mi
    from mi_neurallens.render_utils import default_variant
    mi.set_variant(default_variant())
    from mi_neurallens.neural.model import bundled_model_path, load_model
    from mi_neurallens.optics.formats import load_lens
    from mi_neurallens.training import maps, stop_head
    from mi_neurallens.training.config import load_config
    from mi_neurallens.training.evaluate import heldout_valid, stop_errors

    lens = load_lens(a.lens)
    model = load_model(bundled_model_path(a.lens), lens)
    cfg = load_config(None, lens=lens.name)
    keys = a.keys.split(",")
    tms = [model.maps[k] for k in keys]
    rule = stop_head.stop_loss_weights

    def weights(mode, oscale):          # "square" is measured here only; the package has uniform and goals
        if mode == "square":
            w = np.asarray(oscale, np.float64) ** 2
            return np.maximum(w / w.mean(), 1e-3)
        return rule(mode, oscale)

    stop_head.stop_loss_weights = weights
    rows = []
    for mode in a.modes.split(","):
        nc = dataclasses.replace(cfg.net("stop", tms[0].direction), loss_weights=mode, lm_minutes=a.lm_minutes)
        seeds = [maps.map_seed(cfg, tm.path_id, tm.direction) + 17 for tm in tms]
        t0 = time.perf_counter()
        heads = stop_head.train_stop_heads(lens, tms, nc, seeds=seeds, progress=False)
        wall = time.perf_counter() - t0
        for tm, h, s in zip(tms, heads, seeds):
            x, y = heldout_valid(lens, (tm.path_id, tm.direction, tm.z_in, tm.z_out), tm.domain, 200_000,
                                 s - 17 + 101, cfg.mcmc_threshold, cfg.fresnel, stops=True)
            e = stop_errors(dataclasses.replace(tm, stop_head=h).eval_reduced_np(x)[1][:, 5:], y[:, 5:])
            e0 = stop_errors(tm.eval_reduced_np(x)[1][:, 5:], y[:, 5:])
            lm = h.training.get("lm", {})
            rows.append({"mode": mode, "map": tm.key, "crossings": h.crossings, "median_um": e["stop_um_median"],
                         "p99_um": e["stop_um_p99"], "shipped_median_um": e0["stop_um_median"],
                         "shipped_p99_um": e0["stop_um_p99"], "finish_iterations": lm.get("iterations"),
                         "finish_seconds": lm.get("seconds"), "finish_stop": lm.get("stop_reason"),
                         "stack_wall_s": wall})
            print(f"{mode:8s} {tm.key:22s} {e['stop_um_median']:6.2f} / {e['stop_um_p99']:6.1f} µm   shipped "
                  f"{e0['stop_um_median']:6.2f} / {e0['stop_um_p99']:6.1f}   finish {lm.get('iterations')} it, "
                  f"{lm.get('seconds', 0):.0f} s, {lm.get('stop_reason')}   stack {wall:.0f} s", flush=True)
    if a.json:
        from mi_neurallens.fileio import atomic_write_json
        atomic_write_json(a.json, {"lens": a.lens, "lm_minutes": a.lm_minutes, "rows": rows})


if __name__ == "__main__":
    main()
