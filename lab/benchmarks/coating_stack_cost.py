"""Issue 57: can a broadband stack cost a traced ghost at most 10 %?  Two ways to a cheaper stack, measured.

1. ``--exact``: the characteristic-matrix stack (trace/interactions.py) against a bare Fresnel term, on 2^20 rays
   crossing K interfaces each (a ghost's trace is a chain of them), and a variant that takes each layer's
   normal-incidence phase A = 2π n h / λ once per ray (its sine and cosine shared by every surface through Dr.Jit's
   value numbering) and per surface only a Taylor sine-cosine of ε = A (1 − cos θ_layer), δ = A − ε.
   At commit 1cfabf7 (2 AVX2 cores, llvm_ad_rgb, K = 10): bare 4.7 ms, stack +33.6 ms, the variant +28.5 ms
   (−15 %; max |ΔR| 1.5e-7).
2. ``--table``: the stack's R tabulated on a grid uniform in 1/λ (360–830 nm) and cos θ on the air side, bilinear,
   against the exact R; the issue's check is 1e-5 (float32) over 380–780 nm and 0–60° from air.  At 1cfabf7:
   512×128 entries reach 1.5e-5 (N-BK7-like glass) and 1.9e-5 (n ≈ 1.9); tabulating R − R_bare instead is worse.

    python lab/benchmarks/coating_stack_cost.py --exact [--k 10]
    python lab/benchmarks/coating_stack_cost.py --table
"""
import argparse
import math
import time

import numpy as np


def exact_cost(K):
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    import drjit as dr
    from mi_neurallens.trace import interactions as it

    def sc_small(e):                      # Taylor sine and cosine, |e| <= ~0.8: error < 1e-9
        e2 = e * e
        s = e * (1 + e2 * (-1 / 6 + e2 * (1 / 120 + e2 * (-1 / 5040 + e2 * (1 / 362880 + e2 * (-1 / 39916800))))))
        c = 1 + e2 * (-0.5 + e2 * (1 / 24 + e2 * (-1 / 720 + e2 * (1 / 40320 + e2 * (-1 / 3628800
                                                                                     + e2 * (1 / 479001600))))))
        return s, c

    def stack_eps(n_amb, cos_amb, n_sub, cos_sub, lam_nm, layers):
        s2 = (n_amb * n_amb) * (1.0 - cos_amb * cos_amb)
        inv_lam = 1.0 / lam_nm
        mats = []
        for n_j, h_nm in layers:
            inv_n = 1.0 / n_j
            cos_j = dr.maximum(dr.sqrt(dr.maximum(1.0 - s2 * (inv_n * inv_n), 0)), 1e-6)
            A = ((2.0 * math.pi * h_nm) * inv_lam) * n_j
            sA, cA = dr.sincos(A)
            se, ce = sc_small(A - A * cos_j)
            mats.append((n_j, inv_n, cos_j, 1.0 / cos_j, cA * ce + sA * se, sA * ce - cA * se))
        total = 0.0
        for pol in ("s", "p"):
            a = b = c = d = None
            for n_j, inv_n, cos_j, inv_c, cd, sd in mats:
                e, inv_e = (n_j * cos_j, inv_n * inv_c) if pol == "s" else (n_j * inv_c, inv_n * cos_j)
                b2, c2 = sd * inv_e, e * sd
                if a is None:
                    a, b, c, d = cd, b2, c2, cd
                else:
                    a, b, c, d = a * cd - b * c2, a * b2 + b * cd, c * cd + d * c2, d * cd - c * b2
            e0, es = (n_amb * cos_amb, n_sub * cos_sub) if pol == "s" else (n_amb / cos_amb, n_sub / cos_sub)
            re_n, im_n = e0 * a - es * d, e0 * es * b - c
            re_d, im_d = e0 * a + es * d, e0 * es * b + c
            total = total + (re_n * re_n + im_n * im_n) / (re_d * re_d + im_d * im_d)
        return 0.5 * total

    N = 1 << 20
    rng = mi.PCG32(N)
    lam = 380 + 400 * rng.next_float32()
    n1 = dr.full(mi.Float, 1.0, N)
    layers = [(1.38 + 0.001 * lam / 500, 99.6), (2.10 + 0.002 * lam / 500, 131.0), (1.63 + 0.001 * lam / 500, 84.4)]
    coss = [0.5 + 0.5 * rng.next_float32() for _ in range(K)]
    n2s = [1.5 + 0.03 * k + 0.01 * (lam / 700) for k in range(K)]
    cts = [dr.sqrt(1 - (1 / n2) ** 2 * (1 - c * c)) for c, n2 in zip(coss, n2s)]
    dr.eval(lam, *coss, *n2s, *cts, *[l[0] for l in layers])

    def chain(f):
        acc = 1.0
        for c, n2, ct in zip(coss, n2s, cts):
            acc = acc * (1 - f(n1, c, n2, ct, lam, layers))
        return acc

    def bare(n1, c, n2, ct, lam, layers):
        return it.fresnel_reflectance(n1, n2, c, ct)

    def run(f, reps=7):
        best = 1e9
        for _ in range(reps):
            t = time.perf_counter()
            r = chain(f)
            dr.eval(r)
            dr.sync_thread()
            best = min(best, time.perf_counter() - t)
        return best

    for _ in range(2):
        tb, ts, te = run(bare), run(it.stack_reflectance), run(stack_eps)
        print(f"K={K}: bare {tb * 1e3:.1f} ms, stack +{(ts - tb) * 1e3:.1f} ms, per-ray phase + Taylor "
              f"+{(te - tb) * 1e3:.1f} ms")
    r1 = it.stack_reflectance(n1, coss[0], n2s[0], cts[0], lam, layers)
    r2 = stack_eps(n1, coss[0], n2s[0], cts[0], lam, layers)
    print("max |R - R_variant|", dr.max(dr.abs(r1 - r2)))


