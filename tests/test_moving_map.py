"""One learned camera map for a whole zoom and focus range (zoom and focus parameters as map inputs,
mi_neurallens/transport/configurations.py) on the bundled Canon EF 24-70 mm f/2.8L: the per-ray configuration the
training traces equals each configuration's own lens, the inputs' ranges, the model file, and ``neural_lens`` at
configurations between the listed positions against ``realistic_lens``'s camera rays; and the bundled Canon RF 24 mm,
whose map takes its internal focus as an input."""
from __future__ import annotations

import math

import numpy as np
import pytest

from mi_neurallens.optics import moving as mv
from mi_neurallens.optics.prescription import Lens
from mi_neurallens.transport.configurations import Configurations, _cubic_pieces
from mi_neurallens.transport.exact import ExactMap
from mi_neurallens.transport.planning import Domain

ZOOM = "canon-ef-24-70mm-f2.8l"
PRIME = "canon-rf-24mm-f1.4l-vcm"


@pytest.fixture(scope="module")
def zoom():
    return Lens.load(ZOOM)


@pytest.fixture(scope="module")
def configs(zoom):
    return Configurations.of_lens(zoom)


def test_the_inputs_range_and_frame(zoom, configs):
    """Zoom over the listed positions; at every zoom the focus band holds the focus parameters of infinity and of
    the close focus (0.38 m), paraxial and real-ray (where the sensors focus), with room to spare: at 47-57 mm the
    real rays focus at infinity 0.068 beyond the paraxial focus, where a band around the paraxial ones alone ended; a
    map is evaluated up to BAND_TOLERANCE beyond its band, no further; the unit cube ↔ (t, f) both ways, numpy and
    Dr.Jit alike; the sensor plane of the frame lies at or behind every configuration's own (the longest track)."""
    import drjit as dr
    from mi_neurallens.trace.api import float_type
    from mi_neurallens.transport.configurations import BAND_TOLERANCE
    assert configs.names == ("zoom", "focus") and configs.zoom_range == (0.0, 2.0)
    for t in (0.0, 0.4, 1.3, 1.55, 1.6, 1.7, 2.0):
        lo, hi = configs.band(t)
        for D in (math.inf, 380.0):
            for real in (False, True):
                f = mv.focus_parameter(zoom, t, D, real_rays=real)
                assert lo + 0.05 * (hi - lo) < f < hi - 0.05 * (hi - lo)
        configs.check(t, 0.5 * (lo + hi))
        configs.check(t, lo - 0.9 * BAND_TOLERANCE * (hi - lo))
        with pytest.raises(Exception, match="learned band"):
            configs.check(t, lo - 1.1 * BAND_TOLERANCE * (hi - lo))
        with pytest.raises(Exception, match="learned band"):
            configs.check(t, hi + 0.05)
    with pytest.raises(Exception, match="zoom parameter"):
        configs.check(2.2, 0.0)
    rng = np.random.default_rng(0)
    u = rng.random((1000, 2))
    t, f = configs.u_to_tf(u)
    np.testing.assert_allclose(configs.tf_to_u(t, f), u, atol=1e-12)
    # the zoom's ends drawn twice, its middle 2/3 as densely as uniform (ZOOM_END_WEIGHT 0.5)
    tt, _ = configs.u_to_tf(np.column_stack([np.linspace(0.0, 1.0, 100001), np.full(100001, 0.5)]))
    ends, middle = np.mean(tt < 0.02), np.mean(np.abs(tt - 1.0) < 0.02)
    assert ends == pytest.approx(2 * 0.01, rel=0.02) and middle == pytest.approx(2 / 3 * 0.02, rel=0.02)
    # and the focus band's (FOCUS_END_WEIGHT 0.5), at every zoom: the band's lowest and highest 1 %, its middle 2 %
    for tz in (0.0, 1.3):
        u5 = np.linspace(0.0, 1.0, 100001)
        u4 = configs.tf_to_u([tz], [configs.band(tz)[0]])[0, 0]
        _, ff = configs.u_to_tf(np.column_stack([np.full(len(u5), u4), u5]))
        lo, hi = configs.band(tz)
        s = (ff - lo) / (hi - lo)
        assert np.mean(s < 0.01) == pytest.approx(2 * 0.01, rel=0.02)
        assert np.mean(s > 0.99) == pytest.approx(2 * 0.01, rel=0.02)
        assert np.mean(np.abs(s - 0.5) < 0.01) == pytest.approx(2 / 3 * 0.02, rel=0.02)
    # the warps' weights go with the file; one that records none drew its focus uniformly (LEGACY_END_WEIGHTS)
    d = configs.to_dict()
    assert d["end_weights"] == [0.5, 0.5]
    del d["end_weights"]
    legacy = Configurations.from_dict(d)
    assert legacy.end_weights == (0.5, 0.0) and legacy != configs
    _, fl = legacy.u_to_tf(np.array([[0.5, 0.25]]))
    lo, hi = legacy.band(float(legacy.u_to_tf(np.array([[0.5, 0.25]]))[0][0]))
    assert fl[0] == pytest.approx(lo + 0.25 * (hi - lo), rel=1e-12)
    F = float_type("float64")
    td, fd = configs.u_to_tf_dr([F(u[:, 0]), F(u[:, 1])])
    np.testing.assert_allclose(td.numpy(), t, atol=1e-12)
    np.testing.assert_allclose(fd.numpy(), f, atol=1e-12)
    for tt, ff in configs.corner_configurations():
        assert mv.at(zoom, tt, ff, check=False).image_z <= configs.z_sensor + 1e-9
    # the per-interval cubics are the prescription's monotone cubics
    x = np.arange(3.0)
    y = np.array(zoom.moving.gaps[24])[:, 1]
    c = _cubic_pieces(x, y)
    for tq in np.linspace(0, 2, 23):
        k = min(int(tq), 1)
        s = tq - k
        assert c[k] @ [1, s, s * s, s ** 3] == pytest.approx(float(mv.pchip(x, y, tq)), abs=1e-12)
    back = Configurations.from_dict(configs.to_dict())
    assert back == configs and back.lens is None


