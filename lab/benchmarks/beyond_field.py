"""Lights just outside the field the ghost maps learned: the learned flare against the traced one.

    python benchmarks/beyond_field.py [--lenses a,b] [--beyond 3] [--samples 22] [--json OUT]

A forward ghost map learns the rays within the film's field × the training's ``field_margin`` (its domain's
``s_max``); beyond it the map answers "blocked".  For each lens (default: every bundled model) the night scene's
point light is put ``--beyond`` degrees outside that field (5 m away, along the film's diagonal) and the whole
default ghost selection is rendered ``exact`` and ``neural`` (same seed, 2^samples): their MAPE
(``metrics.mape_masked``), the flux ratio and how many ghosts the neural render traced because of the light.
Run it from another checkout (``PYTHONPATH=/tmp/old``) for the behaviour before ``FlareRenderer.beyond_field``.
"""
from __future__ import annotations

import argparse
import math
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LENSES = ("wide-22mm", "ood-59mm", "dgauss-50mm", "canon-ef-24mm-f1.4l", "canon-rf-24mm-f1.4l-vcm")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lenses", default=",".join(LENSES))
    ap.add_argument("--model", help="model file (one lens; default: the bundled model of each lens)")
    ap.add_argument("--beyond", type=float, default=3.0, help="degrees beyond the learned field")
    ap.add_argument("--samples", type=int, default=22, help="log2 samples of each render (all ghosts)")
    ap.add_argument("--json", help="write the rows here")
    a = ap.parse_args(argv)
    if ROOT not in sys.path:
        sys.path.append(ROOT)
    import mitsuba as mi
    from mi_neurallens.render_utils import default_variant
    mi.set_variant(default_variant())
    from mi_neurallens.commands.render import load_scene
    from mi_neurallens.flare.render import FlareOptions, FlareRenderer
    from mi_neurallens.metrics import LUMINANCE, mape_masked
    from mi_neurallens.flare.verify import learned_field_sine
    from mi_neurallens.neural.model import bundled_model_path, load_model
    rows = []
    for lens in a.lenses.split(","):
        model = a.model or bundled_model_path(lens)
        s_max = learned_field_sine(load_model(model))
        field = math.degrees(math.asin(s_max))
        theta = math.radians(field + a.beyond)
        r = 5.0 * math.tan(theta)                     # along the 3:2 film's diagonal
        x, y = r * 3 / math.hypot(3, 2), r * 2 / math.hypot(3, 2)
        scene = load_scene(os.path.join(ROOT, "scenes", "night_point.xml"), lens=lens, sensor_type="neural_lens",
                           sets=[f"model={model}"], params=[f"light_x={x}", f"light_y={y}"])
        imgs, traced = {}, 0
        for mode in ("exact", "neural"):
            fr = FlareRenderer(scene, 0, FlareOptions(mode=mode, samples=1 << a.samples))
            res = fr.render(seed=1)
            imgs[mode] = res.total
            if mode == "neural":
                traced = sum(1 for s in res.stats if getattr(s, "why_traced", None))
                n = len(res.stats)
        flux = [float((imgs[k][..., :3] @ LUMINANCE).sum()) for k in ("neural", "exact")]
        row = dict(lens=lens, field_deg=field, light_deg=math.degrees(theta), light_m=[x, y, 5.0],
                   ghosts=n, traced_beyond_field=traced, mape=float(mape_masked(imgs["neural"], imgs["exact"])),
                   flux_ratio=flux[0] / flux[1] if flux[1] > 0 else None, log2_samples=a.samples)
        rows.append(row)
        print(f"{lens}: learned field {field:.1f}°, light at {row['light_deg']:.1f}°: neural vs exact MAPE "
              f"{row['mape']:.4f}, flux {row['flux_ratio']:.4f}, {traced} of {n} ghosts traced beyond the field",
              flush=True)
    if a.json:
        from mi_neurallens.fileio import atomic_write_json
        atomic_write_json(a.json, {"command": " ".join(["benchmarks/beyond_field.py"] + (argv or sys.argv[1:])),
                                   "rows": rows}, indent=1)


if __name__ == "__main__":
    main()
