#!/usr/bin/env python3
"""Behaviour fingerprint of the whole product, for refactors: record before, record after, compare.

    python scripts/check_equivalence.py record before.npz      # on the old tree
    python scripts/check_equivalence.py record after.npz       # on the new tree
    python scripts/check_equivalence.py compare before.npz after.npz

``record`` runs, on fixed seeds and small sizes (about two minutes on two cores):

* the demo's three renders (``make demo``): the still life through the 22 mm lens with
  ``realistic_lens`` at a high spp (the reference), ``realistic_lens`` and ``neural_lens`` at a low spp;
* a flare render of the bundled scene ``night_point``, exact and neural (``mode = exact`` / ``auto``), per ghost;
* ``evaluate`` of the bundled 22 mm model (its backward transmit map and its first ghost map);
* every transport map method (exact, neural, ABCD, Taylor 3/5) on the same fixed lens-space rays;
* ``Lens.trace`` in float32 and float64, transmit and a ghost.

It uses only the public API (with a fallback for the pre-``transport`` map factory), so the same script
runs on both trees.  ``compare`` prints, per array, the largest difference relative to the array's
largest magnitude, and fails (exit 1) when one exceeds the tolerance: 2e-6 for exact-arithmetic
arrays (rays, maps, metrics), and for images 1e-4 relative on the image's mean (float32 rounding
moved through a path tracer flips a few Russian-roulette or boundary decisions, which changes a
handful of pixels by a sample's weight; the mean and the per-pixel median must not move).
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def _scene(path, sensor_type, **params):
    import mitsuba as mi
    try:                                       # bundled scenes are package data since the product's shape
        from mi_neurallens.resources import scene_path
        path = str(scene_path(os.path.basename(path)))
    except ImportError:
        path = os.path.join(ROOT, path)
    with open(path) as f:
        xml = f.read()
    if sensor_type != "realistic_lens":
        xml = xml.replace('type="realistic_lens"', f'type="{sensor_type}"')
    return mi.load_string(xml, **{k: str(v) for k, v in params.items()})


def _get(r, k):
    return r[k] if isinstance(r, dict) else getattr(r, k)


def _make_map(lens, method, path, direction):
    try:
        from mi_neurallens.transport import make_map
    except ImportError:   # before the transport package existed
        from mi_neurallens.baselines import make_method as make_map
    return make_map(lens, method, path, direction)


def record(out: str) -> None:
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    import mi_neurallens as nl
    from mi_neurallens.neural.model import bundled_model_path
    nl.register()
    res: dict[str, np.ndarray] = {}
    t0 = time.perf_counter()

    # --- the demo's three renders (smaller)
    for name, st, spp, seed in (("render.reference", "realistic_lens", 128, 1000),
                                ("render.realistic", "realistic_lens", 16, 0),
                                ("render.neural", "neural_lens", 16, 0)):
        sc = _scene("scenes/still_life.xml", st, width=96, height=64, spp=spp)
        res[name] = np.asarray(mi.render(sc, spp=spp, seed=seed), np.float64)
        print(f"{name}: {time.perf_counter() - t0:.1f} s", flush=True)

    # --- flares, exact and neural, per ghost
    from mi_neurallens.flare.render import render_flare
    for mode in ("exact", "auto"):
        sc = _scene("scenes/night_point.xml", "realistic_lens", width=96, height=64)
        model = bundled_model_path("wide-22mm")
        fr = render_flare(sc, 0, seed=3, per_ghost=True, mode=mode, samples=1 << 17, model=model, diffraction=False)
        res[f"flare.{mode}.total"] = np.asarray(fr.total, np.float64)
        for pid, img in sorted(fr.ghosts.items()):
            res[f"flare.{mode}.ghost{pid}"] = np.asarray(img, np.float64)
        print(f"flare {mode}: {time.perf_counter() - t0:.1f} s", flush=True)

    # --- evaluate of the bundled model
    from mi_neurallens.neural.model import load_model
    from mi_neurallens.training.evaluate import evaluate_map
    lens = nl.Lens.load("wide-22mm")
    model = load_model(bundled_model_path("wide-22mm"), lens)
    keys = ["backward.0", f"forward.{model.ghost_ids[0]}"]
    for k in keys:
        tm = model.maps[k]
        m = evaluate_map(lens, tm, n=20000, seed=5, boundary=False)
        vals = [v for sec in ("regressor", "classifier") for _, v in sorted(m[sec].items())
                if isinstance(v, (int, float))]
        res[f"evaluate.{k}"] = np.asarray(vals, np.float64)
    print(f"evaluate: {time.perf_counter() - t0:.1f} s", flush=True)

    # --- every map method on the same rays
    rng = np.random.default_rng(11)
    n = 4096
    for direction, path in (("backward", "transmit"), ("forward", "transmit"), ("forward", model.ghost_ids[0])):
        for method in ("exact", "neural", "abcd", "taylor3", "taylor5"):
            if method == "neural" and not model.has(path, direction):
                continue
            m = _make_map(lens, method, path, direction)
            h = 1.0 if direction == "forward" else -1.0
            o = np.c_[rng.uniform(-6, 6, n), rng.uniform(-6, 6, n), np.full(n, m.z_in - h * 1.0)]
            d = np.c_[rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.3, n), np.zeros(n)]
            d[:, 2] = h * np.sqrt(1 - d[:, 0] ** 2 - d[:, 1] ** 2)
            lam = rng.uniform(420, 680, n)
            r = m.eval_np(o, d, lam)
            v = np.asarray(_get(r, "valid"), bool)
            for k in ("position", "direction", "throughput"):
                a = np.asarray(_get(r, k), np.float64)
                res[f"map.{method}.{direction}.{path}.{k}"] = np.where(
                    v.reshape((-1,) + (1,) * (a.ndim - 1)), a, 0.0)
            res[f"map.{method}.{direction}.{path}.valid"] = v.astype(np.float64)
    print(f"maps: {time.perf_counter() - t0:.1f} s", flush=True)

    # --- Lens.trace
    o = np.c_[rng.uniform(-8, 8, n), rng.uniform(-8, 8, n), np.full(n, -5.0)]
    d = np.c_[rng.uniform(-0.4, 0.4, n), rng.uniform(-0.4, 0.4, n), np.ones(n)]
    for prec in ("float32", "float64"):
        for path in ("transmit", (5, 2)):
            r = lens.trace(o, d, 550.0, path=path, precision=prec)
            tag = f"trace.{prec}.{path if isinstance(path, str) else 'ghost'}"
            res[tag + ".position"] = np.nan_to_num(r.position)
            res[tag + ".throughput"] = r.throughput
            res[tag + ".valid"] = r.valid.astype(np.float64)
    np.savez_compressed(out, **res)
    print(f"wrote {out}: {len(res)} arrays in {time.perf_counter() - t0:.1f} s")


def compare(a_path: str, b_path: str) -> int:
    A, B = np.load(a_path), np.load(b_path)
    bad = 0
    for k in sorted(set(A.files) | set(B.files)):
        if k not in A.files or k not in B.files:
            print(f"MISSING  {k}: only in {'before' if k in A.files else 'after'}")
            bad += 1
            continue
        a, b = A[k], B[k]
        if a.shape != b.shape:
            print(f"SHAPE    {k}: {a.shape} vs {b.shape}")
            bad += 1
            continue
        scale = max(float(np.max(np.abs(a))) if a.size else 0.0, 1e-30)
        diff = float(np.max(np.abs(a - b))) if a.size else 0.0
        if k.startswith(("render.", "flare.")):
            mean_rel = abs(float(a.mean()) - float(b.mean())) / max(abs(float(a.mean())), 1e-30)
            frac = float(np.mean(np.abs(a - b) > 1e-4 * scale))
            ok = mean_rel <= 1e-4 and frac <= 1e-3
            note = f"mean rel {mean_rel:.2e}, pixels off by >1e-4 of max: {100 * frac:.3f} %"
        elif k.endswith(".valid"):
            frac = float(np.mean(a != b))
            ok = frac <= 1e-3
            note = f"{int(np.sum(a != b))} of {a.size} differ"
        else:
            ok = diff <= 2e-6 * scale
            note = f"max |diff| / max |a| = {diff / scale:.2e}"
        print(f"{'ok      ' if ok else 'DIFFERS '} {k}: {note}")
        bad += not ok
    print(f"{len(set(A.files) | set(B.files)) - bad} agree, {bad} differ")
    return 1 if bad else 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record")
    r.add_argument("out")
    c = sub.add_parser("compare")
    c.add_argument("before")
    c.add_argument("after")
    args = ap.parse_args(argv)
    if args.cmd == "record":
        record(args.out)
        return 0
    return compare(args.before, args.after)


if __name__ == "__main__":
    sys.exit(main())
