"""``mi-neurallens compare``: ground truth vs neural lens, side by side, with honest numbers.

Renders the scene three times with the same film, sampler type and integrator:

1. a converged ``realistic_lens`` **reference** (``--reference-spp``, its own seeds),
2. ``realistic_lens`` at ``--spp`` (exact tracer),
3. ``neural_lens`` at ``--spp`` (the lens's bundled or given model; same pupil sampling, so equal spp
   is equal work),

then writes into ``--out``: ``reference.exr``, ``realistic.exr``, ``neural.exr`` (+ PNGs), one
``compare.png`` (the three images and the relative-error maps of both against the reference) and
``compare.json`` / ``compare.md`` with MAPE and relMSE (definitions in :mod:`mi_neurallens.metrics`)
and render times of the two test renders (best of two, after a warm-up render of the same size
that compiles the kernels; the reference time includes compilation).
"""
from __future__ import annotations

import json
import os
import time

from ..render_utils import add_variant_argument


def add_parser(subparsers):
    p = subparsers.add_parser("compare", help="realistic_lens vs neural_lens side by side (PNG + MAPE table)",
                              description=__doc__.split("\n\n", 1)[1])
    p.add_argument("scene", help="Mitsuba XML scene using realistic_lens, or a bundled scene's name (e.g. still_life)")
    p.add_argument("--lens", help="lens (bundled name or file); default: the scene's")
    p.add_argument("--model", help="neural model file (default: the bundled model of the lens)")
    p.add_argument("--spp", type=int, default=64, help="samples per pixel of the two test renders (64)")
    p.add_argument("--reference-spp", type=int, default=1024, help="samples per pixel of the reference (1024)")
    p.add_argument("--resolution", help="film size WxH (default: the scene's)")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                   help="sensor property for all three renders (repeatable)")
    p.add_argument("-D", dest="params", action="append", default=[], metavar="NAME=VALUE",
                   help="XML parameter ($NAME) value (repeatable)")
    add_variant_argument(p)
    p.add_argument("--out", "-o", help="output folder (default: out/compare-<scene>)")
    p.add_argument("--exposure", type=float, default=0.0, help="PNG exposure in stops")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=run)
    return p


