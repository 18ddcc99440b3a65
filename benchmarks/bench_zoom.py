"""One learned camera map for a lens's whole zoom and focus range, measured at configurations the training never
drew: per focal length and focus distance, the map against the tracer on the same rays, and ``neural_lens`` against
``realistic_lens`` on the still life, at equal samples and in time.

    python benchmarks/bench_zoom.py [--lens canon-ef-24-70mm-f2.8l] [--model FILE] [--focal 24.9,35,45,60,68.14]
                                    [--focus inf,0.5] [--res 160x106] [--spp 64] [--reference-spp 1024]
                                    [--rays 400000] [--repeats 15] [--out out/bench/bench_zoom.json]
    python benchmarks/bench_zoom.py --lens canon-rf-24mm-f1.4l-vcm --focal none --focus inf,2,1,0.5,0.3,0.24 \
                                    --out out/bench/bench_focus.json        # a prime that focuses internally

Per configuration (the focal length, mm, solved to the zoom parameter; the focus distance, m, to the focus
parameter at the real rays' best focus, as the sensors do):

* **map accuracy**: ``--rays`` rays uniform over the map's ray domain at that configuration, traced in float64 by
  the tracer and evaluated by the map: the exit position (µm) and direction (arcsec) errors of the rays both call
  valid (median, p99), and the misclassified fraction;
* **render accuracy**: MAPE of ``neural_lens`` and of ``realistic_lens`` at ``--spp`` against a ``realistic_lens``
  reference at ``--reference-spp``, and their ratio (1: the learned map adds nothing to the noise);
* **render time**: each sensor at ``--spp``, best of ``--repeats``, the two sensors' renders taking turns (warm-up
  excluded, ``dr.sync_thread()``);
* **camera time**: the same sensors' camera rays alone (``sample_ray`` on the render's film samples, no scene), best
  of ``--repeats``, taking turns: the part of the render the lens is (a render also traces its kernel in Python).

Run it on an idle machine; it writes the JSON and prints a table.
"""
from __future__ import annotations

import argparse
import math
import os
import platform
import sys
import time

import numpy as np

from mi_neurallens.fileio import atomic_write_json
from mi_neurallens.render_utils import add_variant_argument, default_variant

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def map_accuracy(lens, tm, zoom: float, focus: float, n: int, seed: int) -> dict:
    """The map against the tracer at one configuration (zoom parameter, focus parameter): ``n`` rays uniform over
    the map's ray domain, float64."""
    from mi_neurallens.training.evaluate import map_outputs_np, regression_errors
    from mi_neurallens.transport.sampling import PathSampler
    dom = tm.domain
    rng = np.random.default_rng(seed)
    x = dom.u_to_x(rng.random((n, dom.dims)))
    x[:, 4:dom.dims] = dom.conditions.values(zoom, focus)
    x[:, dom.dims:] = dom.conditions.products_np(x)
    ps = PathSampler(lens, tm.path_id, tm.direction, tm.z_in, tm.z_out, dom, precision="float64")
    valid, y = ps.trace_x(x)
    logit, yp = map_outputs_np(tm, x)
    pv = logit > 0
    both = valid & pv
    r = regression_errors(yp[both, :5], y[both, :5], tm.heading)
    return {"rays": int(n), "valid_fraction": float(valid.mean()), "misclassification": float((pv != valid).mean()),
            "position_um_median": r["position_um_median"], "position_um_p99": r["position_um_p99"],
            "direction_arcsec_median": r["direction_arcsec_median"], "direction_arcsec_p99": r["direction_arcsec_p99"],
            "throughput_rel_median": r["throughput_rel_median"]}


def load(mi, kind, lens, focal, focus, res, spp, variant, model=None):
    from mi_neurallens.commands.render import load_scene
    from mi_neurallens.resources import scene_path
    sets = ([] if focal is None else [f"focal_length={focal}"]) + [f"focus_distance={focus}"] + \
        ([f"model={model or lens}"] if kind == "neural_lens" else [])
    return load_scene(str(scene_path("still_life")), variant=variant, lens=lens, resolution=res, spp=spp, sets=sets,
                      sensor_type=kind)


def render(mi, scene, spp, seed=0):
    import drjit as dr
    img = mi.render(scene, spp=spp, seed=seed)
    dr.sync_thread()
    return np.array(img)


def best_in_turns(scenes: dict, repeats, run) -> dict:
    """Best time (s) of ``run(scene, seed)`` for each scene of ``scenes`` over ``repeats`` (after one warm-up call
    each, which compiles), the scenes taking turns (one call each per round) so that a slow spell of a shared machine
    slows both sensors' runs, not one sensor's block.  ``run`` ends with ``dr.sync_thread()``."""
    import drjit as dr
    for scene in scenes.values():
        run(scene, 99)
    best = {k: math.inf for k in scenes}
    for k in range(repeats):
        for name, scene in scenes.items():
            dr.sync_thread()
            t0 = time.perf_counter()
            run(scene, 100 + k)
            best[name] = min(best[name], time.perf_counter() - t0)
    return best


def timed(mi, scenes: dict, spp, repeats) -> dict:
    """Best render time (s) of each scene of ``scenes`` at ``spp`` (:func:`best_in_turns`)."""
    return best_in_turns(scenes, repeats, lambda scene, seed: render(mi, scene, spp, seed=seed))


