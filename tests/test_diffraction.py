"""The aperture's diffraction starburst (flare/diffraction.py and lens_flare's ``diffraction``): the pattern
against closed forms (Airy rings and encircled energy, Parseval), its special functions against scipy, the
spikes of a bladed iris counted on the kernel and on a render, and the energy it redistributes."""
from __future__ import annotations

import math

import numpy as np
import pytest

from mi_neurallens.flare.diffraction import (Pupil, bessel_j1, film_kernel, power_spectrum, sine_integral,
                                             working_fnumber_and_pupil)


def test_special_functions_match_scipy():
    from scipy import special          # the dev extra's (declared for these checks)
    x = np.linspace(-60.0, 60.0, 24001)
    assert np.abs(bessel_j1(x) - special.j1(x)).max() < 1e-8
    x = np.concatenate([x, np.geomspace(60.0, 1e6, 2000)])
    assert np.abs(sine_integral(x) - special.sici(x)[0]).max() < 1e-9


@pytest.mark.parametrize("lam", [450.0, 550.0, 650.0])
def test_a_round_iris_gives_the_airy_pattern(lam):
    """On pixels of λN/10: the first dark ring at 1.22 λN (within 2 %), encircled energy 83.8 / 91.0 / 93.8 % at
    1.22 / 2.23 / 3.24 λN (within 1 %), and all of it, but the Airy tail beyond the canvas, on the canvas."""
    N, W = 8.0, 200
    p = lam * 1e-6 * N / 10.0
    K = film_kernel(Pupil(0), N, (p, p), (W, W), [lam], [[1.0]])[..., 0]
    j, i = np.meshgrid(np.arange(-W, W), np.arange(-W, W), indexing="ij")
    r = np.hypot(i, j) / 10.0                                           # in λN
    centres = np.arange(0.9, 1.6, 0.01)
    prof = np.array([K[np.abs(r - c) < 0.015].mean() for c in centres])         # every ring of ±0.015 has pixels
    assert centres[np.argmin(prof)] == pytest.approx(1.22, rel=0.02)
    for radius, ee in ((1.22, 0.838), (2.23, 0.910), (3.24, 0.938)):
        assert K[r <= radius].sum() == pytest.approx(ee, abs=0.01)
    # the Airy envelope's tail beyond radius R (f units, R = 20 λN / 2λN) is 1/(π² R); the square canvas keeps more
    tail = 1.0 / (math.pi ** 2 * (W / 10.0 / 2.0))
    assert 1.0 - tail < K.sum() < 1.0


@pytest.mark.parametrize("blades", [0, 5, 6])
def test_the_pattern_integrates_to_the_pupil_area(blades):
    """Parseval: ∫|P̂|² = the pupil's area (the kernel integrates to 1: it redistributes light and adds none);
    |P̂(0)|² = area²; 64 blades are nearly the circle."""
    P = Pupil(blades, 7.0)
    g = np.linspace(-40.0, 40.0, 1601)
    d = g[1] - g[0]
    fx, fy = np.meshgrid(g, g)
    ps = power_spectrum(fx, fy, P)
    tail = 1.0 / (math.pi ** 2 * 40.0)                                  # the (circle's) tail beyond the grid
    assert ps.sum() * d * d / P.area == pytest.approx(1.0 - tail, abs=2e-3)
    assert power_spectrum(np.array([0.0]), np.array([0.0]), P)[0] == pytest.approx(P.area ** 2, rel=1e-9)
    f = np.linspace(0.0, 3.0, 31)
    circle = power_spectrum(f, 0 * f, Pupil(0)) / math.pi ** 2
    many = Pupil(64, 7.0)
    np.testing.assert_allclose(power_spectrum(f, 0 * f, many) / many.area ** 2, circle, atol=2e-3)


def _spike_angles(img, radius, n_angles=1440):
    """The spikes of ``img`` crossing the circle of ``radius`` pixels about its centre: the runs of angles where it
    stands out of the circle's median by 10x, each at its brightest angle (degrees, [0, 360))."""
    H, W = img.shape
    cy, cx = (H - 1) / 2.0, (W - 1) / 2.0
    a = np.arange(n_angles) * 360.0 / n_angles
    t = np.radians(a)
    vals = np.array([img[int(round(cy + radius * math.sin(u))), int(round(cx + radius * math.cos(u)))] for u in t])
    up = vals > 10.0 * np.median(vals)
    if up.all():
        return np.array([])
    k0 = int(np.argmin(up))                                   # start the walk on a quiet angle: runs never wrap
    order = np.roll(np.arange(n_angles), -k0)
    out, run = [], []
    for k in list(order) + [order[0]]:
        if up[k]:
            run.append(k)
        elif run:
            out.append(a[run[int(np.argmax(vals[run]))]])
            run = []
    return np.sort(np.array(out))


