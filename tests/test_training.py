"""Training data and the trainer: CIE wavelengths, MCMC validity and coverage, a tiny training run."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from mi_neurallens import Lens, NeuralLensError
from mi_neurallens.optics.glass import AIR, constant
from mi_neurallens.optics.prescription import Surface
from mi_neurallens.trace.api import float_type
from mi_neurallens.training import data
from mi_neurallens.transport import planes as plan, sampling
from mi_neurallens.transport import planning
from mi_neurallens.training.config import load_config


def thick_lens():
    """A single biconvex element (n = 1.6, f ≈ 42 mm) behind a stop."""
    return Lens((Surface(math.inf, 3.0, AIR, 7.0, is_stop=True),
                 Surface(50.0, 6.0, constant(1.6), 12.0),
                 Surface(-50.0, 40.0, AIR, 12.0)), name="thick")


# ----------------------------------------------------------------------------- wavelengths
def test_cie_sampling_matches_mitsuba_and_its_pdf():
    import mitsuba as mi
    u = np.linspace(0.001, 0.999, 257)
    lam, w = planning.sample_cie_wavelength(u)
    ref = np.array([mi.scalar_rgb.sample_rgb_spectrum(float(v)) for v in u])
    np.testing.assert_allclose(lam, ref[:, 0], rtol=1e-5)
    np.testing.assert_allclose(w, ref[:, 1], rtol=1e-4)
    # the pdf integrates to 1 on [360, 830] nm and the inverse is exact
    g = np.linspace(360, 830, 200001)
    assert abs(np.trapezoid(planning.pdf_cie_wavelength(g), g) - 1.0) < 1e-3
    np.testing.assert_allclose(planning.cie_u_of_lambda(lam), u, atol=1e-9)
    # Dr.Jit version (what the generator runs) agrees
    F = float_type("float32")
    lam_d, _ = planning.sample_cie_wavelength(F(u.astype(np.float32)))
    np.testing.assert_allclose(lam_d.numpy(), lam, rtol=1e-5)


def test_domain_u_to_x_is_the_cie_sample_and_inverts_across_its_blocks():
    """u_to_x works in blocks of 2¹⁶ rows: every row, those of a partial last block too, is the closed form
    (r_max·u₀, the disc point of (u₁, u₂), sample_cie_wavelength(u₃)), and x_to_u inverts it."""
    dom = planning.Domain(12.5, 0.3)
    u = np.random.default_rng(2).random(((1 << 16) + 777, 4)) * 0.998 + 0.001
    x = dom.u_to_x(u)
    rho, th = 0.3 * np.sqrt(u[:, 1]), math.pi * u[:, 2]
    np.testing.assert_array_equal(x[:, 0], 12.5 * u[:, 0])
    np.testing.assert_allclose(x[:, 1:3], np.stack([rho * np.cos(th), rho * np.sin(th)], 1), rtol=0, atol=1e-15)
    np.testing.assert_allclose(x[:, 3], planning.sample_cie_wavelength(u[:, 3])[0], rtol=1e-15)
    np.testing.assert_allclose(dom.x_to_u(x), u, atol=1e-9)


def test_generator_wavelength_histogram_follows_cie():
    lens = thick_lens()
    ps = sampling.PathSampler(lens, 0, "forward", -1.0, 60.0, planning.Domain(8.0, 0.1))
    u, y = ps.random_valid(1 << 18, seed=5)
    lam = ps.domain.u_to_x(u)[:, 3]
    edges = np.linspace(360, 830, 48)
    h, _ = np.histogram(lam, edges)
    c = np.linspace(0, 1, 4001)
    cdf_lam = planning.sample_cie_wavelength(c)[0]
    expected = np.diff(np.interp(edges, cdf_lam, c)) * len(lam)
    chi2 = np.sum((h - expected) ** 2 / expected)
    assert chi2 < 120, chi2          # 47 bins: ~47 ± 10 for a correct sampler
    # and it is not uniform
    assert h[len(h) // 2] > 3 * h[0]


# ----------------------------------------------------------------------------- MCMC
def test_mcmc_samples_valid_and_cover_valid_region():
    lens = Lens.load("wide-22mm")
    s0, _ = plan.sensor_distance_range(lens, 300.0)
    z_front, z_rear = plan.planes(lens, s0)
    dom = plan.forward_domain(lens, z_front, 45.0)
    pid = 2560
    ps = sampling.PathSampler(lens, pid, "forward", z_front, z_rear, dom)
    rng = np.random.default_rng(3)
    m = sampling.MCMCSampler(ps, rng, n_chains=1 << 13, p_large=0.3, sigma=0.03, seed_rays=1 << 20)
    for _ in range(8):
        m.step()
    u, x, y = m.sample(1 << 17)
    assert 0.05 < m.acceptance < 1.0
    # every sample is valid when re-traced (float32 tracer), and in float64 all but a rounding few
    assert ps.valid_u(u).all()
    ps64 = sampling.PathSampler(lens, pid, "forward", z_front, z_rear, dom, precision="float64")
    assert ps64.valid_u(u).mean() > 0.999
    # coverage: marginal histograms match rejection sampling (uniform over the valid region)
    ur, _, _, st = sampling.rejection_sample(ps, 1 << 17, np.random.default_rng(4))
    for k in range(4):
        hm, _ = np.histogram(u[:, k], np.linspace(0, 1, 21))
        hr, _ = np.histogram(ur[:, k], np.linspace(0, 1, 21))
        tv = 0.5 * np.abs(hm / hm.sum() - hr / hr.sum()).sum()
        assert tv < 0.06, (k, tv)
    # a 2-D joint histogram too (r vs direction radius)
    hm, _, _ = np.histogram2d(u[:, 0], u[:, 1], 8, [[0, 1], [0, 1]])
    hr, _, _ = np.histogram2d(ur[:, 0], ur[:, 1], 8, [[0, 1], [0, 1]])
    assert 0.5 * np.abs(hm / hm.sum() - hr / hr.sum()).sum() < 0.08



def test_stream_keeps_the_rows_a_launch_traced_beyond_a_call():
    """The finish asks a stream for 8 192 rows an iteration while a rejection launch traces 2^21 rays: the
    valid rays a call does not take are handed out by the next calls (no new launch until they run out),
    every row once, all valid and uniform like a single large draw; a reseed drops them."""
    lens = thick_lens()
    ps = sampling.PathSampler(lens, 0, "forward", -1.0, 60.0, planning.Domain(8.0, 0.1))
    st = data.RegressorStream(ps, seed=3, bounded=False)
    t0 = ps.rays_traced
    u1, x1, y1 = st.sample(4096)
    launched = ps.rays_traced - t0
    assert launched == 1 << 21 and len(u1) == 4096 and np.isfinite(y1).all()
    parts = [st.sample(4096)[0] for _ in range(20)]
    assert ps.rays_traced - t0 == launched            # 84 k rows from the first launch's ≈ 0.6 M valid rays
    u = np.concatenate([u1] + parts)
    assert len(np.unique(u, axis=0)) == len(u)        # no row handed out twice
    assert ps.valid_u(u).all()
    np.testing.assert_allclose(ps.domain.u_to_x(u1), x1)
    ref, _, _, _ = sampling.rejection_sample(ps, len(u), np.random.default_rng(9))
    for k in range(4):
        hm, _ = np.histogram(u[:, k], np.linspace(0, 1, 11))
        hr, _ = np.histogram(ref[:, k], np.linspace(0, 1, 11))
        assert 0.5 * np.abs(hm / hm.sum() - hr / hr.sum()).sum() < 0.02, k
    assert len(st._u) <= data.RegressorStream.KEEP
    st.reseed(5)
    assert len(st._u) == 0
    t1 = ps.rays_traced
    st.sample(16)
    assert ps.rays_traced - t1 == launched


def test_film_reach_keeps_exactly_the_rays_that_come_near_the_film():
    """Ghost 3072 of the 22 mm lens (a reflection between its last two surfaces) leaves the lens at grazing
    angles: a third of its rays land more than 1.5 film half-diagonals off axis, some metres away.  With a
    film reach the sampler keeps exactly the rays that pass within the radius on the nearest or the farthest
    sensor plane (checked by straight propagation in numpy), the classifier's margin target is the reach's
    1 − r²/R² where the reach is the closest aperture, and the reach survives the domain's stored form."""
    lens = Lens.load("wide-22mm")
    s_range = plan.sensor_distance_range(lens, 300.0)
    z_front, z_rear = plan.planes(lens, s_range[0])
    reach = plan.film_reach(lens, s_range, 1.5 * 21.6333)
    free = plan.forward_domain(lens, z_front, 45.0)
    dom = plan.forward_domain(lens, z_front, 45.0, reach=reach)
    assert planning.Domain.from_dict(dom.to_dict()) == dom and planning.Domain.from_dict(free.to_dict()).reach is None
    u = np.random.default_rng(2).random((1 << 18, 4))
    v0, y0 = sampling.PathSampler(lens, 3072, "forward", z_front, z_rear, free, precision="float64").trace_u(u)
    ps = sampling.PathSampler(lens, 3072, "forward", z_front, z_rear, dom, precision="float64")
    v1, y1 = ps.trace_u(u)

    def radius(y, z):
        dz = np.sqrt(1.0 - y[:, 2] ** 2 - y[:, 3] ** 2)
        return np.hypot(y[:, 0] + y[:, 2] * (z - z_rear) / dz, y[:, 1] + y[:, 3] * (z - z_rear) / dz)

    r_min = np.minimum(radius(y0[v0], reach.z_near_mm), radius(y0[v0], reach.z_far_mm))
    assert 0.2 < (r_min > reach.radius_mm).mean() < 0.6 and r_min.max() > 1000.0
    np.testing.assert_array_equal(v1[v0], r_min <= reach.radius_mm)
    assert not (v1 & ~v0).any()
    np.testing.assert_array_equal(y1[v1], y0[v1])
    valid, margin, hard = ps.margin_u(u)
    np.testing.assert_array_equal(valid, v1)
    r_max = np.maximum(radius(y0[v0], reach.z_near_mm), radius(y0[v0], reach.z_far_mm))
    m_reach = 1.0 - np.minimum(radius(y0[v0], reach.z_near_mm), radius(y0[v0], reach.z_far_mm)) ** 2 / reach.radius_mm ** 2
    # never above the reach's own margin (float64 rounding of a ray propagated 1 m: relative 1e-9)
    assert (margin[v0] <= m_reach + 1e-7 * np.maximum(1.0, np.abs(m_reach))).all()
    far = r_max > 3 * reach.radius_mm
    assert far.any() and (margin[v0][far] < 0).all()


