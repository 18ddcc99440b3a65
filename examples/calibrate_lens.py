"""Calibration by inverse rendering: recover a camera's focus distance and one curvature of its lens from a
photograph (here: a converged render of the true camera), by gradient descent through ``realistic_lens``.

    python examples/calibrate_lens.py [--steps 200] [--lens dgauss-50mm] [--surface 0] [--off 0.3]
                                      [--curvature-off 0.3] [--out out/examples/calibrate]

The scene: a smooth printed pattern on a plane tilted away from the camera (so that the focus shows as the band
where it is sharp, and a changed curvature as a changed magnification), lit by a white environment.  The start
is ``--off`` (30 %) off in the focus distance and ``--curvature-off`` (30 %) off in the curvature of ``--surface``; both are
optimised with Adam on their relative values (one learning rate for both, decaying 20x over the run).  The loss is the mean squared difference to the target,
rendered with ``lens_ad`` at 8 spp a step (a new seed each step).  Writes ``history.json`` (loss and both
parameters per step) and ``calibration.png`` (target, start, result, convergence) into ``--out``.
"""
from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np


def pattern(n: int = 768, seed: int = 3):
    """A printed chart with detail at every scale, like a photograph's: random-phase noise whose amplitude falls as
    1/f (frequencies from 1 to n/8 cycles across the chart), in three colour channels (float32, (n, n, 3), in
    [0.05, 0.95]).  Defocus removes detail at every scale, so the loss has a slope at any blur."""
    rng = np.random.default_rng(seed)
    fx = np.fft.fftfreq(n) * n
    F = np.hypot(*np.meshgrid(fx, fx))
    amp = np.where((F >= 1) & (F <= n / 8), 1.0 / np.maximum(F, 1.0), 0.0)
    out = []
    for _ in range(3):
        spec = amp * np.exp(2j * np.pi * rng.random((n, n)))
        img = np.real(np.fft.ifft2(spec))
        out.append((img - img.mean()) / (3 * img.std()))
    a = np.stack(out, -1)
    return np.clip(0.5 + a, 0.05, 0.95).astype(np.float32)


