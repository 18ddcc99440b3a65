"""Flare benchmark: forward samples/s per ghost (exact vs neural where a ghost map exists), pass
fractions before/after the pilot bounds, and equal-time MAPE against a converged exact reference.

    python benchmarks/bench_flare.py [--lens wide-22mm] [--ghosts N] [--samples 2^20] [--ref-samples 2^23]
    python benchmarks/bench_flare.py --coatings none,quarter_wave,broadband [--lens ood-59mm]

With ``--coatings`` it times instead each of the N strongest ghosts traced exactly (pilot bounds) with each
coating of ``lens_flare`` (best of 5 renders after a compiling one, alternating), and reports each coating's
time against the first one's.

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
    p.add_argument("--out", default=os.path.join("out", "bench", "bench_flare.json"))
    a = p.parse_args(argv)
    import mitsuba as mi
    import drjit as dr
    mi.set_variant(default_variant())
    import mi_neurallens as nl
    nl.register()
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
    fr0 = FlareRenderer(scene, 0, FlareOptions(mode="exact"))
    ids = fr0.ghost_ids()[:a.ghosts]
    if a.coatings:
        return coating_cost(a, scene, ids)
    rows = []
    for pid in ids:
        row = {"path_id": pid}
        ref = FlareRenderer(scene, 0, FlareOptions(mode="exact", ghosts=[pid], samples=a.ref_samples)).render(seed=99)
        modes = ["exact"]
        if model is not None:
            from mi_neurallens.neural.model import NeuralLensModel
            m = NeuralLensModel.load(model)
            if m.has(pid, "forward"):
                modes.append("neural")
        for mode in modes:
            for bounds in ("none", "pilot"):
                fr = FlareRenderer(scene, 0, FlareOptions(mode=mode, ghosts=[pid], samples=a.samples, bounds=bounds,
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
            ref = FlareRenderer(scene, 0, FlareOptions(mode="exact", ghosts=[pid], samples=a.ref_samples)).render(seed=99)
            fr = FlareRenderer(scene, 0, FlareOptions(mode="neural", ghosts=[pid], samples=n_eq, model=model))
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


def coating_cost(a, scene, ids, rounds=5):
    """Seconds per exact ghost render with each coating (best of ``rounds``, coatings alternating)."""
    import drjit as dr
    from mi_neurallens.flare.render import FlareOptions, FlareRenderer
    names = a.coatings.split(",")
    rows = []
    for pid in ids:
        frs = {c: FlareRenderer(scene, 0, FlareOptions(mode="exact", ghosts=[pid], samples=a.samples, coating=c))
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
           "samples": a.samples, "coatings": names, "rows": rows,
           "command": "python benchmarks/bench_flare.py " + " ".join(__import__("sys").argv[1:])}
    atomic_write_json(a.out, out, indent=1)
    print("wrote", a.out)


if __name__ == "__main__":
    main()
