"""Paraxial optics (mi_neurallens.optics.paraxial) against optiland, rayoptics and closed forms.

Every bundled lens plus two hand-built ones (the pbrt wide.22mm prescription, and a dispersive
conic/asphere triplet that exercises the vertex-curvature rule) is checked at the d line and the F line.
The reference libraries get each medium as a CONSTANT index equal to our ``medium.index(λ)``, so a
difference can only come from the first-order optics, not from the glass model.
"""
from __future__ import annotations

import functools
import json
import math

import numpy as np
import pytest

from mi_neurallens import Lens, LensError, Surface
from mi_neurallens.optics.glass import AIR, Medium, constant
from mi_neurallens.optics.paraxial import ParaxialSystem

WAVELENGTHS = (587.5618, 486.1327)

# pbrt wide.22mm.dat (FORMATS.md §2): radius, thickness, eta, aperture DIAMETER; radius 0 = stop
WIDE22 = [(35.98738, 1.21638, 1.54, 23.716), (11.69718, 9.9957, 1, 17.996),
          (13.08714, 5.12622, 1.772, 12.364), (-22.63294, 1.76924, 1.617, 9.812),
          (71.05802, 0.8184, 1, 9.152), (0, 2.27766, 0, 8.756), (-9.58584, 2.43254, 1.617, 8.184),
          (-11.28864, 0.11506, 1, 9.152), (-166.7765, 3.09606, 1.713, 10.648),
          (-7.5911, 1.32682, 1.805, 11.44), (-16.7662, 3.98068, 1, 12.276),
          (-7.70286, 1.21638, 1.617, 13.42), (-11.97328, 14.3183, 1, 17.996)]

NBK7 = Medium("N-BK7", "sellmeier", (1.03961212, 0.00600069867, 0.231792344, 0.0200179144,
                                     1.01046945, 103.560653))
NSF5 = Medium("N-SF5", "sellmeier", (1.52481889, 0.011254756, 0.187085527, 0.0588995392,
                                     1.42729015, 129.141675))


def hand_wide22() -> Lens:
    s = []
    for r, t, n, ap in WIDE22:
        s.append(Surface(radius=math.inf if r == 0 else r, thickness=t,
                         medium=AIR if n in (0, 1) else constant(n), semi_diameter=ap / 2,
                         is_stop=r == 0))
    return Lens(tuple(s), name="hand-wide22")


def hand_aspheric() -> Lens:
    """A dispersive Cooke-like triplet with a conic and an even-asphere surface."""
    S = Surface
    return Lens((
        S(21.48, 2.0, NBK7, 8.0, conic=-0.6, aspheric=(-2e-6, 1e-9)),
        S(-120.0, 4.5, AIR, 8.0),
        S(-22.0, 1.0, NSF5, 5.5),
        S(20.5, 1.2, AIR, 5.5),
        S(math.inf, 2.5, AIR, 4.6, is_stop=True),
        S(70.0, 2.2, NBK7, 6.5),
        S(-17.5, 41.0, AIR, 6.5, conic=0.8, aspheric=(3e-6,)),
    ), name="hand-aspheric")


HAND = {"hand-wide22": hand_wide22, "hand-aspheric": hand_aspheric}


def _bundled_names():
    try:
        from mi_neurallens.optics.formats import bundled_lenses
    except ImportError:
        return []
    return list(bundled_lenses())


LENS_NAMES = list(HAND) + _bundled_names()


@functools.lru_cache(maxsize=None)
def get_lens(name) -> Lens:
    return HAND[name]() if name in HAND else Lens.load(name)


