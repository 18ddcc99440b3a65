"""The ``realistic_lens`` sensor: loading, radiometry, agreement with thinlens, focus, distortion,
pupil sampling, errors.  Small films and few samples: the whole file runs in well under a minute."""
from __future__ import annotations

import math

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")
import drjit as dr  # noqa: E402

import mi_neurallens as nl  # noqa: E402
from mi_neurallens.optics.glass import AIR, constant  # noqa: E402
from mi_neurallens.optics.prescription import Lens, Surface  # noqa: E402
from mi_neurallens.render_utils import default_variant  # noqa: E402
from mi_neurallens.sensors.common import configure_lens  # noqa: E402
from mi_neurallens.sensors.pupil import PupilBounds, measure_pass_fraction  # noqa: E402

RGB, SPECTRAL = default_variant(), default_variant("spectral")   # $MI_NEURALLENS_VARIANT


def use(variant=RGB):
    mi.set_variant(variant)
    names = nl.register()
    assert "realistic_lens" in names
    return names


def film(w, h):
    return {"type": "hdrfilm", "width": w, "height": h, "rfilter": {"type": "box"}, "pixel_format": "rgb"}


def sensor(w=16, h=12, spp=64, **kw):
    d = {"type": "realistic_lens", "film": film(w, h), "sampler": {"type": "ldsampler", "sample_count": spp}}
    d.update(kw)
    return d


def render(sensor_dict, shapes=None, env=1.0, max_depth=2, seed=0):
    scene = {"type": "scene", "integrator": {"type": "path", "max_depth": max_depth}, "sensor": sensor_dict}
    if env:
        scene["env"] = {"type": "constant", "radiance": {"type": "rgb", "value": env}}
    scene.update(shapes or {})
    img = mi.render(mi.load_dict(scene), seed=seed)
    return np.array(img, dtype=np.float64)


