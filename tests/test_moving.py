"""Moving groups (zoom and the lens's own focusing, mi_neurallens/optics/moving.py) on the bundled Canon EF 24-70 mm
f/2.8L: the listed positions reproduced, the interpolation, focal lengths and focus distances solved (paraxially
and by real rays), the sensors' ``focal_length``, the breathing of an internally focused lens, the file format;
and on the bundled Canon RF 24 mm, a prime that focuses internally by two groups (its close gaps published)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from mi_neurallens.errors import LensError
from mi_neurallens.optics import moving as mv
from mi_neurallens.optics.prescription import Lens

ZOOM = "canon-ef-24-70mm-f2.8l"
#: the file's (JP 2014-041222 A, Ex. 1) listed positions and gaps (the label's surface index: its gap after it)
LISTED_EFL = (24.9, 35.13, 68.14)
LISTED = {5: [(55.36, 55.36), (31.61, 31.61), (3.78, 3.78)],
          24: [(1.19, 2.3838035791), (3.58, 5.6647305554), (10.91, 18.3469018668)]}
PRIME = "canon-rf-24mm-f1.4l-vcm"
#: its file's (JP 2025-15010 A, Ex. 3) variable gaps D9, D11, D15, D22 at infinity and at the 0.24 m close focus
PRIME_LISTED = {8: (1.2, 4.82), 10: (8.91, 5.28), 14: (6.78, 3.91), 21: (1.85, 4.73)}


@pytest.fixture(scope="module")
def zoom():
    return Lens.load(ZOOM)


def test_pchip_is_scipys():
    """The monotone cubic through the positions is scipy's PchipInterpolator (an implementation we did not write)."""
    from scipy.interpolate import PchipInterpolator
    rng = np.random.default_rng(3)
    for n in (2, 3, 5):
        x = np.cumsum(rng.uniform(0.5, 2.0, n))
        y = rng.uniform(-5, 5, n)
        xq = np.linspace(x[0], x[-1], 57)
        np.testing.assert_allclose(mv.pchip(x, y, xq), PchipInterpolator(x, y)(xq), rtol=0, atol=1e-12)


def test_listed_positions_are_reproduced_exactly(zoom):
    mg = zoom.moving
    assert mg.positions == 3 and mg.zoom_efl_mm == LISTED_EFL and mg.close_focus_mm == 380.0
    assert mg.close_gaps == "modelled"                      # the catalogue's 10-digit close gaps
    for i, rows in LISTED.items():
        for k, (d_inf, d_close) in enumerate(rows):
            assert mg.gaps_at(k, 0.0)[i] == d_inf and mg.gaps_at(k, 1.0)[i] == pytest.approx(d_close, abs=1e-12)
    # a gap listed equal at two positions (none here) stays put; a monotone one stays between its neighbours
    g = [mg.gaps_at(t, 0.0)[5] for t in np.linspace(0, 2, 41)]
    assert all(a >= b for a, b in zip(g, g[1:]))


def test_focal_lengths_at_the_listed_positions_and_between(zoom):
    """EFL at infinity focus within 0.1 % of the listed focal lengths; monotone in the zoom parameter; a requested
    focal length is met; outside the range a clear error naming it."""
    for k, f in enumerate(LISTED_EFL):
        assert abs(mv.focal_length(zoom, float(k)) / f - 1) < 1e-3
    efl = [mv.focal_length(zoom, t) for t in np.linspace(0, 2, 21)]
    assert all(b > a for a, b in zip(efl, efl[1:]))
    for f in (28.0, 50.0, 60.0):
        t = mv.zoom_parameter(zoom, f)
        assert mv.focal_length(zoom, t) == pytest.approx(f, rel=1e-7)
    with pytest.raises(LensError, match="24.9-68.14 mm"):
        mv.zoom_parameter(zoom, 80.0)