# ------------------------------------------------------------------------------ reference libraries
@functools.lru_cache(maxsize=None)
def optiland_numbers(name, wl):
    from optiland import optic
    from optiland.materials import IdealMaterial

    lens = get_lens(name)
    mat = lambda m: IdealMaterial(n=float(m.index(wl)))
    L = optic.Optic()
    L.surfaces.add(index=0, radius=np.inf, thickness=np.inf, material=mat(lens.object_medium))
    for i, s in enumerate(lens.surfaces):
        kw = {}
        if s.conic or s.is_aspheric:
            kw = dict(surface_type="even_asphere", conic=s.conic,
                      coefficients=[0.0] + [float(a) for a in s.aspheric])
        L.surfaces.add(index=i + 1, radius=s.radius, thickness=s.thickness, material=mat(s.medium),
                       is_stop=s.is_stop, **kw)
    # the image surface carries the image-space medium too (optiland's default there is n = 1)
    L.surfaces.add(index=len(lens.surfaces) + 1, material=mat(lens.surfaces[-1].medium))
    # the aperture is the stop surface's own diameter: optiland derives the EPD from it
    L.set_aperture(aperture_type="float_by_stop_size", value=2.0 * lens.stop.semi_diameter)
    L.fields.set_type(field_type="angle")
    L.fields.add(y=0.0)
    L.wavelengths.add(value=wl * 1e-3, is_primary=True)
    p = L.paraxial
    f = lambda v: float(np.ravel(v)[0])
    return dict(
        efl=f(p.f2()),
        bfl=lens.surfaces[-1].thickness + f(p.F2()),       # F2 is relative to the image surface
        ep_z=f(p.EPL()),                                     # relative to the first surface (z = 0)
        ep_r=f(p.EPD()) / 2,
        xp_z=lens.image_z + f(p.XPL()),                      # XPL is relative to the image surface
        xp_r=f(p.XPD()) / 2,
        fno=f(p.FNO()),
    )


def rayoptics_model(lens, wl, object_distance=1e10):
    """rayoptics model with constant indices n(λ)/n_object(λ).

    Dividing every index by the object-space index changes no ray path (Snell's law and the
    paraxial equations depend on index ratios only), so every length is unchanged.  It is needed
    because rayoptics 0.9.8 mixes reduced and true slopes when the object space is not n = 1
    (``enp_dist = -ybar1/(n_0*ubar1)`` on top of slopes already scaled): for the ood-59mm lens
    (Ciddor air, n = 1.000277) its raw entrance-pupil distance is off by a factor n_0³ (0.028 mm),
    while optiland with the raw indices and our exact tracer in the paraxial limit both agree
    with us to < 1e-5 mm (see test_pupils_match_exact_trace_in_paraxial_limit).
    """
    from opticalglass.opticalmedium import ConstantIndex
    from rayoptics.environment import OpticalModel

    n_obj = float(lens.object_medium.index(wl))

    opm = OpticalModel()
    sm, osp = opm["seq_model"], opm["optical_spec"]
    osp["pupil"].value = 10.0                     # EPD; rescaled to the stop size below
    osp["wvls"].set_from_list([[wl, 1.0]])
    osp["fov"].set_from_list([0.0, 5.0])
    opm.radius_mode = True
    sm.gaps[0].thi = object_distance
    sm.gaps[0].medium = ConstantIndex(1.0, "object")
    for i, s in enumerate(lens.surfaces):
        sm.add_surface([0.0 if math.isinf(s.radius) else s.radius, s.thickness], sd=s.semi_diameter)
        sm.gaps[-1].medium = ConstantIndex(float(s.medium.index(wl)) / n_obj, f"m{i}")
        if s.conic or s.is_aspheric:
            from rayoptics.elem.profiles import EvenPolynomial
            sm.ifcs[-1].profile = EvenPolynomial(r=s.radius, cc=s.conic,
                                                 coefs=[0.0] + [float(a) for a in s.aspheric])
        if s.is_stop:
            sm.set_stop()
    opm.update_model()
    return opm


@functools.lru_cache(maxsize=None)
def rayoptics_numbers(name, wl):
    lens = get_lens(name)
    opm = rayoptics_model(lens, wl)
    pd = opm["analysis_results"]["parax_data"]
    fod = pd.fod
    sm = opm["seq_model"]
    # rayoptics sizes the beam by the EPD we gave it (10 mm); the stop's own size sets the real
    # pupil: scale by stop semi-diameter / marginal-ray height at the stop.
    scale = lens.stop.semi_diameter / abs(pd.ax_ray[sm.stop_surface][0])
    return dict(
        efl=fod.efl, bfl=fod.bfl,
        ep_z=fod.enp_dist,                       # from the first interface
        ep_r=fod.enp_radius * scale,
        # exp_dist is computed as (distance from the image surface) + img_dist; with the image
        # surface a hair off the paraxial focus this is not "from the last interface", so rebase
        # it on the image surface (our image_z) explicitly.
        xp_z=lens.image_z + (fod.exp_dist - fod.img_dist),
        xp_r=fod.exp_radius * scale,
        fno=fod.efl / (2.0 * fod.enp_radius * scale),
    )