def centre(img, k=2):
    h, w = img.shape[:2]
    return img[h // 2 - k:h // 2 + k, w // 2 - k:w // 2 + k].reshape(-1, img.shape[2]).mean(0)


def light(pos, radius, radiance):
    return {"type": "sphere", "center": list(pos), "radius": radius,
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": radiance}}}


# ------------------------------------------------------------------------------------------ loading
@pytest.mark.parametrize("variant", [RGB, SPECTRAL])
def test_load_dict_and_xml_and_furnace_centre(variant):
    """Loads from a dict and from XML in RGB and spectral; a uniform environment of radiance 1 seen
    through the lens stopped to f/8 without Fresnel loss renders to 1 at the centre."""
    use(variant)
    s = mi.load_dict(sensor(lens="wide-22mm", fstop=8.0, fresnel=False))
    assert "RealisticLens[lens='wide-22mm'" in str(s) and "f/8" in str(s)
    xml = """<scene version="3.0.0"><integrator type="path"/>
      <sensor type="realistic_lens"><string name="lens" value="wide-22mm"/><float name="fstop" value="8"/>
        <boolean name="fresnel" value="false"/>
        <sampler type="ldsampler"><integer name="sample_count" value="1024"/></sampler>
        <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="24"/>
          <string name="pixel_format" value="rgb"/><rfilter type="box"/></film></sensor>
      <emitter type="constant"><rgb name="radiance" value="1"/></emitter></scene>"""
    img = np.array(mi.render(mi.load_string(xml)), dtype=np.float64)
    c = centre(img, 1)
    assert np.all(np.abs(c - 1.0) < 0.02), c
    assert img[0, 0].mean() < 0.7 * c.mean()        # vignetting toward the corners
    use(RGB)


@pytest.mark.parametrize("variant", [RGB, SPECTRAL])
def test_dispersive_lens_furnace_is_white(variant):
    """One importance-sampled wavelength per ray with the RGB (XYZ→sRGB·D65) or spectral weight: a
    dispersive lens stopped down, no Fresnel loss, keeps white white and the centre at 1."""
    use(variant)
    img = render(sensor(8, 6, 1024, lens="canon-ef-24mm-f1.4l", fstop=8.0, fresnel=False))
    c = centre(img, 1)
    assert np.all(np.abs(c - 1.0) < 0.03), c
    assert np.ptp(c) < 0.03, c
    use(RGB)


def test_relative_illumination_matches_numpy_trace():
    """Furnace with Fresnel loss, wide open: pixel = relative illumination × transmittance, checked
    against an independent numpy estimate with ``lens.trace`` (uniform rays into a large disk)."""
    use(RGB)
    W, H, spp = 24, 18, 1024
    img = render(sensor(W, H, spp, lens="wide-22mm"))[..., 1]
    lens = nl.Lens.load("wide-22mm")
    px = lens.paraxial()
    norm = 1.0 / (math.pi * (1.0 / (2.0 * px.fnumber)) ** 2)
    z_img, z_s = lens.image_z, lens.vertex_z[-1]
    dz = z_img - z_s
    w_mm, h_mm = 36.0, 27.0
    rng = np.random.default_rng(5)
    n = 300_000
    for (i, j) in [(12, 9), (15, 11), (18, 13), (21, 15), (23, 17)]:
        fx = ((i + rng.random(n)) / W - 0.5) * w_mm
        fy = ((j + rng.random(n)) / H - 0.5) * h_mm
        R = 14.0                                   # a disk much larger than the rear element (9 mm)
        rad = R * np.sqrt(rng.random(n))
        phi = 2 * np.pi * rng.random(n)
        X, Y = rad * np.cos(phi), rad * np.sin(phi)
        d = np.stack([X - fx, Y - fy, np.full(n, -dz)], 1)
        cos = dz / np.linalg.norm(d, axis=1)
        res = lens.trace(np.stack([fx, fy, np.full(n, z_img)], 1), d, 550.0, direction="backward")
        est = np.mean(res.throughput * cos ** 4) * math.pi * R * R / dz ** 2 * norm
        assert abs(img[j, i] - est) < 0.04 * est + 0.004, (i, j, img[j, i], est)
    assert img[17, 23] < 0.4 * img[9, 12]


# ------------------------------------------------------------------------------------------ thin lens
def planoconvex(f=500.0, fnum=16.0, n=1.5168):
    return Lens((Surface(math.inf, 1.0, AIR, f / fnum / 2, is_stop=True),
                 Surface(f * (n - 1), 3.0, constant(n), 20.0),
                 Surface(math.inf, f, AIR, 20.0)), name="planoconvex-500")


def test_agrees_with_thinlens(tmp_path):
    """A weak slow plano-convex lens (f = 500 mm, f/16, 0.9° field) renders like Mitsuba's thinlens with
    the same focal plane, aperture (entrance pupil) and field: in focus chart + a defocused ball."""
    use(RGB)
    lens = planoconvex()
    path = str(tmp_path / "pc500.json")
    lens.save(path)
    W, H, spp, focus = 48, 36, 256, 8.0
    st = configure_lens(lens, focus_distance_mm=focus * 1000, sensor_width_mm=8.0, film_size=(W, H))
    px = st.lens.paraxial()
    s_img = st.image_z - px.rear_principal_z
    d_front = (st.image_z - px.front_principal_z) / 1000.0
    fov = 2 * math.degrees(math.atan(0.5 * st.sensor_width_mm / s_img))
    shapes = {
        "chart": {"type": "rectangle",
                  "to_world": mi.ScalarTransform4f().translate([0.003, 0.002, focus]).rotate([0, 1, 0], 180)
                  .scale([0.1, 0.1, 1]),
                  "bsdf": {"type": "diffuse", "reflectance": {
                      "type": "checkerboard", "color0": {"type": "rgb", "value": 0.05},
                      "color1": {"type": "rgb", "value": 0.9}, "to_uv": mi.ScalarTransform4f().scale([6, 6, 1])}}},
        "ball": {"type": "sphere", "center": [0.02, 0.01, 4.0], "radius": 0.01,
                 "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.9, 0.1, 0.1]}}},
    }
    a = render(sensor(W, H, spp, lens=path, fresnel=False, focus_distance=focus, sensor_width=8.0), shapes)
    tl = {"type": "thinlens", "fov": fov, "fov_axis": "x", "aperture_radius": px.entrance_pupil_radius / 1000,
          "focus_distance": focus - d_front, "to_world": mi.ScalarTransform4f().translate([0, 0, d_front]),
          "film": film(W, H), "sampler": {"type": "ldsampler", "sample_count": spp}}
    b = render(tl, shapes)
    b2 = render(tl, shapes, seed=11)
    down = lambda x: x.reshape(H // 4, 4, W // 4, 4, 3).mean((1, 3))
    diff, noise = np.abs(down(a) - down(b)).mean(), np.abs(down(b2) - down(b)).mean()
    assert diff < 3.0 * noise + 2e-3, (diff, noise)
    assert abs(a.mean() - b.mean()) < 0.01 * b.mean()
    # the defocused ball: same blur (its red-minus-green footprint)
    fa, fb = (a[..., 0] - a[..., 1]), (b[..., 0] - b[..., 1])
    assert abs(fa.sum() - fb.sum()) < 0.05 * fb.sum()
    assert np.abs(fa - fb).sum() < 0.25 * fb.sum()


# ------------------------------------------------------------------------------------------ focus
def test_focus_spot_and_defocus_disc():
    """dgauss-50mm at f/4 focused at 1 m: a small light at 1 m is a spot of ~1 px; one at 10 m is a
    disc whose diameter matches the paraxial prediction (exit pupil, image distances)."""
    use(RGB)
    W, H, spp, sw = 64, 48, 1024, 4.0
    kw = dict(lens="dgauss-50mm", fstop=4.0, focus_distance=1.0, sensor_width=sw, fresnel=False)
    pix = sw / W
    near = render(sensor(W, H, spp, **kw), {"l": light([0, 0, 1.0], 0.0002, 2000.0)}, env=0)[..., 1]
    tot = near.sum()
    yy, xx = np.mgrid[0:H, 0:W] + 0.5
    cx, cy = (near * xx).sum() / tot, (near * yy).sum() / tot
    assert abs(cx - W / 2) < 0.5 and abs(cy - H / 2) < 0.5
    r = np.hypot(xx - cx, yy - cy)
    assert near[r < 2.0].sum() > 0.8 * tot                 # 80 % of the energy within 2 px
    # a light 1 cm in radius 10 m away: its sharp image is ~1.6 px across, small against the disc
    far = render(sensor(W, H, spp, **kw), {"l": light([0, 0, 10.0], 0.01, 2000.0)}, env=0)[..., 1]
    st = configure_lens(nl.Lens.load("dgauss-50mm"), fstop=4.0, focus_distance_mm=1000.0,
                        sensor_width_mm=sw, film_size=(W, H))
    px = st.lens.paraxial()
    z_far = st.lens.vertex_z[-1] + px.image_distance(10000.0 - st.image_z)
    d_pred = 2 * px.exit_pupil_radius * abs(st.image_z - z_far) / abs(z_far - px.exit_pupil_z) / pix
    plateau = np.median(far[far > 0.2 * far.max()])
    area = (far > 0.5 * plateau).sum()
    d_meas = 2 * math.sqrt(area / math.pi)
    assert d_pred > 8
    assert abs(d_meas - d_pred) < 0.1 * d_pred + 1.0, (d_meas, d_pred)


# ------------------------------------------------------------------------------------------ distortion
def chief_ray_height(lens, theta_deg, lam=550.0):
    """Image-plane x (mm) of the chief ray (through the stop centre) of a parallel beam at
    ``theta_deg`` toward -x (an object on the +x side of lens space)."""
    t = math.radians(theta_deg)
    x0 = np.linspace(-25, 25, 4001)
    n = x0.size
    o = np.stack([x0, np.zeros(n), np.full(n, -5.0)], 1)
    d = np.tile([-math.sin(t), 0.0, math.cos(t)], (n, 1))
    res = lens.trace(o, d, lam, record=True, precision="float64", fresnel=False)
    xs = res.points[:, 1 + lens.stop_index, 0]
    ok = np.isfinite(xs)
    x0s = np.interp(0.0, xs[ok], x0[ok])
    r = lens.trace(np.array([[x0s, 0, -5.0]]), d[:1], lam, precision="float64", fresnel=False)
    return float(r.position[0, 0])


def test_distortion_matches_chief_rays():
    """Point-like lights far away at field angles 0–33°: their image centroids sit where the traced
    chief rays land (not where an ideal f·tanθ lens would put them).  Renders a 320 px wide film,
    cropped to a 16 px strip through the centre."""
    use(RGB)
    W, H, spp, ch = 320, 240, 256, 16
    lens = nl.Lens.load("wide-22mm")
    angles = [0.0, 12.0, 24.0, 33.0]
    D = 1000.0
    shapes = {f"l{k}": light([D * math.sin(math.radians(a)), 0.0, D * math.cos(math.radians(a))], 2.5, 300.0)
              for k, a in enumerate(angles)}   # 2.5 m at 1 km: ~0.5 px images
    f = film(W, H)
    f.update(crop_offset_x=0, crop_offset_y=H // 2 - ch // 2, crop_width=W, crop_height=ch)
    img = render(dict(sensor(W, H, spp, lens="wide-22mm", fstop=8.0, fresnel=False), film=f), shapes,
                 env=0)[..., 1]
    assert img.shape == (ch, W)
    efl = lens.paraxial().efl
    yy, xx = np.mgrid[0:ch, 0:W] + 0.5
    worst_ideal = 0.0
    for a in angles:
        h = chief_ray_height(lens, a)           # lens-space x (negative: the image is inverted)
        u_pred = (0.5 + h / 36.0) * W           # film x (px) of lens-space x = h
        I = img * (np.abs(xx - u_pred) < 6)
        u_meas = (I * xx).sum() / I.sum()
        v_meas = (I * yy).sum() / I.sum()
        assert abs(u_meas - u_pred) < 0.3, (a, u_meas, u_pred)
        assert abs(v_meas - ch / 2) < 0.3
        worst_ideal = max(worst_ideal, abs(u_pred - (0.5 - efl * math.tan(math.radians(a)) / 36.0) * W))
    assert worst_ideal > 1.2                     # the lens has measurable distortion


# ------------------------------------------------------------------------------------------ pupil
def test_exit_pupil_bounds_enclose_every_passing_ray_and_are_efficient():
    lens = nl.Lens.load("wide-22mm")
    st = configure_lens(lens, film_size=(4, 3))
    ep, re = PupilBounds(st, "exit_pupil"), PupilBounds(st, "rear_element")
    n = 1 << 20
    rng = np.random.default_rng(2)
    fx = (rng.random(n) - 0.5) * 36.0
    fy = (rng.random(n) - 0.5) * 27.0
    X, Y, _ = re.sample_np(fx, fy, rng.random(n), rng.random(n))
    res = lens.trace(np.stack([fx, fy, np.full(n, re.z_img)], 1),
                     np.stack([X - fx, Y - fy, np.full(n, -re.dz)], 1), 550.0, direction="backward")
    assert res.valid.sum() > 20000
    assert ep.contains_np(fx[res.valid], fy[res.valid], X[res.valid], Y[res.valid]).all()
    pe, pr = measure_pass_fraction(ep), measure_pass_fraction(re)
    assert pe > 0.75 and pe > 10 * pr, (pe, pr)


def test_exit_pupil_and_rear_element_renders_agree():
    """No bias: the same chart through exit-pupil and rear-element sampling (block means)."""
    use(RGB)
    W, H = 32, 24
    shapes = {"chart": {"type": "rectangle",
                        "to_world": mi.ScalarTransform4f().translate([0, 0, 2.0]).rotate([0, 1, 0], 180)
                        .scale([1.6, 1.2, 1]),
                        "bsdf": {"type": "diffuse", "reflectance": {
                            "type": "checkerboard", "color0": {"type": "rgb", "value": 0.1},
                            "color1": {"type": "rgb", "value": 0.9},
                            "to_uv": mi.ScalarTransform4f().scale([3, 3, 1])}}}}
    kw = dict(lens="wide-22mm", focus_distance=2.0)
    a = render(sensor(W, H, 256, **kw), shapes)[..., 1]
    b = render(sensor(W, H, 4096, pupil_sampling="rear_element", **kw), shapes)[..., 1]
    down = lambda x: x.reshape(H // 4, 4, W // 4, 4).mean((1, 3))
    da, db = down(a), down(b)
    assert np.abs(da - db).max() < 0.06 * da.max(), np.abs(da - db).max()
    assert abs(a.mean() - b.mean()) < 0.01 * a.mean()


# ------------------------------------------------------------------------------------------ errors
def _load_error(**kw):
    use(RGB)
    with pytest.raises(Exception) as e:
        mi.load_dict(sensor(**kw))
    msg = str(e.value)
    c = e.value
    while c.__cause__ is not None:
        c = c.__cause__
        msg += " | " + str(c)
    return msg


@pytest.mark.parametrize("kw, text", [
    (dict(focus_distance=2.0, sensor_distance=15.0), "not both"),
    (dict(focus_distance=-1.0), "'focus_distance': must be > 0"),
    (dict(sensor_distance=-3.0), "'sensor_distance': must be > 0"),
    (dict(fstop=1.0), "f/1 is wider than lens 'wide-22mm' allows: its widest aperture is f/2.68"),
    (dict(fstop=-2.0), "'fstop': must be > 0"),
    (dict(sensor_width=0.0), "'sensor_width': must be > 0"),
    (dict(scene_unit_mm=-1.0), "'scene_unit_mm': must be > 0"),
    (dict(lens="no-such-lens"), "no-such-lens"),
    (dict(lens="/nonexistent/dir/x.json"), "not found"),
    (dict(pupil_sampling="random"), "'pupil_sampling': must be one of 'exit_pupil', 'rear_element'"),
    (dict(focus_distance=0.01), "closer than this lens can focus"),
    (dict(fresnel="maybe"), "'fresnel'"),
    (dict(focal_length=50.0), "focal_length"),
])
def test_bad_properties_raise_clear_errors(kw, text):
    assert text in _load_error(**kw)


def test_unknown_lens_lists_bundled_names():
    msg = _load_error(lens="no-such-lens")
    assert "wide-22mm" in msg and "realistic_lens: property 'lens'" in msg


def test_ptracer_gets_a_clear_message():
    use(RGB)
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "ptracer"}, "sensor": sensor(8, 6, 4),
                          "l": light([0, 0, 2], 0.1, 1.0)})
    with pytest.raises(Exception) as e:
        mi.render(scene)
    msg = str(e.value)
    c = e.value
    while c.__cause__ is not None:
        c = c.__cause__
        msg += str(c)
    assert "not supported" in msg and "sample_direction" in msg


def test_sensor_methods():
    use(RGB)
    s = mi.load_dict(sensor(8, 6, 4, lens="wide-22mm",
                            to_world=mi.ScalarTransform4f().translate([1.0, 2.0, 3.0])))
    params = mi.traverse(s)
    assert "to_world" in params
    bb = s.bbox()
    assert bb.contains(mi.ScalarPoint3f(1.0, 2.0, 3.02))
    n = 64
    u = dr.linspace(mi.Float, 0.01, 0.99, n)
    ray, w = s.sample_ray_differential(mi.Float(0.0), mi.Float(0.0), mi.Point2f(0.5, 0.5),
                                       mi.Point2f(u, dr.reverse(u)))
    assert not ray.has_differentials
    ok = np.array(w)[1] > 0
    assert ok.mean() > 0.5
    o = np.array(ray.o)[:, ok]
    assert np.all(o[2] > 3.0 + 0.04) and np.all(o[2] < 3.0 + 0.06)   # front of the lens, ~48 mm ahead
    d = np.array(ray.d)[:, ok]
    assert np.all(d[2] > 0.99)                                       # centre pixel looks along +z


def test_fstop_rounded_to_the_printed_widest_value_is_wide_open():
    use(RGB)
    s = mi.load_dict(sensor(8, 6, 4, lens="wide-22mm", fstop=2.68))   # widest is f/2.6837
    assert s.setup.fnumber == pytest.approx(s.setup.max_fnumber)
    s = mi.load_dict(sensor(8, 6, 4, lens="wide-22mm", fstop=4.0))
    assert s.setup.fnumber == pytest.approx(4.0, rel=1e-9)