def test_bounded_rejection_is_uniform_over_the_valid_region_and_wastes_fewer_rays():
    """Pilot-traced bounds (transport/bounds.py) must not change the sampled distribution: every valid
    ray of an independent pilot lies inside the boxes, and the marginals match plain rejection."""
    lens = Lens.load("wide-22mm")
    s0, _ = plan.sensor_distance_range(lens, 300.0)
    z_front, z_rear = plan.planes(lens, s0)
    dom = plan.backward_domain(lens, 0, z_rear, z_front, np.random.default_rng(0), n=1 << 20)
    ps = sampling.PathSampler(lens, 0, "backward", z_rear, z_front, dom)
    b = ps.build_bounds(np.random.default_rng(1), n_pilot=1 << 21)
    assert b is not None and b.missed == 0.0
    assert b.volume_fraction(dom) < 0.4                      # a real reduction of the sampled volume
    ur, yr = ps.random_valid(1 << 21, 11, bounds=False)
    ub, yb = ps.random_valid(1 << 21, 12, bounds=True)
    assert len(ub) > 3 * len(ur)                             # acceptance 12 % -> ~58 %
    # the returned u addresses its own sample, and the sample is valid in float64 too
    ps64 = sampling.PathSampler(lens, 0, "backward", z_rear, z_front, dom, precision="float64")
    v64, y64 = ps64.trace_u(ub[:20000])
    assert v64.mean() > 0.999
    np.testing.assert_allclose(y64[v64, :2], yb[:20000][v64, :2], atol=2e-3)
    for k in range(4):
        hr, _ = np.histogram(ur[:, k], np.linspace(0, 1, 21))
        hb, _ = np.histogram(ub[:, k], np.linspace(0, 1, 21))
        assert 0.5 * np.abs(hr / hr.sum() - hb / hb.sum()).sum() < 0.015, k
    hr, _, _ = np.histogram2d(ur[:, 0], ur[:, 1], 8, [[0, 1], [0, 1]])
    hb, _, _ = np.histogram2d(ub[:, 0], ub[:, 1], 8, [[0, 1], [0, 1]])
    assert 0.5 * np.abs(hr / hr.sum() - hb / hb.sum()).sum() < 0.02
    # a bounds that cut the valid region would be caught by `missed`
    from mi_neurallens.transport.bounds import ValidBounds
    cut = ValidBounds(b.r_edges, b.wx_lo, 0.5 * (b.wx_lo + b.wx_hi), b.wy_lo, b.wy_hi)
    assert not cut.contains(dom.u_to_x(ur)).all()