# Tolerances.  EFL/BFL: relative 1e-5 (the brief); both libraries are double-precision paraxial
# traces with the same indices, so they agree far better.  Pupils: rayoptics models "infinity" as an
# object 1e10 mm away; chief-ray heights ~1e9 mm lose ~1e-7 mm to rounding, so positions get
# 1e-5 mm + 1e-6 relative and radii relative 1e-6 — still 100x tighter than any real modelling
# difference (e.g. forgetting an index changes the pupil position by > 1e-3 mm).
POS_ABS, POS_REL, RAD_REL = 1e-5, 1e-6, 1e-6


def _close(a, b, rel=0.0, abs_=0.0):
    return math.isclose(a, b, rel_tol=rel, abs_tol=abs_)


@pytest.mark.parametrize("wl", WAVELENGTHS)
@pytest.mark.parametrize("name", LENS_NAMES)
@pytest.mark.parametrize("library", ["optiland", "rayoptics"])
def test_against_reference_library(name, wl, library):
    lens = get_lens(name)
    p = lens.paraxial(wl)
    ref = (optiland_numbers if library == "optiland" else rayoptics_numbers)(name, wl)
    scale = max(1.0, abs(p.efl))
    assert _close(p.efl, ref["efl"], rel=1e-5), (p.efl, ref["efl"])
    assert _close(p.bfl, ref["bfl"], rel=1e-5, abs_=1e-9 * scale), (p.bfl, ref["bfl"])
    assert _close(p.entrance_pupil_z, ref["ep_z"], rel=POS_REL, abs_=POS_ABS), (p.entrance_pupil_z, ref["ep_z"])
    assert _close(p.exit_pupil_z, ref["xp_z"], rel=POS_REL, abs_=POS_ABS), (p.exit_pupil_z, ref["xp_z"])
    assert _close(p.entrance_pupil_radius, ref["ep_r"], rel=RAD_REL)
    assert _close(p.exit_pupil_radius, ref["xp_r"], rel=RAD_REL)
    assert _close(p.fnumber, ref["fno"], rel=1e-5)
    # the Lens wrappers read the same numbers
    assert lens.efl(wl) == p.efl and lens.bfl(wl) == p.bfl


@pytest.mark.parametrize("name", LENS_NAMES)
def test_finite_conjugates_against_rayoptics(name):
    """Image distance and magnification of an object 40 focal lengths away, vs rayoptics."""
    lens = get_lens(name)
    wl = 587.5618
    p = lens.paraxial(wl)
    d = 40.0 * abs(p.efl) + max(0.0, p.ffl)
    fod = rayoptics_model(lens, wl, object_distance=d)["analysis_results"]["parax_data"].fod
    assert _close(p.image_distance(d), fod.img_dist, rel=1e-7, abs_=1e-7)
    assert _close(p.magnification(d), fod.m, rel=1e-7)