def test_the_knot_inputs_carry_the_cam_curves_join(zoom, configs):
    """The gaps' cubics (Fritsch–Carlson, per interval) join at the inner listed position with continuous slope but a
    jump in curvature: over the zoom no gap is one cubic in t, and every gap is, to rounding, linear in 1, t, t², t³
    and the knot inputs' truncated powers (t − 1)₊², (t − 1)₊³, which the configurations multiply r, ωx, ωy by."""
    from mi_neurallens.transport.configurations import knot_monomials
    assert knot_monomials(2) == () and knot_monomials(3) == ((2, 0, 1), (3, 0, 1))
    assert configs.monomials[-2:] == knot_monomials(zoom.moving.positions)
    t = np.linspace(0.0, 2.0, 161)
    G = np.array([[g for _, g in sorted(zoom.moving.gaps_at(v).items())] for v in t])
    moving = np.ptp(G, 0) > 1e-6
    assert moving.sum() >= 3
    G = G[:, moving]
    cubic = np.vander(t, 4, increasing=True)
    knots = np.c_[cubic, np.maximum(t - 1, 0) ** 2, np.maximum(t - 1, 0) ** 3]
    rms = lambda A: np.sqrt(np.mean((A @ np.linalg.lstsq(A, G, rcond=None)[0] - G) ** 2, 0))
    assert rms(knots).max() < 1e-9 * np.abs(G).max()
    assert rms(cubic).max() > 1e-3                       # mm: what a smooth function of t alone misses
    # the products' columns: r, ωx, ωy times (t − 1)₊^a, numpy and Dr.Jit alike
    from mi_neurallens.trace.api import float_type
    x = np.c_[np.random.default_rng(4).random((len(t), 4)), t, np.full(len(t), 0.3)]
    P = configs.products_np(x)
    np.testing.assert_allclose(P[:, -6:-3], x[:, :3] * np.maximum(t - 1, 0)[:, None] ** 2, rtol=1e-12)
    np.testing.assert_allclose(P[:, -3:], x[:, :3] * np.maximum(t - 1, 0)[:, None] ** 3, rtol=1e-12)
    F = float_type("float64")
    Pd = np.stack([np.asarray(v) for v in configs.products_dr([F(x[:, i]) for i in range(6)])], 1)
    np.testing.assert_allclose(Pd, P, rtol=1e-12, atol=1e-15)


def test_a_run_on_a_base_keeps_its_domain_and_draws_as_this_version_does(configs):
    """A finish on a base map trains on the base's domain (bounds, band, frame: what its kept networks' inputs are
    normalised by) but draws its rays with this version's end weights, which the new model file then records."""
    import dataclasses
    from mi_neurallens.training.whole_lens import _base_domain
    legacy = configs.to_dict()
    legacy.pop("end_weights")
    legacy["z_sensor_mm"] += 0.25                       # the base's own frame, not this run's
    base = {"r_max_mm": 11.0, "s_max": 0.4, "lambda_min_nm": 400.0, "lambda_max_nm": 700.0, "conditions": legacy}
    planned = Domain(12.0, 0.5, conditions=configs)
    dom = _base_domain(base, planned)
    assert (dom.r_max, dom.s_max) == (11.0, 0.4) and dom.conditions.z_sensor == configs.z_sensor + 0.25
    assert dom.conditions.end_weights == configs.end_weights == (0.5, 0.5)
    assert dom.to_dict()["conditions"]["end_weights"] == [0.5, 0.5]
    assert Domain.from_dict(base).conditions.end_weights == (0.5, 0.0)     # the base's own record is untouched
    fixed = Domain(11.0, 0.4)
    assert _base_domain(fixed.to_dict(), dataclasses.replace(planned, conditions=None)) == fixed


