"""Baselines (ABCD, Taylor polynomial optics, fitted sparse polynomials): closed forms, convergence
orders and the shared TransportMap interface."""
from __future__ import annotations

import math

import numpy as np
import pytest

from mi_neurallens import Lens
from mi_neurallens.baselines import ABCDMap, FittedMap, TaylorMap
from mi_neurallens.transport import make_map
from mi_neurallens.baselines.poly import SparsePoly, TPS, compose, design_matrix, omp, tps_vars
from mi_neurallens.baselines.taylor import _Ctx, surface_step
from mi_neurallens.optics.glass import AIR, constant
from mi_neurallens.optics.prescription import Surface
from mi_neurallens.trace.api import float_type
from mi_neurallens.trace.paths import interaction_step, resolve_path
from mi_neurallens.transport.planning import Domain


@pytest.fixture(scope="module")
def wide():
    return Lens.load("wide-22mm")


def single_surface_lens(R=20.0, n=1.6, k=0.0):
    return Lens((Surface(radius=R, thickness=5.0, medium=constant(n), semi_diameter=6.0, conic=k),
                 Surface(radius=math.inf, thickness=10.0, medium=constant(n), semi_diameter=6.0, is_stop=True),
                 Surface(radius=math.inf, thickness=20.0, medium=AIR, semi_diameter=8.0)), name="one-surface")


# ------------------------------------------------------------------------------------------ TPS
def test_tps_arithmetic_matches_functions():
    x, y = tps_vars(2, 6)
    f = (1.0 + 0.3 * x - 0.2 * y).sqrt() / (2.0 + x * y) + (0.4 + x).cos()
    p = np.array([0.05, -0.03])
    exact = math.sqrt(1 + 0.015 + 0.006) / (2 - 0.0015) + math.cos(0.45)
    assert abs(f.eval_np(p[0:1], p[1:2])[0] - exact) < 1e-9          # 7th-order remainder ~ 1e-10
    g = compose([f], [x * x + y, x - 2.0 * y])[0]
    a, b = p[0] ** 2 + p[1], p[0] - 2 * p[1]
    exact_g = math.sqrt(1 + 0.3 * a - 0.2 * b) / (2 + a * b) + math.cos(0.4 + a)
    assert abs(g.eval_np(p[0:1], p[1:2])[0] - exact_g) < 1e-6


# ------------------------------------------------------------------------------------------ Taylor, one surface
def test_single_refraction_taylor_matches_analytic_derivatives():
    """One spherical refraction in the meridional plane: the series of the step equals the analytic ray
    (intersection + Snell) to degree 5, and its linear part is the paraxial refraction matrix."""
    R, n2 = 20.0, 1.6
    lens = single_surface_lens(R, n2)
    step = interaction_step(lens, "T", 0, 1)
    z_p = -3.0
    x, y, u, v = tps_vars(4, 5)
    (X, Y, U, V), h, zv, F, hit = surface_step(lens, step, (x, y, u, v), 1, z_p, _Ctx(lam_nm=550.0))
    # degree 1 = transfer(−z_p)… then refraction in direction cosines: u' = u/n − (n−1)/(n R) · y_vertex
    c, d = 1.0 / R, -z_p
    assert X.coef((1, 0, 0, 0)) == pytest.approx(1.0, abs=1e-14)
    assert X.coef((0, 0, 1, 0)) == pytest.approx(d, abs=1e-12)
    assert U.coef((1, 0, 0, 0)) == pytest.approx(-(n2 - 1.0) / n2 * c, rel=1e-12)
    assert U.coef((0, 0, 1, 0)) == pytest.approx(1.0 / n2 - (n2 - 1.0) / n2 * c * d, rel=1e-12)

    # the analytic map in the meridional plane, differentiated numerically (complex-free: high-order FD
    # replaced by comparing values at small inputs — remainder must scale as s^6)
    def exact(x0, u0):
        w0 = math.sqrt(1 - u0 * u0)
        # sphere centre at z = R (vertex at 0); ray from (x0, z_p)
        ox, oz = x0, z_p - R
        b = ox * u0 + oz * w0
        cc = ox * ox + oz * oz - R * R
        t = -b - math.sqrt(b * b - cc)
        px, pz = x0 + t * u0, z_p + t * w0
        nx, nz = px / R, (pz - R) / R                        # outward normal of the sphere, toward −z side
        nx, nz = (nx, nz) if nz < 0 else (-nx, -nz)
        ci = -(u0 * nx + w0 * nz)
        eta = 1.0 / n2
        ct = math.sqrt(1 - eta * eta * (1 - ci * ci))
        f = eta * ci - ct
        u1, w1 = eta * u0 + f * nx, eta * w0 + f * nz
        return px + (-pz) / w1 * u1, u1

    errs = []
    for s in (0.4, 0.2, 0.1):
        xe, ue = exact(s, 0.3 * s)
        xt = X.eval_np(np.array([s]), np.zeros(1), np.array([0.3 * s]), np.zeros(1))[0]
        ut = U.eval_np(np.array([s]), np.zeros(1), np.array([0.3 * s]), np.zeros(1))[0]
        errs.append(max(abs(xe - xt), abs(ue - ut)))
    slope = np.polyfit(np.log([0.4, 0.2, 0.1]), np.log(errs), 1)[0]
    assert slope > 6.5                                        # remainder O(s^7) for the odd maps