@pytest.mark.parametrize("name", LENS_NAMES)
def test_focus_round_trip_and_matrix(name):
    lens = get_lens(name)
    p = lens.paraxial()
    M = p.abcd()
    assert np.linalg.det(M) == pytest.approx(1.0, abs=1e-12)
    assert M[1, 0] == pytest.approx(-p.power, rel=1e-15)
    assert p.sensor_distance_for(math.inf) == p.bfl
    assert p.focus_distance_for(p.bfl) == math.inf
    for d in (3 * abs(p.efl) + p.ffl, 1000.0, 12345.6, 1e7):
        s = p.sensor_distance_for(d)
        assert s > p.bfl
        assert p.focus_distance_for(s) == pytest.approx(d, rel=1e-9)
    # a sensor closer than the rear focal point focuses nothing
    with pytest.raises(LensError, match="beyond infinity"):
        p.focus_distance_for(p.bfl * 0.99)
    if p.ffl > 0:
        # an object inside the front focal length has no real image
        with pytest.raises(LensError, match="front focal point"):
            p.sensor_distance_for(p.ffl * 0.5)
    else:
        # retrofocus: the front focal point lies behind the first vertex, so any object in front
        # of the lens focuses behind the rear focal point
        assert p.sensor_distance_for(1e-3) > p.bfl
        # ... and a very distant sensor is conjugate to a virtual object behind the first vertex
        with pytest.raises(LensError, match="virtual object"):
            p.focus_distance_for(1e4 * p.efl)
    # JSON-ready, no NaN/inf leaking
    json.dumps(p.to_dict(), allow_nan=False)
    # principal planes: Newton / Gauss in air; EFL = distance H' -> F'
    assert p.rear_focal_z - p.rear_principal_z == pytest.approx(p.efl, rel=1e-12)
    assert p.front_principal_z - p.front_focal_z == pytest.approx(p.front_focal_length, rel=1e-12)
    # working f-number at infinity equals N (image space in air)
    assert p.working_fnumber(math.inf) == pytest.approx(p.fnumber * (1.0 / p.image_index), rel=1e-12)


@pytest.mark.parametrize("name", LENS_NAMES)
def test_pupils_match_exact_trace_in_paraxial_limit(name):
    """The exact (Dr.Jit) tracer at a 0.01° field and 1e-3 of the pupil: entrance pupil = where the
    object-space chief ray (through the stop centre) crosses the axis, exit pupil = where the
    image-space chief ray does; radii from the marginal-ray height ratio and the Lagrange invariant.
    Measured residuals are < 5e-7 mm on every lens (float64 tracer, finite-difference aiming);
    the 1e-5 mm tolerance is 20x that."""
    lens = get_lens(name)
    wl = 587.5618
    p = lens.paraxial(wl)
    ks = lens.stop_index + 1                 # points[:, ks] is the stop hit
    z0 = -5.0 - abs(min(0.0, min(lens.vertex_z[i] + s.sag(s.semi_diameter)
                                 for i, s in enumerate(lens.surfaces))))

    def trace(theta_deg, h):
        t = math.radians(theta_deg)
        d = np.array([0.0, -math.sin(t), math.cos(t)])
        h = np.atleast_1d(np.asarray(h, float))
        o = np.stack([0 * h, h + z0 / d[2] * d[1], 0 * h + z0], 1)
        r = lens.trace(o, np.tile(d, (len(h), 1)), wl, record=True, precision="float64")
        assert r.valid.all()
        return r

    # chief ray at 0.01°: find the launch height (at z = 0) that crosses the stop centre
    th = 0.01
    tan = math.tan(math.radians(th))
    h0 = p.entrance_pupil_z * tan
    h = h0
    for _ in range(3):                        # secant steps on a 1e-6 pupil-radius baseline
        hs = h + np.array([-1.0, 1.0]) * 1e-6 * p.entrance_pupil_radius
        ys = trace(th, hs).points[:, ks, 1]
        h = float(hs[0] - ys[0] * (hs[1] - hs[0]) / (ys[1] - ys[0]))
    r = trace(th, [h])
    assert abs(r.points[0, ks, 1]) < 1e-7 * lens.stop.semi_diameter
    assert h / tan == pytest.approx(p.entrance_pupil_z, abs=1e-5)
    P, D = r.position[0], r.direction[0]
    xp_z = P[2] - P[1] / D[1] * D[2]
    assert xp_z == pytest.approx(p.exit_pupil_z, abs=1e-5)
    # entrance pupil radius: an on-axis ray at 1e-3 of the pupil, scaled by its stop height
    hm = 1e-3 * p.entrance_pupil_radius
    ym = trace(0.0, [hm]).points[0, ks, 1]
    ep_r = lens.stop.semi_diameter * hm / abs(ym)
    assert ep_r == pytest.approx(p.entrance_pupil_radius, rel=1e-5)
    # exit pupil radius from the Lagrange invariant of the chief ray: n ū r_ep = n' ū' r_xp
    u_img = abs(D[1] / D[2])
    xp_r = p.object_index * tan * ep_r / (p.image_index * u_img)
    assert xp_r == pytest.approx(p.exit_pupil_radius, rel=1e-5)


