"""Regenerate the pictures of docs/neural_lens.md, docs/flares.md and docs/baselines.md (renders, a few minutes each).

    python docs/make_figures.py [--spp 64] [--reference-spp 1024] [--quick]

1. The paper's path-tracing figure: the still life through each of the three paper lenses, converged
   ``realistic_lens`` reference vs ``realistic_lens`` and ``neural_lens`` at equal spp
   (``mi-neurallens compare``), → docs/images/compare_wide-22mm.jpg (the others stay in out/figures/<lens>/) and
   out/figures/compare.json.
2. The classifier ablation (``use_classifier=false``) → docs/images/neural_ablation_classifier.jpg.
3. Manual focusing with one model: ood-59mm at three sensor distances, exact vs neural
   → docs/images/neural_focus_sweep.jpg.
4. ``--methods``: the depth-of-field render of every transport method (exact, neural, ABCD, Taylor 3/5,
   fitted polynomials) → docs/images/methods_dof_wide-22mm.jpg and out/figures/methods.json.
5. ``--night``: the bundled night scene with its flare, ``realistic_lens`` (exact ghosts) beside ``neural_lens``
   (learned ghosts), the ghosts the model has maps for → docs/images/flare_night_<lens>.jpg and
   out/figures/night.json.
6. ``--aperture``: one wide-22mm model at the render-time aperture: the still life from the widest
   aperture to f/16, and a defocused point light through 5, 6 and 9 blades, exact above neural
   → docs/images/aperture_still_life.jpg, docs/images/aperture_bokeh.png, out/figures/aperture.json.
7. ``--bladed``: single wide-22mm ghosts through 6 blades at 4× the widest f-number, exact beside the learned
   ghost with its iris learned and with the iris's edge traced (``iris_band``), same samples, with their error
   maps → docs/images/flare_bladed_iris_band.png and out/figures/bladed.json.
8. ``--coatings``: the flare of one point light through ood-59mm (real glasses) with bare surfaces, one MgF2
   layer and the broadband stack on every surface, at one exposure and each at its own
   → docs/images/flare_coatings.jpg and out/figures/coatings.json.
9. ``--starburst``: the bundled night scene's flare (its lights' starbursts and ghosts) through wide-22mm and
   ood-59mm at 1.3x the widest f-number (round iris) and at f/11 with 5, 6 and 9 blades, exact ghosts above learned
   → docs/images/flare_starburst_<lens>.jpg and out/figures/starburst.json.
10. ``--zoom``: the still life through canon-ef-24-70mm-f2.8l at four focal lengths, exact above learned, and a
    focus pull through the learned map → docs/images/zoom_canon-ef-24-70.jpg.
11. ``--focus-pull``: a focus pull through the internally focused canon-rf-24mm-f1.4l-vcm, exact above learned
    → docs/images/focus_pull_canon-rf-24mm.jpg.
12. ``--zoom-flare``: the night scene's flare through canon-ef-24-70mm-f2.8l at four focal lengths, its ghosts
    traced → docs/images/flare_zoom_canon-ef-24-70.jpg.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys

import numpy as np

from mi_neurallens.resources import scene_path

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
IMG = os.path.join(ROOT, "docs", "images")
OUT = os.path.join(ROOT, "out", "figures")
LENSES = ("wide-22mm", "ood-59mm", "canon-ef-24mm-f1.4l")
#: the lens whose side-by-side comparison is the docs' picture (README.md, docs/neural_lens.md)
FIGURE_LENS = "wide-22mm"


def compare_all(spp, ref_spp, res):
    rows = {}
    for lens in LENSES:
        out = os.path.join(OUT, lens)
        cmd = [sys.executable, "-m", "mi_neurallens", "compare", "still_life", "--lens", lens,
               "--spp", str(spp), "--reference-spp", str(ref_spp), "--resolution", res, "--out", out,
               "--no-progress"]
        print(" ".join(cmd[1:]), flush=True)
        subprocess.run(cmd, cwd=ROOT, check=True)
        if lens == FIGURE_LENS:
            save_jpeg(os.path.join(out, "compare.png"), os.path.join(IMG, f"compare_{lens}.jpg"))
        rows[lens] = json.load(open(os.path.join(out, "compare.json")))
    with open(os.path.join(OUT, "compare.json"), "w") as f:
        json.dump(rows, f, indent=2)
    print("| lens | spp | MAPE realistic | MAPE neural | ratio | MAPE(neural, realistic) | time realistic (s) | time neural (s) |")
    print("|---|---|---|---|---|---|---|---|")
    for lens, r in rows.items():
        a, b = r["rows"]["realistic"], r["rows"]["neural"]
        print(f"| {lens} | {a['spp']} | {a['mape']:.4f} | {b['mape']:.4f} | {r['ratio_mape_neural_over_realistic']:.3f} | "
              f"{r['mape_neural_vs_realistic_same_spp']:.4f} | {a['seconds']:.2f} | {b['seconds']:.2f} |")
    return rows


def save_jpeg(src, dst, quality=88):
    """``src`` (any image PIL reads) as a JPEG at ``dst`` (renders and photos: a tenth of a PNG's bytes)."""
    from PIL import Image
    im = Image.open(src)
    if im.mode != "RGB":
        im = im.convert("RGBA")
        bg = Image.new("RGB", im.size, (255, 255, 255))
        bg.paste(im, mask=im.split()[3])
        im = bg
    im.save(dst + ".tmp.jpg", "JPEG", quality=quality, optimize=True, progressive=True)
    os.replace(dst + ".tmp.jpg", dst)


def grid(images, titles, path, suptitle, cols):
    import matplotlib
    matplotlib.use("Agg", force=False)
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from mi_neurallens.render_utils import tonemap
    rows = -(-len(images) // cols)
    h, w = images[0].shape[:2]
    fig = Figure(figsize=(3.3 * cols, 3.3 * rows * h / w + 0.6), dpi=110)
    FigureCanvasAgg(fig)
    for i, (img, t) in enumerate(zip(images, titles)):
        ax = fig.add_subplot(rows, cols, i + 1)
        ax.imshow(tonemap(img))
        ax.set_title(t, fontsize=8)
        ax.axis("off")
    import textwrap
    fig.suptitle(textwrap.fill(suptitle, 50 * cols), fontsize=9)     # long titles wrap instead of clipping
    fig.subplots_adjust(left=0.01, right=0.99, top=0.86, bottom=0.01, wspace=0.03, hspace=0.18)
    fig.savefig(path + ".tmp.png")
    if path.endswith(".jpg"):
        save_jpeg(path + ".tmp.png", path)
        os.remove(path + ".tmp.png")
    else:
        os.replace(path + ".tmp.png", path)


def render(sensor_type, lens, spp, res, sets=()):
    from mi_neurallens.commands.render import load_scene, render_passes
    w, h = (int(v) for v in res.split("x"))
    extra = [f"model={lens}"] if sensor_type == "neural_lens" else []
    scene = load_scene(str(scene_path("still_life")), variant="llvm_ad_rgb", lens=lens,
                       resolution=(w, h), spp=spp, sets=list(sets) + extra, sensor_type=sensor_type)
    img, _ = render_passes(scene, spp, max(1, spp // 64), show_progress=False)
    return img


def ablation(spp, res):
    from mi_neurallens.metrics import mape
    real = render("realistic_lens", "wide-22mm", spp * 4, res)
    a = render("neural_lens", "wide-22mm", spp, res)
    b = render("neural_lens", "wide-22mm", spp, res, ["use_classifier=false"])
    grid([real, a, b], [f"realistic_lens ({spp * 4} spp)", f"neural_lens ({spp} spp), MAPE {mape(a, real):.3f}",
                        f"neural_lens without classifier, MAPE {mape(b, real):.3f}"],
         os.path.join(IMG, "neural_ablation_classifier.jpg"),
         "wide-22mm: without the classifier every ray inside the trained domain passes (brighter corners, "
         f"mean {b.mean() / a.mean():.2f}x)", 3)
    return {"mape_with": mape(a, real), "mape_without": mape(b, real), "brightness_ratio": float(b.mean() / a.mean())}


def focus_sweep(spp, res):
    from mi_neurallens import Lens
    from mi_neurallens.metrics import mape
    from mi_neurallens.sensors.common import focus_for_sensor_distance
    lens = Lens.load("ood-59mm")
    imgs, titles, out = [], [], []
    dists = (38.5, 40.0, 42.0)
    for kind in ("realistic_lens", "neural_lens"):
        for s in dists:
            imgs.append(render(kind, "ood-59mm", spp, res, [f"sensor_distance={s}"]))
            fd = focus_for_sensor_distance(lens, s)
            titles.append(f"{kind}, sensor {s} mm (focus {fd / 1000:.2f} m)")
    for i, s in enumerate(dists):
        out.append({"sensor_distance_mm": s, "mape_neural_vs_exact": mape(imgs[3 + i], imgs[i])})
    grid(imgs, titles, os.path.join(IMG, "neural_focus_sweep.jpg"),
         "ood-59mm, manual focusing by moving the sensor: one neural model serves every sensor distance", 3)
    return out


def methods(spp, res, lens="wide-22mm"):
    """Depth-of-field render (the still life) with each transport method behind ``neural_lens``."""
    from mi_neurallens.metrics import mape
    ref = render("realistic_lens", lens, 1024, res)
    imgs, titles, rows = [ref], ["realistic_lens, 1024 spp (reference)"], {}
    for m in ("exact", "neural", "fitted", "taylor5", "taylor3", "abcd"):
        img = render("neural_lens", lens, spp, res, [f"method={m}"])
        rows[m] = mape(img, ref)
        imgs.append(img)
        titles.append(f"method={m}, {spp} spp, MAPE {rows[m]:.3f}")
    grid(imgs[:1] + imgs[1:], titles, os.path.join(IMG, f"methods_dof_{lens}.jpg"),
         f"{lens}: camera-ray transport by each method (same planes, pupil sampling and seeds)", 4)
    print("| method | MAPE vs reference |\n|---|---|")
    for m, v in rows.items():
        print(f"| {m} | {v:.4f} |")
    return rows


def night(spp, lens="ood-59mm", res="480x320", flare_samples=1 << 24):
    """The night scene through ``realistic_lens`` (exact ghosts) and ``neural_lens`` (learned ghosts),
    each planning its own flare sampling as a user's render does; the same ghosts (those with maps) and
    seeds.  Top row: the renders; bottom row: their flare images alone (same exposure).  Times: best of two
    renders after a first one that compiles one kernel per light and ghost.  MAPE: the ghosts alone
    (without the lights' direct images), two independent renders of ``flare_samples`` per light."""
    import time
    from mi_neurallens.commands.render import load_scene, render_passes
    from mi_neurallens.metrics import mape_masked
    from mi_neurallens.neural.model import bundled_model_path, load_model
    ghosts = " ".join(str(g) for g in load_model(bundled_model_path(lens)).ghost_ids)
    w, h = (int(v) for v in res.split("x"))
    from mi_neurallens.flare.render import render_flare
    imgs, flares, secs, ghost_only = {}, {}, {}, {}
    for st, mode in (("realistic_lens", "exact"), ("neural_lens", "neural")):
        scene = load_scene(str(scene_path("night")), variant="llvm_ad_rgb", lens=lens,
                           resolution=(w, h), spp=spp, sensor_type=st,
                           sets=[f"model={lens}"] if st == "neural_lens" else [],
                           params=[f"mode={mode}", f"ghosts={ghosts}", f"flare_samples={flare_samples}",
                                   "diffraction=false"])
        render_passes(scene, spp, max(1, spp // 64), show_progress=False)          # compile
        secs[st] = 1e9
        for _ in range(2):                                                        # best of two
            t0 = time.perf_counter()
            imgs[st], _ = render_passes(scene, spp, max(1, spp // 64), show_progress=False)
            secs[st] = min(secs[st], time.perf_counter() - t0)
        flares[st] = np.asarray(scene.integrator().last_result.total)
        # the ghosts alone (without the lights' own, far brighter images) for the MAPE
        ghost_only[st] = render_flare(scene, mode=mode, ghosts=[int(g) for g in ghosts.split()], diffraction=False,
                                      samples=flare_samples).total
    out = {"lens": lens, "spp": spp, "resolution": res, "flare_samples_per_light": flare_samples,
           "ghosts": ghosts.split(), "seconds_best_of_two": secs,
           "ghost_mape_neural_vs_exact": mape_masked(ghost_only["neural_lens"], ghost_only["realistic_lens"])}
    k = 1.0 / max(float(np.percentile(flares["realistic_lens"], 99.5)), 1e-12)
    grid([imgs["realistic_lens"], imgs["neural_lens"], flares["realistic_lens"] * k, flares["neural_lens"] * k],
         [f"realistic_lens + exact ghosts ({secs['realistic_lens']:.1f} s)",
          f"neural_lens + learned ghosts ({secs['neural_lens']:.1f} s)",
          "flare alone, exact",
          f"flare alone, learned (ghosts: MAPE {out['ghost_mape_neural_vs_exact']:.3f} vs exact)"],
         os.path.join(IMG, f"flare_night_{lens}.jpg"),
         f"night scene, {lens}, {spp} spp, the {len(out['ghosts'])} ghosts with learned maps, "
         f"{flare_samples / 2**20:.0f} M flare samples per light", 2)
    return out


def aperture(spp, res, lens="wide-22mm"):
    """The still life from the widest aperture to f/16 and the bokeh of a point light with 5, 6 and 9
    blades, ``realistic_lens`` (top row) above ``neural_lens`` (bottom row), same seeds."""
    import mitsuba as mi
    from mi_neurallens import Lens
    from mi_neurallens.metrics import mape
    n0 = Lens.load(lens).paraxial().fnumber
    stops = (n0, 4.0, 8.0, 16.0)
    imgs, titles, out = [[], []], [[], []], {"still_life": [], "bokeh": []}
    for N in stops:
        ex = render("realistic_lens", lens, spp, res, [f"fstop={N!r}"])
        nn = render("neural_lens", lens, spp, res, [f"fstop={N!r}"])
        m = mape(nn, ex)
        out["still_life"].append({"fstop": N, "mape_neural_vs_realistic": m})
        imgs[0].append(ex), imgs[1].append(nn)
        titles[0].append(f"realistic_lens f/{N:.3g}")
        titles[1].append(f"neural_lens f/{N:.3g}, MAPE vs exact {m:.4f}")
    grid(imgs[0] + imgs[1], titles[0] + titles[1], os.path.join(IMG, "aperture_still_life.jpg"),
         f"{lens}: one model from f/{n0:.3g} to f/16 (the map was learned wide open; the iris is tested on its "
         f"predicted stop crossing), {spp} spp, same seeds", 4)
    N = 4.0 * n0
    imgs, titles = [[], []], [[], []]
    for blades in (5, 6, 9):
        ex, nn, iou = bokeh_pair(mi, lens, N, blades, 0.35)
        for row, img in enumerate((ex, nn)):
            imgs[row].append(img / img.max() * 1.5)
        out["bokeh"].append({"blades": blades, "fstop": N, "iou": iou})
        titles[0].append(f"realistic_lens, {blades} blades, f/{N:.3g}")
        titles[1].append(f"neural_lens, {blades} blades: mask IoU {iou:.4f}")
    grid(imgs[0] + imgs[1], titles[0] + titles[1], os.path.join(IMG, "aperture_bokeh.png"),
         f"{lens}: a point light 4 m away, focused at 0.35 m (film cropped to the blur disc)", 3)
    return out


def bokeh_pair(mi, lens_name, fstop, blades, focus_m, spp=4096, res=160, seed=7):
    """The blur disc of an on-axis point light (tests/bokeh.py's scene), ``realistic_lens`` and ``neural_lens`` with
    the same seed, the film cropped to 2.5x the paraxial disc: ``(exact, neural, mask IoU)``."""
    from mi_neurallens.optics.prescription import Lens
    sys.path.insert(0, os.path.join(ROOT, "tests"))
    from bokeh import BOKEH_LIGHT_M, bokeh_scene, disc_mask, mask_iou
    lens = Lens.load(lens_name)
    f = lens.efl()
    s_f, s_p = 1000.0 * focus_m, 1000.0 * BOKEH_LIGHT_M
    width_mm = 2.5 * (f / fstop) * f / (s_f - f) * abs(s_p - s_f) / s_p
    pair = [np.array(mi.render(mi.load_dict(bokeh_scene(kind, lens_name, fstop, blades, focus_m, width_mm, res, spp)),
                               seed=seed), dtype=np.float64) for kind in ("realistic_lens", "neural_lens")]
    return pair[0], pair[1], mask_iou(disc_mask(pair[0]), disc_mask(pair[1]))


def bladed(lens="wide-22mm", fstop=10.74, ghosts=(66048, 144, 4224), samples=1 << 24):
    """Each of ``ghosts`` alone through 6 blades at ``fstop``: exact, learned with the iris tested on its predicted
    crossings, and learned with the iris's edge traced (``iris_band`` 1), on the same samples (paired), cropped to
    the ghost, with the relative error of each learned one (×10, where the exact ghost is above 1 % of its peak)."""
    from mi_neurallens.commands.render import load_scene
    from mi_neurallens.flare.verify import paired_renders
    from mi_neurallens.metrics import flare_error_map
    import mitsuba as mi
    scene = load_scene(str(scene_path("night_point")), variant=mi.variant(), lens=lens,
                       sensor_type="neural_lens", sets=[f"model={lens}", f"fstop={fstop!r}", "blades=6"])
    imgs, titles, out = [], [], []
    for g in ghosts:
        ex, learned, _ = paired_renders(scene, [g], samples, iris_band=0.0)
        banded = paired_renders(scene, [g], samples, iris_band=1.0).learned
        y = ex[..., 1]
        rows, cols = np.nonzero(y > 0.01 * y.max())
        pad = 4
        r0, r1 = max(rows.min() - pad, 0), min(rows.max() + pad + 1, y.shape[0])
        c0, c1 = max(cols.min() - pad, 0), min(cols.max() + pad + 1, y.shape[1])
        crop = lambda a: np.asarray(a)[r0:r1, c0:c1, :3]
        scale = 1.5 / max(float(crop(ex).max()), 1e-30)
        row = {"ghost": g}
        panels = [(crop(ex) * scale, f"ghost {g}: exact")]
        for name, img in (("iris learned", learned), ("iris edge traced", banded)):
            rel, mask = flare_error_map(img, ex)
            err = float(rel[mask].mean())
            row[name] = err
            e = np.where(mask, rel, 0.0)[r0:r1, c0:c1]
            panels += [(crop(img) * scale, f"{name}: paired MAPE {err:.4f}"),
                       (np.repeat(np.clip(10 * e, 0, 1)[..., None], 3, axis=2), f"{name}: error ×10")]
        out.append(row)
        for img, t in panels:
            imgs.append(img)
            titles.append(t)
    # one panel size: pad every crop to the largest
    H = max(i.shape[0] for i in imgs)
    W = max(i.shape[1] for i in imgs)
    imgs = [np.pad(i, ((0, H - i.shape[0]), (0, W - i.shape[1]), (0, 0))) for i in imgs]
    grid(imgs, titles, os.path.join(IMG, "flare_bladed_iris_band.png"),
         f"{lens} at f/{fstop:g} (4x its widest f-number), 6 blades: single ghosts, exact and learned on the same "
         f"2^{int(np.log2(samples))} samples (240x160 full-frame film, crops); the learned iris is tested on the stop "
         f"head's predicted crossings, and with iris_band 1 the samples within 3x its p99 error of the iris's edge are "
         f"traced", 5)
    return out


def starburst(lens, samples=1 << 22, res=(480, 320)):
    """The night scene's flare alone (ghosts and the lights' starbursts), exact and learned, at four apertures."""
    import time
    from mi_neurallens import Lens
    from mi_neurallens.commands.render import load_scene
    from mi_neurallens.constants import LAMBDA_D
    from mi_neurallens.flare.render import render_flare
    import mitsuba as mi
    n0 = Lens.load(lens).paraxial(LAMBDA_D).fnumber
    settings = [(1.3 * n0, 0), (11.0, 5), (11.0, 6), (11.0, 9)]
    imgs, titles, out = [], [], {}
    for st, mode in (("realistic_lens", "exact"), ("neural_lens", "neural")):
        for fstop, blades in settings:
            sets = [f"fstop={fstop!r}", f"blades={blades}"] + ([f"model={lens}"] if st == "neural_lens" else [])
            scene = load_scene(str(scene_path("night")), variant=mi.variant(), lens=lens, resolution=res,
                               sensor_type=st, sets=sets)
            mode_here = "exact" if mode == "exact" else "auto"   # auto traces a ghost the model cannot render
            t0 = time.perf_counter()
            r = render_flare(scene, mode=mode_here, samples=samples, seed=5)
            secs = time.perf_counter() - t0
            imgs.append(np.asarray(r.total)[..., :3])
            what = "round iris" if blades == 0 else f"{blades} blades"
            titles.append(f"{'exact' if mode == 'exact' else 'learned'}, f/{fstop:.3g}, {what}")
            out[f"{mode} f/{fstop:.3g} {blades}"] = {"seconds": secs,
                                                     "starburst_share": float(r.diffraction.sum() / r.total.sum())}
    k = 1.0 / max(float(np.percentile(imgs[0], 99.7)), 1e-12)
    grid([im * k for im in imgs], titles, os.path.join(IMG, f"flare_starburst_{lens}.jpg"),
         f"night scene, {lens}: its lights' diffraction starbursts and ghosts ({samples / 2**20:.0f} M samples per "
         f"light), exact ghosts (top) and learned ones (bottom: mode auto, a ghost without a map for this iris is "
         f"traced); one exposure",
         4)
    return out


def coatings(lens="ood-59mm", samples=1 << 22, res=(360, 240)):
    """The exact flare (ghosts only, the automatic selection) of the bundled point-light scene with each coating
    of ``lens_flare``: the top row at the bare lens's exposure (how much each coating removes), the bottom row
    each at its own (the ghosts' colours: the coatings reflect some wavelengths more than others)."""
    from mi_neurallens.commands.render import load_scene
    from mi_neurallens.flare.render import render_flare
    import mitsuba as mi
    scene = load_scene(str(scene_path("night_point")), variant=mi.variant(), lens=lens, resolution=res)
    names = {"none": "bare", "quarter_wave": "one MgF2 layer", "broadband": "broadband (QHQ)"}
    imgs, out = {}, {}
    for c in names:
        r = render_flare(scene, mode="exact", coating=c, samples=samples, seed=3, diffraction=False)
        imgs[c] = np.asarray(r.total)[..., :3]
        y = imgs[c].mean(axis=2)
        out[c] = {"flux": float(y.sum()), "rgb": [float(v) for v in imgs[c].reshape(-1, 3).sum(0)]}
    k0 = 1.0 / max(float(np.percentile(imgs["none"], 99.9)), 1e-12)
    top = [imgs[c] * k0 for c in names]
    bottom = [imgs[c] / max(float(np.percentile(imgs[c], 99.9)), 1e-12) for c in names]
    titles = [f"{t}: {out[c]['flux'] / out['none']['flux']:.3f}x bare flux" for c, t in names.items()]
    titles += [f"{t}, own exposure" for t in names.values()]
    grid(top + bottom, titles, os.path.join(IMG, "flare_coatings.jpg"),
         f"{lens}, one point light, exact ghosts (automatic selection), {samples / 2**20:.0f} M samples; one MgF2 "
         f"layer: lambda/4 at 550 nm; broadband: Al2O3 lambda/4, ZrO2 lambda/2, MgF2 lambda/4 at 550 nm; top: one "
         f"exposure, bottom: each at its own", 3)
    return out


def zoom(spp, res, lens="canon-ef-24-70mm-f2.8l"):
    """The still life through the zoom lens at four focal lengths (focused at 1.5 m), exact (realistic_lens) above
    learned (neural_lens: the one map of the whole range), the learned renders' MAPE against the exact ones; and a
    focus pull at 68.14 mm from infinity to the close focus through the learned map, with each configuration's
    focal length: the breathing."""
    from mi_neurallens import Lens
    from mi_neurallens.metrics import mape
    from mi_neurallens.optics import moving as mv
    base = Lens.load(lens)
    exact, learned, pull, titles_e, titles_l, titles_p, out = [], [], [], [], [], [], {"zoom": [], "focus_pull": []}
    for f in (24.9, 35.0, 50.0, 68.14):
        sets = [f"focal_length={f}", "focus_distance=1.5"]
        e = render("realistic_lens", lens, spp, res, sets)
        n = render("neural_lens", lens, spp, res, sets)
        exact.append(e)
        learned.append(n)
        titles_e.append(f"realistic_lens, {f:g} mm")
        titles_l.append(f"neural_lens, {f:g} mm (MAPE {mape(n, e):.3f})")
        out["zoom"].append({"focal_length_mm": f, "mape_neural_vs_exact": mape(n, e)})
    for d in (math.inf, 2.0, 1.0, 0.38):
        pull.append(render("neural_lens", lens, spp, res, ["focal_length=68.14", f"focus_distance={d}"]))
        L, t, fp = mv.configure(base, 68.14, d * 1000.0)
        titles_p.append(f"neural_lens, 68.14 mm at {'∞' if math.isinf(d) else format(d, 'g') + ' m'} "
                        f"(EFL {L.efl():.1f} mm)")
        out["focus_pull"].append({"focus_m": d, "efl_mm": L.efl(), "focus_parameter": fp})
    grid(exact + learned + pull, titles_e + titles_l + titles_p, os.path.join(IMG, "zoom_canon-ef-24-70.jpg"),
         f"{lens}: top, the exact tracer at four focal lengths (focus 1.5 m); middle, the one learned map of the whole "
         "zoom and focus range at the same; bottom, a focus pull at 68.14 mm through it: the focusing group shortens "
         "the focal length and the view narrows by 7.6 % at 0.38 m (breathing)", 4)
    return out


def zoom_flare(spp, res="360x240", lens="canon-ef-24-70mm-f2.8l", flare_samples=1 << 22,
               focal_lengths=(24.9, 35.0, 50.0, 68.14)):
    """The bundled night scene through the zoom lens at four focal lengths, its flare traced (``mode=exact``; the
    bundled model of this lens has no ghost maps, so ``auto`` traces them too).  Each focal length ranks and draws
    the ghosts of the lens as configured, so the set, their sizes and their brightness change with zoom; the
    flare's kernels of a ghost drawn at an earlier focal length are reused (the configuration's numbers are kernel
    inputs), so a focal length compiles only the kernels of ghosts new to its set."""
    import time
    from mi_neurallens.commands.render import load_scene, render_passes
    w, h = (int(v) for v in res.split("x"))
    imgs, titles, out = [], [], []
    for f in focal_lengths:
        scene = load_scene(str(scene_path("night")), variant="llvm_ad_rgb", lens=lens, resolution=(w, h), spp=spp,
                           sensor_type="realistic_lens", sets=[f"focal_length={f}"],
                           params=["mode=exact", f"flare_samples={flare_samples}", "diffraction=false"])
        t0 = time.perf_counter()
        img, _ = render_passes(scene, spp, max(1, spp // 64), show_progress=False)
        secs = time.perf_counter() - t0
        ghosts = sorted({s.path_id for s in scene.integrator().last_result.stats} - {0})     # 0: the lights' images
        imgs.append(img)
        titles.append(f"{f:g} mm: {len(ghosts)} ghosts")
        out.append({"focal_length_mm": f, "ghosts": ghosts, "seconds": secs})
    grid(imgs, titles, os.path.join(IMG, "flare_zoom_canon-ef-24-70.jpg"),
         f"night scene through {lens} at four focal lengths (realistic_lens, {spp} spp), its strongest ghosts "
         f"traced at each ({flare_samples / 2**20:.0f} M samples per light)", 4)
    return out


def focus_pull(spp, res, lens="canon-rf-24mm-f1.4l-vcm", distances=(math.inf, 1.0, 0.5, 0.24)):
    """A focus pull through an internally focused prime, from infinity to its close focus: exact (realistic_lens)
    above learned (neural_lens: one map of the whole focus range), each configuration's focal length (its
    breathing) in the title and the learned render's MAPE against the exact one."""
    from mi_neurallens import Lens
    from mi_neurallens.metrics import mape
    from mi_neurallens.optics import moving as mv
    base = Lens.load(lens)
    exact, learned, titles_e, titles_l, out = [], [], [], [], []
    for d in distances:
        sets = [f"focus_distance={d}"]
        e = render("realistic_lens", lens, spp, res, sets)
        n = render("neural_lens", lens, spp, res, sets)
        L, _, fp = mv.configure(base, None, d * 1000.0)
        at = "∞" if math.isinf(d) else f"{d:g} m"
        exact.append(e)
        learned.append(n)
        titles_e.append(f"realistic_lens at {at} (EFL {L.efl():.2f} mm)")
        titles_l.append(f"neural_lens at {at} (MAPE {mape(n, e):.3f})")
        out.append({"focus_m": d, "efl_mm": L.efl(), "focus_parameter": fp, "mape_neural_vs_exact": mape(n, e)})
    name = lens.split("-f")[0]
    grid(exact + learned, titles_e + titles_l, os.path.join(IMG, f"focus_pull_{name}.jpg"),
         f"{lens}: a focus pull from infinity to the close focus by the lens's two focusing groups; top, the exact "
         "tracer; bottom, the one learned map of the whole focus range. The focal length shortens toward close "
         "focus (breathing)", len(distances))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--reference-spp", type=int, default=1024)
    ap.add_argument("--resolution", default="320x240")
    ap.add_argument("--skip-compare", action="store_true")
    ap.add_argument("--methods", action="store_true", help="only the per-method depth-of-field figure")
    ap.add_argument("--aperture", action="store_true", help="only the render-time aperture figures")
    ap.add_argument("--night", default="", help="only the night-scene flare figure for these lenses (comma list)")
    ap.add_argument("--bladed", action="store_true", help="only the bladed-ghost figure (the iris's edge traced)")
    ap.add_argument("--coatings", action="store_true", help="only the coatings figure (bare, one layer, broadband)")
    ap.add_argument("--starburst", default="", help="only the starburst figure for these lenses (comma list)")
    ap.add_argument("--zoom", action="store_true", help="only the zoom lens figure (focal lengths, a focus pull)")
    ap.add_argument("--focus-pull", action="store_true", help="only the internally focused prime's focus pull")
    ap.add_argument("--zoom-flare", action="store_true", help="only the zoom lens's flare at four focal lengths")
    a = ap.parse_args(argv)
    os.makedirs(OUT, exist_ok=True)
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    import mi_neurallens
    mi_neurallens.register()
    res = {}
    if a.zoom:
        res = zoom(a.spp, "240x160" if a.resolution == "320x240" else a.resolution)
        print(json.dumps(res, indent=1, default=float))
        return
    if a.zoom_flare:
        res = zoom_flare(a.spp)
        print(json.dumps(res, indent=1, default=float))
        return
    if a.focus_pull:
        res = focus_pull(a.spp, "240x160" if a.resolution == "320x240" else a.resolution)
        print(json.dumps(res, indent=1, default=float))
        return
    if a.starburst:
        for lens in a.starburst.split(","):
            res[lens] = starburst(lens)
            print(json.dumps(res[lens], indent=1))
        with open(os.path.join(OUT, "starburst.json"), "w") as f:
            json.dump(res, f, indent=2)
        return
    if a.coatings:
        res = coatings()
        print(json.dumps(res, indent=1))
        with open(os.path.join(OUT, "coatings.json"), "w") as f:
            json.dump(res, f, indent=2)
        return
    if a.bladed:
        res = bladed()
        print(json.dumps(res, indent=1, default=float))
        with open(os.path.join(OUT, "bladed.json"), "w") as f:
            json.dump(res, f, indent=2, default=float)
        return
    if a.aperture:
        res = aperture(a.spp, "240x180" if a.resolution == "320x240" else a.resolution)
        print(json.dumps(res, indent=1, default=float))
        with open(os.path.join(OUT, "aperture.json"), "w") as f:
            json.dump(res, f, indent=2, default=float)
        return
    if a.night:
        for lens in a.night.split(","):
            res[lens] = night(a.spp, lens)
            print(json.dumps(res[lens], indent=1, default=float))
        with open(os.path.join(OUT, "night.json"), "w") as f:
            json.dump(res, f, indent=2, default=float)
        return
    if a.methods:
        res["methods"] = methods(a.spp, a.resolution)
        with open(os.path.join(OUT, "methods.json"), "w") as f:
            json.dump(res, f, indent=2, default=float)
        return
    if not a.skip_compare:
        res["compare"] = compare_all(a.spp, a.reference_spp, a.resolution)
    res["ablation"] = ablation(a.spp, a.resolution)
    print("ablation", res["ablation"])
    res["focus_sweep"] = focus_sweep(a.spp, a.resolution)
    print("focus sweep", res["focus_sweep"])
    with open(os.path.join(OUT, "figures.json"), "w") as f:
        json.dump(res, f, indent=2, default=float)


if __name__ == "__main__":
    main()