@pytest.mark.parametrize("focal", [24.9, 50.0, 68.14])
def test_the_solved_focus_images_the_object_on_the_sensor(zoom, focal):
    """The close-focus distance (0.38 m) and 1.5 m: paraxially on the sensor to 1e-6 mm (focus parameter solved
    paraxially), and the default (real-ray) solution puts the real rays' best focus within 0.03 mm of the sensor,
    checked by a brute-force search of the smallest RMS spot over random pupil samples (not the solver's closed
    form).  At the listed close focus the paraxial solution is the listed close gaps (f = 1)."""
    t = mv.zoom_parameter(zoom, focal)
    for D in (380.0, 1500.0):
        f = mv.focus_parameter(zoom, t, D)
        assert abs(mv.focus_error(zoom, t, f, D)) < 1e-6
        lens, _, _ = mv.configure(zoom, focal, D)
        assert abs(_brute_best_focus(lens, D)) <= 0.03
    if focal in LISTED_EFL:
        assert mv.focus_parameter(zoom, t, 380.0) == pytest.approx(1.0, abs=0.01)


def _brute_best_focus(lens, D, n=3000):
    rng = np.random.default_rng(1)
    px = lens.paraxial(587.5618)
    r = px.entrance_pupil_radius * np.sqrt(rng.random(n))
    a = 2 * np.pi * rng.random(n)
    tgt = np.stack([r * np.cos(a), r * np.sin(a), np.full(n, px.entrance_pupil_z)], 1)
    o = np.tile([0.0, 0.0, lens.image_z - D], (n, 1))
    d = tgt - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    res = lens.trace(o, d, 587.5618, precision="float64")
    P, V = res.position[res.valid], res.direction[res.valid]
    zs = np.linspace(-0.3, 0.3, 601)
    rms = [np.mean((P[:, 0] + z * V[:, 0] / V[:, 2]) ** 2 + (P[:, 1] + z * V[:, 1] / V[:, 2]) ** 2) for z in zs]
    return zs[int(np.argmin(rms))]


def test_an_internally_focused_prime(capsys):
    """The RF 24 mm focuses by two groups (four gaps; the last gap, to the sensor, stays): the published gaps at
    infinity and close focus read exactly; at infinity it is the patent's lens (EFL 24.713 mm); focused by real
    rays at the listed 0.24 m and at 1 m, the brute-force best focus lies within 0.03 mm of the sensor; the
    published close gaps (f = 1) focus a little nearer than 0.24 m (the patent's close distance is rounded: the
    solved f is 0.985); the EFL shortens to 23.1 mm at 0.24 m; a unit-focusing sensor distance is refused."""
    prime = Lens.load(PRIME)
    mg = prime.moving
    assert mg.positions == 1 and mg.zoom_efl_mm is None and mg.close_focus_mm == 240.0
    assert mg.close_gaps == "published" and mg.focuses and len(prime.surfaces) - 1 not in mg.gaps
    for i, (d_inf, d_close) in PRIME_LISTED.items():
        assert mg.gaps_at(0, 0.0)[i] == d_inf and mg.gaps_at(0, 1.0)[i] == pytest.approx(d_close, abs=1e-12)
    assert mv.at(prime, 0.0, 0.0).efl() == pytest.approx(24.7131, abs=1e-4)
    for D in (240.0, 1000.0):
        lens, _, f = mv.configure(prime, None, D)
        assert abs(_brute_best_focus(lens, D)) <= 0.03
    assert 0.97 < mv.focus_parameter(prime, 0.0, 240.0, real_rays=True) < 1.0
    close, _, _ = mv.configure(prime, None, 240.0)
    assert close.efl() == pytest.approx(23.13, abs=0.01)
    with pytest.raises(LensError, match="no nearer than 0.24 m"):
        mv.configure(prime, None, 200.0)


def test_closer_than_close_focus_is_refused(zoom):
    with pytest.raises(LensError, match="no nearer than 0.38 m"):
        mv.configure(zoom, 50.0, 300.0)


@pytest.mark.parametrize("lens_name, focal, close, film_x, fstop, change", [
    (ZOOM, 68.14, 0.38, 0.9, None, -0.076), (PRIME, None, 0.24, 0.65, 8.0, 0.0143)])