def camera_timed(mi, scenes: dict, spp, repeats) -> dict:
    """Best time (s) of each scene's sensor generating the camera rays of one render at ``spp`` (its film's pixels
    times ``spp``, the same uniform samples for every sensor) and nothing else (:func:`best_in_turns`)."""
    import drjit as dr

    def rays(scene, seed):
        sensor = scene.sensors()[0]
        w, h = (int(v) for v in sensor.film().crop_size())
        n = w * h * spp
        sampler = mi.load_dict({"type": "independent"})
        sampler.seed(seed, n)
        idx = dr.arange(mi.UInt32, n) // spp
        pos = mi.Vector2f(mi.Float(idx % w), mi.Float(idx // w))
        film = (pos + sampler.next_2d()) / mi.Vector2f(w, h)
        ray, weight = sensor.sample_ray(0.0, sampler.next_1d(), film, sampler.next_2d())
        dr.eval(ray, weight)
        dr.sync_thread()

    return best_in_turns(scenes, repeats, rays)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lens", default="canon-ef-24-70mm-f2.8l")
    ap.add_argument("--model", help="the model file to measure (default: the lens's bundled model)")
    ap.add_argument("--focal", default="24.9,35,45,60,68.14",
                    help="focal lengths, mm (a zoom lens), or none (a prime that focuses by moving groups)")
    ap.add_argument("--focus", default="inf,0.5", help="focus distances, m from the sensor")
    ap.add_argument("--res", default="160x106")
    ap.add_argument("--spp", type=int, default=64, help="a power of 4: the still life's ldsampler rounds up to one")
    ap.add_argument("--reference-spp", type=int, default=1024)
    ap.add_argument("--rays", type=int, default=400_000)
    ap.add_argument("--repeats", type=int, default=15,
                    help="renders timed per sensor, taking turns, the best kept (5, one sensor's after the other's, "
                         "left the time ratio spread over 0.94-1.31 on a shared 2-core machine)")
    ap.add_argument("--no-render", action="store_true", help="only the map's accuracy")
    ap.add_argument("--out", default=os.path.join(ROOT, "out", "bench", "bench_zoom.json"))
    add_variant_argument(ap)
    a = ap.parse_args(argv)
    import mitsuba as mi
    variant = a.variant or default_variant()
    mi.set_variant(variant)
    import mi_neurallens as nl
    nl.register()
    from mi_neurallens.metrics import mape
    from mi_neurallens.neural.model import bundled_model_path, load_model
    from mi_neurallens.optics import moving as mv
    lens = nl.Lens.load(a.lens)
    tm = load_model(a.model or bundled_model_path(a.lens), lens).map("transmit", "backward")
    res = tuple(int(v) for v in a.res.split("x"))
    rows, spp = [], {}
    focals = [None] if a.focal.lower() == "none" else [float(v) for v in a.focal.split(",")]
    for i, f in enumerate(focals):
        for j, d in enumerate(float(v) for v in a.focus.split(",")):
            _, zoom, fpar = mv.configure(lens, f, d * 1000.0)
            row = {"focal_length_mm": f, "focus_m": d, "zoom": zoom, "focus_parameter": fpar,
                   "map": map_accuracy(lens, tm, zoom, fpar, a.rays, 1000 + 10 * i + j)}
            if not a.no_render:
                rs = load(mi, "realistic_lens", a.lens, f, d, res, a.reference_spp, variant)
                spp["reference"] = rs.sensors()[0].sampler().sample_count()      # as the scene's sampler took it
                ref = render(mi, rs, spp["reference"], seed=7)
                sc = {k: load(mi, k, a.lens, f, d, res, a.spp, variant, a.model) for k in ("realistic_lens", "neural_lens")}
                spp["render"] = sc["neural_lens"].sensors()[0].sampler().sample_count()
                m = {k: mape(render(mi, s, spp["render"], seed=1), ref) for k, s in sc.items()}
                t = timed(mi, sc, spp["render"], a.repeats)
                c = camera_timed(mi, sc, spp["render"], a.repeats)
                row["render"] = {"mape_realistic": m["realistic_lens"], "mape_neural": m["neural_lens"],
                                 "mape_ratio": m["neural_lens"] / m["realistic_lens"],
                                 "seconds_realistic": t["realistic_lens"], "seconds_neural": t["neural_lens"],
                                 "time_ratio": t["neural_lens"] / t["realistic_lens"],
                                 "camera_seconds_realistic": c["realistic_lens"], "camera_seconds_neural": c["neural_lens"],
                                 "camera_time_ratio": c["neural_lens"] / c["realistic_lens"]}
            rows.append(row)
            mm, rr = row["map"], row.get("render", {})
            at = "" if f is None else f"{f:6.2f} mm, "
            print(f"{at}{d:g} m: pos {mm['position_um_median']:.3g}/{mm['position_um_p99']:.3g} µm, "
                  f"dir {mm['direction_arcsec_median']:.3g}/{mm['direction_arcsec_p99']:.3g}\", misclass "
                  f"{100 * mm['misclassification']:.3g}%"
                  + (f"; MAPE ratio {rr['mape_ratio']:.3f}, time ratio {rr['time_ratio']:.3f} (camera rays "
                     f"{rr['camera_time_ratio']:.3f})" if rr else ""),
                  flush=True)
    out = {"lens": a.lens, "variant": variant, "machine": f"{platform.processor() or platform.machine()}, "
           f"{os.cpu_count()} cores", "resolution": list(res), "spp": spp.get("render", a.spp),
           "reference_spp": spp.get("reference", a.reference_spp),
           "command": "python benchmarks/bench_zoom.py " + " ".join(argv if argv is not None else sys.argv[1:]),
           "rows": rows}
    atomic_write_json(a.out, out)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
