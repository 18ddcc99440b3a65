"""The exact Dr.Jit tracer against optiland, closed forms and conservation laws."""
from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import bundled_names, plate
from mi_neurallens import Lens
from mi_neurallens.errors import NeuralLensError
from mi_neurallens.optics.prescription import Coating
from mi_neurallens.render_utils import default_variant
from mi_neurallens.trace.paths import all_ghosts, ghost_id, ghost_surfaces, resolve_path

WAVELENGTHS = (450.0, 550.0, 650.0)


def field_rays(lens, n, max_field_deg, rng, z0=-5.0):
    """Rays in front of the lens aimed at its entrance region, fields up to ``max_field_deg``."""
    r0 = lens.surfaces[0].semi_diameter
    th = np.radians(rng.uniform(0, max_field_deg, n))
    az = rng.uniform(0, 2 * np.pi, n)
    d = np.stack([np.sin(th) * np.cos(az), np.sin(th) * np.sin(az), np.cos(th)], 1)
    rr = r0 * np.sqrt(rng.uniform(0, 1, n))
    a2 = rng.uniform(0, 2 * np.pi, n)
    # aim at a point on the first-vertex plane, then back off to z0 along the ray
    p = np.stack([rr * np.cos(a2), rr * np.sin(a2), np.zeros(n)], 1)
    o = p + d * (z0 / d[:, 2:3])
    return o, d


def passing_rays(lens, n, rng, lam=550.0):
    """Object-space rays that do pass the lens: traced backward from random sensor points through
    random points of the rear clear aperture, reversed, and started in front of the first surface."""
    last = lens.surfaces[-1]
    zi = lens.image_z
    rs = min(0.8 * last.semi_diameter, 0.5 * lens.efl())
    rr = rs * np.sqrt(rng.uniform(0, 1, n))
    a = rng.uniform(0, 2 * np.pi, n)
    ps = np.stack([rr * np.cos(a), rr * np.sin(a), np.full(n, zi)], 1)
    rq = last.semi_diameter * np.sqrt(rng.uniform(0, 1, n))
    b = rng.uniform(0, 2 * np.pi, n)
    pq = np.stack([rq * np.cos(b), rq * np.sin(b), np.full(n, lens.vertex_z[-1])], 1)
    d = pq - ps
    z0 = min(0.0, float(lens.surfaces[0].sag(lens.surfaces[0].semi_diameter))) - 5.0
    bw = lens.trace(ps, d, lam, direction="backward", precision="float64", z_out=z0)
    return bw.position[bw.valid], -bw.direction[bw.valid]


def _lenses():
    names = bundled_names()
    return names if names else ["wide22"]


def _get(name, request):
    if name == "wide22":
        return request.getfixturevalue("wide22")
    return Lens.load(name)


@pytest.mark.parametrize("name", _lenses())
@pytest.mark.parametrize("precision,tol", [("float32", 1e-3), ("float64", 1e-7)])
def test_real_rays_match_optiland(name, precision, tol, request):
    from mi_neurallens.optics.interop import optiland_trace
    lens = _get(name, request)
    rng = np.random.default_rng(7)
    checked = 0
    for lam in WAVELENGTHS:
        o, d = passing_rays(lens, 3000, rng, lam)
        res = lens.trace(o, d, lam, precision=precision)
        assert res.valid.sum() >= 100, f"too few valid rays through {name}"
        pos, dirn = optiland_trace(lens, o[res.valid], d[res.valid], lam)
        ok = np.isfinite(pos).all(1)
        assert ok.mean() > 0.99
        np.testing.assert_allclose(res.position[res.valid][ok], pos[ok], atol=tol, rtol=0)
        np.testing.assert_allclose(res.direction[res.valid][ok], dirn[ok], atol=tol, rtol=0)
        checked += ok.sum()
    assert checked > 300