def test_a_recipe_sets_how_densely_the_ranges_ends_are_drawn(zoom):
    """``zoom_end_weight`` / ``focus_end_weight``, ``zoom_margin`` and ``zoom_dense_at`` reach the configurations a
    run draws from (and so its model file); the share of drawn zooms near the range's ends (or its listed positions)
    is the warp's; out of range is refused."""
    from mi_neurallens.errors import NeuralLensError
    from mi_neurallens.training.config import load_config
    from mi_neurallens.training.whole_lens import _configurations
    assert _configurations(zoom, load_config()).end_weights == (0.5, 0.5)
    c = _configurations(zoom, load_config(overrides={"zoom_end_weight": 0.75}))
    assert c.end_weights == (0.75, 0.5) and c.to_dict()["end_weights"] == [0.75, 0.5]
    u = (np.arange(20000)[:, None] + 0.5) / 20000 * np.ones((1, 2))
    for cf, a in ((c, 0.75), (_configurations(zoom, load_config(overrides={"zoom_end_weight": 0.0})), 0.0)):
        t, _ = cf.u_to_tf(u)
        ends = float(np.mean((t < 0.1) | (t > 1.9)))
        # the warp's closed form: w(u) = u − a sin(2πu)/2π reaches 0.05 of the range at u = expect / 2
        g = np.linspace(0.0, 0.5, 500001)
        expect = 2 * g[np.searchsorted(g - a / (2 * math.pi) * np.sin(2 * math.pi * g), 0.05)]
        assert ends == pytest.approx(expect, abs=2e-4)
        assert expect > (0.28 if a else 0.0999)       # 0.75: those ends 2.9x as densely as uniform
    with pytest.raises(NeuralLensError, match="zoom_end_weight.*0, 1"):
        _configurations(zoom, load_config(overrides={"zoom_end_weight": 1.0}))
    assert _configurations(zoom, load_config(overrides={"zoom_margin": 0.01})).zoom_margin == 0.01
    with pytest.raises(NeuralLensError, match="zoom_margin"):
        _configurations(zoom, load_config(overrides={"zoom_margin": 0.5}))
    # densest at every listed position: the ends and the 35.13 mm where the gaps' cubics join
    p = _configurations(zoom, load_config(overrides={"zoom_end_weight": 0.75, "zoom_dense_at": "positions"}))
    assert p.zoom_periods == 2 and Configurations.from_dict(p.to_dict()) == p
    t, f = p.u_to_tf(np.column_stack([np.linspace(0.0, 1.0, 200001), np.full(200001, 0.5)]))
    share = [float(np.mean(np.abs(t - k) < 0.002)) / 0.002 for k in (0.0, 0.5, 1.0, 1.5, 2.0)]   # / uniform's
    assert share[2] == pytest.approx(2 * share[0], rel=0.02)                # a knot has two sides, an end one
    assert share[2] == pytest.approx(4.0, rel=0.02)                         # 1 / (1 − a) of uniform
    assert share[1] == pytest.approx(share[3], rel=0.02) and share[1] == pytest.approx(1 / 1.75, rel=0.02)
    u = np.random.default_rng(2).random((300, 2))
    np.testing.assert_allclose(p.tf_to_u(*p.u_to_tf(u)), u, atol=1e-12)
    import drjit as dr  # noqa: F401
    from mi_neurallens.trace.api import float_type
    F = float_type("float64")
    np.testing.assert_allclose(p.u_to_tf_dr([F(u[:, 0]), F(u[:, 1])])[0].numpy(), p.u_to_tf(u)[0], atol=1e-12)
    with pytest.raises(NeuralLensError, match="zoom_dense_at"):
        _configurations(zoom, load_config(overrides={"zoom_dense_at": "middle"}))


def test_a_zoom_margin_draws_beyond_the_listed_ends_along_the_continued_cam_curves(zoom, configs):
    """``zoom_margin``: the training's zooms reach that fraction of the range beyond each end (numpy and Dr.Jit
    alike, both ways), the tracer's gaps there are the end cubics continued (``mv.pchip``'s extension), the file
    keeps it (a file without it: 0), the inputs' normalisation and what sensors may ask for stay the listed range."""
    import dataclasses
    import drjit as dr
    from mi_neurallens.trace.api import float_type
    from mi_neurallens.transport.configurations import ConfigurationGeometry
    wide = dataclasses.replace(configs, zoom_margin=0.01)
    assert configs.zoom_margin == 0.0 and wide.sampled_zoom_range == pytest.approx((-0.02, 2.02), abs=1e-15)
    t, f = wide.u_to_tf(np.array([[0.0, 0.0], [1.0, 1.0], [0.5, 0.5]]))
    np.testing.assert_allclose(t, [-0.02, 2.02, 1.0], atol=1e-12)
    lo, hi = configs.band(0.0)
    assert f[0] == pytest.approx(lo, abs=1e-12)          # the band held at its end values beyond the range
    u = np.random.default_rng(1).random((500, 2))
    t, f = wide.u_to_tf(u)
    assert t.min() < -0.015 and t.max() > 2.015
    np.testing.assert_allclose(wide.tf_to_u(t, f), u, atol=1e-12)
    F = float_type("float64")
    td, fd = wide.u_to_tf_dr([F(u[:, 0]), F(u[:, 1])])
    np.testing.assert_allclose(td.numpy(), t, atol=1e-12)
    np.testing.assert_allclose(fd.numpy(), f, atol=1e-12)
    # the tracer's gaps beyond the ends: the prescription's end cubics continued
    x = np.arange(3.0)
    tq, fq = np.array([-0.02, -0.01, 2.01, 2.02]), np.array([0.0, 0.7, 0.3, 1.0])
    geo = ConfigurationGeometry(wide, zoom, F, F(tq), F(fq))
    z = np.array([dr.ravel(s["z"]).numpy() if hasattr(s["z"], "numpy") else np.full(4, s["z"])
                  for s in geo.surfaces()])
    for i, v in zoom.moving.gaps.items():
        a = np.asarray(v, np.float64)
        gi, gc = mv.pchip(x, a[:, 0], tq), mv.pchip(x, a[:, 1], tq)
        np.testing.assert_allclose(z[i + 1] - z[i], gi + fq * (gc - gi), atol=1e-9)
    # the file keeps it, an older file drew none; normalisation and the sensors' range unchanged
    assert Configurations.from_dict(wide.to_dict()).zoom_margin == 0.01 and Configurations.from_dict(wide.to_dict()) == wide
    d = wide.to_dict()
    del d["zoom_margin"]
    assert Configurations.from_dict(d) == configs
    np.testing.assert_array_equal(wide.norm_center_scale()[0], configs.norm_center_scale()[0])
    np.testing.assert_array_equal(wide.norm_center_scale()[1], configs.norm_center_scale()[1])
    with pytest.raises(Exception, match="zoom parameter"):
        wide.check(-0.01, 0.0)