def test_a_stop_stream_takes_the_regressor_streams_pilot_and_still_samples_its_valid_region():
    """The stop head's stream (a sampler with the crossings) built ``like`` the regressor's stream of the same map
    traces no valid-fraction rays and no pilot: it takes that stream's fraction and bounds, and its rows are valid,
    carry the crossings and follow the regressor stream's distribution.  A stream of another map is refused."""
    lens = Lens.load("wide-22mm")
    s0, _ = plan.sensor_distance_range(lens, 300.0)
    z_front, z_rear = plan.planes(lens, s0)
    dom = plan.backward_domain(lens, 0, z_rear, z_front, np.random.default_rng(0), n=1 << 20)
    reg = data.RegressorStream(sampling.PathSampler(lens, 0, "backward", z_rear, z_front, dom), seed=1)
    assert reg.ps.bounds is not None
    ps = sampling.PathSampler(lens, 0, "backward", z_rear, z_front, dom, stops=True)
    st = data.RegressorStream(ps, seed=2, like=reg)
    assert ps.rays_traced == 0 and ps.bounds is reg.ps.bounds and st.fraction == reg.fraction
    u, x, y = st.sample(50_000)
    assert ps.rays_traced > 0 and y.shape[1] == 5 + 2 * ps.map.stop_crossings and np.isfinite(y).all()
    assert ps.valid_u(u[:5000]).all()
    ur, _, _ = reg.sample(50_000)
    for k in range(4):
        h1, _ = np.histogram(u[:, k], np.linspace(0, 1, 11))
        h2, _ = np.histogram(ur[:, k], np.linspace(0, 1, 11))
        assert 0.5 * np.abs(h1 / h1.sum() - h2 / h2.sum()).sum() < 0.02, k
    other = sampling.PathSampler(lens, 0, "backward", z_rear, z_front, planning.Domain(dom.r_max * 0.5, dom.s_max), stops=True)
    with pytest.raises(NeuralLensError, match="not this sampler's map"):
        data.RegressorStream(other, seed=3, like=reg)


def test_classifier_samples_are_balanced_with_boundary_points():
    lens = thick_lens()
    ps = sampling.PathSampler(lens, 0, "backward", 52.0, -1.0, planning.Domain(12.0, 0.4))
    rng = np.random.default_rng(0)
    u, _, _, st = sampling.rejection_sample(ps, 20000, rng)
    x, lab = data.classifier_samples(ps, u, 30000, rng)
    assert 0.3 < lab.mean() < 0.8
    assert st["acceptance"] < 0.6          # the natural mix is mostly blocked, the training mix is not


@pytest.mark.parametrize("blades", [0, 6])
@pytest.mark.parametrize("path", [0, "ghost"])
def test_aperture_margin_is_the_validity_boundary(blades, path):
    """The tracer's aperture margin (the classifier's ``margin`` target) is ≥ 0 exactly on the valid
    rays that no non-aperture failure stopped, and it is a smooth function of the inputs: a step of
    1e-6 in the unit cube moves it by O(1e-6) near the boundary (|margin| < 0.5, the band the classifier
    regresses), never across a jump."""
    from mi_neurallens.trace.paths import all_ghosts
    lens = thick_lens().with_stop_radius(4.0)
    if blades:
        lens = lens.with_surface(lens.stop_index, blades=blades)
    pid = all_ghosts(lens)[0][0] if path == "ghost" else 0
    ps = sampling.PathSampler(lens, pid, "backward", 52.0, -1.0, planning.Domain(12.0, 0.4), precision="float64")
    rng = np.random.default_rng(3)
    u = rng.random((60000, 4))
    valid, m, hard = ps.margin_u(u)
    np.testing.assert_array_equal(valid, ps.valid_u(u))
    np.testing.assert_array_equal(valid, ~hard & (m >= 0.0))
    assert valid.any() and (~hard & (m < 0.0)).any()            # both sides of an aperture boundary occur
    v2, m2, hard2 = ps.margin_u(np.clip(u + 1e-6, 0.0, 1.0 - 1e-9))
    band = ~hard & ~hard2 & (np.abs(m) < 0.5)
    assert band.sum() > 1000 and np.max(np.abs(m2 - m)[band]) < 1e-3