def scene_dict(mi, lens: str, focus_m: float, width: int, height: int, spp: int):
    tex = {"type": "bitmap", "bitmap": mi.Bitmap(pattern()), "filter_type": "bilinear"}
    plane = mi.ScalarTransform4f().translate([0.0, 0.0, focus_m]).rotate([0, 1, 0], 180).rotate([1, 0, 0], 45) \
        .scale(0.12)
    return {
        "type": "scene",
        "integrator": {"type": "lens_ad", "max_depth": 2},
        "sensor": {"type": "realistic_lens", "lens": lens, "focus_distance": focus_m, "sensor_width": 12.0,
                   "to_world": mi.ScalarTransform4f().look_at([0, 0, 0], [0, 0, 1], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"},
                            "pixel_format": "rgb"},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "chart": {"type": "rectangle", "to_world": plane,
                  "bsdf": {"type": "diffuse", "reflectance": tex}},
        "light": {"type": "constant"},
    }


def calibrate(steps: int = 200, lens: str = "dgauss-50mm", surface: int = 0, off: float = 0.3,
              curvature_off: float = 0.3,
              width: int = 128, height: int = 86, spp: int = 8, lr: float = 0.01, true_focus: float = 0.5,
              log=print):
    """Run the calibration; returns a dict with the history, the true/start/final values and the images."""
    import drjit as dr
    import mitsuba as mi
    if mi.variant() is None or "_ad_" not in mi.variant():
        mi.set_variant("llvm_ad_rgb")
    import mi_neurallens
    mi_neurallens.register()

    key_f, key_c = "sensor.focus_distance", f"sensor.surface_{surface}_curvature"
    scene = mi.load_dict(scene_dict(mi, lens, true_focus, width, height, spp))
    params = mi.traverse(scene)
    true_c = float(params[key_c].numpy()[0])
    target = mi.render(scene, spp=512, seed=12345)
    start_f, start_c = true_focus * (1.0 + off), true_c * (1.0 + curvature_off)
    # the optimiser works on relative values u (value = start · u), so one learning rate fits both
    opt = mi.ad.Adam(lr=lr)
    opt["u_f"], opt["u_c"] = mi.Float(1.0), mi.Float(1.0)

    def write():
        params[key_f] = start_f * opt["u_f"]
        params[key_c] = start_c * opt["u_c"]
        params.update()

    write()
    start_img = mi.render(scene, spp=64, seed=7)
    history = []
    t0 = time.time()
    for it in range(steps):
        # the step size decays 20x over the run, so Adam settles instead of circling the optimum
        opt.set_learning_rate(lr * 0.05 ** (it / max(steps - 1, 1)))
        write()
        img = mi.render(scene, params, seed=it, spp=spp)
        loss = dr.mean(dr.square(img - target), axis=None)
        dr.backward(loss)
        opt.step()
        f, c = start_f * float(opt["u_f"].numpy()[0]), start_c * float(opt["u_c"].numpy()[0])
        history.append({"step": it, "loss": float(np.asarray(loss.numpy()).ravel()[0]), "focus_distance": f, "curvature": c})
        if it % 20 == 0 or it == steps - 1:
            log(f"step {it:3d}  loss {history[-1]['loss']:.3e}  focus {f:.4f} m ({100 * (f / true_focus - 1):+.2f} %)"
                f"  c{surface} {c:.6f}/mm ({100 * (c / true_c - 1):+.2f} %)  {time.time() - t0:.0f} s")
    write()
    final_img = mi.render(scene, spp=64, seed=8)
    return {"history": history, "true": {"focus_distance": true_focus, "curvature": true_c},
            "start": {"focus_distance": start_f, "curvature": start_c},
            "final": {"focus_distance": history[-1]["focus_distance"], "curvature": history[-1]["curvature"]},
            "seconds": time.time() - t0,
            "images": {"target": np.array(target), "start": np.array(start_img), "final": np.array(final_img)}}


def figure(result, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    im = result["images"]
    tone = lambda a: np.clip(a, 0, 1) ** (1 / 2.2)
    fig, ax = plt.subplots(1, 4, figsize=(13, 2.9), gridspec_kw={"width_ratios": [1, 1, 1, 1.25]})
    for a, (k, title) in zip(ax[:3], [("target", "target (true camera)"), ("start", "start"),
                                      ("final", "after calibration")]):
        a.imshow(tone(im[k]))
        a.set_title(title, fontsize=9)
        a.axis("off")
    h = result["history"]
    t = result["true"]
    steps = [e["step"] for e in h]
    ax[3].plot(steps, [100 * abs(e["focus_distance"] / t["focus_distance"] - 1) for e in h], label="focus distance")
    ax[3].plot(steps, [100 * abs(e["curvature"] / t["curvature"] - 1) for e in h], label="curvature")
    ax[3].set_yscale("log")
    ax[3].set_xlabel("Adam step")
    ax[3].set_ylabel("error (%)")
    ax[3].legend(fontsize=8)
    ax[3].grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--lens", default="dgauss-50mm")
    ap.add_argument("--surface", type=int, default=0)
    ap.add_argument("--off", type=float, default=0.3, help="the start's relative error in the focus distance")
    ap.add_argument("--curvature-off", type=float, default=0.3, help="the start's relative error in the curvature")
    ap.add_argument("--out", default=os.path.join("out", "examples", "calibrate"))
    args = ap.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    res = calibrate(args.steps, args.lens, args.surface, args.off, args.curvature_off)
    t, f = res["true"], res["final"]
    print(f"focus distance {f['focus_distance']:.5f} m (true {t['focus_distance']:.5f}: "
          f"{100 * (f['focus_distance'] / t['focus_distance'] - 1):+.3f} %), curvature {f['curvature']:.7f}/mm "
          f"(true {t['curvature']:.7f}: {100 * (f['curvature'] / t['curvature'] - 1):+.3f} %), {res['seconds']:.0f} s")
    with open(os.path.join(args.out, "history.json"), "w") as fh:
        json.dump({k: v for k, v in res.items() if k != "images"}, fh, indent=1)
    figure(res, os.path.join(args.out, "calibration.png"))
    print("wrote", os.path.join(args.out, "calibration.png"))


if __name__ == "__main__":
    main()