def test_one_kernel_traces_every_configuration_as_its_own_lens(zoom, configs):
    """The training's tracer, one configuration per ray in the sensor's frame, against each configuration's own
    lens (``optics.moving.at``) traced in its own lens space, planes moved by the frame's shift: the same rays
    pass, to the same exit rays, at listed positions, between them and at the focus band's edges."""
    dom = Domain(30.0, 0.9, conditions=configs)
    rng = np.random.default_rng(1)
    x = Domain(30.0, 0.9).u_to_x(rng.random((20000, 4)))
    for t, f in ((0.0, 0.0), (0.7, 0.3), (1.6, configs.band(1.6)[0]), (2.0, configs.band(2.0)[1])):
        L = mv.at(zoom, t, f, check=False)
        shift = configs.shift_of(L.image_z)
        z_in, z_out = L.image_z - 1.0, -5.0
        own = ExactMap(L, "transmit", "backward", z_in, z_out, domain=Domain(30.0, 0.9))
        per_ray = ExactMap(zoom, "transmit", "backward", z_in - shift, z_out - shift, domain=dom)
        v1, y1, _ = own.core_reduced_np(x)
        v2, y2, _ = per_ray.core_reduced_np(np.c_[x, np.full(len(x), t), np.full(len(x), f)])
        assert v1.mean() > 0.01 and (v1 == v2).all()
        np.testing.assert_allclose(y2[v1], y1[v1], atol=1e-9)


def test_a_model_file_with_configuration_inputs(configs, tmp_path):
    """A map with six inputs saves and loads; at render time its configuration enters as two kernel inputs
    (``condition_values``) and gives what explicit input columns give."""
    from mi_neurallens.neural.model import NeuralLensModel, NeuralMap, load_model
    rng = np.random.default_rng(2)
    dom = Domain(12.0, 0.6, conditions=configs)
    c, s = dom.norm_center_scale()
    assert len(c) == 6 + 3 * len(configs.monomials) == dom.n_inputs

    def net(*w):
        return [(rng.normal(0, 0.5, (b, a)), rng.normal(0, 0.1, b)) for a, b in zip(w, w[1:])]
    tm = NeuralMap(path_id=0, direction="backward", z_in=150.0, z_out=-1.0, domain=dom, input_center=c,
                   input_scale=s, classifier=net(len(c), 8, 1), regressor=net(len(c), 8, 5), skip=rng.normal(0, 0.1, (5, len(c))),
                   out_scale=np.ones(5), out_shift=np.zeros(5))
    model = NeuralLensModel(lens_name=ZOOM, fingerprint=configs.lens.fingerprint(), z_front=-1.0, z_rear=150.0,
                            z_last_vertex=140.0, sensor_distance_range=(10.0, 11.0), maps={tm.key: tm})
    p = str(tmp_path / "m.model.safetensors")
    model.save(p)
    back = load_model(p, configs.lens).map("transmit", "backward")
    assert back.domain.conditions == configs and back.skip.shape == (5, len(c))
    x = dom.u_to_x(rng.random((500, 6)))
    lg, y = back.eval_reduced_np(x)
    import dataclasses
    one = dataclasses.replace(back, condition_values=(0.8, 0.2))
    xc = x.copy()
    xc[:, 4:6] = (0.8, 0.2)        # the product inputs follow from these: the map computes them
    lg2, y2 = one.eval_reduced_np(x[:, :4])
    lg3, y3 = back.eval_reduced_np(xc)
    np.testing.assert_allclose(y2, y3, atol=1e-12)
    np.testing.assert_allclose(lg2, lg3, atol=1e-12)
    with pytest.raises(Exception, match="condition_values"):
        back.eval_reduced_np(x[:, :4])


def _camera_rays(sensor, n=40000, seed=0):
    """(valid, direction (n, 3)) of ``sensor``'s camera rays for fixed film, pupil and wavelength samples."""
    import drjit as dr
    import mitsuba as mi
    rng = np.random.default_rng(seed)
    f = lambda: mi.Float(rng.random(n).astype(np.float32))
    # each ray's wavelength from its time sample, as an RGB render draws it (sensors/wavelengths.py; 0 is 360 nm)
    time, u1, u2, u3 = f(), f(), mi.Point2f(f(), f()), mi.Point2f(f(), f())
    ray, w = sensor.sample_ray(time, u1, u2, u3)
    ok = dr.detach(w[0]).numpy() > 0
    return ok, np.stack([c.numpy() for c in (ray.d.x, ray.d.y, ray.d.z)], 1)


@pytest.mark.parametrize("lens, focal, focus", [(ZOOM, 30.0, math.inf), (ZOOM, 50.0, math.inf), (ZOOM, 55.0, 0.5),
                                               (PRIME, None, 0.7)])