# ----------------------------------------------------------------------------- config
def test_output_transform_is_the_least_squares_fit_over_many_blocks():
    """fit_output_transform's blocked normal equations give what one least-squares solve of the whole
    (N, 5) design matrix gives (the odd factor on the y columns included), and the residuals' spread."""
    from mi_neurallens.training.outputs import FIT_BLOCK_ROWS, fit_output_transform, odd_factor
    rng = np.random.default_rng(11)
    n = 2 * FIT_BLOCK_ROWS + 1234
    xn = rng.uniform(-1, 1, (n, 4))
    y = np.stack([np.sin(xn @ rng.normal(size=4)) * (3 + j) + 0.2 * j + 0.01 * rng.normal(size=n)
                  for j in range(5)], 1)
    M = odd_factor(xn[:, 2] * 0.4, 0.4)
    skip, shift, scale = fit_output_transform(xn, y, "linear", M)
    for j in range(5):
        A = np.concatenate([xn, np.ones((n, 1))], 1) * M[:, j:j + 1]
        coef, *_ = np.linalg.lstsq(A, y[:, j], rcond=None)
        np.testing.assert_allclose(skip[j], coef[:-1], rtol=0, atol=1e-10)
        assert abs(shift[j] - coef[-1]) < 1e-10
        assert abs(scale[j] / (y[:, j] - A @ coef).std() - 1) < 1e-10
    skip0, shift0, scale0 = fit_output_transform(xn, y, "none")
    assert not skip0.any()
    np.testing.assert_allclose(shift0, y.mean(0), rtol=1e-12)
    np.testing.assert_allclose(scale0, y.std(0), rtol=1e-10)