def _render(path, args, sensor_type, spp, seed, desc, extra_sets=(), warm_up=True):
    from .render import _resolution, load_scene, render_passes
    res = _resolution(args.resolution) if args.resolution else None
    scene = load_scene(path, variant=args.variant, sets=list(args.sets) + list(extra_sets), lens=args.lens,
                       resolution=res, spp=spp, params=args.params, sensor_type=sensor_type)
    # samplers round the count (ldsampler/multijitter: to a square power of two): report what ran
    spp = int(scene.sensors()[0].sampler().sample_count())
    passes = max(1, -(-spp // 64))
    import mitsuba as mi
    if not warm_up:
        img, secs = render_passes(scene, spp, passes, show_progress=not args.no_progress, seed=seed, desc=desc)
        return img, secs, str(scene.sensors()[0]), spp
    # compile (or load) the kernels with the same pass size, then time the best of two renders: the
    # first render of a freshly loaded scene after another one was measured up to 2x slower
    mi.render(scene, spp=-(-spp // passes), seed=seed)
    img, secs = render_passes(scene, spp, passes, show_progress=not args.no_progress, seed=seed, desc=desc)
    _, secs2 = render_passes(scene, spp, passes, show_progress=False, seed=seed, desc=desc)
    return img, min(secs, secs2), str(scene.sensors()[0]), spp


def compare_panel(images: dict, errors: dict, path: str, title: str, exposure: float = 0.0) -> None:
    """One PNG: the images in a row, the error maps below (shared colour scale), labels on each."""
    import matplotlib
    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    import numpy as np
    from ..render_utils import tonemap
    n = len(images)
    h, w = next(iter(images.values())).shape[:2]
    fig = Figure(figsize=(3.2 * n, 3.2 * n * 0 + 2 * 3.2 * h / w + 0.8), dpi=110)
    FigureCanvasAgg(fig)
    vmax = max(0.05, max(float(np.percentile(e, 99)) for e in errors.values()))
    for i, (name, img) in enumerate(images.items()):
        ax = fig.add_subplot(2, n, i + 1)
        ax.imshow(tonemap(img, exposure))
        ax.set_title(name, fontsize=9)
        ax.axis("off")
    last = None
    for i, (name, e) in enumerate(errors.items()):
        ax = fig.add_subplot(2, n, n + 2 + i)
        last = ax.imshow(e, cmap="inferno", vmin=0, vmax=vmax)
        ax.set_title(name, fontsize=9)
        ax.axis("off")
    if last is not None:
        cax = fig.add_axes([0.06, 0.08, 0.2, 0.025])
        cb = fig.colorbar(last, cax=cax, orientation="horizontal")
        cb.set_label("|a − ref| / (ref + 0.01)", fontsize=8)
        cb.ax.tick_params(labelsize=7)
    fig.suptitle(title, fontsize=10)
    fig.subplots_adjust(left=0.01, right=0.99, top=0.88, bottom=0.02, wspace=0.03, hspace=0.15)
    tmp = path + ".tmp.png"
    fig.savefig(tmp)
    os.replace(tmp, path)


def run(args) -> int:
    from ..metrics import EPSILON, error_map, mape, rel_mse
    from ..render_utils import write_exr, write_png
    from ..resources import scene_path
    scene = str(scene_path(args.scene))
    out = args.out or os.path.join("out", "compare-" + os.path.splitext(os.path.basename(scene))[0])
    os.makedirs(out, exist_ok=True)
    neural_sets = []
    if args.model:
        neural_sets.append(f"model={args.model}")
    elif args.lens:
        neural_sets.append(f"model={args.lens}")
    t_all = time.perf_counter()
    ref, t_ref, s_ref, ref_spp = _render(scene, args, "realistic_lens", args.reference_spp, 1000, "reference",
                                         warm_up=False)
    real, t_real, _, spp = _render(scene, args, "realistic_lens", args.spp, 0, "realistic")
    if not neural_sets:
        # the scene's lens names the bundled model
        import xml.etree.ElementTree as ET
        root = ET.parse(scene).getroot()
        el = root.find(".//sensor/string[@name='lens']")
        lens_name = el.get("value") if el is not None else "wide-22mm"
        if lens_name.startswith("$"):
            lens_name = dict(kv.split("=", 1) for kv in args.params).get(lens_name[1:], None) or \
                root.find(f".//default[@name='{lens_name[1:]}']").get("value")
        neural_sets.append(f"model={lens_name}")
    neural, t_neu, s_neu, _ = _render(scene, args, "neural_lens", args.spp, 0, "neural", neural_sets)
    for name, img in (("reference", ref), ("realistic", real), ("neural", neural)):
        write_exr(os.path.join(out, f"{name}.exr"), img)
        write_png(os.path.join(out, f"{name}.png"), img, args.exposure)
    rows = {
        "realistic": {"spp": spp, "seconds": t_real, "mape": mape(real, ref), "rel_mse": rel_mse(real, ref)},
        "neural": {"spp": spp, "seconds": t_neu, "mape": mape(neural, ref), "rel_mse": rel_mse(neural, ref)},
    }
    neural_vs_real = mape(neural, real)
    result = {"scene": scene, "reference": {"spp": ref_spp, "seconds": t_ref, "sensor": s_ref},
              "neural_sensor": s_neu, "epsilon": EPSILON, "rows": rows,
              "mape_neural_vs_realistic_same_spp": neural_vs_real,
              "ratio_mape_neural_over_realistic": rows["neural"]["mape"] / max(rows["realistic"]["mape"], 1e-12),
              "time_ratio_neural_over_realistic": t_neu / t_real}
    title = (f"{os.path.basename(scene)} — reference {ref_spp} spp; realistic and neural at {spp} spp\n"
             f"MAPE vs reference: realistic {rows['realistic']['mape']:.4f}, neural {rows['neural']['mape']:.4f}"
             f"   ·   time: realistic {t_real:.2f} s, neural {t_neu:.2f} s")
    compare_panel({f"reference ({ref_spp} spp)": ref, f"realistic_lens ({spp} spp)": real,
                   f"neural_lens ({spp} spp)": neural},
                  {"realistic error": error_map(real, ref), "neural error": error_map(neural, ref)},
                  os.path.join(out, "compare.png"), title, args.exposure)
    md = ["| render | spp | time (s) | MAPE vs reference | relMSE vs reference |", "|---|---|---|---|---|",
          f"| reference (realistic_lens) | {ref_spp} | {t_ref:.2f} | – | – |"]
    for k, r in rows.items():
        md.append(f"| {k}_lens | {r['spp']} | {r['seconds']:.2f} | {r['mape']:.4f} | {r['rel_mse']:.5f} |")
    md.append("")
    md.append(f"MAPE(neural, realistic) at equal spp: {neural_vs_real:.4f}; "
              f"MAPE ratio neural/realistic: {result['ratio_mape_neural_over_realistic']:.3f}; "
              f"time ratio neural/realistic: {result['time_ratio_neural_over_realistic']:.2f}")
    for fn, text in (("compare.json", json.dumps(result, indent=2)), ("compare.md", "\n".join(md) + "\n")):
        tmp = os.path.join(out, fn + ".tmp")
        with open(tmp, "w") as f:
            f.write(text)
        os.replace(tmp, os.path.join(out, fn))
    print("\n".join(md))
    print(f"wrote {out}/compare.png (+ EXR/PNG of each render, compare.json, compare.md) in "
          f"{time.perf_counter() - t_all:.1f} s")
    return 0