def test_neural_lens_between_the_listed_positions(lens, focal, focus):
    """At focal lengths and focus distances between the listed positions (configurations the training drew no
    closer to than any other), the bundled map's camera rays against realistic_lens's for the same film and pupil
    samples: the same rays pass (≥ 99 %), their directions agree to a median of 15″ (the exit ray carried to the
    scene; the map's held-out median is a few arcseconds).  At 50 mm and infinity the real rays focus 0.5 % of the
    bundled map's focus band beyond it (the band was solved paraxially): evaluated there, within BAND_TOLERANCE.  The
    RF 24 mm (focus alone) at 0.7 m alike."""
    import mitsuba as mi
    from mi_neurallens.render_utils import default_variant
    mi.set_variant(default_variant())
    import mi_neurallens as nl
    nl.register()
    kw = {"lens": lens, "focus_distance": focus, "film": {"type": "hdrfilm", "width": 96, "height": 64}}
    if focal is not None:
        kw["focal_length"] = focal
    ex = mi.load_dict({"type": "realistic_lens", **kw})
    nn = mi.load_dict({"type": "neural_lens", **kw})
    v1, d1 = _camera_rays(ex)
    v2, d2 = _camera_rays(nn)
    assert v1.mean() > 0.3
    assert (v1 == v2).mean() > 0.99
    both = v1 & v2
    a, b = d1[both].astype(np.float64), d2[both].astype(np.float64)
    ang = np.degrees(2.0 * np.arcsin(0.5 * np.linalg.norm(a - b, axis=1))) * 3600.0     # well-conditioned near 0
    print(f"{focal} mm, {focus} m: agree {(v1 == v2).mean():.4f}, direction median {np.median(ang):.3g}\"")
    assert np.median(ang) < 15.0


@pytest.mark.parametrize("lens, focal, close, film_x, fstop, ratio, tol", [
    (ZOOM, 68.14, 0.38, 0.9, None, 0.01357 / 0.01468, 0.01), (PRIME, None, 0.24, 0.65, 8.0, 1.0143, 0.005)])
def test_neural_lens_breathes_as_the_prescription(lens, focal, close, film_x, fstop, ratio, tol):
    """The focus pull at 68.14 mm from infinity to 0.38 m through the learned map: the view narrows as the
    configured prescriptions' paraxial chief rays say (object-side slope per mm of image height 0.01468 at
    infinity, 0.01357 at 0.38 m: by 7.6 %; tests/test_moving.py measures realistic_lens the same way), within 1 %:
    the ratio of the camera rays' mean slopes at one film point 9.6 mm off axis.  The RF 24 mm's map, from
    infinity to 0.24 m: the view widens by 1.4 % (paraxially; the real rays 1.8 %), within 0.5 %, and widens."""
    import drjit as dr
    import mitsuba as mi
    from mi_neurallens.render_utils import default_variant
    mi.set_variant(default_variant())
    import mi_neurallens as nl
    nl.register()
    slope = {}
    for D in (math.inf, close):
        kw = ({} if focal is None else {"focal_length": focal}) | ({} if fstop is None else {"fstop": fstop})
        s = mi.load_dict({"type": "neural_lens", "lens": lens, **kw, "focus_distance": D,
                          "film": {"type": "hdrfilm", "width": 64, "height": 64}, "sensor_width": 24.0})
        rng = np.random.default_rng(0)
        n = 20000
        f = lambda: mi.Float(rng.random(n).astype(np.float32))
        ray, w = s.sample_ray(f(), f(), mi.Point2f(film_x, 0.5), mi.Point2f(f(), f()))
        ok = dr.detach(w[0]).numpy() > 0
        slope[D] = abs(np.mean(ray.d.x.numpy()[ok] / ray.d.z.numpy()[ok]))
    assert slope[close] / slope[math.inf] == pytest.approx(ratio, abs=tol)
    assert (slope[close] > slope[math.inf]) == (ratio > 1)


def test_a_model_is_refused_with_other_moving_groups(zoom, tmp_path):
    """The bundled map was trained for the prescription's moving groups: the same glass with one group's travel
    changed is another lens (its fingerprint), and neural_lens says so."""
    import mitsuba as mi
    from mi_neurallens.render_utils import default_variant
    mi.set_variant(default_variant())
    import mi_neurallens as nl
    nl.register()
    mg = zoom.moving
    other = zoom.replace(moving=mv.MovingGroups({**mg.gaps, 12: ((2.9, 2.9), (6.6, 6.6), (20.41, 20.41))},
                                                mg.zoom_efl_mm, mg.close_focus_mm, mg.close_gaps))
    p = tmp_path / "other.json"
    other.save(p)
    with pytest.raises(Exception, match="trained for lens"):
        mi.load_dict({"type": "neural_lens", "lens": str(p), "model": ZOOM,
                      "film": {"type": "hdrfilm", "width": 32, "height": 32}})


def test_training_a_moving_lens_plans_its_ghosts_over_the_configurations(zoom, configs, tmp_path, capsys):
    """train: every map of a lens with moving groups takes the zoom and focus as inputs, said once; its forward maps'
    one domain (``moving_forward_domain``) carries the configurations, and its ghosts come from the ranking over them
    (read from the work folder's cache here: computing it takes minutes)."""
    import json
    from mi_neurallens.neural.model import NeuralLensModel
    from mi_neurallens.training.config import TrainConfig
    from mi_neurallens.training.whole_lens import _moving_groups, _plan_maps
    from mi_neurallens.transport import planes
    from mi_neurallens.training.config import load_config
    from mi_neurallens.training.whole_lens import select_maps
    from mi_neurallens.transport.planes import recipe_path
    recipe = load_config(recipe_path(ZOOM), ZOOM)
    assert recipe.forward == [] and select_maps(recipe, None) == [("backward", "transmit")]
    assert select_maps(recipe, "ghosts") == [("forward", "ghosts")]          # named: though the recipe lists none
    groups = [("backward", "transmit"), ("forward", "ghosts")]
    assert _moving_groups(zoom, groups) == groups
    assert "ranked at 5 zooms" in capsys.readouterr().err
    ranking = [{"path_id": 201326592, "surfaces": [27, 26], "energy": 0.3}, {"path_id": 48, "surfaces": [5, 4],
                                                                             "energy": 0.2}]
    (tmp_path / "ghost_ranking.json").write_text(json.dumps(ranking))
    cfg = TrainConfig(ship_ghosts=2)
    model = NeuralLensModel(lens_name=ZOOM, fingerprint=zoom.fingerprint(), z_front=-1.0, z_rear=150.0,
                            z_last_vertex=140.0, sensor_distance_range=(10.0, 11.0), maps={})
    todo = _plan_maps(zoom, cfg, model, [("forward", "ghosts")], planes.moving_planes(configs), (10.0, 11.0),
                      str(tmp_path), configs)
    assert [t[0] for t in todo] == [201326592, 48] and model.extra["ghosts_trained"] == [201326592, 48]
    assert all(t[1] == "forward" and t[4].conditions == configs and t[4].reach.z_near_mm == configs.z_sensor
               for t in todo)


