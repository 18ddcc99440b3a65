"""Flare benchmark: forward samples/s per ghost (exact vs neural where a ghost map exists), pass
fractions before/after the pilot bounds, and equal-time MAPE against a converged exact reference.

    python benchmarks/bench_flare.py [--lens wide-22mm] [--ghosts N] [--samples 2^20] [--ref-samples 2^23]
    python benchmarks/bench_flare.py --coatings none,quarter_wave,broadband [--lens ood-59mm]

With ``--starburst`` it times instead the bundled night scene's whole flare (960x640, its lights, the automatic ghost
selection, mode auto) with and without the diffraction starburst (best of 11 renders after one that compiles, and the
first render with diffraction, which builds the film kernel, on its own).

With ``--coatings`` it times instead each of the N strongest ghosts traced exactly (pilot bounds) with each
coating of ``lens_flare`` (best of 5 renders after a compiling one, alternating), and reports each coating's
time against the first one's: on one point light at 240x160 (``--scene point``: the ghost's trace alone, the
worst case) or on the bundled night scene at 960x640 with its four lights (``--scene night``).

Prints a table and writes out/bench/bench_flare.json.  MAPE as in `mi-neurallens flare
--compare` (luminance, mask Y_ref > 1e-2·max, ε = 1e-3·max).
"""
from __future__ import annotations

import argparse, os, platform, time

from mi_neurallens.fileio import atomic_write_json
from mi_neurallens.render_utils import default_variant


