"""The model file: round trip, every bad-file error, and Dr.Jit evaluation == numpy evaluation."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest

from mi_neurallens import Lens, ModelError
from mi_neurallens.neural import NeuralLensModel, NeuralMap, bundled_model_path, load_model
from mi_neurallens.neural.mlp import (STYLE_ENV, mlp_dr, mlp_np, mlp_style, tanh_eigen, tanh_exp2,
                                      tanh_minimax)
from mi_neurallens.trace.api import float_type

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _layers(rng, widths, scale=0.6):
    return [(rng.normal(0, scale, (o, i)), rng.normal(0, 0.2, o)) for i, o in zip(widths[:-1], widths[1:])]


def _map(rng, direction="backward", path_id=0, width=8):
    return NeuralMap(
        path_id=path_id, direction=direction, z_in=40.0 if direction == "backward" else -1.0,
        z_out=-1.0 if direction == "backward" else 40.0,
        domain={"r_max_mm": 10.0, "s_max": 0.6, "lambda_min_nm": 360.0, "lambda_max_nm": 830.0},
        input_center=np.array([5.0, 0.0, 0.3, 595.0]), input_scale=np.array([5.0, 0.6, 0.3, 235.0]),
        classifier=_layers(rng, [4, width, width, 1]), regressor=_layers(rng, [4, width, width, width, 5]),
        skip=rng.normal(0, 0.5, (5, 4)), out_scale=np.array([2.0, 0.5, 0.1, 0.05, 0.01]),
        out_shift=np.array([0.0, 0.0, 0.0, 0.0, 0.9]), training={"note": "random"}, metrics={"x": 1.0})


@pytest.fixture(scope="module")
def lens():
    return Lens.load("wide-22mm")


@pytest.fixture()
def model(lens):
    rng = np.random.default_rng(0)
    m = NeuralLensModel(lens_name=lens.name, fingerprint=lens.fingerprint(), z_front=-1.0, z_rear=40.0,
                        z_last_vertex=lens.total_track, sensor_distance_range=(14.0, 16.0))
    for tm in (_map(rng), _map(rng, "forward", 0), _map(rng, "forward", 2560)):
        m.maps[tm.key] = tm
    m.extra["ghost_ranking"] = [{"path_id": 2560, "energy": 1e-4}]
    return m


def _save(model, tmp_path, name="m.model.safetensors"):
    p = str(tmp_path / name)
    model.save(p)
    return p


def _rays(n, heading, seed=1):
    rng = np.random.default_rng(seed)
    o = np.stack([rng.uniform(-9, 9, n), rng.uniform(-9, 9, n), np.full(n, 45.0 if heading < 0 else -5.0)], 1)
    a, s = rng.uniform(0, 2 * np.pi, n), 0.62 * np.sqrt(rng.random(n))
    d = np.stack([s * np.cos(a), s * np.sin(a), heading * np.sqrt(1 - s * s)], 1)
    return o, d, rng.uniform(380, 800, n)


def test_round_trip(model, lens, tmp_path):
    p = _save(model, tmp_path)
    assert [f for f in os.listdir(tmp_path) if f.startswith(".tmp")] == []
    m2 = load_model(p, lens)
    assert set(m2.maps) == set(model.maps)
    assert m2.fingerprint == lens.fingerprint() and m2.sensor_distance_range == (14.0, 16.0)
    assert m2.extra["ghost_ranking"][0]["path_id"] == 2560 and m2.ghost_ids == [2560]
    for k, a in model.maps.items():
        b = m2.maps[k]
        assert (b.z_in, b.z_out, b.domain, b.training, b.metrics) == (a.z_in, a.z_out, a.domain, a.training, a.metrics)
        o, d, lam = _rays(2000, a.heading)
        ra, rb = a.eval_np(o, d, lam), b.eval_np(o, d, lam)   # b has float32-rounded weights
        np.testing.assert_array_equal(ra.valid | (np.abs(ra.logit) < 1e-4), rb.valid | (np.abs(ra.logit) < 1e-4))
        np.testing.assert_allclose(ra.position, rb.position, atol=1e-4)
    # metadata is plain JSON inside __metadata__
    from safetensors import safe_open
    with safe_open(p, "np") as f:
        meta = f.metadata()
    doc = json.loads(meta["model"])
    assert meta["format_version"] == "1" and doc["lens"]["fingerprint"] == lens.fingerprint()
    assert {m["key"] for m in doc["maps"]} == set(model.maps)



def test_training_histories_keep_four_digits_and_metrics_keep_all(model, lens, tmp_path):
    """The loss curves are a record for people: stored to 4 significant digits and at most HISTORY_POINTS
    validations, so 32 ghosts' histories do not outweigh their networks; the held-out metrics and everything the
    renderer reads stay exact."""
    tm = model.maps["forward.2560"]
    from mi_neurallens.neural.model import HISTORY_POINTS
    tm.training = {"regressor_history": [{"step": 500, "loss": 0.123456789, "pos_um_med": 3.14159265}],
                   "classifier_history": [{"step": 500 * (i + 1), "loss": 1.0 / (i + 1)} for i in range(100)],
                   "lr": 0.0031234567}
    tm.metrics = {"pos_um_med": 3.14159265}
    m2 = load_model(_save(model, tmp_path), lens).maps["forward.2560"]
    assert m2.training["regressor_history"] == [{"step": 500, "loss": 0.1235, "pos_um_med": 3.142}]
    assert m2.training["lr"] == 0.0031234567 and m2.metrics == {"pos_um_med": 3.14159265}
    h = m2.training["classifier_history"]            # a long curve keeps its ends and evenly spaced points
    assert len(h) == HISTORY_POINTS and h[0]["step"] == 500 and h[-1] == {"step": 50000, "loss": 0.01}
    assert np.all(np.diff([e["step"] for e in h]) > 0)


def _rewrite(p, drop=None, reshape=None, meta_edit=None):
    from safetensors.numpy import load_file, save_file
    from safetensors import safe_open
    t = load_file(p)
    with safe_open(p, "np") as f:
        meta = dict(f.metadata())
    if drop:
        del t[drop]
    if reshape:
        t[reshape] = np.zeros((3, 3), np.float32)
    if meta_edit:
        meta_edit(meta)
    save_file(t, p, metadata=meta)


def test_missing_tensor(model, tmp_path):
    p = _save(model, tmp_path)
    _rewrite(p, drop="backward.0.regressor.1.weight")
    with pytest.raises(ModelError, match="missing tensor 'backward.0.regressor.1.weight'"):
        load_model(p)


def test_wrong_shape(model, tmp_path):
    p = _save(model, tmp_path)
    _rewrite(p, reshape="forward.2560.classifier.0.weight")
    with pytest.raises(ModelError, match=r"forward.2560.classifier.0.weight.*shape \(3, 3\), expected \(8, 4\)"):
        load_model(p)


def test_other_lens(model, tmp_path):
    p = _save(model, tmp_path)
    with pytest.raises(ModelError, match="trained for lens 'wide-22mm'.*not for 'ood-59mm'"):
        load_model(p, Lens.load("ood-59mm"))


def test_truncated(model, tmp_path):
    p = _save(model, tmp_path)
    data = open(p, "rb").read()
    for cut in (len(data) - 7, 100, 5):
        q = str(tmp_path / f"cut{cut}.safetensors")
        open(q, "wb").write(data[:cut])
        with pytest.raises(ModelError, match="truncated|too short"):
            load_model(q)


def test_unknown_version_and_not_a_model(model, tmp_path):
    p = _save(model, tmp_path)
    _rewrite(p, meta_edit=lambda m: m.update(format_version="99"))
    with pytest.raises(ModelError, match="unknown model format version '99'"):
        load_model(p)
    q = str(tmp_path / "other.safetensors")
    from safetensors.numpy import save_file
    save_file({"a": np.zeros(3, np.float32)}, q)
    with pytest.raises(ModelError, match="not a mi-neurallens model"):
        load_model(q)
    with pytest.raises(ModelError, match="not found"):
        load_model(str(tmp_path / "nope.safetensors"))
    r = str(tmp_path / "garbage.safetensors")
    open(r, "wb").write(b"\x10\x00\x00\x00\x00\x00\x00\x00{not json at all}")
    with pytest.raises(ModelError):
        load_model(r)


def test_tanh_eigen():
    x = np.linspace(-12, 12, 100001)
    assert np.max(np.abs(tanh_eigen(x) - np.tanh(x))) < 1e-6
    F = float_type("float32")
    y = tanh_eigen(F(x.astype(np.float32))).numpy()
    assert np.max(np.abs(y - np.tanh(x))) < 1e-6


def test_tanh_minimax():
    """The CPU style's tanh in float32 against numpy's: within 1.3e-6 everywhere (its fit's 9.0e-7 plus float32
    rounding), odd, and within ±1 where tanh saturates."""
    x = np.concatenate([np.linspace(-12, 12, 200001), [-1e4, -7.0, 0.0, 7.0, 1e4]]).astype(np.float32)
    F = float_type("float32")
    y = tanh_minimax(F(x)).numpy()
    ref = np.tanh(x.astype(np.float64))
    assert np.max(np.abs(y - ref)) < 1.3e-6
    assert np.max(np.abs(y - ref)) > 5e-7                    # the fit's own error shows: not the exact tanh
    assert np.array_equal(y, -tanh_minimax(F(-x)).numpy())
    assert np.all(np.abs(y) <= 1.0) and y[-1] > 0.999999 and y[-5] < -0.999999
    d = np.diff(tanh_minimax(F(np.linspace(0, 7, 7001).astype(np.float32))).numpy())
    assert d.min() > -1e-6                                   # monotone up to float32 rounding


def test_tanh_exp2():
    """The GPU style's tanh, 1 − 2/(1 + 2^(2x/ln 2)): here with Dr.Jit's software exp2 and a division (on CUDA the
    hardware's approximations, 2 and 1 ulp: measured there by benchmarks/bench_mlp.py), saturating without a
    clamp and odd to rounding."""
    x = np.concatenate([np.linspace(-12, 12, 100001), [-200.0, -90.0, 0.0, 1e-30, 90.0, 200.0]])
    F = float_type("float32")
    y = tanh_exp2(F(x.astype(np.float32))).numpy()
    assert np.all(np.isfinite(y))
    assert np.max(np.abs(y - np.tanh(x.astype(np.float32).astype(np.float64)))) < 5e-7
    assert y[-1] == 1.0 and y[-6] == -1.0


def test_mlp_style_by_backend_and_override(monkeypatch):
    F = float_type("float32")
    like = F(0.0)
    monkeypatch.delenv(STYLE_ENV, raising=False)
    import drjit as dr
    assert mlp_style(like) == ("gpu" if dr.backend_v(like) == dr.JitBackend.CUDA else "cpu")
    monkeypatch.setenv(STYLE_ENV, "gpu")
    assert mlp_style(like) == "gpu"
    monkeypatch.setenv(STYLE_ENV, "auto")
    assert mlp_style(like) in ("cpu", "gpu")
    monkeypatch.setenv(STYLE_ENV, "tpu")
    with pytest.raises(ValueError, match="MI_NEURALLENS_MLP_STYLE"):
        mlp_style(like)


@pytest.mark.parametrize("style", ["cpu", "gpu"])
@pytest.mark.parametrize("activation", ["tanh", "relu"])
def test_mlp_drjit_equals_numpy(activation, style, monkeypatch):
    """Both evaluation styles (4 partial sums and the minimax rational tanh; one chain from the bias and the exp2
    tanh), with literals and with kernel parameters, equal the float64 reference (exact tanh) to float32 precision
    and their tanh's error."""
    from mi_neurallens.neural.mlp import KernelParams
    monkeypatch.setenv(STYLE_ENV, style)
    rng = np.random.default_rng(5)
    layers = _layers(rng, [4, 32, 32, 32, 5], scale=0.4)
    layers[1][0][3, :7] = 0.0                        # zero weights: left out of the literal kernel
    x = rng.uniform(-1, 1, (4096, 4))
    ref = mlp_np(x, layers, activation)
    F = float_type("float32")
    for params in (None, KernelParams()):
        out = mlp_dr([F(x[:, i].astype(np.float32)) for i in range(4)], layers, activation, params)
        got = np.stack([o.numpy() for o in out], 1)
        np.testing.assert_allclose(got, ref, atol=5e-5 * np.abs(ref).max())
    # plain Python floats (Mitsuba's scalar variants): every term kept, not only the biases
    got = np.array(mlp_dr([float(v) for v in x[7]], layers, activation), dtype=np.float64)
    np.testing.assert_allclose(got, ref[7], atol=5e-5 * np.abs(ref).max())


@pytest.mark.parametrize("direction", ["backward", "forward"])
def test_transport_map_eval_dr_equals_numpy(direction):
    """Full lens-space evaluation (reduction, domain test, classifier, regressor, undo) in Dr.Jit
    matches the float64 numpy reference (exact tanh) to float32 precision and the kernel tanh's error: the CPU's
    minimax rational is within 1.2e-6 of tanh, which moves this random map's outputs 5e-6 of their scale and
    1.9e-5 rad at most (Eigen's rational, 2.6e-7: 1.1e-6 and 3.9e-6)."""
    tm = _map(np.random.default_rng(9), direction, 0, width=16)
    o, d, lam = _rays(8192, tm.heading, seed=4)
    ref = tm.eval_np(o, d, lam)
    F = float_type("float32")
    col = lambda a, i: F(np.ascontiguousarray(a[:, i], dtype=np.float32))
    res = tm.eval_dr(tuple(col(o, i) for i in range(3)), tuple(col(d, i) for i in range(3)),
                     F(lam.astype(np.float32)))
    valid, pos, dirn, thr = res.valid, res.position, res.direction, res.throughput
    v = valid.numpy().astype(bool)
    sure = np.abs(ref.logit) > 1e-3            # away from the decision boundary
    assert 0.05 < ref.valid.mean() < 0.95
    np.testing.assert_array_equal(v[sure], ref.valid[sure])
    P = np.stack([c.numpy() for c in pos], 1)
    D = np.stack([c.numpy() for c in dirn], 1)
    scale = np.abs(ref.position[:, :2]).max()
    np.testing.assert_allclose(P[:, :2], ref.position[:, :2], atol=8e-6 * scale + 1e-6)
    np.testing.assert_allclose(P[:, 2], tm.z_out)
    np.testing.assert_allclose(D, ref.direction, atol=3e-5)  # 3e-5 rad = 6″
    np.testing.assert_allclose(thr.numpy(), ref.throughput, atol=2e-6 * np.abs(ref.throughput).max())


def test_bundled_models_load():
    found = 0
    for name in ("wide-22mm", "ood-59mm", "canon-ef-24mm-f1.4l", "dgauss-50mm"):
        p = bundled_model_path(name)
        if not os.path.exists(p):
            continue
        lens = Lens.load(name)
        m = load_model(p, lens)
        tm = m.map("transmit", "backward")
        assert tm.metrics["regressor"]["n"] > 0
        lo, hi = m.sensor_distance_range
        assert lo <= lens.surfaces[-1].thickness <= hi or lo <= lens.bfl() <= hi
        assert os.path.getsize(p) < 2_000_000
        found += 1
    if not found:
        pytest.skip("no bundled model files yet")


def test_bundled_22mm_backward_map_matches_tracer():
    """End to end in lens space: rays from a sensor plane inside the supported range, neural vs exact."""
    p = bundled_model_path("wide-22mm")
    if not os.path.exists(p):
        pytest.skip("no bundled wide-22mm model")
    lens = Lens.load("wide-22mm")
    m = load_model(p, lens)
    tm = m.map("transmit", "backward")
    lo, hi = m.sensor_distance_range
    rng = np.random.default_rng(0)
    n = 60000
    o = np.stack([rng.uniform(-12, 12, n), rng.uniform(-12, 12, n),
                  np.full(n, lens.total_track + 0.5 * (lo + hi))], 1)
    a, s = rng.uniform(0, 2 * np.pi, n), 0.7 * np.sqrt(rng.random(n))
    d = np.stack([s * np.cos(a), s * np.sin(a), -np.sqrt(1 - s * s)], 1)
    ex = lens.trace(o, d, 550.0, direction="backward", z_out=tm.z_out, precision="float64")
    nn = tm.eval_np(o, d, 550.0)
    assert ex.valid.sum() > 1000
    assert (nn.valid == ex.valid).mean() > 0.995
    both = ex.valid & nn.valid
    err_um = np.hypot(*(nn.position[both, :2] - ex.position[both, :2]).T) * 1000
    # the goals for this map (median ≤ 2 µm, p99 ≤ 20 µm; direction ≤ 5″ / 40″), end to end
    assert np.median(err_um) < 2.0 and np.percentile(err_um, 99) < 20.0, (np.median(err_um), np.percentile(err_um, 99))
    cosang = np.clip(np.sum(nn.direction[both] * ex.direction[both], 1), -1.0, 1.0)
    ang = np.degrees(np.arccos(cosang)) * 3600.0
    assert np.median(ang) < 5.0 and np.percentile(ang, 99) < 40.0, (np.median(ang), np.percentile(ang, 99))
    np.testing.assert_allclose(nn.throughput[both], ex.throughput[both], rtol=0.01)


def test_merge_command(tmp_path):
    """``mi-neurallens merge``: copies maps between model files of one lens, keeps the ghost list in
    ranking order, refuses another lens's model."""
    from mi_neurallens.commands import merge as mm
    from mi_neurallens.errors import ModelError
    from mi_neurallens.neural.model import bundled_model_path, load_model
    src = bundled_model_path("wide-22mm")
    dst = load_model(src)
    dst.maps = {k: v for k, v in dst.maps.items() if k == "backward.0"}
    dst_path = str(tmp_path / "dst.model.safetensors")
    dst.save(dst_path)
    assert mm.merge(src, dst_path, ["forward.10240", "forward.2560"]) == ["forward.10240", "forward.2560"]
    out = load_model(dst_path)
    assert sorted(out.maps) == ["backward.0", "forward.10240", "forward.2560"]
    assert out.extra["ghosts_trained"] == [2560, 10240]          # ranking order, not argument order
    with pytest.raises(ModelError, match="no map"):
        mm.merge(src, dst_path, ["forward.7"])
    # the source's training runs join the destination's, marked with what was merged, once
    refined = load_model(src)
    run = {"command": "mi-neurallens train wide-22mm --finish-only maps", "started": "2026-12-03 00:40 UTC"}
    refined.extra["runs"] = [run]
    refined_path = str(tmp_path / "refined.model.safetensors")
    refined.save(refined_path)
    before = len(load_model(dst_path).extra.get("runs", []))
    for _ in range(2):
        mm.merge(refined_path, dst_path, ["backward.0"])
    runs = load_model(dst_path).extra["runs"]
    # ... with the time the source's file records for the run that wrote it (the destination's own is another)
    took = refined.extra["training_time"]["seconds"]
    assert len(runs) == before + 1 and runs[-1] == {**run, "merged_maps": ["backward.0"], "seconds": took}
    from mi_neurallens.commands.evaluate import provenance_text
    assert f"--finish-only maps` — 2026-12-03 00:40 UTC, {took / 60:.1f} min;" in provenance_text(load_model(dst_path))
    assert "merged into this file: backward.0" in provenance_text(load_model(dst_path))
    with pytest.raises(ModelError, match="lens"):
        mm.merge(bundled_model_path("ood-59mm"), dst_path)


def test_a_run_on_a_base_model_keeps_the_base_runs():
    """A finish-only or keep run's file lists the runs of the model it built on, then its own (a rerun of the
    same command updates its entry); the base's own run keeps the time the base's file recorded for it, which the
    new file's ``training_time`` (its own run's) no longer holds."""
    from mi_neurallens.neural.model import bundled_model_path, load_model
    from mi_neurallens.training.whole_lens import record_run
    base = load_model(bundled_model_path("wide-22mm"))
    first = {"command": "mi-neurallens train wide-22mm", "config_digest": "a", "started": "t0"}
    base.extra["runs"] = [first]
    out = load_model(bundled_model_path("wide-22mm"))
    out.extra.pop("runs", None)
    finish = {"command": "mi-neurallens train wide-22mm --finish-only maps", "config_digest": "b", "started": "t1"}
    record_run(out, finish, base)
    record_run(out, {**finish, "started": "t2"}, base)           # resumed
    assert [r["started"] for r in out.extra["runs"]] == ["t0", "t1"] and out.extra["runs"][-1]["resumed"]
    took = base.extra["training_time"]["seconds"]
    assert out.extra["runs"][0]["seconds"] == took and "seconds" not in out.extra["runs"][1]
    from mi_neurallens.commands.evaluate import provenance_text
    assert f"`mi-neurallens train wide-22mm` — t0, {took / 60:.1f} min;" in provenance_text(out)


def test_merge_keeps_the_stop_head_of_the_map_a_retrained_one_replaces(tmp_path):
    """A map retrained without a stop head (classifier and regressor only) keeps the stop head of the map
    it replaces, which maps the same rays; not when its domain differs."""
    import dataclasses
    from mi_neurallens.neural.model import bundled_model_path, load_model
    from mi_neurallens.training.merge import merge_models
    dst = load_model(bundled_model_path("wide-22mm"))
    old = dst.maps["forward.2560"]
    assert old.stop_head is not None and "stop" in old.metrics
    src = load_model(bundled_model_path("wide-22mm"))
    src.maps = {"forward.2560": dataclasses.replace(old, stop_head=None, metrics={"regressor": {"x": 1}},
                                                     training={"config_digest": "new"})}
    merge_models(src, dst)
    got = dst.maps["forward.2560"]
    assert got.stop_head is old.stop_head and got.metrics["stop"] == old.metrics["stop"]
    assert got.metrics["regressor"] == {"x": 1} and got.training["stop_head_kept_from"] == old.training.get("config_digest")
    path = str(tmp_path / "m.model.safetensors")
    dst.save(path)
    assert load_model(path).maps["forward.2560"].stop_head is not None
    # another domain: the old head would map other rays, so it is not kept
    dst = load_model(bundled_model_path("wide-22mm"))
    other = dataclasses.replace(old, stop_head=None, domain={**old.domain.to_dict(), "r_max_mm": old.domain.r_max * 1.1})
    src.maps = {"forward.2560": other}
    merge_models(src, dst)
    assert dst.maps["forward.2560"].stop_head is None


def test_shared_kernel_parameters_one_kernel_per_architecture():
    """mlp = "shared": every number of a map is a kernel input (weights in packed buffers on LLVM), so two
    maps of one architecture (other weights, planes, normalisation and domain) run the same kernel, and
    their results are the fused ones to float32 rounding and the two tanh approximations' difference."""
    import dataclasses
    import drjit as dr
    from mi_neurallens.jit import from_numpy
    rng = np.random.default_rng(11)
    maps = [_map(rng, "forward", 2560, width=8) for _ in range(2)]
    maps[1] = dataclasses.replace(maps[1], z_in=-1.5, input_center=np.array([4.0, 0.1, 0.2, 600.0]),
                                  domain={"r_max_mm": 9.0, "s_max": 0.55, "lambda_min_nm": 380.0,
                                          "lambda_max_nm": 800.0})
    maps[1].regressor[1][0][3, 4] = 0.0           # a zero weight (literals skip it) must not change the kernel
    o, d, lam = _rays(4096, +1, seed=3)
    F = float_type("float32")
    args = (tuple(from_numpy(F, o[:, i]) for i in range(3)), tuple(from_numpy(F, d[:, i]) for i in range(3)),
            from_numpy(F, lam))
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        kernels, outs = {}, {}
        for mode in ("fused", "shared"):
            for k, tm in enumerate(maps):
                tm = dataclasses.replace(tm, mlp=mode)
                dr.kernel_history()
                res = tm.eval_dr(*args)
                dr.eval(res.valid, res.position, res.direction, res.throughput)
                kernels[mode, k] = [h["hash"] for h in dr.kernel_history() if h["type"] == dr.KernelType.JIT]
                outs[mode, k] = np.stack([res.valid.numpy()] + [c.numpy() for c in res.position + res.direction]
                                         + [res.throughput.numpy()], 1)
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    # the same kernels for both maps: the map's, and on LLVM the one that packs a network's weights into its
    # cooperative-vector buffer (run once per network, the same source for every network)
    assert kernels["shared", 0] == kernels["shared", 1] and len(set(kernels["shared", 0])) <= 2
    assert kernels["fused", 0] != kernels["fused", 1]
    assert len(maps[0].params_pool) > 0 and maps[0].params_pool is not maps[1].params_pool
    # packed weights where they are the same fp32 arithmetic: LLVM float32; float64 keeps the scalars
    from mi_neurallens.neural.model import packed_networks
    F64 = float_type("float64")
    assert packed_networks("shared", F(0.0)) and not packed_networks("shared", F64(0.0))
    assert packed_networks("coopvec", F(0.0)) and not packed_networks("fused", F(0.0))
    for k in range(2):
        v = outs["fused", k][:, 0].astype(bool)
        assert 0.05 < v.mean() < 0.95
        np.testing.assert_array_equal(outs["shared", k][:, 0], outs["fused", k][:, 0])
        # float32 rounding, and tanh: the fused kernel's minimax rational (1.2e-6) against Dr.Jit's on the packed ones
        np.testing.assert_allclose(outs["shared", k][v], outs["fused", k][v], rtol=1e-5, atol=4e-5)


def test_held_out_evaluation_compiles_one_kernel_per_architecture_with_the_literals_numbers():
    """The held-out evaluation and the calibration (training.evaluate.map_outputs_np) run a map's float64 core
    with its numbers as kernel parameters: two maps of one architecture share one kernel, and the logit and
    outputs are the literal kernel's to float64 rounding."""
    import dataclasses
    import drjit as dr
    from mi_neurallens.training.evaluate import map_outputs_np
    rng = np.random.default_rng(5)
    maps = [_map(rng, "forward", 2560, width=8) for _ in range(2)]
    x = maps[0].domain.u_to_x(rng.random((3000, 4)))
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        hashes = []
        for tm in maps:
            dr.kernel_history()
            logit, y = map_outputs_np(tm, x)
            hashes.append({h["hash"] for h in dr.kernel_history() if h["type"] == dr.KernelType.JIT})
            ref_logit, ref_y = tm.eval_reduced_np(x)           # the map's own mode: literals
            np.testing.assert_allclose(logit, ref_logit, rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(y, ref_y, rtol=1e-12, atol=1e-12)
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert hashes[0] == hashes[1] and len(hashes[0]) >= 1
    assert maps[0].mlp == "fused"                               # the map itself is left as it was