def test_a_ghost_traces_every_configuration_as_its_own_lens(zoom, configs):
    """The forward maps' domain of a zoom lens (``planes.moving_forward_domain``): the field of the widest
    configuration, a front radius that covers every configuration's front element, the film reach on the one sensor
    plane; a ghost traced one configuration per ray through it equals each configuration's own lens traced in its
    own space (as the camera map's test above, on a two-reflection path)."""
    from mi_neurallens.transport import planes
    z_front, _ = planes.moving_planes(configs)
    dom = planes.moving_forward_domain(configs, z_front, 21.63, 1.1, 32.0)
    assert dom.conditions is configs and dom.dims == 6
    assert dom.reach.z_near_mm == dom.reach.z_far_mm == configs.z_sensor
    wide = max(planes.default_field_half_angle(mv.at(zoom, 0.0, f), 21.63, 1.1) for f in configs.band(0.0))
    assert math.sin(math.radians(wide)) == pytest.approx(dom.s_max, rel=1e-3)
    pid = 48                        # ghost_id(4, 3): among the strongest over the zoom range
    free = Domain(dom.r_max, dom.s_max)
    rng = np.random.default_rng(3)
    x = free.u_to_x(rng.random((20000, 4)))
    for t, f in ((0.0, 0.0), (1.3, configs.band(1.3)[1])):
        L = mv.at(zoom, t, f, check=False)
        shift = configs.shift_of(L.image_z)
        own = ExactMap(L, pid, "forward", z_front + shift, configs.z_sensor + shift, domain=free)
        per_ray = ExactMap(zoom, pid, "forward", z_front, configs.z_sensor,
                           domain=Domain(dom.r_max, dom.s_max, conditions=configs))
        v1, y1, _ = own.core_reduced_np(x)
        v2, y2, _ = per_ray.core_reduced_np(np.c_[x, np.full(len(x), t), np.full(len(x), f)])
        assert v1.sum() > 50 and (v1 == v2).all()
        np.testing.assert_allclose(y2[v1], y1[v1], atol=1e-8)


def test_the_ghost_ranking_over_the_zoom_keeps_each_ghost_at_its_strongest(zoom, configs):
    """``flare.energy.moving_ghost_ranking`` traces every configuration in one kernel per ghost; each ghost's energy
    is the largest of what ``ghost_energy_ranking`` gives each configuration's own lens on the same rays."""
    from mi_neurallens.flare.energy import ghost_energy_ranking, moving_ghost_ranking
    from mi_neurallens.trace.paths import ghost_id
    ids = [ghost_id(12, 9), ghost_id(3, 1), ghost_id(20, 18)]
    kw = dict(n_rays=1 << 11, n_angles=3, ghosts=ids)
    got = {d["path_id"]: d["energy"] for d in moving_ghost_ranking(configs, zooms=2, **kw)}
    best = dict.fromkeys(ids, 0.0)
    for t in configs.zoom_range:
        for f in configs.band(t):
            for d in ghost_energy_ranking(mv.at(zoom, t, f, check=False), **kw):
                best[d["path_id"]] = max(best[d["path_id"]], d["energy"])
    assert all(best[g] > 0 for g in ids)
    for g in ids:
        assert got[g] == pytest.approx(best[g], rel=1e-3)


def test_a_learned_map_at_the_sensors_configuration(configs):
    """``LensSetup.configured_map``, what ``neural_lens`` and ``lens_flare`` both apply to a map with configuration
    inputs: the sensor's zoom and focus parameters as its condition inputs, its planes moved by the configured lens's
    shift from the sensor frame; outside the learned band, an error naming it."""
    import dataclasses
    import mitsuba as mi
    from mi_neurallens.errors import NeuralLensError
    from mi_neurallens.render_utils import default_variant
    mi.set_variant(default_variant())
    import mi_neurallens as nl
    nl.register()
    s = mi.load_dict({"type": "neural_lens", "lens": ZOOM, "focal_length": 40.0, "focus_distance": 1.2,
                      "film": {"type": "hdrfilm", "width": 32, "height": 32}})
    st = s.setup
    tm = s.model.map("transmit", "backward")
    got = st.configured_map(tm)
    assert got.condition_values == configs.values(st.zoom, st.focus_parameter)
    assert got.z_in - tm.z_in == pytest.approx(st.lens.image_z - configs.z_sensor, abs=1e-12)
    assert (got.z_in, got.z_out) == (s.tmap.z_in, s.tmap.z_out)
    far = dataclasses.replace(st, focus_parameter=configs.band(st.zoom)[1] + 0.1)
    with pytest.raises(NeuralLensError, match="focus parameter"):
        far.configured_map(tm)


