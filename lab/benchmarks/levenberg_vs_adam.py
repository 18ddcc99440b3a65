"""Adam alone against Adam + the Levenberg–Marquardt finish: the same ghost networks, the same wall time.

    python benchmarks/levenberg_vs_adam.py [--lens canon-ef-24mm-f1.4l] [--ghosts 12,320,1056,96]
                                           [--minutes 1.5] [--lm-share 0.67] [--kinds regressor,classifier]
                                           [--json OUT]

For each ghost of the lens's bundled model (its planes and input domain, film reach included), the
recipe's forward network (the Canon's: 3×16 regressor, 2×16 margin classifier) is trained from the same
random weights and the same tracer streams twice, one variant after the other on the idle machine:

* ``adam``: the stacked Adam trainer for ``minutes`` per map (all ghosts in one stack, K × minutes);
* ``adam+lm``: Adam for (1 − lm_share) × minutes per map, then each map's Levenberg–Marquardt finish
  for lm_share × minutes (``lm_minutes``; mi_neurallens/training/levenberg.py).

Goals off (equal time, not first-to-goal), the best weights by validation kept as in training.  Per map:
the validation's exit-position and direction errors (median, p99; the 20 k-ray validation set of
training) or misclassification (400 k rays uniform over the domain), at the end and as a curve over the
map's own seconds (a stack's Adam seconds divided among its maps), and the first second at which the
regressor met the flare goals at 2 K (3 / 30 µm, 30 / 200″) — the time-to-goal a training run pays.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def problems(lens, model, ghosts, kind, cfg):
    """The trainer's problem dicts of the ghosts ``ghosts`` on the bundled maps' planes and domains."""
    from mi_neurallens.training.data import Domain, PathSampler, RegressorStream
    from mi_neurallens.training.maps import classifier_problem, map_seed, regressor_problem
    out = []
    for pid in ghosts:
        tm = model.maps[f"forward.{pid}"]
        spec = (pid, "forward", tm.z_in, tm.z_out, Domain.from_dict(tm.domain))
        seed = map_seed(cfg, pid, "forward")
        ps = PathSampler(lens, *spec, fresnel=cfg.fresnel)
        stream = RegressorStream(ps, seed, cfg.mcmc_threshold)
        if kind == "regressor":
            out.append(regressor_problem(lens, spec, stream, seed, f"forward.{pid}", cfg))
        else:
            out.append(classifier_problem(lens, spec, ps, stream, seed, f"forward.{pid}", cfg))
    return out


def curve(state, k):
    """[(map seconds, record)] of one map's validations: Adam's stack seconds / K, then its own LM time."""
    out, adam_end = [], None
    for rec in state["history"]:
        if rec.get("phase") == "lm":
            if adam_end is None:
                adam_end = rec["seconds"]
            t = adam_end / k + (rec["seconds"] - adam_end)
        else:
            t = rec["seconds"] / k
        out.append((t, rec))
    return out


def summarise(kind, res, k, goals):
    rows = []
    for r in res:
        c = curve(r["state"], k)
        if kind == "regressor":
            best = min(c, key=lambda tr: tr[1]["val_mse"])[1]
            met = [t for t, rec in c if rec["pos_um_med"] <= goals[0][0] and rec["pos_um_p99"] <= goals[0][1]
                   and rec["dir_as_med"] <= goals[1][0] and rec["dir_as_p99"] <= goals[1][1]]
            rows.append({"pos_um_med": best["pos_um_med"], "pos_um_p99": best["pos_um_p99"],
                         "dir_as_med": best["dir_as_med"], "dir_as_p99": best["dir_as_p99"],
                         "seconds": c[-1][0], "first_met_goals_s": met[0] if met else None,
                         "lm": r["state"].get("lm"),
                         "curve": [(round(t, 2), rec["pos_um_med"]) for t, rec in c]})
        else:
            best = min(c, key=lambda tr: tr[1]["val_misclass"] + 0.01 * tr[1]["val_bce"])[1]
            rows.append({"misclass": best["val_misclass"], "seconds": c[-1][0], "lm": r["state"].get("lm"),
                         "curve": [(round(t, 2), rec["val_misclass"]) for t, rec in c]})
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lens", default="canon-ef-24mm-f1.4l")
    ap.add_argument("--ghosts", default="12,320,1056,96")
    ap.add_argument("--minutes", type=float, default=1.5, help="wall time per map and network, both variants")
    ap.add_argument("--lm-share", type=float, default=2.0 / 3.0, help="the finish's share of it in adam+lm")
    ap.add_argument("--kinds", default="regressor,classifier")
    ap.add_argument("--json", default=os.path.join(ROOT, "benchmarks", "results", "levenberg", "adam_vs_lm.json"))
    a = ap.parse_args(argv)
    import mitsuba as mi
    from mi_neurallens.render_utils import default_variant
    mi.set_variant(default_variant())
    from mi_neurallens import Lens
    from mi_neurallens.fileio import atomic_write_json
    from mi_neurallens.neural.model import bundled_model_path, load_model
    from mi_neurallens.training import classifier, regressor
    from mi_neurallens.training.config import default_config_path, load_config
    lens = Lens.load(a.lens)
    model = load_model(bundled_model_path(a.lens), lens)
    cfg = load_config(default_config_path(a.lens), lens=a.lens)
    ghosts = [int(g) for g in a.ghosts.split(",")]
    doc = {"lens": a.lens, "ghosts": ghosts, "minutes_per_map": a.minutes, "lm_share": a.lm_share,
           "machine": platform.processor() or platform.machine(), "cpus": os.cpu_count(), "kinds": {}}
    for kind in a.kinds.split(","):
        base = cfg.net(kind, "forward")
        goals = (base.goal_position_um, base.goal_direction_arcsec)
        fn = regressor.train_regressors if kind == "regressor" else classifier.train_classifiers
        doc["kinds"][kind] = {"network": f"{base.hidden}x{base.width}", "goals": goals, "variants": {}}
        for name, adam_min, lm_min in (("adam", a.minutes, 0.0),
                                        ("adam+lm", a.minutes * (1 - a.lm_share), a.minutes * a.lm_share)):
            nc = dataclasses.replace(base, max_minutes=adam_min, lm_minutes=lm_min, stop_at_goals=False,
                                     patience=10 ** 9, max_steps=10 ** 9)
            probs = problems(lens, model, ghosts, kind, cfg)
            t0 = time.perf_counter()
            res = fn(probs, nc, progress=False)
            wall = time.perf_counter() - t0
            rows = summarise(kind, res, len(ghosts), goals)
            doc["kinds"][kind]["variants"][name] = {"adam_minutes": adam_min, "lm_minutes": lm_min,
                                                    "wall_seconds": wall, "maps": dict(zip(map(str, ghosts), rows))}
            for g, r in zip(ghosts, rows):
                if kind == "regressor":
                    print(f"{kind} {name:8s} ghost {g}: {r['pos_um_med']:.2f} / {r['pos_um_p99']:.1f} µm, "
                          f"{r['dir_as_med']:.1f} / {r['dir_as_p99']:.0f}\", goals first met at "
                          f"{r['first_met_goals_s']} s", flush=True)
                else:
                    print(f"{kind} {name:8s} ghost {g}: misclassification {100 * r['misclass']:.3f} %", flush=True)
            os.makedirs(os.path.dirname(a.json), exist_ok=True)
            atomic_write_json(a.json, doc)
    print(f"wrote {a.json}")


if __name__ == "__main__":
    main()
