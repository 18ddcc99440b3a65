"""The aperture at render time: neural vs exact images from the widest aperture to 8× its f-number.

For every bundled scene, each of the paper's three lenses and f-numbers k × N_widest (k = 1, 2, 4, 8),
renders a converged ``realistic_lens`` reference (``--reference-spp``, its own seed), then
``realistic_lens`` and ``neural_lens`` at ``--spp`` with the same seed, and reports

* MAPE(neural, reference) / MAPE(realistic, reference) — goal ≤ 1.1 (equal spp is equal work: the
  pupil bounds follow the aperture for both sensors);
* MAPE(neural, realistic), same seeds — goal ≤ 0.02.

    python benchmarks/aperture.py [--res 96x72] [--spp 64] [--reference-spp 1024]
                                  [--lenses wide-22mm,...] [--scenes still_life,...] [--mults 1,2,4,8]

Prints a Markdown table and writes ``benchmarks/results/aperture.json``.  The neural models must have
stop heads (``mi-neurallens train LENS --paths backward-transmit --keep both``); scenes whose focus is
closer than a model supports are rendered at its closest focus (``bokeh``: 0.35 m, or farther where the
model needs it).

``--bokeh``: the blur disc of a point light through 5, 6 and 9 blades instead (issue 16's bokeh goal: the
masks of the disc, above 10 % of its mean, neural vs exact, IoU ≥ 0.98), each lens focused near and the film
cropped to the disc (:func:`bokeh_pair`), at 2×, 4× and 8× unless ``--mults`` says otherwise; writes
``…/aperture_bokeh.json``.  ``--speed``: the camera-ray rate of both sensors at each f-number instead.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
from mi_neurallens.constants import LAMBDA_D  # noqa: E402
from mi_neurallens.render_utils import BOKEH_LIGHT_M, add_variant_argument  # noqa: E402

LENSES = ("wide-22mm", "ood-59mm", "canon-ef-24mm-f1.4l")
SCENES = ("still_life", "chart", "bokeh", "night")
#: XML parameters per scene: for night.xml a modest flare budget, planned by the tracer in both sensors
#: (``pilot_with=exact``) so that the flare, like the camera rays, uses the same samples in the neural
#: and the realistic render and MAPE(neural, realistic) is the maps' error, not the pilots' noise
#: (bokeh's focus: see closest_focus_m)
PARAMS = {"night": ["flare_samples=1000000", "pilot_with=exact"]}


def closest_focus_m(lens: str, want_m: float = 0.35) -> float:
    """``want_m``, or the closest focus (m from the sensor plane) the lens's bundled model supports if
    that is farther (then 2 % beyond it): bokeh.xml focuses at 0.2 m, nearer than any model was trained."""
    from mi_neurallens.neural.model import bundled_model_path, load_model
    from mi_neurallens.optics.prescription import Lens
    from mi_neurallens.sensors.common import focus_for_sensor_distance
    L = Lens.load(lens)
    s_max = float(load_model(bundled_model_path(lens), L).sensor_distance_range[1])
    near = focus_for_sensor_distance(L, s_max) / 1000.0
    return want_m if near < want_m else 1.02 * near


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--res", default="96x72")
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--reference-spp", type=int, default=1024)
    ap.add_argument("--lenses", default=",".join(LENSES))
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--mults", default=None, help="multiples of the widest f-number (default 1,2,4,8; --bokeh: 2,4,8)")
    add_variant_argument(ap)
    ap.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "aperture.json"))
    ap.add_argument("--bokeh", action="store_true",
                    help="only the blur disc of a point light through 5, 6 and 9 blades: mask IoU, neural vs exact "
                         "(default mults 2,4,8)")
    ap.add_argument("--bokeh-spp", type=int, default=4096, help="--bokeh: samples per pixel (160x160 film)")
    ap.add_argument("--speed", action="store_true",
                    help="only the cost of the iris: camera rays/s of both sensors at each f-number (idle machine)")
    args = ap.parse_args(argv)
    if args.bokeh:
        return bokeh(args)
    args.mults = args.mults or "1,2,4,8"
    if args.speed:
        return speed(args)
    import mitsuba as mi
    import numpy as np
    from mi_neurallens.commands.render import load_scene
    from mi_neurallens.fileio import atomic_write_json
    from mi_neurallens.metrics import mape
    from mi_neurallens.optics.prescription import Lens
    w, h = (int(v) for v in args.res.lower().split("x"))
    rows = []

    def render(path, lens, kind, fstop, spp, seed, params):
        sets = [f"fstop={fstop!r}"] + ([f"model={lens}"] if kind == "neural_lens" else [])
        scene = load_scene(path, variant=args.variant, sets=sets, lens=lens, resolution=(w, h), spp=spp,
                           params=params, sensor_type=kind)
        t = time.perf_counter()
        img = np.array(mi.render(scene, seed=seed), dtype=np.float64)
        return img, time.perf_counter() - t

    for lens in args.lenses.split(","):
        n0 = Lens.load(lens).paraxial(LAMBDA_D).fnumber
        for name in args.scenes.split(","):
            path = os.path.join(ROOT, "scenes", f"{name}.xml")
            params = PARAMS.get(name, []) + ([f"focus={closest_focus_m(lens):.4g}"] if name == "bokeh" else [])
            for k in (float(v) for v in args.mults.split(",")):
                N = k * n0
                ref, t_ref = render(path, lens, "realistic_lens", N, args.reference_spp, 1000, params)
                real, t_real = render(path, lens, "realistic_lens", N, args.spp, 1, params)
                neur, t_neur = render(path, lens, "neural_lens", N, args.spp, 1, params)
                m_r, m_n = mape(real, ref), mape(neur, ref)
                row = {"lens": lens, "scene": name, "mult": k, "fstop": N, "mape_realistic": m_r,
                       "mape_neural": m_n, "ratio": m_n / m_r, "mape_neural_vs_realistic": mape(neur, real),
                       "seconds_realistic": t_real, "seconds_neural": t_neur}
                rows.append(row)
                print(f"{lens:20s} {name:12s} {k:g}x f/{N:5.2f}: MAPE real {m_r:.4f} neural {m_n:.4f} "
                      f"ratio {m_n / m_r:.3f}  neural-vs-real {row['mape_neural_vs_realistic']:.4f}", flush=True)
    print("\n| lens | scene | f-number | MAPE realistic | MAPE neural | ratio | MAPE(neural, realistic) |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['lens']} | {r['scene']} | {r['mult']:g}× (f/{r['fstop']:.2f}) | {r['mape_realistic']:.4f} | "
              f"{r['mape_neural']:.4f} | {r['ratio']:.3f} | {r['mape_neural_vs_realistic']:.4f} |")
    ok = [r["ratio"] <= 1.1 and r["mape_neural_vs_realistic"] <= 0.02 for r in rows]
    print(f"\ngoals met in {sum(ok)} of {len(ok)} configurations")
    atomic_write_json(args.out, {"machine": platform.processor() or platform.machine(), "argv": sys.argv[1:],
                                 "res": [w, h], "spp": args.spp, "reference_spp": args.reference_spp, "rows": rows})
    return 0




def bokeh_disc_mm(lens, fstop: float, focus_m: float, light_m: float = BOKEH_LIGHT_M) -> float:
    """Paraxial diameter (mm, on the sensor) of the blur disc of a point ``light_m`` away with the lens focused at
    ``focus_m`` (both from the sensor plane, treated as object distances: an estimate that sizes the film)."""
    f = lens.efl()
    s_f, s_p = 1000.0 * focus_m, 1000.0 * light_m
    return (f / fstop) * f / (s_f - f) * abs(s_p - s_f) / s_p


def bokeh_pair(mi, lens_name: str, fstop: float, blades: int, focus_m: float, spp: int = 4096, res: int = 160,
               seed: int = 7, model: str | None = None):
    """The blur disc of the on-axis point light of :func:`~mi_neurallens.render_utils.bokeh_scene`, ``realistic_lens`` and ``neural_lens``
    (``model``, default the lens's bundled one) with the same seed, the film (``res``², box filter) cropped to 2.5× the paraxial disc
    (:func:`bokeh_disc_mm`).  Returns ``(exact, neural, iou)``: H×W×3 images and the IoU of the masks of the disc
    (pixels above 10 % of the mean of the non-zero ones, green channel).  Raises where a sensor refuses the iris
    (blades near wide open)."""
    import numpy as np
    from mi_neurallens.optics.prescription import Lens
    sys.path.insert(0, os.path.join(ROOT, "tests"))
    from bokeh import bokeh_scene, disc_mask, mask_iou
    width_mm = 2.5 * bokeh_disc_mm(Lens.load(lens_name), fstop, focus_m)
    pair = []
    for kind in ("realistic_lens", "neural_lens"):
        scene = mi.load_dict(bokeh_scene(kind, lens_name, fstop, blades, focus_m, width_mm, res, spp, model=model))
        pair.append(np.array(mi.render(scene, seed=seed), dtype=np.float64))
    return pair[0], pair[1], mask_iou(disc_mask(pair[0]), disc_mask(pair[1]))


def bokeh(args):
    """Mask IoU of the blur disc, neural vs exact, per lens × f-number × blade count (:func:`bokeh_pair`)."""
    import mitsuba as mi
    from mi_neurallens.fileio import atomic_write_json
    from mi_neurallens.optics.prescription import Lens
    import mi_neurallens
    mi.set_variant(args.variant)
    mi_neurallens.register()
    mults = args.mults or "2,4,8"     # 6 blades at the widest f-number are refused (docs/neural_lens.md)
    rows = []
    for lens in args.lenses.split(","):
        n0 = Lens.load(lens).paraxial(LAMBDA_D).fnumber
        focus = closest_focus_m(lens)
        for k in (float(v) for v in mults.split(",")):
            for blades in (5, 6, 9):
                t = time.perf_counter()
                try:
                    _, _, iou = bokeh_pair(mi, lens, k * n0, blades, focus, spp=args.bokeh_spp)
                except Exception as e:   # blades near wide open (docs/neural_lens.md): n/a
                    print(f"  {lens} {k:g}x {blades} blades: n/a ({str(e).splitlines()[-1][:160]})")
                    iou = None
                rows.append({"lens": lens, "mult": k, "fstop": k * n0, "blades": blades, "focus_m": focus,
                             "iou": iou, "seconds": time.perf_counter() - t})
                if iou is not None:
                    print(f"{lens:20s} {k:g}x f/{k * n0:5.2f} {blades} blades: mask IoU {iou:.4f}", flush=True)
    print("\n| lens | f-number | 5 blades | 6 blades | 9 blades |\n|---|---|---|---|---|")
    for i in range(0, len(rows), 3):
        r = rows[i]
        cells = " | ".join("n/a" if x["iou"] is None else f"{x['iou']:.4f}" for x in rows[i:i + 3])
        print(f"| {r['lens']} | {r['mult']:g}× (f/{r['fstop']:.2f}) | {cells} |")
    ok = [r["iou"] >= 0.98 for r in rows if r["iou"] is not None]
    print(f"\nIoU >= 0.98 in {sum(ok)} of {len(ok)}")
    out = os.path.splitext(args.out)[0] + "_bokeh.json"
    atomic_write_json(out, {"machine": platform.processor() or platform.machine(), "argv": sys.argv[1:],
                            "spp": args.bokeh_spp, "res": 160, "light_m": BOKEH_LIGHT_M, "rows": rows})
    return 0


def speed(args, n: int = 1 << 20, repeats: int = 5):
    """Camera-ray generation (``sample_ray`` on ``n`` rays, best of ``repeats``) of ``realistic_lens`` and
    ``neural_lens`` at each f-number, round and with 6 blades: what the stop head and the iris test cost
    (the neural map skips both at the trained aperture)."""
    import drjit as dr
    import mitsuba as mi
    from mi_neurallens.optics.prescription import Lens
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from bench_render import time_rays
    import mi_neurallens
    mi.set_variant(args.variant)
    mi_neurallens.register()
    rows = []
    for lens in args.lenses.split(","):
        n0 = Lens.load(lens).paraxial(LAMBDA_D).fnumber
        for k in (float(v) for v in args.mults.split(",")):
            for blades in (0, 6):
                rate = {}
                for kind in ("realistic_lens", "neural_lens"):
                    d = {"type": kind, "lens": lens, "fstop": k * n0, "blades": blades,
                         "film": {"type": "hdrfilm", "width": 320, "height": 240}}
                    if kind == "neural_lens":
                        d["model"] = lens
                    try:
                        sensor = mi.load_dict(d)
                    except Exception as e:   # e.g. blades near wide open (docs/neural_lens.md): n/a
                        rate[kind] = None
                        print(f"  {lens} {k:g}x blades={blades} {kind}: n/a ({str(e).splitlines()[-1][:160]})")
                        continue
                    rate[kind] = time_rays(mi, dr, sensor, n, repeats)
                rows.append({"lens": lens, "mult": k, "blades": blades, "rays_per_s": rate})
                fmt = {kk: "n/a" if v is None else f"{v / 1e6:6.2f} M rays/s" for kk, v in rate.items()}
                print(f"{lens:20s} {k:g}x blades={blades}: realistic {fmt['realistic_lens']}, "
                      f"neural {fmt['neural_lens']}", flush=True)
    out = os.path.splitext(args.out)[0] + "_speed.json"
    from mi_neurallens.fileio import atomic_write_json
    atomic_write_json(out, {"machine": platform.processor() or platform.machine(), "n": n, "repeats": repeats,
                            "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