def test_a_configured_map_folds_its_configuration_into_the_first_layers(configs):
    """:class:`~mi_neurallens.neural.model.ConditionFold`: at a fixed configuration the 33 inputs of the EF 24-70's
    camera map are affine in the ray's four, so the folded networks (4 inputs, folded in float64) compute what the
    trained ones do, to float32 rounding (float32 only: a float64 kernel of these networks compiles for 10 s), and
    another configuration changes only kernel parameters (the same kernel source, no recompilation)."""
    import dataclasses
    import drjit as dr
    import mitsuba as mi
    from mi_neurallens.render_utils import default_variant
    from mi_neurallens.trace.api import float_type
    mi.set_variant(default_variant())
    import mi_neurallens as nl
    nl.register()
    s = mi.load_dict({"type": "neural_lens", "lens": ZOOM, "focal_length": 52.0, "focus_distance": 0.9,
                      "film": {"type": "hdrfilm", "width": 32, "height": 32}})
    tm = s.setup.configured_map(s.model.map("transmit", "backward"))
    width = tm.regressor[0][0].shape[0]                # the first hidden layer: 33 inputs folded to the ray's 4
    assert tm.regressor[0][0].shape[1] == 33 == tm.domain.n_inputs
    assert tm.condition_fold() is not None and tm.condition_fold().first["regressor"][0].shape == (width, 4)
    full = dataclasses.replace(tm, fold_conditions=False)
    rng = np.random.default_rng(3)
    u = rng.random((4000, 4))
    x = tm.domain.u_to_x(np.hstack([u, np.full((len(u), tm.domain.conditions.dims), 0.5)]))[:, :4]
    F = float_type("float32")
    xs = [F(x[:, i]) for i in range(4)]
    (la, ya), (lb, yb) = tm.eval_reduced_dr(xs), full.eval_reduced_dr(xs)
    a, b = np.array([la] + list(ya)), np.array([lb] + list(yb))
    assert a.shape == (1 + 5 + 2 * tm.stop_crossings, len(x))
    scale = np.maximum(np.abs(b).max(1, keepdims=True), 1e-3)           # per output
    assert np.all(np.abs(a - b) <= 2e-4 * scale), (np.abs(a - b) / scale).max()
    assert np.abs(a - b).max() > 0.0                                    # two evaluations, not one twice
    # another configuration: new kernel parameters, not a new kernel
    other = dataclasses.replace(tm, condition_values=tuple(v + 0.01 for v in tm.condition_values))
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.kernel_history_clear() if hasattr(dr, "kernel_history_clear") else dr.kernel_history()
        dr.eval(tm.eval_reduced_dr(xs))
        dr.eval(other.eval_reduced_dr(xs))
        hist = [h for h in dr.kernel_history() if h["type"] == dr.KernelType.JIT]
    assert len(hist) >= 2 and hist[-1]["hash"] == hist[-2]["hash"]