def test_config_rejects_unknown_keys(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text("seed = 3\n[regressor]\nmax_stepz = 10\n")
    with pytest.raises(NeuralLensError, match="max_stepz"):
        load_config(str(p))
    p.write_text("seed = 3\n[classifier]\ntarget = 'sdf'\n")
    with pytest.raises(NeuralLensError, match="target = 'sdf'; choose one of \\['margin', 'label'\\]"):
        load_config(str(p))
    p.write_text("seed = 3\n[regressor]\nschedule = 'paper'\n")
    c = load_config(str(p))
    assert c.regressor.lr == 1e-4 and c.regressor.decay == 0.95 and c.regressor.batch == 8192
    # an override of one key of a table keeps the recipe's other keys of that table
    p.write_text("[regressor]\nmax_steps = 7\n[forward_classifier]\nhidden = 3\nmax_minutes = 2.0\n")
    c = load_config(str(p), overrides={"regressor": {"patience": 5}, "forward_classifier": {"max_minutes": 6.0}})
    assert (c.regressor.max_steps, c.regressor.patience) == (7, 5)
    assert c.forward_classifier["hidden"] == 3 and c.forward_classifier["max_minutes"] == 6.0
    # the forward defaults (flare goals) stay under a recipe's [forward_*] keys
    assert c.forward_classifier["target"] == "margin" and c.net("classifier", "forward").goal_misclassification < 0.005
    # the camera map's stop head gets a longer finish than a ghost's (used only through an iris): a forward
    # head takes at most 0.5 min of it unless [forward_stop] names its own, and none when [stop] has none
    c = load_config(None)
    assert c.net("stop", "backward").lm_minutes == 1.5 and c.net("stop", "forward").lm_minutes == 0.5
    # every head is the regressor's recipe (3×16, 4 000 Adam steps, the finish); the camera head's finish is longer
    fs, bs = c.net("stop", "forward"), c.net("stop", "backward")
    assert (fs.hidden, fs.width, fs.max_steps) == (3, 16, 4000) and (bs.hidden, bs.width, bs.max_steps) == (3, 16, 4000)
    p.write_text("[forward_stop]\nmax_minutes = 1.0\n")
    assert load_config(str(p)).net("stop", "forward").lm_minutes == 0.5
    p.write_text("[stop]\nlm_minutes = 0.0\n")
    assert load_config(str(p)).net("stop", "forward").lm_minutes == 0.0
    p.write_text("[forward_stop]\nlm_minutes = 2.0\n")
    assert load_config(str(p)).net("stop", "forward").lm_minutes == 2.0


def test_close_focus_auto_is_300_mm_unless_the_lens_is_long_and_then_a_quarter_magnification():
    """``close_focus_mm = "auto"`` (the default): the 300 mm every bundled model was trained with for the lenses up
    to 60 mm, and for a long lens — the 250 mm telephoto cannot focus 300 mm away at all — the distance where the
    paraxial magnification is 1:4, checked against the lens's own paraxial image of an object there.  A distance
    the lens cannot focus names the setting and what auto would give; bad values are refused."""
    from mi_neurallens.optics.glass import LAMBDA_D
    assert load_config(None).close_focus_mm == "auto"
    for name in ("dgauss-50mm", "wide-22mm", "ood-59mm", "canon-ef-24mm-f1.4l", "canon-rf-24mm-f1.4l-vcm"):
        lens = Lens.load(name)
        assert plan.close_focus_mm(lens, "auto") == 300.0
        assert plan.sensor_distance_range(lens, "auto") == plan.sensor_distance_range(lens, 300.0)
    tele = Lens.load("telephoto-250mm")
    d = plan.close_focus_mm(tele, "auto")
    assert 1000.0 < d < 2000.0
    assert abs(tele.paraxial(LAMBDA_D).magnification(d)) == pytest.approx(0.25, rel=1e-9)
    s0, s1 = plan.sensor_distance_range(tele, "auto")
    assert s1 == pytest.approx(tele.paraxial(LAMBDA_D).sensor_distance_for(d)) and s1 > s0
    with pytest.raises(NeuralLensError, match=r"close_focus_mm = 300: cannot focus.*\"auto\", which would be 1331 mm"):
        plan.sensor_distance_range(tele, 300.0)
    assert plan.sensor_distance_range(tele, 0.0)[1] == pytest.approx(tele.paraxial(LAMBDA_D).bfl)
    for bad in ("near", -5.0):
        with pytest.raises(NeuralLensError, match="close_focus_mm"):
            plan.close_focus_mm(tele, bad)


def test_budget_is_the_sum_of_the_networks_wall_budgets():
    """What `train` announces before a lens: the most minutes its networks may take — Adam's budget and the
    finish's per size tried, per map — checked against the defaults' numbers written out."""
    from mi_neurallens.training.config import budget_minutes, minutes_text
    from mi_neurallens.training.whole_lens import _budget_text, _spent_text
    c = load_config(None)
    fwd = budget_minutes(c, "forward", 33)
    # forward: regressor 1 + 1, classifier 0.4 + 0.35, stop head 0.5 + 0.5 minutes per map
    assert fwd == pytest.approx({"regressor": 66.0, "classifier": 24.75, "stop": 33.0})
    bwd = budget_minutes(c, "backward", 1)
    assert bwd == pytest.approx({"regressor": 5.5, "classifier": 2.0, "stop": 2.0})
    sized = load_config(None, overrides={"forward_regressor": {"sizes": ["3x16", "5x32"]}, "stop": {"max_minutes": 0.0}})
    got = budget_minutes(sized, "forward", 2)
    assert got["regressor"] == pytest.approx(2 * 2 * (1.0 + 1.0)) and got["stop"] == 0.0     # each size finished
    wide = load_config(None, overrides={"regressor": {"widen_width": 24, "widen_minutes": 3.0}})
    assert budget_minutes(wide, "backward", 1)["regressor"] == pytest.approx(5.5 + 3.0)    # the widened finish too
    assert minutes_text(12.34) == "12.3 min" and minutes_text(170.0) == "2 h 50 min"
    line = _budget_text(c, {"backward": [object()], "forward": [object()] * 33})
    assert "34 map(s) to train (1 backward, 33 forward)" in line and "at most 2 h 13 min" in line
    done = _spent_text("forward", {"maps": 2, "seconds": 90.0, "phases": {"regressor": 60.0, "classifier": 30.0}}, 4000)
    assert done.startswith("2 forward map(s) trained in 1.5 min (regressors 1.0 min, classifiers 0.5 min")
    assert done.endswith("1 h 07 min since the start")


def test_bundled_recipes_load():
    """Every bundled recipe parses (tomllib refuses a repeated key) and names a bundled lens."""
    import os
    from mi_neurallens.optics.formats import bundled_lenses
    from mi_neurallens.resources import bundled_library
    recipes = sorted(str(p) for p in (bundled_library().path / "recipes").glob("*.toml"))
    assert len(recipes) >= 3
    for r in recipes:
        c = load_config(r)
        assert os.path.basename(r)[:-len(".toml")] in bundled_lenses()
        # the 22 mm and 59 mm lenses' ghost stop heads shipped as 2×32 Adam heads, the Canons' were trained
        # (again) as the defaults' 3×16 heads with the finish: each recipe reproduces what its model holds
        fs = c.net("stop", "forward")
        shipped = (3, 16, 0.5) if "canon-" in r else (2, 32, 0.0)
        assert (fs.hidden, fs.width, fs.lm_minutes) == shipped, r


# ----------------------------------------------------------------------------- a tiny training run
def test_tiny_training_run_learns(tmp_path):
    """Train the backward transmit map of a single thick lens for a few hundred steps: held-out errors
    must fall far below the untrained network's (a broken loss, optimiser or data pipeline fails)."""
    pytest.importorskip("torch")
    from mi_neurallens.neural import NeuralLensModel, load_model
    from mi_neurallens.training.evaluate import evaluate_map
    from mi_neurallens.training.maps import train_map
    lens = thick_lens()
    s0, s1 = plan.sensor_distance_range(lens, 500.0)
    z_front, z_rear = plan.planes(lens, s0)
    dom = plan.backward_domain(lens, 0, z_rear, z_front, np.random.default_rng(0), n=1 << 18)
    small = dict(hidden=3, width=16, batch=1024, pool=40000, refresh_every=200, eval_every=100,
                 max_minutes=1.0, warmup_steps=20, residual="none", patience=100, loss_weights="uniform",
                 lm_minutes=0.0)                 # Adam alone (tests/test_levenberg.py tests the finish)
    cfg = load_config(overrides={"regressor": dict(small, max_steps=400, lr=1e-2),
                                 "classifier": dict(small, hidden=2, width=32, max_steps=600, lr=1e-2,
                                                    target="label"),
                                 "stop": dict(small, hidden=2, width=16, max_steps=200, lr=1e-2, residual="linear"),
                                 "heldout": 10000, "threads": 1})
    tm = train_map(lens, 0, "backward", z_rear, z_front, dom, cfg, str(tmp_path), progress=False, eval_n=10000)
    m = tm.metrics
    # where the wall time went, per phase of the call (what `train` reports after each direction)
    ph = tm.training["phase_seconds"]
    assert set(ph) == {"regressor", "classifier", "stop", "evaluation", "maps"} and ph["maps"] == 1
    assert all(ph[k] > 0 for k in ("regressor", "classifier", "stop", "evaluation"))
    # the untrained start: the same map with the regressor's last layer zeroed (predicts the mean)
    import copy
    tm0 = copy.deepcopy(tm)
    tm0.regressor[-1] = (tm0.regressor[-1][0] * 0, tm0.regressor[-1][1] * 0)
    tm0._fold = None
    m0 = evaluate_map(lens, tm0, n=5000, seed=1, boundary=False)
    assert m["regressor"]["position_um_median"] < 0.1 * m0["regressor"]["position_um_median"]
    assert m["regressor"]["direction_arcsec_median"] < 0.2 * m0["regressor"]["direction_arcsec_median"]
    assert m["regressor"]["position_um_median"] < 300.0
    assert m["classifier"]["misclassification"] < 0.06
    assert m["classifier"]["misclassification"] < 0.3 * min(m["classifier"]["valid_fraction"], 1 - m["classifier"]["valid_fraction"])
    # the default margin target (interval regression of the aperture margin) learns a classifier too
    cfgm = load_config(overrides={"regressor": dict(small, max_steps=400, lr=1e-2),
                                  "classifier": dict(small, hidden=2, width=32, max_steps=400, lr=1e-2,
                                                     target="margin"),
                                  "stop": dict(small, max_minutes=0.0),      # no stop head: none is needed here
                                  "heldout": 10000, "threads": 1})
    tmm = train_map(lens, 0, "backward", z_rear, z_front, dom, cfgm, str(tmp_path / "margin"), progress=False,
                    eval_n=10000)
    mm = tmm.metrics["classifier"]
    # a stop head trains with the map (here a tiny one), unless its time budget is 0
    assert tm.stop_head is not None and tmm.stop_head is None and "stop" not in tmm.metrics
    assert tm.metrics["stop"]["stop_um_median"] < 300.0       # < 5 % of the 7 mm stop radius after 200 steps
    assert tmm.training["classifier"]["target"] == "margin"
    assert mm["misclassification"] < 0.3 * min(mm["valid_fraction"], 1 - mm["valid_fraction"])
    # checkpoints exist and a rerun resumes (finished networks are not retrained)
    tm2 = train_map(lens, 0, "backward", z_rear, z_front, dom, cfg, str(tmp_path), progress=False,
                    evaluate=False)
    np.testing.assert_array_equal(tm2.regressor[0][0], tm.regressor[0][0])
    # and the model file round-trips with its metrics
    model = NeuralLensModel(lens.name, lens.fingerprint(), z_front, z_rear, lens.total_track, (s0, s1))
    model.maps[tm.key] = tm
    model.save(str(tmp_path / "thick.model.safetensors"))
    back = load_model(str(tmp_path / "thick.model.safetensors"), lens)
    assert back.map("transmit", "backward").metrics["regressor"]["n"] == 10000
    # odd_y (the default): y and dy vanish exactly on the mirror plane ωy = 0, as the tracer's do, so
    # the undo of the reflection leaves no seam; the flag survives the file, and Dr.Jit agrees with numpy
    tb = back.map("transmit", "backward")
    assert tm.odd_y and tb.odd_y
    x = dom.u_to_x(np.random.default_rng(5).random((4000, 4)))
    x[:2000, 2] = 0.0
    _, y = tb.eval_reduced_np(x)
    assert np.all(y[:2000, [1, 3]] == 0.0) and np.abs(y[2000:, 1]).max() > 0.1
    import drjit as dr
    F = float_type("float32")
    _, yd = tb.eval_reduced_dr([F(np.ascontiguousarray(x[:, i], np.float32)) for i in range(4)])
    np.testing.assert_allclose(np.stack([v.numpy() for v in yd], 1), y, atol=2e-3, rtol=1e-3)
    # keep = "regressor": only the classifier trains (here a margin one, in another work directory); the
    # regressor, its output transform and its training record come unchanged from the base map
    tk = train_map(lens, 0, "backward", z_rear, z_front, dom, cfgm, str(tmp_path / "keep"), progress=False,
                   eval_n=10000, keep="regressor", base=tb)
    for (W, b), (W0, b0) in zip(tk.regressor, tb.regressor):
        np.testing.assert_array_equal(W, W0)
        np.testing.assert_array_equal(b, b0)
    np.testing.assert_array_equal(tk.skip, tb.skip)
    np.testing.assert_array_equal(tk.out_scale, tb.out_scale)
    assert tk.odd_y == tb.odd_y
    assert tk.training["kept"]["network"] == "regressor"
    assert tk.training["regressor_steps"] == tb.training["regressor_steps"]
    assert tk.training["classifier"]["target"] == "margin" and tb.training["classifier"]["target"] == "label"
    assert not np.array_equal(tk.classifier[0][0], tb.classifier[0][0])
    assert tk.metrics["regressor"]["position_um_median"] == pytest.approx(m["regressor"]["position_um_median"],
                                                                          rel=0.05)
    mk = tk.metrics["classifier"]
    assert mk["misclassification"] < 0.3 * min(mk["valid_fraction"], 1 - mk["valid_fraction"])
    # keep = "classifier" keeps the classifier bit for bit (its calibration offset included)
    tc = train_map(lens, 0, "backward", z_rear, z_front, dom, cfg, str(tmp_path / "keepc"), progress=False,
                   evaluate=False, keep="classifier", base=tk)
    for (W, b), (W0, b0) in zip(tc.classifier, tk.classifier):
        np.testing.assert_array_equal(W, W0)
        np.testing.assert_array_equal(b, b0)
    # keep = "networks": only the stop heads train, together in one stack as in a whole run (here two copies of
    # the map); classifiers, regressors and their metrics come bit for bit from the bases
    from mi_neurallens.training.maps import train_maps
    spec = (0, "backward", z_rear, z_front, dom)
    tbs = train_maps(lens, [spec, spec], cfg, None, progress=False, keep="networks", bases=[tb, tb])
    for t in tbs:
        assert t.stop_head is not None and t.stop_head is not tb.stop_head
        assert t.stop_head.training["stacked_with"] == 2
        for net in ("classifier", "regressor"):
            for (W, b), (W0, b0) in zip(getattr(t, net), getattr(tb, net)):
                np.testing.assert_array_equal(W, W0)
                np.testing.assert_array_equal(b, b0)
        assert t.metrics["regressor"] == tb.metrics["regressor"]
        assert t.metrics["stop"]["stop_um_median"] < 300.0
    with pytest.raises(NeuralLensError, match="stop.max_minutes = 0"):
        train_maps(lens, [spec], cfgm, None, progress=False, keep="networks", bases=[tb])
    # a base map of another path, planes or domain, an unknown network, or no base: clear errors
    with pytest.raises(NeuralLensError, match="not backward.0"):
        train_map(lens, 0, "backward", z_rear, z_front, dom, cfg, None, keep="regressor",
                  base=dataclasses.replace(tb, path_id=3))
    with pytest.raises(NeuralLensError, match="planes"):
        train_map(lens, 0, "backward", z_rear + 1.0, z_front, dom, cfg, None, keep="regressor", base=tb)
    with pytest.raises(NeuralLensError, match="domain"):
        train_map(lens, 0, "backward", z_rear, z_front, planning.Domain(dom.r_max * 2, dom.s_max), cfg, None,
                  keep="regressor", base=tb)
    with pytest.raises(NeuralLensError, match="choose one of"):
        train_map(lens, 0, "backward", z_rear, z_front, dom, cfg, None, keep="weights", base=tb)
    with pytest.raises(NeuralLensError, match="needs the map"):
        train_map(lens, 0, "backward", z_rear, z_front, dom, cfg, None, keep="regressor")


def test_edge_weighted_regressor_loss():
    """``edge_weight`` weights each valid sample by 1 + w·exp(−margin/edge_margin): the rays grazing an
    aperture (margin → 0) weigh 1 + w, the central ones ≈ 1.  Trained with it, the near-edge error (the
    log's ``edge_pos_um_med``) drops relative to the overall one: here from 1.4–1.8× the median to 1.06–1.2×, a
    factor 0.67–0.77 over three stream seeds (the same seed without the weights gives exactly 1)."""
    pytest.importorskip("torch")
    from mi_neurallens.training.config import NetConfig
    from mi_neurallens.training.outputs import edge_weights
    from mi_neurallens.training.regressor import train_regressor
    lens = thick_lens()
    ps = sampling.PathSampler(lens, 0, "backward", 52.0, -1.0, planning.Domain(12.0, 0.4))
    u, x, y, _ = sampling.rejection_sample(ps, 40000, np.random.default_rng(0))
    _, m, _ = ps.margin_u(u)
    w = edge_weights(ps, u, NetConfig(edge_weight=9.0, edge_margin=0.02))
    np.testing.assert_allclose(w, 1.0 + 9.0 * np.exp(-m / 0.02), rtol=1e-6)
    assert w.min() >= 1.0 and w.max() <= 10.0
    assert w[m < 0.005].mean() > 8.0 and w[m > 0.3].max() < 1.0 + 1e-5
    ratio = {}
    for ew in (0.0, 30.0):
        nc = NetConfig(hidden=2, width=16, batch=1024, pool=30000, refresh_every=100, eval_every=100,
                       max_steps=600, max_minutes=1.0, warmup_steps=20, lr=1e-2, patience=100, edge_weight=ew)
        logged = []
        res = train_regressor(data.RegressorStream(ps, seed=1, bounded=False), (x[:5000], y[:5000]), nc,
                              heading=-1, center=x.mean(0), scale_in=x.std(0), seed=0, ckpt=None, threads=1,
                              progress=False, s_max=0.4, log=lambda d, r: logged.append(r))
        assert res["state"]["done"] and logged[-1]["pos_um_med"] < 20.0
        ratio[ew] = logged[-1]["edge_pos_um_med"] / logged[-1]["pos_um_med"]
    assert ratio[0.0] > 1.3 and ratio[30.0] < 0.8 * ratio[0.0]


def test_a_fisheye_camera_map_regresses_its_exit_position_times_dz(tmp_path):
    """``exit_position = "auto"``: a regressor whose exit rays reach beyond 60° off axis (the bundled fisheye-10mm's
    camera map: 76°) regresses the exit position times |dz| (``position_cos``), where a ray leaving nearly parallel to
    the output plane crosses it far away (the Nikon 16 mm fisheye's camera map read 2.4 mm median, 205 m at most, on
    the plane); its transform and logged validation are in that space, and a model map with ``position_cos`` divides
    by its predicted |dz| again, the flag kept by the file.  dgauss-50mm (30°) stays on the plane."""
    pytest.importorskip("torch")
    import dataclasses
    from mi_neurallens.neural.mlp import mlp_np
    from mi_neurallens.neural.model import NeuralLensModel, bundled_model_path, load_model, position_cos
    from mi_neurallens.training.config import NetConfig
    from mi_neurallens.training.evaluate import map_outputs_np, regression_errors
    from mi_neurallens.training.outputs import odd_factor, wants_position_cos
    from mi_neurallens.training.regressor import train_regressor

    def camera_rays(name, n):
        lens = Lens.load(name)
        s0, _ = plan.sensor_distance_range(lens, "auto")
        zf, zr = plan.planes(lens, s0)
        dom = plan.backward_domain(lens, 0, zr, zf, np.random.default_rng(0), n=1 << 17)
        ps = sampling.PathSampler(lens, 0, "backward", zr, zf, dom)
        _, x, y, _ = sampling.rejection_sample(ps, n, np.random.default_rng(1))
        return ps, dom, x, y

    assert not wants_position_cos("auto", camera_rays("dgauss-50mm", 4000)[3])
    ps, dom, x, y = camera_rays("fisheye-10mm", 8000)
    assert wants_position_cos("auto", y) and not wants_position_cos("plane", y) and wants_position_cos("cos", y[:0])
    center, scale = dom.norm_center_scale()
    nc = NetConfig(hidden=2, width=16, batch=1024, pool=30000, refresh_every=100, eval_every=100, max_steps=300,
                   max_minutes=1.0, warmup_steps=20, lr=1e-2, patience=100)
    logged = []
    res = train_regressor(data.RegressorStream(ps, seed=1, bounded=False), (x, y), nc, heading=-1, center=center,
                          scale_in=scale, seed=0, ckpt=None, threads=1, progress=False, s_max=dom.s_max,
                          log=lambda d, r: logged.append(r))
    assert res["position_cos"] and res["state"]["position_cos"]
    xn = (x - center) / scale
    M = odd_factor(x[:, 2], dom.s_max)
    yp = M * (res["out_shift"] + xn @ res["skip"].T) + res["out_scale"] * (M * mlp_np(xn, res["layers"]))
    got = regression_errors(yp, position_cos(y), -1)["position_um_median"]
    np.testing.assert_allclose(got, min(logged, key=lambda r: r["val_mse"])["pos_um_med"], rtol=2e-3)
    # a map with position_cos: its positions are the network's divided by its own |dz|; the file keeps the flag
    m = load_model(bundled_model_path("dgauss-50mm"))
    tm = m.map(0, "backward")
    xs = tm.domain.u_to_x(np.random.default_rng(2).random((500, 4)))
    _, plane = map_outputs_np(tm, xs)
    tc = dataclasses.replace(tm, position_cos=True)
    _, cos = map_outputs_np(tc, xs)
    dz = np.sqrt(1.0 - plane[:, 2] ** 2 - plane[:, 3] ** 2)
    np.testing.assert_allclose(cos[:, :2], plane[:, :2] / dz[:, None], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(cos[:, 2:], plane[:, 2:], rtol=0, atol=0)
    m.maps[tc.key] = tc
    m.save(tmp_path / "position_cos.model.safetensors")
    assert NeuralLensModel.load(str(tmp_path / "position_cos.model.safetensors"), None).map(0, "backward").position_cos


def test_a_regressor_trained_on_its_input_box_is_returned_in_the_maps_normalisation():
    """With ``input_box`` the regressor trains on its valid rays' bounding box (recorded in its state) and comes
    back folded into the normalisation it was given: evaluated there, it reproduces the held-out position error
    its own validation logged at the kept (best) step, and the box is not the normalisation it was given."""
    pytest.importorskip("torch")
    from mi_neurallens.neural.mlp import mlp_np
    from mi_neurallens.training.config import NetConfig
    from mi_neurallens.training.evaluate import regression_errors
    from mi_neurallens.training.outputs import odd_factor
    from mi_neurallens.training.regressor import train_regressor
    lens = thick_lens()
    ps = sampling.PathSampler(lens, 0, "backward", 52.0, -1.0, planning.Domain(12.0, 0.4))
    _, x, y, _ = sampling.rejection_sample(ps, 8000, np.random.default_rng(0))
    center, scale = x.mean(0) + [3.0, 0.1, 0.1, 0.0], 6.0 * x.std(0)     # a domain far wider than the valid rays
    nc = NetConfig(hidden=2, width=16, batch=1024, pool=30000, refresh_every=100, eval_every=100, max_steps=400,
                   max_minutes=1.0, warmup_steps=20, lr=1e-2, patience=100, input_box=True)
    logged = []
    res = train_regressor(data.RegressorStream(ps, seed=1, bounded=False), (x, y), nc, heading=-1, center=center,
                          scale_in=scale, seed=0, ckpt=None, threads=1, progress=False, s_max=0.4,
                          log=lambda d, r: logged.append(r))
    cb, sb = (np.asarray(v) for v in res["state"]["input_box"])
    assert np.abs(sb[:3] / scale[:3]).max() < 0.5 and np.abs(cb - center)[:3].min() > 0.0
    xn = (x - center) / scale
    M = odd_factor(x[:, 2], 0.4)
    yp = M * (res["out_shift"] + xn @ res["skip"].T) + res["out_scale"] * (M * mlp_np(xn, res["layers"]))
    best = min(logged, key=lambda r: r["val_mse"])
    got = regression_errors(yp, y, -1)["position_um_median"]
    assert got < 50.0
    np.testing.assert_allclose(got, best["pos_um_med"], rtol=2e-3)
