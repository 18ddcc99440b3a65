"""Fine-tuning a learned lens map by inverse rendering: the map of a lens's nominal prescription, corrected toward
renders of the lens as built, by gradient descent on the regressor's weights through ``neural_lens``.

    python examples/fine_tune_map.py [--steps 150] [--lens dgauss-50mm] [--surface 0] [--off 0.005]
                                     [--out out/examples/fine_tune]

The bundled model of ``--lens`` was trained on its prescription; the camera being photographed (here: rendered
by ``realistic_lens``) is that lens with the curvature of ``--surface`` ``--off`` (0.5 %) off — a manufacturing
error, so the map is one of a slightly wrong prescription.  Both cameras keep the sensor distance that focuses the
nominal lens on the chart.  The regressor's layers (``sensor.regressor_{i}_weight``/``_bias`` in ``mi.traverse``)
are optimised with Adam on the mean squared difference of a ``lens_ad`` render (8 spp, a new seed each step) to
the target (512 spp); the classifier stays as trained.  The error is measured without the renders' noise too:
where the same camera samples meet the chart through the map and through the as-built lens (median, µm on the
chart).  Writes ``history.json``, ``fine_tune.png`` (target, start, result, the error per step) and the tuned
model ``<lens>-tuned.model.safetensors`` into ``--out``; its metadata records that it no longer is the map of
its prescription (``fine_tuned``), and ``neural_lens`` says so when it loads it.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

_HERE = os.path.dirname(os.path.abspath(__file__))
if _HERE not in sys.path:
    sys.path.insert(0, _HERE)
from calibrate_lens import pattern  # noqa: E402  (the same printed chart)


def scene_dict(mi, sensor: dict, chart_m: float, width: int, height: int, spp: int):
    """The chart tilted 45° at ``chart_m`` (m) in front of ``sensor`` (a sensor dict without film or sampler)."""
    tex = {"type": "bitmap", "bitmap": mi.Bitmap(pattern()), "filter_type": "bilinear"}
    plane = mi.ScalarTransform4f().translate([0.0, 0.0, chart_m]).rotate([0, 1, 0], 180).rotate([1, 0, 0], 45) \
        .scale(0.12)
    s = {"sensor_width": 12.0, "to_world": mi.ScalarTransform4f().look_at([0, 0, 0], [0, 0, 1], [0, 1, 0]),
         "film": {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"},
                  "pixel_format": "rgb"},
         "sampler": {"type": "independent", "sample_count": spp}, **sensor}
    return {"type": "scene", "integrator": {"type": "lens_ad", "max_depth": 2}, "sensor": s,
            "chart": {"type": "rectangle", "to_world": plane, "bsdf": {"type": "diffuse", "reflectance": tex}},
            "light": {"type": "constant"}}


def ray_miss_um(mi, dr, a, b, chart_m: float, n: int = 200_000) -> float:
    """The median distance (µm) between where the same camera samples of sensors ``a`` and ``b`` meet the plane
    ``chart_m`` in front of them, over the samples both pass."""
    rng = np.random.default_rng(5)
    u = [mi.Float(rng.random(n).astype(np.float32)) for _ in range(5)]
    hits = []
    for s in (a, b):
        ray, w = s.sample_ray(0.0, u[0], mi.Point2f(u[1], u[2]), mi.Point2f(u[3], u[4]))
        t = (chart_m - ray.o.z) / ray.d.z
        hits.append((dr.detach(ray.o.x + t * ray.d.x).numpy(), dr.detach(ray.o.y + t * ray.d.y).numpy(),
                     dr.detach(w[0]).numpy() > 0))
    ok = hits[0][2] & hits[1][2]
    d = np.hypot(hits[0][0] - hits[1][0], hits[0][1] - hits[1][1])[ok]
    return float(np.median(d)) * 1e6


def fine_tune(steps: int = 150, lens: str = "dgauss-50mm", surface: int = 0, off: float = 0.005,
              width: int = 128, height: int = 86, spp: int = 8, lr: float = 2e-3, chart_m: float = 0.5,
              log=print):
    """Run the fine-tuning; returns a dict with the history (loss and ray miss per step), the images and the tuned
    model (a :class:`~mi_neurallens.neural.model.NeuralLensModel`, not yet saved)."""
    import drjit as dr
    import mitsuba as mi
    if mi.variant() is None or "_ad_" not in mi.variant():
        mi.set_variant("llvm_ad_rgb")
    import mi_neurallens
    mi_neurallens.register()

    # the nominal lens focused on the chart gives the sensor distance both cameras keep
    probe = mi.load_dict(scene_dict(mi, {"type": "realistic_lens", "lens": lens, "focus_distance": chart_m},
                                    chart_m, width, height, spp))
    sensor_mm = float(mi.traverse(probe)["sensor.sensor_distance"].numpy()[0])
    # the camera as built: the prescription with one curvature off
    built = mi.load_dict(scene_dict(mi, {"type": "realistic_lens", "lens": lens, "sensor_distance": sensor_mm},
                                    chart_m, width, height, spp))
    pb = mi.traverse(built)
    key_c = f"sensor.surface_{surface}_curvature"
    pb[key_c] = pb[key_c] * (1.0 + off)
    pb.update()
    target = mi.render(built, spp=512, seed=12345)
    # the images' noise floor: another render of the same camera at the comparison renders' spp
    floor = mi.render(built, spp=256, seed=9)

    scene = mi.load_dict(scene_dict(mi, {"type": "neural_lens", "model": lens, "sensor_distance": sensor_mm},
                                    chart_m, width, height, spp))
    params = mi.traverse(scene)
    keys = [k for k in params.keys() if k.startswith("sensor.regressor_")]
    opt = mi.ad.Adam(lr=lr)
    for k in keys:
        opt[k] = params[k]
    params.update(opt)
    sensor, built_sensor = scene.sensors()[0], built.sensors()[0]
    start_img = mi.render(scene, spp=256, seed=7)
    history = []
    t0 = time.time()
    for it in range(steps):
        opt.set_learning_rate(lr * 0.1 ** (it / max(steps - 1, 1)))
        params.update(opt)
        miss = ray_miss_um(mi, dr, sensor, built_sensor, chart_m) if it % 10 == 0 else None
        img = mi.render(scene, params, seed=it, spp=spp)
        loss = dr.mean(dr.square(img - target), axis=None)
        dr.backward(loss)
        opt.step()
        history.append({"step": it, "loss": float(np.asarray(loss.numpy()).ravel()[0]), "miss_um": miss})
        if it % 10 == 0 or it == steps - 1:
            log(f"step {it:3d}  loss {history[-1]['loss']:.3e}"
                + (f"  ray miss {miss:.1f} um" if miss is not None else "") + f"  {time.time() - t0:.0f} s")
    params.update(opt)
    final_miss = ray_miss_um(mi, dr, sensor, built_sensor, chart_m)
    history.append({"step": steps, "loss": None, "miss_um": final_miss})
    final_img = mi.render(scene, spp=256, seed=8)
    model = sensor.fine_tuned_model(toward=f"renders of {lens} with surface {surface}'s curvature {100 * off:+g} %",
                                    steps=steps, loss="mean squared image difference (lens_ad)")
    return {"history": history, "seconds": time.time() - t0, "model": model,
            "start_miss_um": history[0]["miss_um"], "final_miss_um": final_miss,
            "images": {"target": np.array(target), "start": np.array(start_img), "final": np.array(final_img),
                       "floor": np.array(floor)}}


def image_error(a, b) -> float:
    """Relative mean absolute difference of two images."""
    return float(np.mean(np.abs(a - b)) / np.mean(np.abs(b)))


def _box(a, r: int):
    """``a`` (2-D) averaged over (2r+1)² neighbourhoods (edges clamped)."""
    p = np.pad(a, r, mode="edge")
    return sum(p[i:i + a.shape[0], j:j + a.shape[1]] for i in range(2 * r + 1) for j in range(2 * r + 1)) / (2 * r + 1) ** 2


def figure(result, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    im = result["images"]
    tone = lambda a: np.clip(a, 0, 1) ** (1 / 2.2)
    fig, ax = plt.subplots(1, 4, figsize=(13, 2.9), gridspec_kw={"width_ratios": [1, 1, 1, 1.25]})
    ax[0].imshow(tone(im["target"]))
    ax[0].set_title("target: the lens as built (exact)", fontsize=9)
    ax[0].axis("off")
    # where the renders differ from the target: the luminance difference, blurred over 5x5 pixels (the noise averages out)
    diff = lambda k: np.abs(_box(np.mean(im[k] - im["target"], -1), 2))
    vmax = float(np.percentile(diff("start"), 99))
    for a, (k, title) in zip(ax[1:3], [("start", "map of the prescription"), ("final", "fine-tuned map")]):
        a.imshow(diff(k), cmap="magma", vmin=0, vmax=vmax)
        a.set_title(f"{title}: |render − target|\n{100 * image_error(im[k], im['target']):.2f} % (noise alone "
                    f"{100 * image_error(im['floor'], im['target']):.2f} %)", fontsize=8.5)
        a.axis("off")
    h = [e for e in result["history"] if e["miss_um"] is not None]
    ax[3].plot([e["step"] for e in h], [e["miss_um"] for e in h], "o-", ms=3)
    ax[3].set_xlabel("Adam step")
    ax[3].set_ylabel("ray miss on the chart (µm, median)")
    ax[3].grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--lens", default="dgauss-50mm")
    ap.add_argument("--surface", type=int, default=0)
    ap.add_argument("--off", type=float, default=0.005, help="the as-built lens's relative curvature error")
    ap.add_argument("--out", default=os.path.join("out", "examples", "fine_tune"))
    args = ap.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    res = fine_tune(args.steps, args.lens, args.surface, args.off)
    im = res["images"]
    print(f"ray miss {res['start_miss_um']:.1f} -> {res['final_miss_um']:.1f} um (median on the chart); image error "
          f"{100 * image_error(im['start'], im['target']):.2f} -> {100 * image_error(im['final'], im['target']):.2f} % "
          f"(noise floor {100 * image_error(im['floor'], im['target']):.2f} %); {res['seconds']:.0f} s")
    model_path = os.path.join(args.out, f"{args.lens}-tuned.model.safetensors")
    res["model"].save(model_path)
    with open(os.path.join(args.out, "history.json"), "w") as fh:
        json.dump({k: v for k, v in res.items() if k not in ("images", "model")}, fh, indent=1)
    figure(res, os.path.join(args.out, "fine_tune.png"))
    print("wrote", os.path.join(args.out, "fine_tune.png"), "and", model_path)


if __name__ == "__main__":
    main()