# ------------------------------------------------------------------------------ closed forms
def _singlet(R1, R2, t, n, sd=5.0, stop_gap=2.0, back=None):
    g = constant(n, "glass")
    return Lens((
        Surface(math.inf, stop_gap, AIR, sd, is_stop=True),
        Surface(R1, t, g, sd),
        Surface(R2, 100.0 if back is None else back, AIR, sd),
    ), name="singlet")


@pytest.mark.parametrize("R1,R2,t,n", [(50.0, -80.0, 6.0, 1.5168), (30.0, 200.0, 4.0, 1.8),
                                       (-100.0, -25.0, 3.0, 1.6), (40.0, math.inf, 5.0, 1.7)])
def test_thick_lens_lensmaker(R1, R2, t, n):
    lens = _singlet(R1, R2, t, n)
    p = lens.paraxial()
    c1, c2 = 1 / R1, (0.0 if math.isinf(R2) else 1 / R2)
    phi = (n - 1) * (c1 - c2 + (n - 1) * t * c1 * c2 / n)
    f = 1 / phi
    assert p.efl == pytest.approx(f, rel=1e-12)
    assert p.bfl == pytest.approx(f * (1 - (n - 1) * t * c1 / n), rel=1e-12)
    # the stop is the first surface (z = 0), 2 mm in front of the lens: ffl is measured from it
    assert p.ffl == pytest.approx(f * (1 + (n - 1) * t * c2 / n) - 2.0, rel=1e-12)
    # principal planes: H at the first vertex + f (n−1) t c2 / n ... (standard thick-lens result)
    z1 = lens.vertex_z[1]
    assert p.front_principal_z == pytest.approx(z1 - f * (n - 1) * t * c2 / n, abs=1e-12 * abs(f))
    assert p.rear_principal_z == pytest.approx(z1 + t - f * (n - 1) * t * c1 / n, abs=1e-12 * abs(f))
    # stop 2 mm in front of the lens in air: entrance pupil = stop itself; exit pupil = its image
    assert p.entrance_pupil_z == 0.0 and p.entrance_pupil_radius == 5.0
    assert p.fnumber == pytest.approx(abs(f) / 10.0, rel=1e-12)
    if phi > 0:
        # Gauss with distances from the principal planes (exact in air for any thick lens)
        for d in (3 * f, 10 * f, 1234.5):
            s_obj = d + p.front_principal_z - 0.0          # object -> H (object at z = -d)
            s_img = 1 / (1 / f - 1 / s_obj)                # H' -> image
            assert p.sensor_distance_for(d) == pytest.approx(p.rear_principal_z + s_img - lens.vertex_z[-1],
                                                             rel=1e-11)
            assert p.magnification(d) == pytest.approx(-s_img / s_obj, rel=1e-11)
    # the exit pupil is the stop imaged through the lens: Gauss from the stop (a virtual object
    # 2 mm in front of the vertex)
    s_obj = 2.0 + (p.front_principal_z - z1)
    s_img = 1 / (1 / f - 1 / s_obj)
    assert p.exit_pupil_z == pytest.approx(p.rear_principal_z + s_img, rel=1e-11)
    assert p.exit_pupil_radius == pytest.approx(5.0 * abs(s_img / s_obj), rel=1e-11)


def test_thin_lens_limit_gaussian_formula():
    """A 20 µm thick biconvex lens of f ≈ 100 mm obeys 1/s + 1/s' = 1/f from the vertices."""
    n, R = 1.5, 100.0
    lens = _singlet(R, -R, 0.02, n, sd=1.0, stop_gap=0.5)
    p = lens.paraxial()
    f = 1 / ((n - 1) * 2 / R)
    assert p.efl == pytest.approx(f, rel=2e-4)           # thickness correction ~ (n−1) t/(n R) ≈ 7e-5
    for d in (150.0, 300.0, 1000.0, 1e5):
        s = p.sensor_distance_for(d - 0.5)               # from the stop (first vertex), 0.5 mm in front
        assert s == pytest.approx(1 / (1 / f - 1 / d), rel=5e-4)
    assert p.focus_distance_for(1 / (1 / f - 1 / 400.0)) + 0.5 == pytest.approx(400.0, rel=5e-4)