def test_degree1_taylor_equals_abcd(wide):
    """Degree 1 Taylor polynomial of the transmit path = the ABCD matrix (slopes = cosines to first order)."""
    for direction in ("forward", "backward"):
        t1 = TaylorMap(wide, "transmit", direction, degree=1, wavelength="interp", wavelengths=(550.0,))
        ab = ABCDMap(wide, "transmit", direction)
        M = ab.matrix(550.0)
        P = t1.node_polys[0]
        h = 1.0 if direction == "forward" else -1.0      # slope = cosine / dz, dz = ±1 to first order
        assert P[0].coef((1, 0, 0, 0)) == pytest.approx(M[0, 0], rel=1e-10)
        assert P[0].coef((0, 0, 1, 0)) == pytest.approx(M[0, 1] / h, rel=1e-10)
        assert P[2].coef((1, 0, 0, 0)) == pytest.approx(h * M[1, 0], rel=1e-10)
        assert P[2].coef((0, 0, 1, 0)) == pytest.approx(M[1, 1], rel=1e-10)
        assert P[1].coef((0, 1, 0, 0)) == pytest.approx(M[0, 0], rel=1e-10)   # x and y blocks alike
        assert P[0].coef((0, 1, 0, 0)) == 0.0


def test_abcd_transmit_equals_paraxial_abcd(wide):
    """ABCD of the transmit path from the first to the last vertex, converted to reduced angles, equals
    ParaxialSystem.abcd(); also for a lens with dispersion and conics (ood-59mm)."""
    for lens, lam in ((wide, 587.5618), (Lens.load("ood-59mm"), 550.0)):
        zl = float(lens.vertex_z[-1])
        ab = ABCDMap(lens, "transmit", "forward", z_in=0.0, z_out=zl)
        px = lens.paraxial(lam)
        M = ab.matrix(lam)
        conv = np.diag([1.0, px.image_index]) @ M @ np.diag([1.0, 1.0 / px.object_index])
        np.testing.assert_allclose(conv, px.abcd(), rtol=1e-12, atol=1e-12)