@pytest.mark.parametrize("blades,spikes", [(5, 10), (6, 6), (9, 18)])
def test_an_iris_of_n_blades_throws_n_or_2n_spikes(blades, spikes):
    """Even n: n spikes (opposite edges share one); odd n: 2n; along the blades' normals, turning with the
    blade rotation."""
    for rot in (0.0, 10.0):
        K = film_kernel(Pupil(blades, rot), 11.0, (0.0375, 0.0375), (200, 200), [550.0], [[1.0]])[..., 0]
        ang = _spike_angles(K[1:, 1:], 80)       # the canvas's centre pixel sits at index 200 of 400
        assert len(ang) == spikes, (rot, ang)
        # the first spike lies along the first blade's normal (or its opposite), at the rotation
        off = np.abs(((ang - rot) + 180.0 / spikes) % (360.0 / spikes) - 180.0 / spikes)
        assert off.max() < 1.5, (rot, ang)


def test_working_fnumber_follows_the_focus_and_the_iris():
    """N_w of the configured lens: the f-number at infinity focus, ≈ N (1 + |m| / m_p) focused near (the
    paraxial working f-number of the object in focus); the pupil is the iris's shape and rotation."""
    from mi_neurallens import Lens
    lens = Lens.load("ood-59mm")
    p = lens.paraxial()
    inf = lens.with_sensor_distance(p.sensor_distance_for(math.inf))
    N_w, pupil = working_fnumber_and_pupil(inf)
    assert N_w == pytest.approx(p.fnumber, rel=1e-6) and pupil == Pupil(0, 0.0)
    near = lens.with_sensor_distance(p.sensor_distance_for(600.0))
    assert working_fnumber_and_pupil(near)[0] == pytest.approx(near.paraxial().working_fnumber(600.0), rel=1e-3)
    assert working_fnumber_and_pupil(near)[0] > 1.05 * p.fnumber
    bladed = near.with_surface(near.stop_index, blades=7, blade_rotation_deg=12.0)
    assert working_fnumber_and_pupil(bladed)[1] == Pupil(7, 12.0)


# ------------------------------------------------------------------------------------------ in a flare render
def _scene(mi, blades=6, fstop=11.0, light_z=4.0):
    from mi_neurallens.render_utils import default_variant
    mi.set_variant(default_variant())
    import mi_neurallens
    mi_neurallens.register()
    return mi.load_dict({"type": "scene",
                         "sensor": {"type": "realistic_lens", "lens": "wide-22mm", "fstop": fstop, "blades": blades,
                                    "film": {"type": "hdrfilm", "width": 160, "height": 160, "pixel_format": "rgb"}},
                         "light": {"type": "point", "position": [0.0, 0.0, light_z],
                                   "intensity": {"type": "rgb", "value": 100.0}}})


def test_the_starburst_redistributes_the_lights_own_image():
    """A point light's starburst is its forward-traced image convolved with the kernel: as much light as that image
    (within 0.5 %), spread into the spikes of its 6 blades; a lens_flare render shows it by default."""
    mi = pytest.importorskip("mitsuba")
    from mi_neurallens.flare.render import render_flare
    sc = _scene(mi)
    direct = render_flare(sc, transmit_only=True, diffraction=False, samples=1 << 18, seed=1).total
    star = render_flare(sc, transmit_only=True, samples=1 << 18, seed=1)
    assert star.diffraction is not None and np.array_equal(star.total, star.diffraction)
    assert star.total.sum() == pytest.approx(direct.sum(), rel=5e-3)
    assert (star.total >= -1e-6 * star.total.max()).all()
    # the light's image is a few pixels; its starburst reaches across the film along 6 spikes
    y = star.total[..., 1]
    cy, cx = np.unravel_index(np.argmax(y), y.shape)
    assert direct[..., 1][np.abs(np.arange(160) - cy)[:, None] + np.abs(np.arange(160) - cx)[None, :] > 6].sum() \
        < 1e-3 * direct[..., 1].sum()
    crop = y[cy - 60:cy + 61, cx - 60:cx + 61]
    assert len(_spike_angles(crop, 50)) == 6
    # the integrator's default, and its switch
    integ = {"type": "lens_flare", "flare_samples": 1 << 16, "max_ghosts": 2, "nested": {"type": "direct"}}
    sc2 = _scene(mi)
    for on in (True, False):
        s = mi.load_dict({"type": "scene", "sensor": sc2.sensors()[0], "light": sc2.emitters()[0],
                          "integrator": dict(integ, **({} if on else {"diffraction": False}))})
        mi.render(s, spp=1)
        assert (s.integrator().last_result.diffraction is not None) == on