def test_breathing_of_the_internal_focus(lens_name, focal, close, film_x, fstop, change):
    """Focusing the 24-70 at 68 mm from infinity to 0.38 m moves its focusing group (EFL 68.1 → 58.4 mm), and its
    field of view changes as the configured prescription's paraxial optics say: realistic_lens's camera rays
    through a film point 9.6 mm off axis leave at the slope of the paraxial chief ray (object-side slope per mm
    of image height: 0.01468 at infinity, 0.01357 at 0.38 m: the view narrows by 7.6 %), within 1 %.  The RF 24 mm
    breathes the other way: from infinity to 0.24 m its EFL shortens (24.71 → 23.13 mm) and its view widens by
    1.4 % (0.04045 → 0.04103 per mm; 3.6 mm off axis at f/8, where the bundle is narrow enough for its mean slope
    to be the chief ray's), within 0.5 % (the real rays: 1.8 %, the close-focus distortion)."""
    import mitsuba as mi
    import drjit as dr
    from mi_neurallens.render_utils import default_variant
    mi.set_variant(default_variant())
    import mi_neurallens as nl
    nl.register()
    h = (film_x - 0.5) * 24.0                        # film x of a 24 mm wide sensor: mm off axis
    measured, predicted = {}, {}
    for D in (math.inf, close):
        zoomed = ({} if focal is None else {"focal_length": focal}) | ({} if fstop is None else {"fstop": fstop})
        s = mi.load_dict({"type": "realistic_lens", "lens": lens_name, **zoomed, "focus_distance": D,
                          "film": {"type": "hdrfilm", "width": 64, "height": 64}, "sensor_width": 24.0})
        n = 20000
        rng = np.random.default_rng(0)
        u3 = mi.Point2f(rng.random(n).astype(np.float32), rng.random(n).astype(np.float32))
        ray, w = s.sample_ray(0.0, mi.Float(0.5), mi.Point2f(film_x, 0.5), u3)
        ok = dr.detach(w[0]).numpy() > 0
        d = np.stack([c.numpy() for c in (ray.d.x, ray.d.z)], 1)[ok]
        measured[D] = abs(np.mean(d[:, 0] / d[:, 1])) / h          # the bundle's mean slope per mm of image height
        L = s.setup.lens
        px = L.paraxial(587.5618)
        if math.isinf(D):
            predicted[D] = 1.0 / px.image_height_per_tan()
        else:
            dmm = D * 1000.0
            m = px.magnification(dmm - L.total_track - L.surfaces[-1].thickness)
            predicted[D] = (1.0 / abs(m)) / (px.entrance_pupil_z - (L.image_z - dmm))
    assert predicted[close] / predicted[math.inf] - 1 == pytest.approx(change, abs=0.001)    # the prescription's
    tol = 0.01 if abs(change) > 0.05 else 0.005
    assert measured[close] / measured[math.inf] == pytest.approx(predicted[close] / predicted[math.inf], abs=tol)
    assert (measured[close] > measured[math.inf]) == (change > 0)                             # the sign, measured
    for D in measured:
        assert measured[D] == pytest.approx(predicted[D], rel=0.02)


