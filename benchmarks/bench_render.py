"""Render time of the still-life scene with Mitsuba's ``perspective`` and ``thinlens`` and our
``realistic_lens`` and ``neural_lens`` (when the lens has a bundled model) (same scene, resolution, spp, sampler; one process; warm-up excluded;
``dr.sync_thread()``), each lens sensor with every ``ray_kernel`` listed (the first untagged, the others as
``realistic_lens[separate]``: its camera rays in a kernel of their own), plus the camera-ray generation rate of each sensor alone.

    python benchmarks/bench_render.py [--res 320x240] [--spp 64] [--repeats 5] [--lens wide-22mm]
                                      [--ray-kernels inline,separate] [--pupil-table] [--furnace]

Prints a table and writes ``out/bench/bench_render.json``.  ``--pupil-table`` adds the
exit-pupil vs rear-element pass fractions of every bundled lens; ``--furnace`` adds the furnace
(uniform environment) values of ``wide-22mm`` (docs/realistic_lens.md quotes both).  The bar: realistic_lens within
1.5x of thinlens on the still life.
"""
from __future__ import annotations

import argparse
import math
import os
import platform
import sys
import time
import xml.etree.ElementTree as ET

from mi_neurallens.fileio import atomic_write_json
from mi_neurallens.neural.mlp import forced_style
from mi_neurallens.render_utils import add_variant_argument, default_variant
try:
    from mi_neurallens.resources import scene_path
except ImportError:     # a tree from before the scenes were package data (benchmarks/before_after.py runs old trees)
    def scene_path(name):
        import mi_neurallens
        return os.path.join(os.path.dirname(os.path.dirname(mi_neurallens.__file__)), "scenes", f"{name}.xml")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def sensor_xml(kind, setup, fov, d_front, aperture, focus_rel):
    if kind == "perspective":
        return f'<sensor type="perspective"><float name="fov" value="{fov}"/><string name="fov_axis" value="x"/></sensor>'
    return (f'<sensor type="thinlens"><float name="fov" value="{fov}"/><string name="fov_axis" value="x"/>'
            f'<float name="aperture_radius" value="{aperture}"/><float name="focus_distance" value="{focus_rel}"/>'
            '</sensor>')


def row_name(sensor: str, ray_kernel: str, args) -> str:
    """A lens sensor's row: untagged for the first ``--ray-kernels`` value, ``sensor[ray_kernel]`` for the others."""
    return sensor if ray_kernel == args.ray_kernels[0] else f"{sensor}[{ray_kernel}]"


def build_scenes(mi, args):
    from mi_neurallens.commands.render import load_scene
    from mi_neurallens.render_utils import apply_sensor_overrides
    path = str(scene_path("still_life"))
    w, h = args.res
    real = load_scene(path, variant=args.variant, lens=args.lens, resolution=(w, h), spp=args.spp,
                      sets=[f"ray_kernel={args.ray_kernels[0]}"])
    rl = real.sensors()[0]
    st = rl.setup
    px = st.lens.paraxial()
    # pinhole / thin lens at the front principal plane with the paraxial field of view and focus
    fov = 2 * math.degrees(math.atan(0.5 * st.sensor_width_mm / abs(px.image_height_per_tan())))
    d_front = (st.image_z - px.front_principal_z) / st.scene_unit_mm
    aperture = px.entrance_pupil_radius / st.scene_unit_mm
    focus_rel = st.focus_distance_mm / st.scene_unit_mm - d_front
    text = open(path, encoding="utf-8").read()
    text = apply_sensor_overrides(text, resolution=(w, h), spp=args.spp, lens=args.lens)
    out = {}
    from mi_neurallens.neural.model import bundled_model_path
    neural = args.model or os.path.exists(bundled_model_path(args.lens))
    for rk in args.ray_kernels:
        out[row_name("realistic_lens", rk, args)] = real if rk == args.ray_kernels[0] else load_scene(
            path, variant=args.variant, lens=args.lens, resolution=(w, h), spp=args.spp, sets=[f"ray_kernel={rk}"])
        if neural:
            out[row_name("neural_lens", rk, args)] = load_scene(path, variant=args.variant, lens=args.lens, resolution=(w, h),
                                                  spp=args.spp, sensor_type="neural_lens",
                                                  sets=[f"model={args.model or args.lens}", f"ray_kernel={rk}"])
    for kind in ("perspective", "thinlens"):
        root = ET.fromstring(text)
        old = root.find("sensor")
        new = ET.fromstring(sensor_xml(kind, st, fov, d_front, aperture, focus_rel))
        # same transform (moved forward to the front principal plane), film and sampler
        tw = old.find("transform")
        tw_new = ET.SubElement(new, "transform", {"name": "to_world"})
        ET.SubElement(tw_new, "translate", {"z": f"{d_front}"})
        for ch in tw:
            tw_new.append(ch)
        new.append(old.find("sampler"))
        new.append(old.find("film"))
        idx = list(root).index(old)
        root.remove(old)
        root.insert(idx, new)
        xml = ET.tostring(root, encoding="unicode")
        out[kind] = mi.load_string(xml)
    return out