def test_fov_and_depth_of_field_closed_forms():
    lens = _singlet(50.0, -50.0, 4.0, 1.5)
    p0 = lens.paraxial()
    lens = lens.with_sensor_distance(p0.bfl)             # focused at infinity
    p = lens.paraxial()
    f = p.efl
    assert p.image_height_per_tan() == pytest.approx(f, rel=1e-12)
    assert p.fov_deg(2 * f * math.tan(math.radians(20))) == pytest.approx(40.0, rel=1e-12)
    fov = p.fov_deg(36.0, 24.0)
    assert fov.horizontal == pytest.approx(2 * math.degrees(math.atan(18 / f)), rel=1e-12)
    assert fov.vertical == pytest.approx(2 * math.degrees(math.atan(12 / f)), rel=1e-12)
    assert fov.diagonal == pytest.approx(2 * math.degrees(math.atan(math.hypot(18, 12) / f)), rel=1e-12)
    # depth of field: classic thin-lens-in-air formulas with s from the front principal plane
    N, c, d = 4.0, 0.03, 2000.0
    dof = p.depth_of_field(d, N, c)
    s = d + p.front_principal_z
    near = s * f * f / (f * f + N * c * (s - f)) - p.front_principal_z
    far = s * f * f / (f * f - N * c * (s - f)) - p.front_principal_z
    assert dof.near_mm == pytest.approx(near, rel=1e-10)
    assert dof.far_mm == pytest.approx(far, rel=1e-10)
    H = f * f / (N * c) + f - p.front_principal_z
    assert dof.hyperfocal_mm == pytest.approx(H, rel=1e-10)
    assert math.isinf(p.depth_of_field(H * 1.0001, N, c).far_mm)
    assert p.depth_of_field(H * 1.0001, N, c).near_mm == pytest.approx(H / 2, rel=1e-3)


def test_afocal_system_raises():
    """A Keplerian telescope of two f = 100 mm plano-convex lenses (n = 1.5, R = 50, 1 mm thick).

    Their principal planes sit at the curved vertices' … H'1 = z0 + t(1 − 1/n), H2 = z3 + t/n, so the
    system is afocal when the air space gives H'1 → H2 = 2f = 200 mm: gap = 200 − 2 t/n… solved here.
    """
    g = constant(1.5, "glass")
    t, n, f = 1.0, 1.5, 100.0
    # H'1 = t - t/n; H2 = (t + gap1 + 1) + t/n  ->  H2 - H'1 = 2f
    gap1 = 2 * f - t - 1.0 - 2 * t / n + t
    lens = Lens((
        Surface(50.0, t, g, 5.0), Surface(math.inf, gap1, AIR, 5.0),
        Surface(math.inf, 1.0, AIR, 3.0, is_stop=True),
        Surface(math.inf, t, g, 5.0), Surface(-50.0, 10.0, AIR, 5.0),
    ), name="telescope")
    with pytest.raises(LensError, match="afocal"):
        ParaxialSystem(lens)
    # 1 mm more and it focuses again (power = −Δ/f²)
    p = lens.with_surface(1, thickness=gap1 + 1.0).paraxial()
    assert p.power == pytest.approx(-1.0 / f**2, rel=1e-9)


def test_dispersion_changes_efl():
    lens = hand_aspheric()
    f_d, f_F, f_C = (lens.efl(w) for w in (587.5618, 486.1327, 656.2725))
    assert f_F != f_d != f_C
    # bad wavelength / object distance give LensError
    with pytest.raises(LensError):
        lens.paraxial(-5)
    with pytest.raises(LensError):
        lens.paraxial().sensor_distance_for(-10.0)