def test_sensors_take_the_focal_length(zoom):
    import mitsuba as mi
    from mi_neurallens.render_utils import default_variant
    mi.set_variant(default_variant())
    import mi_neurallens as nl
    nl.register()
    film = {"type": "hdrfilm", "width": 48, "height": 32}
    s = mi.load_dict({"type": "realistic_lens", "lens": ZOOM, "focal_length": 50.0, "focus_distance": 2.0,
                      "film": film})
    assert s.setup.focal_length_mm == pytest.approx(50.0) and s.setup.sensor_distance_mm == 38.47
    wide = mi.load_dict({"type": "realistic_lens", "lens": ZOOM, "film": film})
    assert wide.setup.focal_length_mm == pytest.approx(24.898, abs=1e-3)
    assert wide.setup.max_fnumber < s.setup.max_fnumber                      # the f-number changes with zoom
    for kw, match in (({"focal_length": 90.0}, "24.9-68.14 mm"), ({"sensor_distance": 40.0}, "moving groups"),
                      ({"focus_distance": 0.2}, "no nearer")):
        with pytest.raises(Exception, match=match):
            mi.load_dict({"type": "realistic_lens", "lens": ZOOM, "film": film, **kw})
    with pytest.raises(Exception, match="not a zoom lens"):
        mi.load_dict({"type": "realistic_lens", "lens": "wide-22mm", "focal_length": 22.0, "film": film})
    with pytest.raises(Exception, match="trained for lens 'wide-22mm'"):
        mi.load_dict({"type": "neural_lens", "lens": ZOOM, "model": "wide-22mm", "film": film})
    # params.update() refocuses by the groups; gradients would miss the groups' motion: a clear error
    import drjit as dr
    sc0 = mi.load_dict({"type": "scene", "sensor": {"type": "realistic_lens", "lens": ZOOM, "focal_length": 50.0,
                                                    "focus_distance": 2.0, "film": film}})
    p = mi.traverse(sc0)
    p["sensor.focus_distance"] = mi.Float(1.0)
    p.update()
    assert sc0.sensors()[0].setup.focus_parameter > s.setup.focus_parameter        # the group moved to focus nearer
    dr.enable_grad(p["sensor.focus_distance"])
    with pytest.raises(Exception, match="not differentiated"):
        p.update()
    # a render between two listed positions: finite, lit, in focus enough to differ from the wide end
    sc = mi.load_dict({"type": "scene", "sensor": {"type": "realistic_lens", "lens": ZOOM, "focal_length": 45.0,
                                                   "focus_distance": 1.0, "film": film,
                                                   "sampler": {"type": "independent", "sample_count": 4}},
                       "light": {"type": "constant"}, "integrator": {"type": "path"}})
    img = np.array(mi.render(sc))
    assert np.isfinite(img).all() and 0.05 < img.mean() < 2.0


@pytest.mark.parametrize("sensor", ["realistic_lens", "neural_lens"])
def test_zoom_and_focus_as_parameters_compile_nothing(zoom, sensor):
    """A zoom lens's ``focal_length`` is a parameter like ``focus_distance``: after ``params.update()`` the render is
    the one of the scene loaded at the new focal length and focus, and after the first update (which makes the
    numbers kernel inputs) zooming and refocusing compile no kernel: the configuration's numbers (vertex positions,
    planes, stop, the map's folded layers and planes) are kernel inputs.  A lens that does not zoom has no
    ``focal_length`` parameter."""
    import mitsuba as mi
    import drjit as dr
    from mi_neurallens.metrics import mape
    from mi_neurallens.render_utils import default_variant
    mi.set_variant(default_variant())
    import mi_neurallens as nl
    nl.register()

    def scene(**kw):
        return mi.load_dict({"type": "scene", "sensor": {"type": sensor, "lens": ZOOM, "film": {
            "type": "hdrfilm", "width": 40, "height": 26}, "sampler": {"type": "independent", "sample_count": 4},
            **({"model": ZOOM} if sensor == "neural_lens" else {}), **kw},
            "light": {"type": "constant"}, "integrator": {"type": "path"},
            "ball": {"type": "sphere", "center": [0.0, 0.0, 1.5], "radius": 0.3,
                     "bsdf": {"type": "diffuse", "reflectance": {"type": "checkerboard"}}}})

    loaded = scene(focus_distance=2.0)           # at the first listed position (a float64 focal length)
    p = mi.traverse(loaded)
    p["sensor.focus_distance"] = 1.5                # a focus pull there keeps that focal length
    p.update()
    assert loaded.sensors()[0].setup.zoom == 0.0
    sc = scene(focal_length=30.0, focus_distance=2.0, fstop=4.0)       # the stop's radius moves with the zoom
    p = mi.traverse(sc)
    assert "sensor.focal_length" in p.keys() and p["sensor.focal_length"][0] == pytest.approx(30.0)
    hashes = []
    for f, d in ((40.0, 2.0), (55.0, 2.0), (55.0, 1.1)):
        p["sensor.focal_length"], p["sensor.focus_distance"] = f, d
        p.update()
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            dr.kernel_history()
            img = np.array(mi.render(sc, seed=5))
            hashes.append({h["hash"] for h in dr.kernel_history() if h["type"] == dr.KernelType.JIT})
        assert sc.sensors()[0].setup.focal_length_mm == pytest.approx(f)
        ref = np.array(mi.render(scene(focal_length=f, focus_distance=d, fstop=4.0), seed=5))
        assert img.mean() > 0.01 and mape(img, ref) < 1e-4, (f, d, mape(img, ref))
    assert hashes[1] <= hashes[0] and hashes[2] <= hashes[0]
    prime = mi.traverse(mi.load_dict({"type": "scene", "sensor": {"type": "realistic_lens",
                                                                   "lens": "canon-rf-24mm-f1.4l-vcm"}}))
    assert "sensor.focus_distance" in prime.keys() and "sensor.focal_length" not in prime.keys()