def time_rays(mi, dr, sensor, n, repeats):
    """Camera-ray generation alone: sample_ray on n samples (stratified grid), rays/s."""
    import numpy as np
    rng = np.random.default_rng(0)
    s1, s2x, s2y, s3x, s3y = (mi.Float(rng.random(n).astype(np.float32)) for _ in range(5))
    ts = []
    for r in range(repeats + 1):
        t = time.perf_counter()
        ray, w = sensor.sample_ray(mi.Float(0.0) + 0 * s1, s1, mi.Point2f(s2x, s2y), mi.Point2f(s3x, s3y))
        dr.eval(ray.o, ray.d, w)
        dr.sync_thread()
        if r:
            ts.append(time.perf_counter() - t)
    return n / min(ts)


def kernel_times(mi, dr, scene, spp):
    """One more render with Dr.Jit's kernel history on: each kernel launched (size, operations, execution ms),
    in order: where a frame's time goes (the camera-ray kernel of ray_kernel=separate, the path tracer's)."""
    dr.kernel_history()                                  # drop what came before
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        img = mi.render(scene, spp=spp, seed=99)
        dr.eval(img)
        dr.sync_thread()
        hist = dr.kernel_history()
    return [{"size": int(k["size"]), "operations": int(k["operation_count"]),
             "execution_ms": float(k.get("execution_time", float("nan")))}
            for k in hist if k["type"] == dr.KernelType.JIT]


def pupil_table():
    import time as _t
    import mi_neurallens as nl
    from mi_neurallens.sensors.common import configure_lens
    from mi_neurallens.sensors.pupil import PupilBounds, measure_pass_fraction
    rows = []
    print("| lens | f-number | exit_pupil | rear_element | gain | bounds build (s) |")
    print("|---|---|---|---|---|---|")
    for name in ["wide-22mm", "dgauss-50mm", "canon-ef-24mm-f1.4l", "ood-59mm", "telephoto-250mm",
                 "fisheye-10mm"]:
        L = nl.Lens.load(name)
        for k in (1, 4):
            st = configure_lens(L, fstop=L.paraxial().fnumber * k, film_size=(3, 2))
            t = _t.perf_counter()
            ep = PupilBounds(st, "exit_pupil")
            tb = _t.perf_counter() - t
            re = PupilBounds(st, "rear_element")
            a, b = measure_pass_fraction(ep, 1 << 20), measure_pass_fraction(re, 1 << 20)
            print(f"| {name} | f/{st.fnumber:.3g} | {a:.3f} | {b:.4f} | {a / b:.1f}x | {tb:.2f} |")
            rows.append({"lens": name, "fnumber": st.fnumber, "exit_pupil": a, "rear_element": b,
                         "build_s": tb})
    return rows