def test_asphere_newton_converges():
    """After ASPHERE_NEWTON_ITERATIONS the hit lies on the asphere to 1e-9 mm (float64), over the
    whole clear aperture, for a strongly aspheric surface."""
    import drjit as dr
    from mi_neurallens.optics.glass import AIR, constant
    from mi_neurallens.optics.prescription import Surface
    from mi_neurallens.trace.api import float_type
    from mi_neurallens.trace.surfaces import SurfaceGeometry
    s = Surface(radius=-30.0, thickness=5.0, medium=constant(1.6), semi_diameter=15.7, conic=-0.5,
                aspheric=(2.04769e-05, 2.22129e-08, -2.10838e-11, -1.46493e-13, 2.10282e-16))
    g = SurfaceGeometry(s, 3.0)
    F = float_type("float64")
    rng = np.random.default_rng(0)
    n = 20000
    r = 15.7 * np.sqrt(rng.uniform(0, 1, n))
    a = rng.uniform(0, 2 * np.pi, n)
    d = rng.normal(size=(n, 3)) * 0.25
    d[:, 2] = 1
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # start 10 mm in front of the surface point we aim at
    p_target = np.stack([r * np.cos(a), r * np.sin(a), 3.0 + s.sag(r)], 1)
    o = p_target - 10 * d
    O = tuple(F(o[:, i]) for i in range(3))
    D = tuple(F(d[:, i]) for i in range(3))
    t, ok = g.intersect(O, D)
    hit = tuple(dr.fma(t, D[i], O[i]) for i in range(3))
    res = g.residual(hit).numpy()
    assert ok.numpy().all()
    assert np.abs(res).max() < 1e-9
    np.testing.assert_allclose(np.stack([h.numpy() for h in hit], 1), p_target, atol=1e-7)


def test_rotational_symmetry(wide22):
    rng = np.random.default_rng(3)
    o, d = field_rays(wide22, 2000, 20, rng)
    res = wide22.trace(o, d, 550.0, precision="float64")
    for ang in (0.3, 2.0, -1.1):
        c, s = math.cos(ang), math.sin(ang)
        R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        rot = wide22.trace(o @ R.T, d @ R.T, 550.0, precision="float64")
        np.testing.assert_array_equal(rot.valid, res.valid)
        v = res.valid
        np.testing.assert_allclose(rot.position[v], res.position[v] @ R.T, atol=1e-9)
        np.testing.assert_allclose(rot.direction[v], res.direction[v] @ R.T, atol=1e-12)
        np.testing.assert_allclose(rot.throughput[v], res.throughput[v], rtol=1e-12)


def test_float32_rays_stay_float32_and_agree_with_the_float64_path(wide22):
    """Lens.trace with float32 rays (precision float32) returns float32 results — no float64 copies in or
    out — equal to the float64-array path at float32 precision; float64 rays still get float64 results."""
    rng = np.random.default_rng(4)
    o, d = field_rays(wide22, 5000, 25, rng)
    lam = rng.uniform(420.0, 680.0, len(o))
    r64 = wide22.trace(o, d, lam)
    r32 = wide22.trace(o.astype(np.float32), d.astype(np.float32), lam.astype(np.float32))
    assert r64.position.dtype == np.float64 and r32.position.dtype == np.float32
    assert r32.direction.dtype == np.float32 and r32.throughput.dtype == np.float32
    assert 0.05 < r32.valid.mean() < 1.0          # some pass, some are blocked
    np.testing.assert_array_equal(r32.valid, r64.valid)
    v = r64.valid
    np.testing.assert_allclose(r32.position[v], r64.position[v], atol=2e-4)
    np.testing.assert_allclose(r32.direction[v], r64.direction[v], atol=2e-6)
    np.testing.assert_allclose(r32.throughput[v], r64.throughput[v], rtol=1e-5)
    assert np.isnan(r32.position[~v]).all() and (r32.throughput[~v] == 0).all()


def test_forward_backward_inverse(wide22):
    """Forward then backward (reversed ray from the image plane) returns to the input ray."""
    rng = np.random.default_rng(5)
    o, d = field_rays(wide22, 2000, 18, rng, z0=-3.0)
    fw = wide22.trace(o, d, 520.0, precision="float64")
    v = fw.valid
    bw = wide22.trace(fw.position[v], -fw.direction[v], 520.0, direction="backward",
                      precision="float64", z_out=-3.0)
    assert bw.valid.all()
    np.testing.assert_allclose(bw.position, o[v], atol=1e-8)
    np.testing.assert_allclose(bw.direction, -d[v], atol=1e-11)
    np.testing.assert_allclose(bw.throughput, fw.throughput[v], rtol=1e-10)  # Fresnel T is reciprocal