def test_a_conditioned_maps_goals_hold_in_its_worst_configuration_cell(zoom, configs):
    """A map over moving groups is checked against its goals cell by cell (the range's ends and corners, where its
    error grows): rays at a listed end and at infinity or close focus fall in the cells so named (infinity is the end
    of the focus band the focus parameter images infinity at), cells with too few rays are left out, and the
    regressor's and the classifier's goals fail on a worst cell above them even where the all-ray figure meets them."""
    import dataclasses
    from types import SimpleNamespace
    from mi_neurallens.training.classifier import ClassifierFit
    from mi_neurallens.training.config import NetConfig
    from mi_neurallens.training.regressor import RegressorFit
    t0, t1 = configs.zoom_range
    tf = [(t0, mv.focus_parameter(zoom, t0, math.inf)), (t1, mv.focus_parameter(zoom, t1, zoom.moving.close_focus_mm)),
          (0.5 * (t0 + t1), float(np.mean(configs.band(0.5 * (t0 + t1))))), (t1, mv.focus_parameter(zoom, t1, math.inf))]
    x = np.zeros((4000, 6))
    x[:, 4:6] = np.repeat(np.array(tf), [1000, 1000, 1000, 1000], axis=0)
    cells = configs.cells(x, min_rays=500)
    assert sorted(cells) == ["mid, mid", "tele, close", "tele, infinity", "wide, infinity"]
    np.testing.assert_array_equal(np.flatnonzero(cells["tele, close"]), np.arange(1000, 2000))
    # with its corners: the listed ends at infinity and close focus are in their end cells and in the corners there;
    # a zoom 5 % of the range inside the tele end is in "tele, close" only (CORNER_EDGES: the zoom's outer 3 %)
    with_corners = configs.cells(x, min_rays=500, corners=True)
    assert sorted(with_corners) == sorted([*cells, "tele, close, corner", "tele, infinity, corner",
                                                  "wide, infinity, corner"])
    np.testing.assert_array_equal(with_corners["tele, close, corner"], cells["tele, close"])
    t_in = t1 - 0.05 * (t1 - t0)
    x[1500:2000, 4:6] = (t_in, mv.focus_parameter(zoom, t_in, zoom.moving.close_focus_mm))
    inner = configs.cells(x, min_rays=500, corners=True)
    assert inner["tele, close"].sum() == 1000 and inner["tele, close, corner"].sum() == 500
    assert "tele, close, corner" not in configs.cells(x, min_rays=501, corners=True)
    x[1000:2000, 4:6] = tf[1]
    x[1000:2000:2, 4:6] = tf[0]                           # 500 of "tele, close" move to "wide, infinity"
    assert "tele, close" not in configs.cells(x, min_rays=501) and "tele, close" in configs.cells(x, min_rays=500)
    # the zoom margin's rays (beyond the listed range: trained on, never rendered) are in no cell, but for the
    # finish's row weights; the ends themselves are in, also as float32 inputs
    wide = dataclasses.replace(configs, zoom_margin=0.05)
    y = np.zeros((3000, 6))
    for k, t in enumerate((t1, t1 + 0.02 * (t1 - t0), t0 - 0.02 * (t1 - t0))):
        y[1000 * k:1000 * (k + 1), 4:6] = (t, float(np.mean(wide.band(t1))))
    inner = wide.cells(y.astype(np.float32), min_rays=1)
    assert sorted(inner) == ["tele, mid"] and np.flatnonzero(inner["tele, mid"]).tolist() == list(range(1000))
    every = wide.cells(y, min_rays=1, margin=True)
    assert sorted(every) == ["tele, mid", "wide, mid"] and every["tele, mid"].sum() == 2000
    # the goals: median 2 um / 5 arcsec, 0.5 % misclassified, each within the margin 0.9
    nc = NetConfig()
    rec = {"pos_um_med": 1.0, "pos_um_p99": 10.0, "dir_as_med": 3.0, "dir_as_p99": 20.0}
    met = lambda **r: RegressorFit.goals_met(SimpleNamespace(state={"history": [{**rec, **r}]}, nc=nc))
    assert met() and met(cell_pos_um_med=1.7, cell_dir_as_med=4.4)
    assert not met(cell_pos_um_med=1.7, cell_dir_as_med=4.6) and not met(cell_pos_um_med=1.9, cell_dir_as_med=4.4)
    cmet = lambda *cell: ClassifierFit.goals_met(SimpleNamespace(
        state={"history": [{"val_misclass": 0.003, **({} if c is None else {"cell_misclass": c})} for c in cell]}, nc=nc))
    assert cmet(None)                                     # a fixed prime: its last validation, all rays
    # over moving groups, the worst cell at the last two validations: one lucky validation does not stop it
    assert cmet(0.0044, 0.0044) and cmet(0.0060, 0.0044, 0.0040)
    assert not cmet(0.0046) and not cmet(0.0044) and not cmet(0.0046, 0.0044) and not cmet(0.0044, 0.0046)
    # what train and evaluate print below the table: each figure's worst cell
    from mi_neurallens.training.evaluate import worst_cells
    m = {"cells": {"wide, infinity": {"position_um_median": 1.2, "direction_arcsec_median": 5.5, "misclassification": 0.002},
                   "tele, close": {"position_um_median": 1.9, "direction_arcsec_median": 4.0, "misclassification": None}}}
    assert worst_cells(m) == "position 1.9 µm (tele, close), direction 5.5″ (wide, infinity), misclassified 0.200% (wide, infinity)"
    assert worst_cells({}) == ""


def test_the_cell_weighted_finish_weighs_each_rows_cell_by_its_error(zoom, configs):
    """``lm_cell_weight`` = p: a cell's rows weigh (its goal ratio / the cells' median ratio)^p within the clip, the
    score is the worst cell's ratio, and fresh rows carry their cell's weight (times an edge weight, 1 here)."""
    from types import SimpleNamespace
    from mi_neurallens.training.config import NetConfig
    from mi_neurallens.training.regressor import RegressorFit
    e = lambda p, d: {"position_um_median": p, "direction_arcsec_median": d}
    med = {"wide, infinity": e(1.0, 6.0), "mid, mid": e(1.0, 2.5), "tele, close": e(3.0, 2.0), "tele, mid": e(0.2, 0.5)}
    fit = SimpleNamespace(nc=NetConfig(lm_cell_weight=2.0), state={}, CELL_WEIGHT_CLIP=RegressorFit.CELL_WEIGHT_CLIP)
    worst = RegressorFit.cell_weights(fit, med)
    assert worst == pytest.approx(1.5)                       # tele, close: 3 um against 2
    # ratios 1.2, 0.5, 1.5, 0.1; their median 0.85
    assert fit.cell_w["wide, infinity"] == pytest.approx((1.2 / 0.85) ** 2)
    assert fit.cell_w["tele, close"] == pytest.approx((1.5 / 0.85) ** 2)
    assert fit.cell_w["tele, mid"] == pytest.approx(0.25)    # (0.1 / 0.85)^2 = 0.014, clipped at 1/4
    t0, t1 = configs.zoom_range
    x = np.zeros((3, 6))
    x[:, 4:6] = [(t0, mv.focus_parameter(zoom, t0, math.inf)), (t1, configs.band(t1)[1]),
                 (t0, float(np.mean(configs.band(t0))))]             # wide, mid: no weight given, 1
    stream = SimpleNamespace(sample=lambda k: (np.zeros((3, 6)), x, np.zeros((3, 5))))
    rows = SimpleNamespace(stream=stream, center=np.zeros(6), scale_in=np.ones(6), f32=np.asarray,
                           targets=lambda x, xn, y: y, space=lambda y: y, nc=fit.nc, cell_w=fit.cell_w, conf=configs)
    np.testing.assert_allclose(RegressorFit.fresh_rows(rows, 3)["W"], [fit.cell_w["wide, infinity"],
                                                                       fit.cell_w["tele, close"], 1.0])
    rows.cell_w = None
    assert "W" not in RegressorFit.fresh_rows(rows, 3)