def test_abcd_ghost_reflection_matrix():
    """Ghost (1, 0) of a one-element lens (curved front R, flat back, stop inside the glass gap): the path
    matrix equals the hand-written product of transfers, refractions and the reflections
    s' = −s − 2cy (curved) and s' = −s (flat); the degree-1 Taylor map of the same ghost equals it."""
    R, n = 30.0, 1.6
    lens = single_surface_lens(R=R, n=n)
    z_in, z_out = -1.0, 40.0
    ab = ABCDMap(lens, (1, 0), "forward", z_in=z_in, z_out=z_out)
    Tm = lambda d: np.array([[1.0, d], [0.0, 1.0]])
    refr = lambda n1, n2, c: np.array([[1.0, 0.0], [-(n2 - n1) / n2 * c, n1 / n2]])
    refl = lambda c: np.array([[1.0, 0.0], [-2.0 * c, -1.0]])
    M = Tm(1.0)                                   # z_in → front vertex
    M = refr(1.0, n, 1.0 / R) @ M
    M = refl(0.0) @ Tm(15.0) @ M                  # through the stop plane to the flat back, reflect
    M = refl(1.0 / R) @ Tm(-15.0) @ M             # back to the front, reflect from inside
    M = refr(n, 1.0, 0.0) @ Tm(15.0) @ M          # out through the flat back
    M = Tm(z_out - 15.0) @ M
    np.testing.assert_allclose(ab.matrix(550.0), M, rtol=1e-12, atol=1e-12)
    t1 = TaylorMap(lens, (1, 0), "forward", z_in=z_in, z_out=z_out, degree=1, wavelengths=(550.0,))
    P = t1.node_polys[0]
    assert P[0].coef((1, 0, 0, 0)) == pytest.approx(M[0, 0], rel=1e-10)
    assert P[0].coef((0, 0, 1, 0)) == pytest.approx(M[0, 1], rel=1e-10)
    assert P[2].coef((1, 0, 0, 0)) == pytest.approx(M[1, 0], rel=1e-10)
    assert P[2].coef((0, 0, 1, 0)) == pytest.approx(M[1, 1], rel=1e-10)
    # Fresnel at normal incidence: T(air→glass) · R(glass→air) · R(glass→air) · T(glass→air)
    r = ((n - 1) / (n + 1)) ** 2
    assert ab.T550 == pytest.approx((1 - r) * r * r * (1 - r), rel=1e-12)


def test_taylor_composition_equals_direct_and_converges(wide):
    """Composition of per-surface polynomials (truncated) = series pushed through the whole path; and the
    error against the tracer near the axis shrinks at the order the degree predicts (log-log slope)."""
    for path in ("transmit", 192):
        a = TaylorMap(wide, path, "forward", degree=5, build="compose", wavelengths=(550.0,))
        b = TaylorMap(wide, path, "forward", degree=5, build="direct", wavelengths=(550.0,))
        for pa, pb in zip(a.node_polys[0], b.node_polys[0]):
            np.testing.assert_allclose(pa.c, pb.c, rtol=1e-9, atol=1e-12)
    rng = np.random.default_rng(0)
    n = 400
    base_o = rng.uniform(-1, 1, (n, 2))
    base_d = rng.uniform(-1, 1, (n, 2))
    for deg in (3, 5):
        m = TaylorMap(wide, "transmit", "forward", degree=deg, wavelengths=(550.0,))
        scales = np.array([0.25, 0.5, 1.0])
        errs = []
        for s in scales:
            o = np.c_[base_o * 0.5 * s, np.full(n, m.z_in)]
            d = np.c_[base_d * 0.02 * s, np.ones(n)]
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            ref = wide.trace(o, d, 550.0, z_out=m.z_out, precision="float64")
            r = m.eval_np(o, d, 550.0)
            errs.append(np.abs(r.position[ref.valid, :2] - ref.position[ref.valid, :2]).max())
        slope = np.polyfit(np.log(scales), np.log(errs), 1)[0]
        assert slope == pytest.approx(deg + 2, abs=0.6), (deg, errs)


