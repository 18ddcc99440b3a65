"""Where a stop head's error lives: per crossing, per aperture, and how steep the function is at its tail.

    python benchmarks/stop_head_tail.py LENS KEY [--model FILE] [--rays 200000] [--json OUT]

Traces held-out valid rays of the map ``KEY`` (float64, the seed the benchmarks use), evaluates the model's map on
them and prints, for its stop head:

- the per-ray error (µm; the largest over the crossings, the goal's measure: median ≤ 2, p99 ≤ 20) and each
  crossing's own;
- the same on the rays that pass a circular iris at 1×, 2×, 4× and 8× the widest f-number (every crossing within
  R/f of the axis): the rays on whose crossings a stopped-down render depends;
- the exit-position error of the regressor on those rays (what moves a ghost's image through a small iris);
- how steep the worst crossing is as a function of the input direction, |∂s/∂ωx| and |∂s/∂ωy| (mm per unit
  direction cosine, central differences of the float64 tracer), on all rays and on the rays of the error's top 1 %:
  a tail where the function is many times steeper than typical is a tail a smooth network of this size does not
  follow.
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def crossing_errors(sp, s):
    """(N, k) distance (µm) between predicted and true crossings, columns (sx, sy, …)."""
    k = s.shape[1] // 2
    return np.stack([np.hypot(sp[:, 2 * i] - s[:, 2 * i], sp[:, 2 * i + 1] - s[:, 2 * i + 1]) for i in range(k)],
                    1) * 1000.0


def stats(e):
    return {"n": int(len(e)), "median": float(np.median(e)), "p99": float(np.percentile(e, 99))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("lens")
    ap.add_argument("key", help="map key, e.g. forward.278528")
    ap.add_argument("--model", help="model file (default: the bundled model of the lens)")
    ap.add_argument("--rays", type=int, default=200_000)
    ap.add_argument("--json", help="write the numbers here")
    a = ap.parse_args(argv)
    import mitsuba as mi
    from mi_neurallens.render_utils import default_variant
    mi.set_variant(default_variant())
    from mi_neurallens.fileio import atomic_write_json
    from mi_neurallens.neural.model import NeuralLensModel, bundled_model_path
    from mi_neurallens.optics.formats import load_lens
    from mi_neurallens.training.data import PathSampler
    from mi_neurallens.training.evaluate import heldout_valid, map_outputs_np

    lens = load_lens(a.lens)
    path = a.model or bundled_model_path(a.lens)
    tm = NeuralLensModel.load(path).maps[a.key]
    if tm.stop_head is None:
        raise SystemExit(f"{a.key} of {path} has no stop head")
    spec = (tm.path_id, tm.direction, tm.z_in, tm.z_out)
    x, y = heldout_valid(lens, spec, tm.domain, a.rays, 1000, stops=True)
    _, yp = map_outputs_np(tm, x)
    s, sp = y[:, 5:], yp[:, 5:]
    err = crossing_errors(sp, s)
    worst = err.max(1)
    R = float(lens.stop.semi_diameter)
    reach = np.max([np.hypot(s[:, 2 * i], s[:, 2 * i + 1]) for i in range(s.shape[1] // 2)], 0) / R
    pos = np.hypot(yp[:, 0] - y[:, 0], yp[:, 1] - y[:, 1]) * 1000.0
    out = {"lens": a.lens, "key": a.key, "model": os.path.relpath(path, ROOT) if path.startswith(ROOT) else path,
           "stop_radius_mm": R, "crossings": int(err.shape[1]), "stop_um": stats(worst),
           "per_crossing_um": [stats(err[:, i]) for i in range(err.shape[1])], "apertures": {}}
    print(f"{a.lens} {a.key}: {len(x)} held-out rays, {err.shape[1]} crossing(s), stop radius {R:.3f} mm")
    print(f"  stop error (largest crossing) median {out['stop_um']['median']:.2f} µm, p99 {out['stop_um']['p99']:.1f};"
          " per crossing " + ", ".join(f"{c['median']:.2f} / {c['p99']:.1f}" for c in out["per_crossing_um"]))
    for f in (1, 2, 4, 8):
        m = reach < 1.0 / f
        if m.sum() < 100:
            continue
        row = {"fraction": float(m.mean()), "stop_um": stats(worst[m]), "position_um": stats(pos[m])}
        out["apertures"][str(f)] = row
        print(f"  rays through {f}× the widest f-number ({100 * m.mean():5.1f} %): stop {row['stop_um']['median']:.2f}"
              f" / {row['stop_um']['p99']:.1f} µm, regressor position {row['position_um']['median']:.2f} / "
              f"{row['position_um']['p99']:.1f} µm")
    # steepness of the worst crossing along the two direction inputs (central differences, float64 tracer)
    ps = PathSampler(lens, *spec, tm.domain, precision="float64", stops=True)
    j = err.argmax(1)
    top = worst >= np.percentile(worst, 99)
    h = 1e-6
    out["steepness_mm_per_unit"] = {}
    for col, name in ((1, "wx"), (2, "wy")):
        xp, xm = x.copy(), x.copy()
        xp[:, col] += h
        xm[:, col] -= h
        (_, yp_), (_, ym_) = ps.trace_x(xp), ps.trace_x(xm)
        rows = np.arange(len(x))
        g = np.hypot(yp_[rows, 5 + 2 * j] - ym_[rows, 5 + 2 * j], yp_[rows, 6 + 2 * j] - ym_[rows, 6 + 2 * j]) / (2 * h)
        ok = np.isfinite(g)
        q = {"all_median": float(np.median(g[ok])), "all_p99": float(np.percentile(g[ok], 99)),
             "top1pct_median": float(np.median(g[ok & top])), "finite": float(ok.mean())}
        out["steepness_mm_per_unit"][name] = q
        print(f"  |∂s/∂{name}| of the worst crossing: all rays median {q['all_median']:.0f}, p99 {q['all_p99']:.0f};"
              f" the error's top 1 %: median {q['top1pct_median']:.0f} mm per unit")
    if a.json:
        atomic_write_json(a.json, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