def _fresnel_T_independent(n1, n2, ci):
    """Transmittance from the amplitude *transmission* coefficients (not 1 − R)."""
    st2 = (n1 / n2) ** 2 * (1 - ci ** 2)
    ct = np.sqrt(1 - st2)
    ts = 2 * n1 * ci / (n1 * ci + n2 * ct)
    tp = 2 * n1 * ci / (n2 * ci + n1 * ct)
    fac = (n2 * ct) / (n1 * ci)
    return 0.5 * fac * (ts ** 2 + tp ** 2), ct


def _coated_T_independent(n1, nc, n2, ci, lam, h):
    """Thin-film transmittance from the Airy transmission amplitude, per polarisation, averaged."""
    s1 = np.sqrt(1 - ci ** 2)
    cc = np.sqrt(1 - (n1 * s1 / nc) ** 2 + 0j)
    c2 = np.sqrt(1 - (n1 * s1 / n2) ** 2 + 0j)
    beta = 2 * np.pi * nc * h * cc / lam
    out = 0
    for pol in ("s", "p"):
        def rt(na, ca, nb, cb):
            if pol == "s":
                return (na * ca - nb * cb) / (na * ca + nb * cb), 2 * na * ca / (na * ca + nb * cb)
            return (nb * ca - na * cb) / (nb * ca + na * cb), 2 * na * ca / (nb * ca + na * cb)
        r12, t12 = rt(n1, ci, nc, cc)
        r23, t23 = rt(nc, cc, n2, c2)
        t = t12 * t23 * np.exp(1j * beta) / (1 + r12 * r23 * np.exp(2j * beta))
        out = out + 0.5 * np.abs(t) ** 2 * (n2 * c2.real) / (n1 * ci)
    return out, c2.real


@pytest.mark.parametrize("n1,n2", [(1.0, 1.5), (1.7, 1.0), (1.52, 1.75), (1.0, 1.9)])
def test_R_plus_T_is_one(n1, n2):
    import drjit as dr
    from mi_neurallens.trace.api import float_type
    from mi_neurallens.trace.interactions import coated_reflectance, fresnel_reflectance
    F = float_type("float64")
    crit = 0.0 if n1 <= n2 else math.sqrt(1 - (n2 / n1) ** 2)
    ci = np.linspace(max(crit, 0.0) + 1e-3, 1.0, 200)
    T, ct = _fresnel_T_independent(n1, n2, ci)
    R = fresnel_reflectance(n1, n2, F(ci), F(ct)).numpy()
    np.testing.assert_allclose(R + T, 1.0, atol=1e-12)
    if n1 == 1.0:  # coated air–glass interface
        lam, nc = 520.0, 1.38
        h = 550.0 / (4 * nc)
        Tc, ct = _coated_T_independent(n1, nc, n2, ci, lam, h)
        Rc = coated_reflectance(n1, n2, F(ci), F(ct), F(np.full_like(ci, lam)), nc, h).numpy()
        np.testing.assert_allclose(Rc + Tc, 1.0, atol=1e-12)
        assert Rc.max() < R.max()


def test_quarter_wave_coating_normal_incidence():
    """At its design wavelength and normal incidence a quarter-wave layer reflects
    ((n1 n2 − nc²)/(n1 n2 + nc²))²."""
    from mi_neurallens.trace.api import float_type
    from mi_neurallens.trace.interactions import coated_reflectance
    F = float_type("float64")
    n2, nc, lam = 1.52, 1.38, 550.0
    R = coated_reflectance(1.0, n2, F(1.0), F(1.0), F(lam), nc, lam / (4 * nc)).numpy()[0]
    assert R == pytest.approx(((n2 - nc ** 2) / (n2 + nc ** 2)) ** 2, rel=1e-12)


