"""Lens design inside a scene: optimise the curvatures and spacings of a three-element lens at a fixed focal length
so that a rendered chart is sharp across the field, by gradient descent through ``realistic_lens`` — and compare
with what a lens-design optimiser (optiland's least squares on RMS spot size) reaches from the same start.

    python examples/design_lens.py [--steps 400] [--out out/examples/design]

The starting design (stated here, not tuned): a Cooke-triplet layout with equiconvex outer elements and an
equiconcave middle one, every element n = 1.62 (no dispersion), curvatures ±0.0294/mm and ±0.0470/mm, focal
length 50 mm, f/3.7, the stop between the middle and the rear element.  The variables: the six curvatures and
the two air gaps around the middle element; the focus follows (``focus_distance`` at infinity: the sensor sits
at the paraxial focus of every step's lens).

Our loss: the chart as an ideal 50 mm lens would image it (Mitsuba's ``perspective`` camera: no aberration,
distortion or vignetting) is the target; over a 4 × 3 grid of regions, the mean squared difference of render
and target, each divided by its own mean over the region (the falloff the ideal camera lacks does not count);
plus 10 (EFL/50 − 1)², the focal length read from ``sensor.lens_parameters.derived["efl"]`` (attached).  Adam
on scaled variables, 8 spp a step at 288 × 192 (100 µm pixels), ``lens_ad``.  optiland: the same variables plus the image distance, operands EFL = 50 mm and the RMS
spot size at 0, 0.7 and 1 of the half field, ``LeastSquares``.  Both designs are then evaluated the same way:
optiland's RMS spot size at the three fields, each design at its own paraxial focus.

Writes ``design.json`` (the three designs, their spot sizes, the loss history) and ``design.png`` (renders and
layouts of the start, our result and optiland's) into ``--out``.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import tempfile
import time

import numpy as np

F_MM = 50.0
#: the variables: (name, scale) — a step of 1 in the optimiser's unit moves the parameter by ``scale``
VARIABLES = [("surface_0_curvature", 0.01), ("surface_1_curvature", 0.01), ("surface_2_curvature", 0.01),
             ("surface_3_curvature", 0.01), ("surface_5_curvature", 0.01), ("surface_6_curvature", 0.01),
             ("surface_1_thickness", 1.0), ("surface_4_thickness", 1.0)]
HALF_FIELD_DEG = 16.0


def start_design():
    """The starting triplet (see the module docstring), focal length 50 mm."""
    from mi_neurallens.optics.glass import AIR, constant
    from mi_neurallens.optics.prescription import Lens, Surface
    n = constant(1.62)
    k = 50.0 / 36.70143141760229            # the unit design's focal length 36.70 mm, scaled to 50
    c1, c2 = 0.04 / k, 0.064 / k
    sd = [8.5 * k, 8.0 * k, 6.5 * k, 6.5 * k, 7.0 * k, 7.5 * k]
    surf = [Surface(1 / c1, 4.0 * k, n, sd[0]), Surface(-1 / c1, 4.0 * k, AIR, sd[1]),
            Surface(-1 / c2, 1.5 * k, n, sd[2]), Surface(1 / c2, 2.0 * k, AIR, sd[3]),
            Surface(math.inf, 2.0 * k, AIR, 3.75 * k, is_stop=True),
            Surface(1 / c1, 4.0 * k, n, sd[4]), Surface(-1 / c1, 27.52 * k, AIR, sd[5])]
    lens = Lens(surf, name="triplet-start")
    return lens.with_sensor_distance(lens.paraxial().bfl)


def chart_scene(mi, lens_path, width, height, spp):
    from calibrate_lens import pattern
    tex = {"type": "bitmap", "bitmap": mi.Bitmap(pattern(1024, seed=5)), "filter_type": "bilinear"}
    half = 10.0 * math.tan(math.radians(HALF_FIELD_DEG)) * 1.25
    return {
        "type": "scene", "integrator": {"type": "lens_ad", "max_depth": 2},
        "sensor": {"type": "realistic_lens", "lens": lens_path, "sensor_width": 2 * F_MM * math.tan(math.radians(HALF_FIELD_DEG)),
                   "to_world": mi.ScalarTransform4f().look_at([0, 0, 0], [0, 0, 1], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"},
                            "pixel_format": "rgb"},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "chart": {"type": "rectangle",
                  "to_world": mi.ScalarTransform4f().translate([0, 0, 10.0]).rotate([0, 1, 0], 180).scale(half),
                  "bsdf": {"type": "diffuse", "reflectance": tex}},
        "light": {"type": "constant"},
    }


def target_image(mi, width, height, spp=64):
    """The chart through an ideal lens: Mitsuba's ``perspective`` camera with the field of view of a perfect
    50 mm lens on the same sensor (no aberrations, no distortion, no vignetting)."""
    d = chart_scene(mi, None, width, height, spp)
    d["integrator"] = {"type": "path", "max_depth": 2}
    sensor = d["sensor"]
    d["sensor"] = {"type": "perspective", "fov_axis": "x", "fov": 2 * HALF_FIELD_DEG,
                   "to_world": sensor["to_world"], "film": sensor["film"], "sampler": sensor["sampler"]}
    return mi.render(mi.load_dict(d), seed=99)


def region_loss(dr, img, target, grid=(4, 3)):
    """The mean squared difference of image and target, each divided by its own mean over each of a grid of
    regions (so that the lens's falloff and vignetting, which the ideal target lacks, do not count)."""
    h, w = target.shape[0], target.shape[1]
    total = 0.0
    for j in range(grid[1]):
        for i in range(grid[0]):
            ys, ye = j * h // grid[1], (j + 1) * h // grid[1]
            xs, xe = i * w // grid[0], (i + 1) * w // grid[0]
            a, t = img[ys:ye, xs:xe, :], target[ys:ye, xs:xe, :]
            total = total + dr.mean(dr.square(a / dr.mean(a, axis=None) - t / dr.mean(t, axis=None)), axis=None)
    return total / (grid[0] * grid[1])


def optimise_render(lens, steps=400, width=288, height=192, spp=8, lr=0.1, log=print):
    """Our optimisation (see the module docstring); returns the final lens, the history and three renders."""
    import drjit as dr
    import mitsuba as mi
    if mi.variant() is None or "_ad_" not in mi.variant():
        mi.set_variant("llvm_ad_rgb")
    import mi_neurallens
    from mi_neurallens.trace import parameters as lp
    mi_neurallens.register()
    tmp = tempfile.mkdtemp()
    path = os.path.join(tmp, "start.json")
    lens.save(path)
    scene = mi.load_dict(chart_scene(mi, path, width, height, spp))
    sensor = scene.sensors()[0]
    target = target_image(mi, width, height)
    params = mi.traverse(scene)
    start = {k: float(params["sensor." + k].numpy()[0]) for k, _ in VARIABLES}
    opt = mi.ad.Adam(lr=lr)
    for k, _ in VARIABLES:
        opt[k] = mi.Float(0.0)

    def write():
        for k, scale in VARIABLES:
            params["sensor." + k] = start[k] + scale * opt[k]
        params.update()

    write()
    before = np.array(mi.render(scene, spp=64, seed=3))
    history = []
    t0 = time.time()
    for it in range(steps):
        opt.set_learning_rate(lr * 0.1 ** (it / max(steps - 1, 1)))
        write()
        img = mi.render(scene, params, seed=it, spp=spp)
        efl = sensor.lens_parameters.derived["efl"]
        loss = region_loss(dr, img, target) + 10.0 * dr.square(efl / F_MM - 1.0)
        dr.backward(loss)
        opt.step()
        # keep the lens valid: project, and carry the correction back into the optimiser's variables
        fixed = mi_neurallens.project_valid(params, "sensor")
        for k, v in fixed.items():
            scale = dict(VARIABLES).get(k)
            if scale is not None:
                opt[k] = mi.Float((v - start[k]) / scale)
        history.append({"step": it, "loss": float(np.ravel(loss.numpy())[0]),
                        "efl": float(np.ravel(dr.detach(efl).numpy())[0])})
        if it % 25 == 0 or it == steps - 1:
            log(f"step {it:3d}  loss {history[-1]['loss']:+.4f}  EFL {history[-1]['efl']:.3f} mm  "
                f"{time.time() - t0:.0f} s")
    write()
    after = np.array(mi.render(scene, spp=64, seed=4))
    values = {k: start[k] + s * float(opt[k].numpy()[0]) for k, s in VARIABLES}
    final = lp.lens_with(lens, values)
    final = final.with_sensor_distance(final.paraxial().bfl)
    return final, history, before, after, np.array(target), time.time() - t0


def render_lens(lens, width=288, height=192, spp=64):
    import mitsuba as mi
    tmp = tempfile.mkdtemp()
    path = os.path.join(tmp, "lens.json")
    lens.save(path)
    return np.array(mi.render(mi.load_dict(chart_scene(mi, path, width, height, spp)), seed=5))


def optiland_optic(lens):
    """The lens in optiland (object at infinity, n = 1.62 glass, the stop's size as the aperture, fields 0, 0.7
    and 1 of the half field, 587.6 nm)."""
    from optiland import optic
    from optiland.materials import IdealMaterial
    L = optic.Optic()
    L.surfaces.add(index=0, radius=np.inf, thickness=np.inf, material=IdealMaterial(n=1.0))
    for i, s in enumerate(lens.surfaces):
        L.surfaces.add(index=i + 1, radius=s.radius, thickness=s.thickness,
                       material=IdealMaterial(n=float(s.medium.index(587.56))), is_stop=s.is_stop)
    L.surfaces.add(index=len(lens.surfaces) + 1, material=IdealMaterial(n=1.0))
    L.set_aperture(aperture_type="float_by_stop_size", value=2.0 * lens.stop.semi_diameter)
    L.fields.set_type(field_type="angle")
    for h in (0.0, 0.7, 1.0):
        L.fields.add(y=h * HALF_FIELD_DEG)
    L.wavelengths.add(value=0.58756, is_primary=True)
    return L


def rms_spots(lens):
    """optiland's RMS spot size (µm) at 0, 0.7 and 1 of the half field, on the lens's own image plane."""
    from optiland.optimization.operand.ray import RayOperand
    L = optiland_optic(lens)
    return [1000.0 * float(RayOperand.rms_spot_size(L, -1, 0.0, h, 12, 0.58756, nan_policy="omit"))
            for h in (0.0, 0.7, 1.0)]


def optimise_optiland(lens, max_iterations=60):
    """optiland's least squares from ``lens``: the same variables plus the image distance; EFL = 50 mm and the
    RMS spot sizes at the three fields as operands.  Returns the optimised lens (our type)."""
    from optiland import optimization
    from mi_neurallens.trace import parameters as lp
    L = optiland_optic(lens)
    prob = optimization.OptimizationProblem()
    prob.add_operand(operand_type="f2", target=F_MM, weight=10.0, input_data={"optic": L})
    for h in (0.0, 0.7, 1.0):
        prob.add_operand(operand_type="rms_spot_size", target=0.0, weight=1.0,
                         input_data={"optic": L, "surface_number": -1, "Hx": 0.0, "Hy": h, "num_rays": 12,
                                     "wavelength": 0.58756, "distribution": "hexapolar"})
    for k, _ in VARIABLES:
        i, kind = lp.parse(k)
        prob.add_variable(L, "radius" if kind == "curvature" else "thickness", surface_number=i + 1)
    prob.add_variable(L, "thickness", surface_number=len(lens.surfaces))
    optimization.LeastSquares(prob).optimize(maxiter=max_iterations)
    values = {}
    for k, _ in VARIABLES:
        i, kind = lp.parse(k)
        s = L.surfaces[i + 1]
        values[k] = (1.0 / float(s.geometry.radius)) if kind == "curvature" else float(L.surfaces.get_thickness(i + 1)[0])
    out = lp.lens_with(lens, values)
    return out.with_sensor_distance(float(L.surfaces.get_thickness(len(lens.surfaces))[0]))


def figure(designs, renders, spots, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mi_neurallens.optics.plot import plot_lens
    tone = lambda a: np.clip(a, 0, 1) ** (1 / 2.2)
    fig, ax = plt.subplots(2, 3, figsize=(18, 8), gridspec_kw={"height_ratios": [1, 1.1], "hspace": 0.5})
    for col, (title, lens) in enumerate(designs.items()):
        ax[0, col].imshow(tone(renders[title]))
        ax[0, col].set_title(f"{title}\nEFL {lens.paraxial().efl:.2f} mm, RMS spot at 0 / 0.7 / 1 field: "
                             + " / ".join(f"{x:.0f}" for x in spots[title]) + " µm", fontsize=10)
        ax[0, col].axis("off")
        plot_lens(lens, ax[1, col], fields_deg=(0.0, 0.7 * HALF_FIELD_DEG, HALF_FIELD_DEG), wavelengths_nm=(587.56,))
        par = lens.paraxial()
        ax[1, col].set_title(f"{title}: f/{par.fnumber:.2f}, track {lens.total_track:.1f} mm, "
                             f"BFL {par.bfl:.1f} mm", fontsize=10, loc="left")
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--out", default=os.path.join("out", "examples", "design"))
    args = ap.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    start = start_design()
    ours, history, before, after, target, seconds = optimise_render(start, args.steps)
    t = time.time()
    theirs = optimise_optiland(start)
    t_opt = time.time() - t
    designs = {"start": start, "lens_ad (render loss)": ours.replace(name="triplet-lens_ad"),
               "optiland (RMS spot)": theirs.replace(name="triplet-optiland")}
    spots = {k: rms_spots(v) for k, v in designs.items()}
    for k, v in designs.items():
        print(f"{k:24s} EFL {v.paraxial().efl:7.3f} mm   RMS spot at 0 / 0.7 / 1 field: "
              + " / ".join(f"{x:6.1f}" for x in spots[k]) + " µm")
    print(f"ours {seconds:.0f} s, optiland {t_opt:.0f} s")
    renders = {"start": before, "lens_ad (render loss)": after, "optiland (RMS spot)": render_lens(theirs)}
    with open(os.path.join(args.out, "design.json"), "w") as fh:
        json.dump({"designs": {k: v.to_dict() for k, v in designs.items()}, "rms_spot_um": spots,
                   "history": history, "seconds": {"lens_ad": seconds, "optiland": t_opt}}, fh, indent=1)
    figure(designs, renders, spots, os.path.join(args.out, "design.png"))
    print("wrote", os.path.join(args.out, "design.png"))


if __name__ == "__main__":
    import sys
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    main()
