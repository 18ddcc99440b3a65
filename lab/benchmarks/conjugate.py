"""Where the camera map focuses: the object-side conjugate of a sensor point, exact vs learned.

A map can be within its goals ray by ray (µm, arcseconds) and still focus elsewhere: what sets the
point a pencil of rays converges to is how the exit direction *changes* across the pupil, not its value.
For sensor points on and off the axis, with the lens focused at ``--focus`` (m from the sensor plane, default
the model's closest focus: the bokeh benchmarks' setting) and stopped down to ``--mult`` × its widest
f-number, this traces 2^20 rays through the exit pupil with both transports on the *same* rays (the
``realistic_lens`` sensor's sampling) and finds each pencil's convergence point (least squares over the
rays' lines, lens space, mm).  A learned map whose conjugate lies ``dz`` away defocuses a sharp object at
that field point by about m² · dz on the sensor (m the magnification).

    python benchmarks/conjugate.py [--lenses wide-22mm,...] [--mult 8] [--focus M] [--model PATH]

Prints one row per lens and field point; ``--json`` writes them.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from mi_neurallens.constants import LAMBDA_D  # noqa: E402
from mi_neurallens.render_utils import add_variant_argument  # noqa: E402

LENSES = ("wide-22mm", "ood-59mm", "canon-ef-24mm-f1.4l")


def convergence_point(p, q, chunk: int = 1 << 16):
    """The point closest (least squares) to the lines p + t q (N×3 each, q unit): Σ (I − q qᵀ) x = Σ (I − q qᵀ) p."""
    import numpy as np
    A, B = np.zeros((3, 3)), np.zeros(3)
    for i in range(0, len(p), chunk):
        pp, qq = p[i:i + chunk], q[i:i + chunk]
        M = np.eye(3)[None] - qq[:, :, None] * qq[:, None, :]
        A += M.sum(0)
        B += np.einsum("nij,nj->i", M, pp)
    return np.linalg.solve(A, B)


def conjugates(mi, dr, lens_name: str, fstop: float, focus_m: float, field_mm=(0.0, 3.0, 8.0), model=None,
               n: int = 1 << 20, seed: int = 2) -> list:
    """For each sensor point (x = ``field_mm``, y = 0): the exact and the learned pencil's convergence points
    (lens space, mm) and how many of its rays both transports pass."""
    import numpy as np
    sensors = {}
    for kind in ("realistic_lens", "neural_lens"):
        d = {"type": kind, "lens": lens_name, "focus_distance": focus_m, "fstop": fstop,
             "film": {"type": "hdrfilm", "width": 16, "height": 16}}
        if kind == "neural_lens":
            d["model"] = model or lens_name
        sensors[kind] = mi.load_dict(d)
    ex_s, nn_s = sensors["realistic_lens"], sensors["neural_lens"]
    u = np.random.default_rng(seed).random((n, 2)).astype(np.float32)
    rows = []
    for x0 in field_mm:
        fx, fy = mi.Float(np.full(n, x0, np.float32)), mi.Float(np.zeros(n, np.float32))
        o, d, _, _ = ex_s._film_rays(fx, fy, mi.Point2f(mi.Float(u[:, 0]), mi.Float(u[:, 1])))   # the sensor's rays
        out = []
        for s in (ex_s, nn_s):
            pos, dirn, _, valid = s._transport(o, d, mi.Float(LAMBDA_D), True)
            p = np.stack([np.array(c, dtype=np.float64) for c in pos], 1)
            q = np.stack([np.array(c, dtype=np.float64) for c in dirn], 1)
            out.append((p, q / np.linalg.norm(q, axis=1, keepdims=True), np.array(valid).astype(bool)))
        both = out[0][2] & out[1][2]
        ce = convergence_point(out[0][0][both], out[0][1][both])
        cn = convergence_point(out[1][0][both], out[1][1][both])
        rows.append({"field_mm": x0, "rays": int(both.sum()), "exact": ce.tolist(), "neural": cn.tolist(),
                     "sensor_z": float(ex_s.pupil.z_img)})
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lenses", default=",".join(LENSES))
    ap.add_argument("--mult", type=float, default=8.0, help="f-number as a multiple of the widest (default 8)")
    ap.add_argument("--focus", type=float, default=None, help="focus distance (m); default: the model's closest")
    ap.add_argument("--model", default=None, help="model file (one lens; default: its bundled model)")
    ap.add_argument("--json", default=None)
    add_variant_argument(ap)
    a = ap.parse_args(argv)
    import drjit as dr
    import mitsuba as mi
    import mi_neurallens
    from aperture import closest_focus_m
    from mi_neurallens.optics.prescription import Lens
    mi.set_variant(a.variant)
    mi_neurallens.register()
    rows = []
    print("| lens | f-number | focus (m) | sensor x (mm) | exact conjugate z (mm, lens space) | learned − exact: dx, dz (mm) | dz ÷ distance |")
    print("|---|---|---|---|---|---|---|")
    for lens in a.lenses.split(","):
        N = a.mult * Lens.load(lens).paraxial(LAMBDA_D).fnumber
        focus = a.focus if a.focus is not None else closest_focus_m(lens)
        for r in conjugates(mi, dr, lens, N, focus, model=a.model):
            r.update(lens=lens, fstop=N, focus_m=focus)
            rows.append(r)
            dist = r["sensor_z"] - r["exact"][2]
            dx, dz = r["neural"][0] - r["exact"][0], r["neural"][2] - r["exact"][2]
            print(f"| {lens} | f/{N:.3g} | {focus:.3g} | {r['field_mm']:g} | {r['exact'][2]:.2f} | {dx:+.3f}, {dz:+.2f} | "
                  f"{dz / dist:+.2%} |", flush=True)
    if a.json:
        from mi_neurallens.fileio import atomic_write_json
        atomic_write_json(a.json, {"argv": sys.argv[1:], "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