def test_a_light_beside_the_frame_still_throws_its_spikes_into_it():
    """A light whose own image misses the film: its starburst (the image as a point at its centroid with its
    energy, the fringe-averaged pattern) reaches in.  Checked on a light inside the frame, where both ways apply:
    away from the light's image the point estimate agrees with the convolution of the traced image (10 %)."""
    mi = pytest.importorskip("mitsuba")
    from mi_neurallens.flare.render import FlareOptions, FlareRenderer
    sc = _scene(mi, light_z=4.0)
    fr = FlareRenderer(sc, 0, FlareOptions(transmit_only=True, samples=1 << 18))
    conv = fr.render(seed=1).diffraction[..., 1]
    from mi_neurallens.flare.starburst import offframe_starburst
    point = offframe_starburst(fr, fr.lights[0], seed=1)[..., 1]
    cy, cx = np.unravel_index(np.argmax(conv), conv.shape)
    yy, xx = np.mgrid[:160, :160]
    far = np.hypot(yy - cy, xx - cx) > 20
    assert point[far].sum() == pytest.approx(conv[far].sum(), rel=0.1)
    # moved beside the frame: the spikes reach in
    side = _scene(mi, light_z=4.0)
    params = mi.traverse(side)
    key = next(k for k in params.keys() if k.endswith("position"))
    params[key] = [4.2, 0.0, 4.0]                                 # 46° off axis; the film reaches 39°
    params.update()
    fr = FlareRenderer(side, 0, FlareOptions(transmit_only=True, samples=1 << 18))
    r = fr.render(seed=1)
    assert not any(s.hits for s in r.stats)                       # its own image misses the film ...
    assert r.total[..., 1].sum() > 1e-6 * conv.sum()              # ... its spikes do not
    off = FlareRenderer(side, 0, FlareOptions(transmit_only=True, samples=1 << 18, diffraction=False)).render(seed=1)
    assert off.total.sum() == 0.0