def test_moving_groups_are_in_the_fingerprint_and_the_file(zoom, tmp_path):
    """A model trained for one set of moving groups cannot be used with another: the fingerprint covers them (and
    a lens without keeps its fingerprint); the project JSON writes and reads them, schema-valid."""
    fixed = mv.at(zoom, 0.0, 0.0)
    assert fixed.moving is None and fixed.fingerprint() != zoom.fingerprint()
    other = zoom.replace(moving=mv.MovingGroups({**zoom.moving.gaps, 12: ((2.9, 2.9), (6.6, 6.6), (20.41, 20.41))},
                                                zoom.moving.zoom_efl_mm, zoom.moving.close_focus_mm))
    assert other.fingerprint() != zoom.fingerprint()
    p = tmp_path / "z.json"
    zoom.save(p)
    back = Lens.load(p)
    assert back == zoom and back.fingerprint() == zoom.fingerprint()
    import jsonschema
    from importlib import resources as ir
    schema = json.loads((ir.files("mi_neurallens") / "data" / "lens.schema.json").read_text())
    jsonschema.validate(json.loads(p.read_text()), schema)
    doc = json.loads(p.read_text())
    doc["moving"]["gaps"]["5"][0][0] = 50.0                  # no longer the lens as written
    with pytest.raises(LensError, match="first position"):
        from mi_neurallens.optics.formats.project_json import lens_from_dict
        lens_from_dict(doc)


def test_lens_info_prints_the_configuration(capsys):
    from mi_neurallens.cli import main
    assert main(["lens", "info", ZOOM, "--focal-length", "50", "--focus-distance", "1000", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["configuration"]["focal_length_mm"] == pytest.approx(50.0)
    assert d["efl"] < 50.0                                   # breathing: shorter at 1 m than at infinity
    assert d["fingerprint"] == Lens.load(ZOOM).fingerprint()
    assert main(["lens", "info", ZOOM, "--focal-length", "35"]) == 0
    assert "Moving groups" in capsys.readouterr().out
    assert main(["lens", "info", ZOOM, "--focal-length", "10"]) != 0


def test_convert_writes_one_configuration(tmp_path, capsys):
    """``lens convert --focal-length`` writes one fixed configuration (no moving groups: a lens neural_lens can
    learn), and refuses a lens without moving groups before writing anything."""
    from mi_neurallens.cli import main
    out = tmp_path / "z50.json"
    assert main(["lens", "convert", ZOOM, str(out), "--focal-length", "50", "--focus-distance", "2000"]) == 0
    fixed = Lens.load(out)
    assert fixed.moving is None and "one configuration" in fixed.metadata["source"]["conversion"][-1]
    assert abs(mv.focal_length(Lens.load(ZOOM), mv.zoom_parameter(Lens.load(ZOOM), 50.0)) - 50.0) < 1e-6
    assert fixed.efl() < 50.0                               # focused at 2 m: a little shorter (breathing)
    with pytest.raises(SystemExit):
        main(["lens", "convert", "wide-22mm", str(tmp_path / "w.json"), "--focal-length", "22"])
    assert not (tmp_path / "w.json").exists()