def main(argv=None):
    p = argparse.ArgumentParser()
    p.add_argument("--lens", default="wide-22mm")
    p.add_argument("--ghosts", type=int, default=4, help="benchmark the N strongest ghosts")
    p.add_argument("--samples", type=int, default=1 << 20)
    p.add_argument("--ref-samples", type=int, default=1 << 23)
    p.add_argument("--model", default=None)
    p.add_argument("--coatings", default="", help="comma list of lens_flare coatings to time against the first")
    p.add_argument("--starburst", action="store_true", help="time the night scene's flare with and without diffraction")
    p.add_argument("--scene", default="point", choices=["point", "night"],
                   help="--coatings on one point light at 240x160 (point) or on the night scene at 960x640 (night)")
    p.add_argument("--out", default=os.path.join("out", "bench", "bench_flare.json"))
    a = p.parse_args(argv)
    import mitsuba as mi
    import drjit as dr
    mi.set_variant(default_variant())
    import mi_neurallens as nl
    nl.register()
    if a.starburst:
        return starburst_cost(a)
    from mi_neurallens.flare.render import FlareOptions, FlareRenderer
    from mi_neurallens.commands.flare import mape
    from mi_neurallens.neural.model import bundled_model_path
    model = a.model or bundled_model_path(a.lens)
    model = model if os.path.exists(model) else None
    scene = mi.load_dict({"type": "scene",
                          "sensor": {"type": "realistic_lens", "lens": a.lens,
                                     "film": {"type": "hdrfilm", "width": 240, "height": 160}},
                          "light": {"type": "point", "position": [0.9, 0.45, 5.0],
                                    "intensity": {"type": "rgb", "value": [100, 100, 100]}}})
    fr0 = FlareRenderer(scene, 0, FlareOptions(mode="exact", diffraction=False))
    ids = fr0.ghost_ids()[:a.ghosts]
    if a.coatings:
        if a.scene == "night":
            from mi_neurallens.commands.render import load_scene
            from mi_neurallens.resources import scene_path
            scene = load_scene(str(scene_path("night")), lens=a.lens, resolution=(960, 640))
            ids = FlareRenderer(scene, 0, FlareOptions(mode="exact", diffraction=False)).ghost_ids()[:a.ghosts]
        return coating_cost(a, scene, ids)
    rows = []
    for pid in ids:
        row = {"path_id": pid}
        ref = FlareRenderer(scene, 0, FlareOptions(mode="exact", ghosts=[pid], samples=a.ref_samples, diffraction=False)).render(seed=99)
        modes = ["exact"]
        if model is not None:
            from mi_neurallens.neural.model import NeuralLensModel
            m = NeuralLensModel.load(model)
            if m.has(pid, "forward"):
                modes.append("neural")
        for mode in modes:
            for bounds in ("none", "pilot"):
                fr = FlareRenderer(scene, 0, FlareOptions(mode=mode, ghosts=[pid], samples=a.samples, bounds=bounds, diffraction=False,
                                                          model=model if mode == "neural" else None))
                fr.render(seed=0)  # warm-up (compile)
                best = 1e9
                for k in range(3):
                    t0 = time.perf_counter(); r = fr.render(seed=k + 1); dr.sync_thread()
                    best = min(best, time.perf_counter() - t0)
                st = r.stats[0]
                row[f"{mode}_{bounds}"] = {"seconds": best, "samples_per_s": st.samples / best,
                                           "fraction_before": st.fraction_before,
                                           "fraction_after": st.fraction_after,
                                           "mape_vs_ref": mape(r.total, ref.total)}
        rows.append(row)
    print(f"{'ghost':>8} {'mode':>14} {'Msamples/s':>10} {'before':>7} {'after':>7} {'MAPE':>7}")
    for row in rows:
        for k, v in row.items():
            if k == "path_id":
                continue
            print(f"{row['path_id']:>8} {k:>14} {v['samples_per_s'] / 1e6:10.2f} {v['fraction_before']:7.3f} "
                  f"{v['fraction_after']:7.3f} {v['mape_vs_ref']:7.4f}")
    # equal-time MAPE: the neural render gets the wall time the exact one took for a.samples
    for row in rows:
        if "neural_pilot" in row and "exact_pilot" in row and row["neural_pilot"]["samples_per_s"] > 0:
            e, n = row["exact_pilot"], row["neural_pilot"]
            pid = row["path_id"]
            n_eq = max(int(a.samples * n["samples_per_s"] / e["samples_per_s"]) // 256 * 256, 256)
            ref = FlareRenderer(scene, 0, FlareOptions(mode="exact", ghosts=[pid], samples=a.ref_samples, diffraction=False)).render(seed=99)
            fr = FlareRenderer(scene, 0, FlareOptions(mode="neural", ghosts=[pid], samples=n_eq, model=model,
                                                              diffraction=False))
            fr.render(seed=0)
            t0 = time.perf_counter(); r = fr.render(seed=1); dr.sync_thread()
            row["neural_equal_time"] = {"samples": n_eq, "seconds": time.perf_counter() - t0,
                                        "exact_seconds": e["seconds"], "mape_vs_ref": mape(r.total, ref.total),
                                        "exact_mape_vs_ref": e["mape_vs_ref"]}
            print(f"{pid:>8} equal time ({e['seconds']:.3f} s): exact {a.samples} samples MAPE {e['mape_vs_ref']:.4f}, "
                  f"neural {n_eq} samples MAPE {row['neural_equal_time']['mape_vs_ref']:.4f}")
    out = {"machine": platform.processor() or platform.machine(), "threads": dr.thread_count(),
           "lens": a.lens, "samples": a.samples, "ref_samples": a.ref_samples, "model": model, "rows": rows}
    atomic_write_json(a.out, out, indent=1)
    print("wrote", a.out)


def starburst_cost(a, rounds=11):
    """Seconds of the night scene's flare at 960x640 without and with diffraction (see the module docstring)."""
    import drjit as dr
    from mi_neurallens.commands.render import load_scene
    from mi_neurallens.flare.render import FlareOptions, FlareRenderer
    from mi_neurallens.resources import scene_path
    scene = load_scene(str(scene_path("night")), lens=a.lens, resolution=(960, 640))
    frs = {d: FlareRenderer(scene, 0, FlareOptions(samples=a.samples, diffraction=d)) for d in (False, True)}
    frs[False].render(seed=0)                                       # compiles every ghost's kernels
    t0 = time.perf_counter(); frs[True].render(seed=0); dr.sync_thread()
    first = time.perf_counter() - t0                                # builds the film kernel (and compiles transmit)
    best = {False: 1e9, True: 1e9}
    for k in range(rounds):
        for d, fr in frs.items():
            t0 = time.perf_counter(); fr.render(seed=k + 1); dr.sync_thread()
            best[d] = min(best[d], time.perf_counter() - t0)
    t0 = time.perf_counter(); frs[True].diffraction_kernel(); kernel_cached = time.perf_counter() - t0
    frs[True]._film_kernel = None                                   # forget it: time building it
    t0 = time.perf_counter(); frs[True].diffraction_kernel(); kernel = time.perf_counter() - t0
    out = {"machine": platform.processor() or platform.machine(), "threads": dr.thread_count(), "lens": a.lens,
           "samples_per_light": a.samples, "lights": len(frs[True].lights), "resolution": [960, 640],
           "seconds_without": best[False], "seconds_with": best[True], "ratio": best[True] / best[False],
           "first_render_with_seconds": first, "kernel_build_seconds": kernel, "kernel_cached_seconds": kernel_cached,
           "command": "python benchmarks/bench_flare.py " + " ".join(__import__("sys").argv[1:])}
    print(f"night scene, {a.lens}, {out['lights']} lights, 960x640: flare {best[False]:.2f} s without diffraction, "
          f"{best[True]:.2f} s with ({out['ratio']:.3f}x); the film kernel builds in {kernel:.2f} s (once per "
          f"aperture, focus and film)")
    atomic_write_json(a.out, out, indent=1)
    print("wrote", a.out)


def coating_cost(a, scene, ids, rounds=5):
    """Seconds per exact ghost render with each coating (best of ``rounds``, coatings alternating)."""
    import drjit as dr
    from mi_neurallens.flare.render import FlareOptions, FlareRenderer
    names = a.coatings.split(",")
    rows = []
    for pid in ids:
        frs = {c: FlareRenderer(scene, 0, FlareOptions(mode="exact", ghosts=[pid], samples=a.samples, coating=c,
                                                         diffraction=False))
               for c in names}
        for fr in frs.values():
            fr.render(seed=0)                                   # compile
        best = {c: 1e9 for c in names}
        for k in range(rounds):
            for c, fr in frs.items():
                t0 = time.perf_counter(); fr.render(seed=k + 1); dr.sync_thread()
                best[c] = min(best[c], time.perf_counter() - t0)
        row = {"path_id": pid, "seconds": best, "ratio": {c: best[c] / best[names[0]] for c in names}}
        rows.append(row)
        print(f"{pid:>8} " + "  ".join(f"{c} {best[c] * 1e3:7.1f} ms ({row['ratio'][c]:.3f}x)" for c in names),
              flush=True)
    out = {"machine": platform.processor() or platform.machine(), "threads": dr.thread_count(), "lens": a.lens,
           "samples": a.samples, "coatings": names, "rows": rows, "scene": a.scene,
           "command": "python benchmarks/bench_flare.py " + " ".join(__import__("sys").argv[1:])}
    atomic_write_json(a.out, out, indent=1)
    print("wrote", a.out)


if __name__ == "__main__":
    main()
