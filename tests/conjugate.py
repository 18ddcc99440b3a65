"""Where the camera map focuses: the object-side conjugate of a sensor point, exact vs learned
(tests/test_aperture.py).

A map can be within its goals ray by ray (µm, arcseconds) and still focus elsewhere: what sets the point a
pencil of rays converges to is how the exit direction *changes* across the pupil, not its value.  For a sensor
point, with the lens focused at ``focus_m`` (m from the sensor plane) and stopped down, :func:`conjugates` traces
rays through the exit pupil with both transports on the *same* rays (the ``realistic_lens`` sensor's sampling)
and finds each pencil's convergence point (least squares over the rays' lines, lens space, mm).
"""
from __future__ import annotations

from mi_neurallens.constants import LAMBDA_D


def closest_focus_m(lens: str, want_m: float = 0.35) -> float:
    """``want_m``, or the closest focus (m from the sensor plane) the lens's bundled model supports if
    that is farther (then 2 % beyond it): bokeh.xml focuses at 0.2 m, nearer than any model was trained."""
    from mi_neurallens.neural.model import bundled_model_path, load_model
    from mi_neurallens.optics.prescription import Lens
    from mi_neurallens.sensors.common import focus_for_sensor_distance
    L = Lens.load(lens)
    s_max = float(load_model(bundled_model_path(lens), L).sensor_distance_range[1])
    near = focus_for_sensor_distance(L, s_max) / 1000.0
    return want_m if near < want_m else 1.02 * near


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