def taylor_throughput_vs_tracer(lens, n=200):
    """(Taylor degree-5 throughput, traced throughput) of ``n`` near-axis rays that pass ``lens``, at 550 nm."""
    m = TaylorMap(lens, "transmit", "forward", degree=5, wavelengths=(550.0,))
    rng = np.random.default_rng(1)
    o = np.c_[rng.uniform(-0.5, 0.5, (n, 2)), np.full(n, m.z_in)]
    d = np.c_[rng.uniform(-0.01, 0.01, (n, 2)), np.ones(n)]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ref = lens.trace(o, d, 550.0, z_out=m.z_out, precision="float64")
    return m.eval_np(o, d, 550.0).throughput[ref.valid], ref.throughput[ref.valid]


def test_taylor_fresnel_series(wide):
    """The throughput polynomial reproduces the traced Fresnel product near the axis (degree 5, 1e-6)."""
    got, ref = taylor_throughput_vs_tracer(wide)
    np.testing.assert_allclose(got, ref, atol=1e-6)


def test_taylor_wavelength_modes_dispersive():
    """ood-59mm (tabulated dispersion): at a node the 'interp' polynomial equals that node's expansion; the
    'variable' expansion at 550 nm (l = 0) has the same linear part."""
    lens = Lens.load("ood-59mm")
    a = TaylorMap(lens, "transmit", "forward", degree=3, wavelength="interp")
    b = TaylorMap(lens, "transmit", "forward", degree=3, wavelength="variable")
    o = np.array([[0.5, 0.2, a.z_in]])
    d = np.array([[0.01, -0.005, 1.0]])
    d /= np.linalg.norm(d)
    ra, rb = a.eval_np(o, d, 550.0), b.eval_np(o, d, 550.0)
    ref = lens.trace(o, d, 550.0, z_out=a.z_out, precision="float64")
    assert np.abs(ra.position - ref.position).max() < 1e-4
    assert np.abs(rb.position - ref.position).max() < 1e-3
    # dispersion is there: 450 vs 650 nm land apart, and both modes agree on the sign
    p4, p6 = a.eval_np(o, d, 450.0).position, a.eval_np(o, d, 650.0).position
    r4 = lens.trace(o, d, 450.0, z_out=a.z_out, precision="float64").position
    r6 = lens.trace(o, d, 650.0, z_out=a.z_out, precision="float64").position
    assert np.sign(p4[0, 0] - p6[0, 0]) == np.sign(r4[0, 0] - r6[0, 0])


# ------------------------------------------------------------------------------------------ fitting
def test_omp_recovers_known_polynomial():
    rng = np.random.default_rng(3)
    V = rng.uniform(-1, 1, (3000, 4))
    from mi_neurallens.baselines.poly import monomial_template
    ex = monomial_template(4, 6)
    truth = {(0, 0, 0, 0): 0.3, (1, 0, 0, 0): -1.2, (2, 1, 0, 1): 0.7, (0, 0, 3, 0): 2.0, (1, 1, 1, 1): -0.4}
    y = sum(c * np.prod(V ** np.array(e), axis=1) for e, c in truth.items())
    A = design_matrix(V, ex)
    idx, coef = omp(A, y, 5)
    got = {tuple(int(v) for v in ex[i]): c for i, c in zip(idx, coef)}
    assert set(got) == set(truth)
    for e, c in truth.items():
        assert got[e] == pytest.approx(c, abs=1e-10)


