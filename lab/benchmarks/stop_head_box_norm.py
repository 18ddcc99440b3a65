"""A stop head trained on its map's input normalisation against one trained on its valid rays' bounding box.

    python benchmarks/stop_head_box_norm.py [--lens canon-ef-24mm-f1.4l] [--key forward.278528]
                                            [--modes map,box] [--lm-minutes 3] [--size 3x16] [--json OUT]

A learned map normalises its inputs (r, ωx, ωy, λ) over its whole sampled domain, so that its classifier sees
every ray; a ghost's valid rays may fill only a corner of it (the Canon EF's ghost 278528: ωy in the lowest
quarter, ωx in 60 %), and the stop head, which only ever sees valid rays, then has to resolve its function inside
a small part of its inputs' range.  ``box`` trains the head with ``input_box = true``
(:func:`~mi_neurallens.training.input_box.input_box`: the bounding box of its first pool, 2 % margin, λ as the
map's), folded back into its first layer and skip (:func:`~mi_neurallens.training.input_box.fold_input_box`), so
the head computes the same function of the map's own normalised inputs: the model file, the render kernel and
the head's cost are unchanged.  ``map`` is the head as ``train`` makes it by default.  Both with the lens's stop
settings, the given size and minutes of the Levenberg–Marquardt finish, the same seed; the held-out crossing
errors (µm, 200 000 rays, float64 tracer) beside the bundled head's.  One mode at a time, the machine otherwise
idle: the finish is bounded by wall time.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def run(lens_name: str, key: str, mode: str, lm_minutes: float, size: str, seed: int = 12345) -> dict:
    from mi_neurallens.neural.model import NeuralLensModel
    from mi_neurallens.optics.formats import load_lens
    from mi_neurallens.training.config import default_config_path, load_config
    from mi_neurallens.training.evaluate import heldout_valid, map_outputs_np, stop_errors
    from mi_neurallens.training.stop_head import train_stop_heads
    hidden, width = (int(v) for v in size.split("x"))
    model = NeuralLensModel.load(os.path.join(ROOT, "lenses", "models", f"{lens_name}.model.safetensors"))
    tm = model.maps[key]
    lens = load_lens(lens_name)
    cfg = load_config(default_config_path(lens_name), lens_name,
                      {"forward_stop": {"lm_minutes": lm_minutes, "hidden": hidden, "width": width, "lm_iterations": 0,
                                        "input_box": mode == "box"}})
    nc = cfg.net("stop", tm.direction)
    t0 = time.perf_counter()
    head = train_stop_heads(lens, [dataclasses.replace(tm, stop_head=None)], nc, seeds=[seed], fresnel=cfg.fresnel,
                            mcmc_threshold=cfg.mcmc_threshold, progress=False)[0]
    seconds = time.perf_counter() - t0
    x, y = heldout_valid(lens, (tm.path_id, tm.direction, tm.z_in, tm.z_out), tm.domain, 200_000, 1000, stops=True)
    _, yp = map_outputs_np(dataclasses.replace(tm, stop_head=head), x)
    _, yb = map_outputs_np(tm, x)
    lm = head.training.get("lm", {})
    return {"lens": lens_name, "key": key, "mode": mode, "size": size, "lm_minutes": lm_minutes, "seed": seed,
            "train_seconds": round(seconds, 1), "lm_iterations": lm.get("iterations"),
            "lm_stop": lm.get("stop_reason"), "input_box": head.training.get("input_box"),
            "heldout": stop_errors(yp[:, 5:], y[:, 5:]), "bundled": stop_errors(yb[:, 5:], y[:, 5:])}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lens", default="canon-ef-24mm-f1.4l")
    ap.add_argument("--key", default="forward.278528")
    ap.add_argument("--modes", default="map,box")
    ap.add_argument("--lm-minutes", type=float, default=3.0)
    ap.add_argument("--size", default="3x16", help="hidden layers x width of the head")
    ap.add_argument("--json", help="write the rows here")
    a = ap.parse_args(argv)
    import mitsuba as mi
    from mi_neurallens.render_utils import default_variant
    mi.set_variant(default_variant())
    rows = []
    for mode in a.modes.split(","):
        r = run(a.lens, a.key, mode, a.lm_minutes, a.size)
        rows.append(r)
        h, b = r["heldout"], r["bundled"]
        print(f"{a.key} {mode:4s} {a.size} {a.lm_minutes:g} min: {h['stop_um_median']:.2f} / {h['stop_um_p99']:.1f} µm "
              f"(bundled {b['stop_um_median']:.2f} / {b['stop_um_p99']:.1f}), {r['lm_iterations']} iterations, "
              f"{r['lm_stop']}", flush=True)
    if a.json:
        from mi_neurallens.fileio import atomic_write_json
        atomic_write_json(a.json, {"benchmark": "stop_head_box_norm", "machine": platform.processor() or platform.machine(),
                                   "cpus": os.cpu_count(), "command": " ".join(["python"] + sys.argv), "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