def test_an_emitter_the_backward_render_sees_gets_the_kernel_minus_a_delta():
    """A small area emitter (``small_emitters``) is already in the backward image: its starburst moves light out of
    its image into the spikes (negative there, positive around) and adds none; with include_transmit the flare
    holds its image too, so the two together are that image convolved."""
    mi = pytest.importorskip("mitsuba")
    from mi_neurallens.flare.render import render_flare
    _scene(mi)
    sph = {"type": "sphere", "center": [0.0, 0.0, 3.0], "radius": 0.01,
           "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 500.0}}}
    sc = mi.load_dict({"type": "scene", "shape": sph,
                       "sensor": {"type": "realistic_lens", "lens": "wide-22mm", "fstop": 11.0, "blades": 6,
                                  "film": {"type": "hdrfilm", "width": 96, "height": 96, "pixel_format": "rgb"}}})
    kw = dict(transmit_only=True, small_emitters=1, small_emitter_size=0.1, samples=1 << 18, seed=2)
    plain = render_flare(sc, diffraction=False, **kw).total
    star = render_flare(sc, **kw).diffraction
    assert plain.sum() > 0 and star.min() < 0.0 < star.max()
    assert abs(star.sum()) < 5e-3 * plain.sum()
    both = render_flare(sc, include_transmit=True, **kw)
    np.testing.assert_allclose(both.total.sum(), plain.sum(), rtol=5e-3)


def test_bright_pixels_of_the_backward_image_can_be_spread_too():
    """``diffraction_threshold``: the nested render's pixels above it (a small bright emitter seen directly) lose
    light to the spikes, which the pixels around gain; the image's total stays (5e-3)."""
    mi = pytest.importorskip("mitsuba")
    _scene(mi)
    sph = {"type": "sphere", "center": [0.0, 0.0, 3.0], "radius": 0.05,
           "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 200.0}}}
    sensor = {"type": "realistic_lens", "lens": "wide-22mm", "fstop": 11.0, "blades": 6,
              "film": {"type": "hdrfilm", "width": 96, "height": 96, "pixel_format": "rgb"}}
    imgs = {}
    for t in (0.0, 1.0):
        sc = mi.load_dict({"type": "scene", "shape": sph, "sensor": sensor,
                           "integrator": {"type": "lens_flare", "nested": {"type": "direct"}, "max_ghosts": 1,
                                          "flare_samples": 1 << 12, "diffraction_threshold": t}})
        imgs[t] = np.array(mi.render(sc, spp=16, seed=3))
    diff = imgs[1.0] - imgs[0.0]
    assert diff.min() < 0.0 < diff.max()
    assert abs(diff.sum()) < 5e-3 * imgs[0.0].sum()


def test_an_aperture_mask_joins_its_pattern_to_the_iris(tmp_path):
    """A clean mask gives the closed-form kernel (0.5 %); a vertical scratch throws a horizontal streak (more light
    along the x axis than the y axis near the light) and takes what it blocks; a render reads the mask's file."""
    m_ones = np.ones((64, 64))
    K0 = film_kernel(Pupil(0), 8.0, (0.0375, 0.0375), (120, 80), [550.0], [[1.0]])[..., 0]
    Km = film_kernel(Pupil(0), 8.0, (0.0375, 0.0375), (120, 80), [550.0], [[1.0]], mask=m_ones)[..., 0]
    assert np.abs(Km - K0).max() < 5e-3 * K0.max()
    scratch = np.ones((256, 256))
    scratch[:, 126:130] = 0.0
    Ks = film_kernel(Pupil(0), 8.0, (0.0375, 0.0375), (120, 80), [550.0], [[1.0]], mask=scratch)[..., 0]
    j, i = np.mgrid[-80:80, -120:120]
    band = (np.hypot(i, j) > 2) & (np.hypot(i, j) < 8)
    horiz, vert = Ks[band & (np.abs(j) <= 1)].sum(), Ks[band & (np.abs(i) <= 1)].sum()
    assert horiz > 2.0 * vert and K0[band & (np.abs(j) <= 1)].sum() == pytest.approx(K0[band & (np.abs(i) <= 1)].sum())
    assert Ks.sum() == pytest.approx(K0.sum() * (1.0 - 4.0 / 256 * 4 / math.pi), rel=0.01)   # the bar's share of the disc
    mi = pytest.importorskip("mitsuba")
    from mi_neurallens.flare.render import FlareError, render_flare
    sc = _scene(mi, blades=0)
    path = str(tmp_path / "scratch.exr")
    mi.Bitmap(scratch.astype(np.float32)).write(path)
    plain = render_flare(sc, transmit_only=True, samples=1 << 16, seed=1).total
    masked = render_flare(sc, transmit_only=True, samples=1 << 16, seed=1, aperture_mask=path).total
    assert masked.sum() < plain.sum() and not np.allclose(masked, plain)
    with pytest.raises(FlareError, match="no such image"):
        render_flare(sc, transmit_only=True, samples=1 << 12, aperture_mask=str(tmp_path / "none.png"))


@pytest.mark.parametrize("blades,spikes,rotation", [(5, 10, 0.0), (6, 6, 20.0), (9, 18, 0.0)])
def test_spikes_counted_on_a_render(blades, spikes, rotation):
    """On the rendered starburst of a point light at f/11: n spikes for an even n, 2n for an odd n, turned with
    ``blade_rotation``."""
    mi = pytest.importorskip("mitsuba")
    from mi_neurallens.flare.render import render_flare
    sc = _scene(mi, blades=blades)
    y = render_flare(sc, transmit_only=True, samples=1 << 16, seed=1, blade_rotation=rotation).total[..., 1]
    cy, cx = np.unravel_index(np.argmax(y), y.shape)
    ang = _spike_angles(y[cy - 60:cy + 61, cx - 60:cx + 61], 45)
    assert len(ang) == spikes, ang
    off = np.abs(((ang - rotation) + 180.0 / spikes) % (360.0 / spikes) - 180.0 / spikes)
    assert off.max() < 3.0, ang                    # a pixel at radius 45 spans 1.3°