def table_accuracy():
    from mi_neurallens.optics.coatings import preset
    from mi_neurallens.trace.interactions import stack_reflectance
    st = preset("broadband")
    sq = lambda a: np.sqrt(np.maximum(a, 0))      # noqa: E731

    def R(lam, u, nsub):
        layers = [(l.medium.index(lam), l.thickness_nm) for l in reversed(st.layers)]
        ns = nsub(lam)
        cs = sq(1 - (1 - u * u) / ns ** 2)
        return stack_reflectance(1.0, u, ns, cs, lam, layers, sqrt=sq, cos=np.cos, sin=np.sin)

    glasses = {"n 1.5": lambda lam: 1.5 + 0.004 / (lam / 1000) ** 2, "n 1.9": lambda lam: 1.9 + 0.012 / (lam / 1000) ** 2}
    lam_f = np.linspace(380, 780, 1601)[:, None]
    u_f = np.linspace(0.5, 1, 501)[None, :]                   # 0-60 degrees from air
    x0, x1 = 1 / 830, 1 / 360
    for name, ns in glasses.items():
        Rf = R(lam_f, u_f, ns)
        for nl, nu in ((64, 32), (128, 64), (256, 128), (512, 128)):
            xg, ug = np.linspace(x0, x1, nl), np.linspace(0, 1, nu)
            T = R(1 / xg[:, None], ug[None, :], ns)
            fx = (1 / lam_f - x0) / (x1 - x0) * (nl - 1)
            ix = np.clip(np.floor(fx).astype(int), 0, nl - 2)
            wx = fx - ix
            fu = u_f * (nu - 1)
            iu = np.clip(np.floor(fu).astype(int), 0, nu - 2)
            wu = fu - iu
            Ti = ((1 - wx) * (1 - wu) * T[ix, iu] + wx * (1 - wu) * T[ix + 1, iu] + (1 - wx) * wu * T[ix, iu + 1]
                  + wx * wu * T[ix + 1, iu + 1])
            print(f"{name}: {nl}x{nu} table, max |error| {np.abs(Ti - Rf).max():.2e} (380-780 nm, 0-60 deg)")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--exact", action="store_true")
    ap.add_argument("--table", action="store_true")
    ap.add_argument("--k", type=int, default=10)
    a = ap.parse_args()
    if a.table:
        table_accuracy()
    if a.exact or not a.table:
        exact_cost(a.k)