def test_fitted_map_reproduces_known_polynomial(wide):
    """FittedMap fed a synthetic polynomial 'lens' (reduced-frame outputs polynomial in the normalised
    inputs, with the right ωy parities) reproduces it exactly through eval_np/undo."""
    dom = Domain(r_max=5.0, s_max=0.3)                       # λ over 360–830 nm
    rng = np.random.default_rng(5)
    x = dom.u_to_x(rng.random((4000, 4)))
    V = (x - [2.5, 0, 0, 595.0]) / [2.5, 0.3, 0.3, 235.0]
    r, wx, wy, l = V.T
    Y = np.stack([1.0 + 2 * r + 0.5 * wx * wx - 0.1 * r * wy * wy, 0.7 * wy - 0.2 * r * wy + 0.05 * wy * l,
                  0.1 * r - 0.2 * wx + 0.01 * r ** 3, 0.3 * wy + 0.04 * r * r * wy, 0.9 - 0.01 * r * r], 1)
    f = FittedMap(wide, "transmit", "forward", z_in=-1.0, z_out=30.0, domain=dom, degree=4, terms=12,
                  valid="all", data=(x, Y))
    from mi_neurallens.trace.symmetry import reduced_ray
    (px, py), (dx, dy, dz) = reduced_ray(x[:, 0], x[:, 1], x[:, 2], 1)
    out = f.eval_np(np.c_[px, py, np.full(len(x), -1.0)], np.c_[dx, dy, dz], x[:, 3])
    np.testing.assert_allclose(out.position[:, :2], Y[:, :2], atol=1e-10)
    np.testing.assert_allclose(out.direction[:, :2], Y[:, 2:4], atol=1e-10)
    np.testing.assert_allclose(out.throughput, Y[:, 4], atol=1e-10)
    assert out.valid.all()


# ------------------------------------------------------------------------------------------ interface
def _rays(m, n=3000, seed=9, s=0.3, r=6.0):
    rng = np.random.default_rng(seed)
    o = np.c_[rng.uniform(-r, r, (n, 2)), np.full(n, m.z_in - 0.5 * m.heading)]
    d = np.c_[rng.uniform(-s, s, (n, 2)), np.full(n, float(m.heading))]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    lam = rng.uniform(420, 680, n)
    return o, d, lam


def _dr_eval(m, o, d, lam):
    import drjit as dr
    F = float_type("float64")
    O = tuple(F(o[:, i]) for i in range(3))
    D = tuple(F(d[:, i]) for i in range(3))
    res = m.eval_dr(O, D, F(lam))
    v, p, dd, T = res.valid, res.position, res.direction, res.throughput
    dr.eval(v, p, dd, T)
    return (v.numpy().astype(bool), np.stack([c.numpy() for c in p], 1), np.stack([c.numpy() for c in dd], 1),
            T.numpy())


@pytest.mark.parametrize("method,kw", [("abcd", {"aperture": "stop"}), ("taylor3", {"aperture": "all"}),
                                       ("taylor5", {"wavelength": "variable"}), ("fitted", {"valid": "aperture"})])
def test_eval_dr_equals_eval_np(wide, method, kw):
    direction = "forward"
    if method == "fitted":
        kw = dict(kw, n_samples=3000, degree=5, terms=12, domain=Domain(r_max=8.0, s_max=0.3))
    m = make_map(wide, method, "transmit", direction, **kw)
    o, d, lam = _rays(m)
    a = m.eval_np(o, d, lam)
    v, p, dd, T = _dr_eval(m, o, d, lam)
    assert (v == a.valid).mean() > 0.999
    both = v & a.valid
    assert both.sum() > 100
    np.testing.assert_allclose(p[both], a.position[both], atol=1e-8)
    np.testing.assert_allclose(dd[both], a.direction[both], atol=1e-10)
    np.testing.assert_allclose(T[both], a.throughput[both], atol=1e-10)
    assert m.flops() > 0


def test_make_map_planes_and_errors(wide):
    from mi_neurallens.errors import NeuralLensError
    from mi_neurallens.baselines.common import default_map_planes
    m = make_map(wide, "abcd", "transmit", "backward")
    zi, zo = default_map_planes(wide, "backward")
    assert (m.z_in, m.z_out) == (zi, zo) and zi > zo
    with pytest.raises(NeuralLensError, match="unknown method"):
        make_map(wide, "spline")
    ex = make_map(wide, "exact", "transmit", "forward")
    o, d, lam = _rays(ex, n=500)
    r = ex.eval_np(o, d, 550.0)
    t = make_map(wide, "taylor5", "transmit", "forward")
    rt = t.eval_np(o, d, 550.0)
    ok = r.valid
    assert ok.sum() > 50 and np.nanmedian(np.abs(rt.position[ok] - r.position[ok])) < 0.05