@pytest.mark.parametrize("n", [1.5, 1.8])
def test_plate_sum_of_paths_closed_form(n):
    """On a plane-parallel plate at normal incidence Σ over paths with 0, 2, 4, … internal
    reflections of the throughput is the incoherent closed form (1 − R)/(1 + R); each round
    trip shifts an oblique ray by 2 h tan θt (checked at 20°)."""
    L = plate(thickness=5.0, n=n)
    o = np.array([[0.0, 0.0, -1.0]])
    d = np.array([[0.0, 0.0, 1.0]])
    R = ((n - 1) / (n + 1)) ** 2
    total = 0.0
    for k in range(8):
        pid = ((1 << (2 * k)) - 1) << 1  # T@front, (R@back, R@front)^k, T@back
        res = L.trace(o, d, 550.0, path=pid, precision="float64")
        assert res.valid[0]
        assert res.throughput[0] == pytest.approx((1 - R) ** 2 * R ** (2 * k), rel=1e-10)
        total += res.throughput[0]
    assert total == pytest.approx((1 - R) / (1 + R), rel=1e-12)
    th = math.radians(20)
    d2 = np.array([[math.sin(th), 0.0, math.cos(th)]])
    t0 = L.trace(o, d2, 550.0, precision="float64")
    g = L.trace(o, d2, 550.0, path=ghost_id(1, 0), precision="float64")
    tt = math.asin(math.sin(th) / n)
    assert g.position[0, 0] - t0.position[0, 0] == pytest.approx(2 * 5.0 * math.tan(tt), rel=1e-10)
    np.testing.assert_allclose(g.direction, t0.direction, atol=1e-14)


def test_ghost_enumeration(wide22):
    ghosts = all_ghosts(wide22)
    n = len(wide22.optical_indices)
    assert n == 12 and len(ghosts) == n * (n - 1) // 2 == 66
    assert len({g[0] for g in ghosts}) == 66
    for pid, a, b in ghosts:
        assert ghost_surfaces(pid) == (a, b)
        spec = resolve_path(wide22, pid)
        assert spec.num_reflections == 2
        kinds = [s.kind for s in spec.interactions]
        # a forward ghost hits a + (a - b) + (n - b) surfaces
        assert len(kinds) == a + 1 + (a - b) + (n - b - 1)
        refl = [s.surface for s in spec.interactions if s.kind == "R"]
        assert refl == [wide22.optical_indices[a], wide22.optical_indices[b]]
    assert len(all_ghosts(plate())) == 1


def test_energy_conservation_over_paths(wide22):
    """Energy arriving at the sensor over the transmit path and all 66 ghosts never exceeds what
    entered; on a plate it approaches the closed form as more paths are added."""
    rng = np.random.default_rng(0)
    o, d = passing_rays(wide22, 4000, rng)
    total = wide22.trace(o, d, 550.0, precision="float64").throughput
    for pid, a, b in all_ghosts(wide22):
        total = total + wide22.trace(o, d, 550.0, path=pid, precision="float64").throughput
    assert np.all(total <= 1.0)
    assert total.max() > 0.5


def test_stop_blades_and_housing(wide22):
    """A hexagonal stop whose inscribed circle is the round stop's radius passes every ray the round
    stop passed, plus rays that cross the stop plane between the inscribed and circumscribed
    circles; a housing tighter than a clear aperture blocks rays."""
    rng = np.random.default_rng(11)
    o, d = field_rays(wide22, 40000, 5, rng)
    wide22 = wide22.with_stop_radius(2.0)  # stopped down so that the stop, not a rim, limits
    base = wide22.trace(o, d, 550.0)
    hexa = wide22.with_surface(wide22.stop_index, blades=6)
    res = hexa.trace(o, d, 550.0, record=True)
    r_stop = wide22.stop.semi_diameter
    stop_step = [i for i, s in enumerate(resolve_path(wide22, 0).steps) if s.kind == "stop"][0] + 1
    p = res.points[:, stop_step, :2]
    rho = np.hypot(p[:, 0], p[:, 1])
    assert np.all(res.valid[base.valid])
    gained = res.valid & ~base.valid
    assert gained.sum() > 20
    assert np.all(rho[gained] >= r_stop * (1 - 1e-6))
    assert np.all(rho[gained] <= r_stop / math.cos(math.pi / 6) * (1 + 1e-6))
    # every gained ray crosses the stop plane inside the hexagon (edge normals at 0°, 60°, …)
    th = np.radians(60.0 * np.arange(6))
    support = p[gained] @ np.stack([np.cos(th), np.sin(th)])
    assert np.all(support.max(1) <= r_stop * (1 + 1e-6))
    # and the hexagon's area gain over the circle shows up in the ray count: 2√3/π − 1 ≈ 10 %
    assert 0.05 < gained.sum() / base.valid.sum() < 0.15
    tight = wide22.with_surface(0, housing_radius=wide22.surfaces[0].semi_diameter * 0.15)
    assert tight.trace(o, d, 550.0).valid.sum() < base.valid.sum()


