"""Where along the zoom a configured camera map errs: the map against the float64 tracer on the same rays at a
sweep of zoom parameters t, the focus parameter fixed or at the band's middle.

Asked for issue 55: why bench_zoom's 35 mm (t = 0.992, next to the listed position t = 1) erred 1.5x as much as
45 mm.  Answer at commit 4db2aa6: two error lobes at t = 0.98 and 1.02 around the cam curves' interior knot
(Fritsch-Carlson cubics join there with C1 continuity: their curvature jumps), of opposite sign in dx, and a
steep rise within the last 0.05 of t at both ends of the learned range.

    python lab/benchmarks/zoom_error_along_t.py --focus 0.2 --t 0.94,1.06,0.01
    python lab/benchmarks/zoom_error_along_t.py --t 0,2.001,0.1          # the band's middle at each t
"""
from __future__ import annotations

import argparse

import numpy as np


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lens", default="canon-ef-24-70mm-f2.8l")
    ap.add_argument("--model", default=None, help="model file (default: the lens's bundled model)")
    ap.add_argument("--focus", type=float, default=None, help="focus parameter (default: the band's middle)")
    ap.add_argument("--distance", type=float, default=None,
                    help="instead of --focus: the focus distance (mm from the sensor; inf: infinity), solved paraxially "
                         "for the focus parameter at each t")
    ap.add_argument("--t", default="0,2.001,0.1", help="start,stop,step of the zoom parameter")
    ap.add_argument("--rays", type=int, default=60000)
    a = ap.parse_args()
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    import mi_neurallens as nl
    nl.register()
    from mi_neurallens.neural.model import bundled_model_path, load_model
    from mi_neurallens.training.evaluate import map_outputs_np, regression_errors
    from mi_neurallens.transport.sampling import PathSampler
    lens = nl.Lens.load(a.lens)
    tm = load_model(a.model or bundled_model_path(a.lens), lens).map("transmit", "backward")
    dom = tm.domain
    u = np.random.default_rng(5).random((a.rays, dom.dims))        # the same rays at every t
    ps = PathSampler(lens, tm.path_id, tm.direction, tm.z_in, tm.z_out, dom, precision="float64")
    arcsec = 180 * 3600 / np.pi
    for t in np.arange(*(float(v) for v in a.t.split(","))):
        if a.distance is not None:
            from mi_neurallens.optics.moving import focus_parameter
            f = focus_parameter(lens, t, a.distance)
        else:
            f = a.focus if a.focus is not None else float(np.mean(dom.conditions.band(t)))
        lo, hi = dom.conditions.band(t)
        outside = "" if lo <= f <= hi else f" (outside the learned band [{lo:.3f}, {hi:.3f}]: extrapolated)"
        x = dom.u_to_x(u.copy())
        x[:, 4:dom.dims] = dom.conditions.values(t, f)
        x[:, dom.dims:] = dom.conditions.products_np(x)
        valid, y = ps.trace_x(x)
        logit, yp = map_outputs_np(tm, x)
        both = valid & (logit > 0)
        r = regression_errors(yp[both, :5], y[both, :5], tm.heading)
        e = (yp[both, 2:4] - y[both, 2:4]) * arcsec
        print(f"t={t:.4f} f={f:+.4f}: direction {r['direction_arcsec_median']:.2f}\" position "
              f"{r['position_um_median']:.2f} um; dx error mean {e[:, 0].mean():+.2f}\" median |dx| "
              f"{np.median(np.abs(e[:, 0])):.2f}\", |dy| {np.median(np.abs(e[:, 1])):.2f}\"{outside}", flush=True)


if __name__ == "__main__":
    main()
