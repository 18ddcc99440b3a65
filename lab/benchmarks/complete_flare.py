"""A lens's whole flare — every ghost of the default selection — learned against traced, at several light
positions: the numbers a user decides ``lens_flare``'s mode by.

    python benchmarks/complete_flare.py [--lens wide-22mm] [--model FILE] [--before FILE] [--samples 24]
                                        [--reference 27] [--mlp auto|fused|shared|coopvec] [--boundary-band B]
                                        [--auto-max-cost inf]
                                        [--json OUT]

``scenes/night_point.xml`` (one point light 5 m away, 240×160 full-frame film) with the light at four places
across the field (``--positions``, x:y in m; by default :data:`POSITIONS`, scaled toward the axis for a long lens
whose ghost maps learned a narrower field, which the four must lie within: outside it the learned renders trace).
Per position, the default ghost selection of the flare renderer (99 % of the ghost energy, at most 32 ghosts) is
rendered

* ``exact`` at 2^samples (seed 1): the test budget's noise floor against the reference;
* ``neural`` at 2^samples (seed 1), every ghost from ``--model`` (it must hold them all);
* ``auto`` at 2^samples (seed 1) with ``--model``: learned where a map passes its gates (sharp enough for the
  film, and a verified flare record within 0.01: with its edges learned, or traced at the record's band), with
  how many ghosts it learned, learned with their edges traced, and traced;
* ``auto`` with ``--before`` (e.g. the model as it was before its ghost set was completed: learned where it
  has a map, traced elsewhere), when given;

each against an exact reference at 2^reference (seed 101): MAPE (``metrics.mape_masked``) and the luminance
flux ratio; the neural render also paired against an exact one with the same samples (``pilot_with =
"exact"``: the maps' own error, noise cancelled) and timed against it (second render, kernels compiled).

``--mlp``: how the learned renders evaluate their networks (the flare's ``mlp`` option; ``coopvec`` is fp16
on CUDA: what tensor cores cost the flare in accuracy).

``--boundary-band B``: the learned renders (neural and auto) trace their samples within ±B of a classifier's
decision (the flare's ``boundary_band``).

``--equal-time``: the exact and neural renders are timed as the best of three warm renders, and the neural
flare is rendered again with the samples it can draw in the exact flare's time (2^samples × exact time /
neural time): the MAPE a user gets from each mode for the same wait.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
POSITIONS = ("0.9:0.45", "0.15:0.1", "1.6:1.0", "-1.2:0.35")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lens", default="wide-22mm")
    ap.add_argument("--model", help="model file (default: the bundled model of the lens)")
    ap.add_argument("--before", help="another model file, rendered in mode auto for comparison")
    ap.add_argument("--samples", type=int, default=24, help="log2 samples of the test renders (all ghosts)")
    ap.add_argument("--reference", type=int, default=27, help="log2 samples of the exact reference")
    ap.add_argument("--positions", help="light positions x:y (m, at z = 5 m; default: the four across the field; for a "
                                        "long lens whose ghost maps learned a narrower field (the farthest beyond 0.95 "
                                        "of its tangent) scaled toward the axis until it lies at 0.8)")
    ap.add_argument("--json", help="write the rows here")
    ap.add_argument("--equal-time", action="store_true", help="also the neural flare at the exact one's wall time")
    ap.add_argument("--mlp", default="auto", help="network evaluation of the learned renders (the flare's mlp option)")
    ap.add_argument("--boundary-band", type=float, default=0.0,
                    help="the learned renders' boundary_band (samples at a classifier's edge traced exactly)")
    ap.add_argument("--auto-max-cost", type=float, default=None,
                    help="mode auto's auto_max_cost (default: the flare's, 1; inf: accuracy alone decides, so every "
                         "ghost whose record passes is learned, at its band)")
    a = ap.parse_args(argv)
    sys.path.insert(0, ROOT)
    import mitsuba as mi
    from mi_neurallens.render_utils import default_variant
    mi.set_variant(default_variant())
    from mi_neurallens.commands.render import load_scene
    from mi_neurallens.fileio import atomic_write_json
    from mi_neurallens.flare.render import FlareOptions, FlareRenderer
    from mi_neurallens.metrics import LUMINANCE, mape_masked
    from mi_neurallens.neural.model import bundled_model_path
    model = a.model or bundled_model_path(a.lens)
    n, nref = 1 << a.samples, 1 << a.reference

    def flux(img):
        return float((img[..., :3] @ LUMINANCE).sum())

    def render(scene, seed, samples, **opts):
        if opts.get("mode") != "exact":
            opts["mlp"] = a.mlp
            opts["boundary_band"] = a.boundary_band
        if opts.get("mode") == "auto" and a.auto_max_cost is not None:
            opts["auto_max_cost"] = a.auto_max_cost
        r = FlareRenderer(scene, 0, FlareOptions(samples=samples, **opts))
        t0 = time.perf_counter()
        img = r.render(seed=seed).total
        return img, time.perf_counter() - t0, r

    def auto_split(r, ids):
        """How mode auto evaluated the ghosts ``ids``: learned at the render's band, learned with a wider band
        (their edges traced: FlareRenderer.auto_choice), traced."""
        bands = [r.auto_choice(g)[0] for g in ids]
        return dict(learned=sum(b is not None and b <= a.boundary_band for b in bands),
                    learned_wider_band=sum(b is not None and b > a.boundary_band for b in bands),
                    traced=sum(b is None for b in bands))

    if a.positions is None:
        from mi_neurallens.flare.verify import learned_field_sine, lights_within_field
        from mi_neurallens.neural.model import load_model
        s_max = learned_field_sine(load_model(model))
        pts = [tuple(float(v) for v in p.split(":")) for p in POSITIONS]
        if lights_within_field(pts, s_max, 0.95) != tuple(pts):   # beyond (nearly) the field: scaled, with room
            pts = lights_within_field(pts, s_max, 0.8)           # for a point light's own spread of angles
        a.positions = ",".join(f"{x:.4g}:{y:.4g}" for x, y in pts)
    rows = []
    for pos in a.positions.split(","):
        x, y = pos.split(":")
        scene = load_scene(os.path.join(ROOT, "scenes", "night_point.xml"), lens=a.lens, sensor_type="neural_lens",
                           sets=[f"model={model}"], params=[f"light_x={x}", f"light_y={y}"])
        ref, _, rr = render(scene, 101, nref, mode="exact")
        ids = [g for g in rr.ghost_ids() if g != 0]
        row = dict(light_m=[float(x), float(y), 5.0], ghosts=len(ids), log2_samples=a.samples,
                   reference_log2_samples=a.reference)
        ex, _, _ = render(scene, 1, n, mode="exact")
        ex, t_ex, _ = render(scene, 1, n, mode="exact")            # warm: kernels compiled
        ne, _, _ = render(scene, 1, n, mode="neural")
        ne, t_ne, rn = render(scene, 1, n, mode="neural")
        if a.equal_time:                                          # interleaved, best of three
            for _ in range(2):
                t_ex = min(t_ex, render(scene, 1, n, mode="exact")[1])
                t_ne = min(t_ne, render(scene, 1, n, mode="neural")[1])
        au, _, _ = render(scene, 1, n, mode="auto")
        au, t_au, ra = render(scene, 1, n, mode="auto")
        row["auto"] = dict(mape=float(mape_masked(au, ref)), flux_ratio=flux(au) / flux(ref), seconds=t_au,
                           **auto_split(ra, ids))
        pe, _, _ = render(scene, 1, n, mode="exact", pilot_with="exact")
        pn, _, _ = render(scene, 1, n, mode="neural", pilot_with="exact")
        row.update(exact=dict(mape=float(mape_masked(ex, ref)), flux_ratio=flux(ex) / flux(ref), seconds=t_ex),
                   neural=dict(mape=float(mape_masked(ne, ref)), flux_ratio=flux(ne) / flux(ref), seconds=t_ne,
                               paired=float(mape_masked(pn, pe)), paired_flux_ratio=flux(pn) / flux(pe)))
        if a.equal_time:
            n_eq = int(round(n * t_ex / t_ne))
            render(scene, 2, n_eq, mode="neural")
            eq, t_eq, _ = render(scene, 1, n_eq, mode="neural")
            row["neural_equal_time"] = dict(samples=n_eq, seconds=t_eq, mape=float(mape_masked(eq, ref)),
                                            flux_ratio=flux(eq) / flux(ref))
        if a.before:
            sb = load_scene(os.path.join(ROOT, "scenes", "night_point.xml"), lens=a.lens, sensor_type="neural_lens",
                            sets=[f"model={a.before}"], params=[f"light_x={x}", f"light_y={y}"])
            ab, _, _ = render(sb, 1, n, mode="auto")
            ab, t_ab, rb = render(sb, 1, n, mode="auto")
            row["auto_before"] = dict(mape=float(mape_masked(ab, ref)), flux_ratio=flux(ab) / flux(ref), seconds=t_ab,
                                      **auto_split(rb, ids))
        row["mlp"] = rn.learned_mlp()
        row["boundary_band"] = a.boundary_band
        rows.append(row)
        e, nn = row["exact"], row["neural"]
        line = (f"light ({x}, {y}, 5) m, {len(ids)} ghosts, 2^{a.samples} vs 2^{a.reference}: exact {e['mape']:.4f} "
                f"(flux {e['flux_ratio']:.4f}, {e['seconds']:.2f} s); neural {nn['mape']:.4f} = "
                f"{nn['mape'] / e['mape']:.2f}x the floor (flux {nn['flux_ratio']:.4f}, {nn['seconds']:.2f} s), "
                f"paired {nn['paired']:.4f} (flux {nn['paired_flux_ratio']:.4f}); auto {row['auto']['mape']:.4f} "
                f"(flux {row['auto']['flux_ratio']:.4f}, {row['auto']['seconds']:.2f} s; ghosts learned "
                f"{row['auto']['learned']} + {row['auto']['learned_wider_band']} with their edges traced, traced "
                f"{row['auto']['traced']})")
        if a.equal_time:
            q = row["neural_equal_time"]
            line += (f"; equal time: neural {q['mape']:.4f} ({q['mape'] / e['mape']:.2f}x exact's) with "
                     f"{q['samples'] / n:.2f}x the samples in {q['seconds']:.2f} s")
        if a.before:
            b = row["auto_before"]
            line += (f"; auto with --before {b['mape']:.4f} (flux {b['flux_ratio']:.4f}, {b['seconds']:.2f} s; learned "
                     f"{b['learned']} + {b['learned_wider_band']}, traced {b['traced']})")
        print(line, flush=True)
    if a.json:
        atomic_write_json(a.json, dict(lens=a.lens, model=os.path.relpath(model, ROOT),
                                       before=a.before and os.path.relpath(a.before, ROOT), rows=rows,
                                       command="python " + " ".join([os.path.relpath(__file__, ROOT)] +
                                                                    (argv or sys.argv[1:]))))


if __name__ == "__main__":
    main()