def test_coating_reduces_ghost_and_raises_transmission(wide22):
    rng = np.random.default_rng(2)
    o, d = field_rays(wide22, 5000, 10, rng)
    coated = wide22.with_coating(Coating(1.38, 550.0))
    t0 = wide22.trace(o, d, 550.0).throughput
    t1 = coated.trace(o, d, 550.0).throughput
    v = t0 > 0
    assert np.all(t1[v] > t0[v])
    g0 = wide22.trace(o, d, 550.0, path=(5, 2)).throughput.sum()
    g1 = coated.trace(o, d, 550.0, path=(5, 2)).throughput.sum()
    assert g1 < 0.5 * g0


def test_mitsuba_variants_match_numpy(wide22):
    """The tracer runs on mi.Float in Mitsuba's llvm_ad_rgb and llvm_ad_spectral variants."""
    import drjit as dr
    import mitsuba as mi
    from mi_neurallens.trace.tracer import LensTracer
    rng = np.random.default_rng(9)
    o, d = field_rays(wide22, 512, 15, rng)
    ref = wide22.trace(o, d, 600.0)
    for variant in (default_variant(), default_variant("spectral")):
        mi.set_variant(variant)
        F = mi.Float
        res = LensTracer(wide22).trace(tuple(F(o[:, i]) for i in range(3)),
                                       tuple(F(d[:, i] / np.linalg.norm(d, axis=1)) for i in range(3)),
                                       F(np.full(len(o), 600.0)))
        dr.eval(res.position, res.valid)
        assert np.array_equal(res.valid.numpy(), ref.valid)
        np.testing.assert_allclose(res.position[0].numpy()[ref.valid], ref.position[ref.valid, 0], atol=1e-4)


def test_bad_paths(wide22):
    o = np.zeros((1, 3))
    d = np.array([[0, 0, 1.0]])
    with pytest.raises(NeuralLensError, match="unknown path"):
        wide22.trace(o, d, 550.0, path="ghostly")
    with pytest.raises(NeuralLensError, match="leaves the lens through the front"):
        wide22.trace(o, d, 550.0, path=1)  # single reflection at the first surface
    with pytest.raises(NeuralLensError, match="0 <= b < a"):
        ghost_id(2, 5)
    with pytest.raises(NeuralLensError, match=r"\(N, 3\)"):
        wide22.trace(np.zeros(3), d, 550.0)
    with pytest.raises(NeuralLensError, match="wavelength"):
        wide22.trace(o, d, -1.0)


def test_record_ends_at_the_blocking_hit(wide22):
    """``record=True`` shows a blocked ray up to and including the hit where it is blocked, and nothing
    after it: a ray above the front element's clear aperture ends on the first surface."""
    sd = wide22.surfaces[0].semi_diameter
    o = np.array([[0.0, 1.3 * sd, -5.0], [0.0, 1.0, -5.0]])
    d = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    r = wide22.trace(o, d, 550.0, record=True, precision="float64")
    assert list(r.valid) == [False, True]
    blocked = r.points[0]
    assert np.isfinite(blocked[1]).all() and blocked[1, 1] > sd          # the hit beyond the clear aperture
    assert np.isnan(blocked[2:]).all()                                    # and nothing after it
    assert np.isfinite(r.points[1]).all()                                 # a valid ray keeps every point