def furnace_table(mi):
    import numpy as np
    rows = []
    print("| setting | variant | centre | mid-edge | corner |")
    print("|---|---|---|---|---|")
    for variant in (default_variant(), default_variant("spectral")):
        mi.set_variant(variant)
        import mi_neurallens
        mi_neurallens.register()
        for kw in (dict(fstop=8.0, fresnel=False), dict(fstop=8.0), dict(fresnel=False), dict()):
            sensor = {"type": "realistic_lens", "lens": "wide-22mm",
                      "film": {"type": "hdrfilm", "width": 64, "height": 48, "rfilter": {"type": "box"},
                               "pixel_format": "rgb"},
                      "sampler": {"type": "ldsampler", "sample_count": 1024}, **kw}
            img = np.array(mi.render(mi.load_dict({
                "type": "scene", "integrator": {"type": "path"}, "sensor": sensor,
                "env": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}}})), dtype=np.float64)
            c, e, k = img[23:25, 31:33].mean(), img[23:25, 0].mean(), img[0, 0].mean()
            print(f"| {kw} | {variant} | {c:.3f} | {e:.3f} | {k:.3f} |")
            rows.append({"setting": {k2: v for k2, v in kw.items()}, "variant": variant,
                         "centre": c, "mid_edge": e, "corner": k})
    return rows


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--res", default="320x240")
    p.add_argument("--spp", type=int, default=64)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--lens", default="wide-22mm")
    p.add_argument("--model", help="neural_lens model file (default: the bundled model of --lens)")
    add_variant_argument(p)
    p.add_argument("--ray-kernels", default="auto",
                   help="comma list of the lens sensors' ray_kernel values to time (auto, inline, separate); the "
                        "first is the plain rows ('realistic_lens'), the others tagged ('realistic_lens[separate]')")
    p.add_argument("--mlp-styles", default="",
                   help="comma list of evaluation styles of the learned maps (cpu, gpu: neural/mlp.py MLP_STYLES) to "
                        "time beside the backend's own, as rows neural_lens{style}")
    p.add_argument("--kernel-history", action="store_true",
                   help="record each sensor's kernels of one more frame (size, operations, execution ms)")
    p.add_argument("--pupil-table", action="store_true", help="also measure pupil-sampling pass fractions")
    p.add_argument("--furnace", action="store_true", help="also render the wide-22mm furnace table")
    p.add_argument("--out", default=os.path.join("out", "bench", "bench_render.json"))
    args = p.parse_args(argv)
    args.res = tuple(int(v) for v in args.res.lower().split("x"))
    args.ray_kernels = [k.strip() for k in args.ray_kernels.split(",") if k.strip()] or ["auto"]
    args.mlp_styles = [k.strip() for k in args.mlp_styles.split(",") if k.strip()]
    import drjit as dr
    import mitsuba as mi
    mi.set_variant(args.variant)
    import mi_neurallens
    mi_neurallens.register()
    scenes = build_scenes(mi, args)
    w, h = args.res
    n_rays = w * h * args.spp
    names = tuple(n for n in ("perspective", "thinlens") if n in scenes) + tuple(
        n for n in scenes if n not in ("perspective", "thinlens"))
    # rows: name -> (scene, evaluation style of the learned maps or None for the backend's own); --mlp-styles adds
    # each neural_lens scene again in the styles listed, tagged neural_lens{style}
    entries = {n: (n, None) for n in names}
    for style in args.mlp_styles:
        for n in names:
            if n.startswith("neural_lens"):
                entries[n.replace("neural_lens", f"neural_lens{{{style}}}", 1)] = (n, style)
    for name, (scene, style) in entries.items():         # warm-up: trace + compile, not timed
        with forced_style(style):
            mi.render(scenes[scene], spp=args.spp, seed=0)
            dr.sync_thread()
    times = {n: [] for n in entries}
    for r in range(args.repeats):                        # interleaved, so load changes hit all alike
        for name, (scene, style) in entries.items():
            with forced_style(style):
                t = time.perf_counter()
                img = mi.render(scenes[scene], spp=args.spp, seed=r + 1)
                dr.eval(img)
                dr.sync_thread()
                times[name].append(time.perf_counter() - t)
    rows = {}
    for name, (scene, style) in entries.items():
        best = min(times[name])
        with forced_style(style):
            # 2^20 rays are launch-bound on a GPU (an H200 read 461 M/s for a map that runs 1.9 G/s at 2^24)
            gen = time_rays(mi, dr, scenes[scene].sensors()[0], 1 << (24 if args.variant.startswith("cuda") else 20),
                            args.repeats)
            history = kernel_times(mi, dr, scenes[scene], args.spp) if args.kernel_history else None
        rows[name] = {"render_s": best, "render_all_s": times[name], "paths_per_s": n_rays / best,
                      "ray_generation_per_s": gen}
        if history is not None:
            rows[name]["kernels"] = history
    base = rows["thinlens"]["render_s"]
    for r in rows.values():
        r["ratio_vs_thinlens"] = r["render_s"] / base
    print(f"still_life {w}x{h}, {args.spp} spp ({n_rays / 1e6:.2f} M camera rays), {args.variant}, "
          f"lens {args.lens}, best of {args.repeats} interleaved runs after warm-up, {dr.thread_count()} threads")
    print(f"{'sensor':26s} {'render s':>9s} {'x thinlens':>10s} {'Mpaths/s':>9s} {'Mrays/s (sensor only)':>22s}")
    for name, r in rows.items():
        print(f"{name:26s} {r['render_s']:9.3f} {r['ratio_vs_thinlens']:10.2f} {r['paths_per_s'] / 1e6:9.2f} "
              f"{r['ray_generation_per_s'] / 1e6:22.1f}")
        if "kernels" in r:
            ks = r["kernels"]
            print(f"{'':26s} {len(ks)} kernels, {sum(k['execution_ms'] for k in ks):.1f} ms: "
                  + ", ".join(f"{k['size']}x{k['operations']} ops {k['execution_ms']:.1f} ms" for k in ks))
    best = {}
    for name, r in rows.items():            # each sensor's fastest ray_kernel: what a user would pick
        kind = name.split("[")[0]
        if kind in ("realistic_lens", "neural_lens") and r["render_s"] < best.get(kind, (math.inf,))[0]:
            best[kind] = (r["render_s"], name)
    if len(best) == 2:
        for rk in args.ray_kernels:
            n, r = rows[row_name("neural_lens", rk, args)], rows[row_name("realistic_lens", rk, args)]
            print(f"neural_lens / realistic_lens, ray_kernel={rk}: {n['render_s'] / r['render_s']:.3f}")
            for style in args.mlp_styles:
                ns = rows[row_name("neural_lens", rk, args).replace("neural_lens", f"neural_lens{{{style}}}", 1)]
                print(f"neural_lens{{{style}}} / realistic_lens, ray_kernel={rk}: {ns['render_s'] / r['render_s']:.3f}")
        print(f"fastest of each: {best['neural_lens'][1]} / {best['realistic_lens'][1]} = "
              f"{best['neural_lens'][0] / best['realistic_lens'][0]:.3f}")
    ok = rows["realistic_lens"]["ratio_vs_thinlens"] <= 1.5
    print(f"bar (realistic_lens <= 1.5x thinlens): {'met' if ok else 'NOT met'}")
    res = {"benchmark": "bench_render", "scene": "still_life", "resolution": [w, h], "spp": args.spp,
           "variant": args.variant, "lens": args.lens, "model": args.model or "bundled", "repeats": args.repeats,
           "threads": dr.thread_count(),
           "machine": {"platform": platform.platform(), "processor": platform.processor(),
                       "cpus": os.cpu_count(), "python": sys.version.split()[0],
                       "mitsuba": mi.__version__, "drjit": dr.__version__},
           "command": "python benchmarks/bench_render.py " + " ".join(argv if argv is not None else sys.argv[1:]),
           "ray_kernels": args.ray_kernels, "mlp_styles": args.mlp_styles, "fastest": {k: v[1] for k, v in best.items()},
           "results": rows, "bar_met": ok}
    if args.pupil_table:
        res["pupil_pass_fractions"] = pupil_table()
    if args.furnace:
        res["furnace_wide22"] = furnace_table(mi)
    atomic_write_json(args.out, res, indent=2)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
