"""Frozen flare kernels (``dr.freeze``): replays give the images tracing gives, learned maps of one
architecture share one recording, and what cannot be frozen runs traced."""
import dataclasses

import numpy as np
import pytest

import mitsuba as mi
import drjit as dr

from mi_neurallens.flare.render import FlareRenderer
from ghosts_only import FlareOptions
from mi_neurallens.neural.model import NeuralMap, bundled_model_path, load_model

from mi_neurallens.render_utils import default_variant
from test_flare import make_scene, point


@pytest.fixture(autouse=True)
def _rgb_variant():
    """Frozen kernels are for RGB variants (a spectral one runs traced): set the default variant, whatever a test
    file run before this one on the same xdist worker left set (its plugins registered), and put it back after."""
    import mi_neurallens as nl
    before = mi.variant()
    if before != default_variant():
        mi.set_variant(default_variant())
        nl.register()
    yield
    if mi.variant() != before:
        mi.set_variant(before)
        nl.register()


def _renderers(scene, model, ids, mode="neural"):
    kw = dict(mode=mode, model=model if mode == "neural" else None, ghosts=ids, samples=1 << 14)
    return (FlareRenderer(scene, 0, FlareOptions(freeze=False, **kw)),
            FlareRenderer(scene, 0, FlareOptions(freeze=True, **kw)))


def _same(a, b):
    """Equal images up to the order of the splats' atomic additions (≈ 1e-7 of the peak between two traced
    renders on two threads); a replay with stale inputs differs by whole ghosts."""
    return a.max() > 0 and float(np.abs(a - b).max()) <= 1e-5 * float(a.max())


def _mixed_ghosts(m, per_arch=2):
    """Up to ``per_arch`` ghosts of each network architecture of model ``m``."""
    by = {}
    for pid in m.ghost_ids:
        by.setdefault(dataclasses.replace(m.map(pid, "forward"), mlp="shared").kernel_signature(), []).append(pid)
    return [p for v in by.values() for p in v[:per_arch]]


def test_frozen_learned_flare_equals_the_traced_one():
    """The same images over renders with other seeds and sample counts (other kernel widths) and after the
    light moved (the emitter is a kernel input); one recording per architecture, not per ghost."""
    m = load_model(bundled_model_path("wide-22mm"))
    ids = _mixed_ghosts(m)
    scene = make_scene(point((0.3, 0.2, 5.0), 100.0), w=64, h=48)
    traced, frozen = _renderers(scene, m, ids)
    assert frozen.learned_mlp() == "shared"
    sigs = {frozen.evaluator(p).freeze_key(mi.Float)[0] for p in ids}
    assert 1 < len(sigs) < len(ids)
    for seed, n in ((0, 1 << 14), (1, 3 << 13), (2, 1 << 14)):
        a, b = traced.render(seed=seed, samples=n).total, frozen.render(seed=seed, samples=n).total
        assert _same(a, b), f"seed {seed}: frozen and traced flares differ"
    assert frozen.kernels.frozen["pilot"].n_recordings == len(sigs) and not frozen.kernels.unfrozen
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("position"))
    params[key] = mi.ScalarPoint3f(-0.4, 0.1, 5.0)
    params.update()
    a, b = traced.render(seed=3).total, frozen.render(seed=3).total
    assert _same(a, b), "a moved light replayed the old one"


def test_frozen_exact_flare_equals_the_traced_one():
    scene = make_scene(point((0.3, 0.2, 4.0), 100.0), w=64, h=48)
    traced, frozen = _renderers(scene, None, [2560, 4608], mode="exact")
    counts = []
    for seed in range(7):           # other sample counts: other kernel widths, the same recordings
        n = (1 << 14) + 4096 * (seed % 2)
        a, b = traced.render(seed=seed, samples=n).total, frozen.render(seed=seed, samples=n).total
        assert _same(a, b)
        counts.append(frozen.kernels.frozen["splat"].n_recordings if "splat" in frozen.kernels.frozen else 0)
    assert not frozen.kernels.unfrozen          # the tracer's configuration numbers handed in: frozen, not traced
    # one recording per ghost, then replays; within a whole test run Dr.Jit records each once more at a render
    # that depends on what ran before on the worker (seen after the 2nd, the 3rd and the 7th): at most two
    # recordings per ghost in 7 renders, so at least 10 of the 14 kernel launches were replays
    assert 2 <= counts[-1] <= 4 and counts == sorted(counts), counts


def test_a_kernel_that_cannot_be_frozen_runs_traced(monkeypatch):
    """A learned map that withholds one of its kernel parameters from the frozen function's inputs: Dr.Jit
    refuses the recording (a variable it was not given), and the renderer traces that kernel instead —
    same image, the reason recorded."""
    m = load_model(bundled_model_path("wide-22mm"))
    ids = m.ghost_ids[:2]
    scene = make_scene(point((0.3, 0.2, 5.0), 100.0), w=64, h=48)
    traced, frozen = _renderers(scene, m, ids)
    inputs = NeuralMap.kernel_inputs
    monkeypatch.setattr(NeuralMap, "kernel_inputs", lambda self, t: inputs(self, t)[1:])
    for seed in range(2):           # a signature is recorded at its second use
        a, b = traced.render(seed=seed).total, frozen.render(seed=seed).total
        assert _same(a, b)
    assert frozen.kernels.unfrozen
    assert all("not specified as an input" in why for why in frozen.kernels.unfrozen.values())


def test_lens_sensors_keep_their_python_data_out_of_drjit_traversal():
    """A frozen function that takes the scene walks every Python plugin's attributes on each call: the lens
    sensors' set-up and neural model (thousands of numpy layers) are kept out of that walk."""
    scene = mi.load_dict({"type": "scene", "sensor": {"type": "neural_lens", "lens": "wide-22mm",
                                                      "film": {"type": "hdrfilm", "width": 32, "height": 24}}})
    sensor = scene.sensors()[0]
    seen = []
    dr.detail.traverse_py_cb_ro(sensor, lambda *a: seen.append(a))
    assert seen == []
    assert sensor.model.lens_name == "wide-22mm" and sensor.setup.lens.name == "wide-22mm"
    assert not any(isinstance(v, type(sensor.model)) for v in vars(sensor).values())


def test_lens_flare_integrator_replays_its_kernels_across_renders():
    """``lens_flare`` keeps its renderer while the sensor is unchanged: later ``mi.render`` calls replay the
    recorded kernels and give the flare of a renderer that traces everything; the camera's pose is read at
    each render.  (The first move of the camera records once more: its pose was a literal until then, and
    Dr.Jit makes a changed literal an input; later moves replay.)"""
    scene = make_scene(point((0.3, 0.2, 4.0), 100.0),
                       integrator={"type": "lens_flare", "flare_samples": 1 << 14, "ghosts": "2560 4608",
                                   "diffraction": False})
    integ = scene.integrator()
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("to_world"))
    images, recordings, renderers = [], [], []
    for step in range(3):
        if step:
            params[key] = mi.Transform4f().translate([0.05, 0.0, 0.0]) @ params[key]
            params.update()
        images.append(np.array(mi.render(scene, seed=1)))
        renderers.append(integ._cached[1])
        recordings.append({k: f.n_recordings for k, f in renderers[-1].kernels.frozen.items()})
    assert renderers[1] is renderers[0] and renderers[2] is renderers[0], "the renderer was not kept"
    assert recordings[2] == recordings[1], "a moved camera recorded the kernels again"
    ref = FlareRenderer(scene, 0, FlareOptions(mode="auto", ghosts=[2560, 4608], samples=1 << 14,
                                               freeze=False)).render(seed=1).total
    assert _same(ref, images[2]) and not _same(images[1], images[2])


@pytest.mark.parametrize("lens, ghost, a, b", [
    ("wide-22mm", 2560, dict(focus_distance=2.0), dict(focus_distance=0.6, fstop=4.0)),
    ("canon-ef-24-70mm-f2.8l", 48, dict(focal_length=30.0), dict(focal_length=52.0))])
def test_another_configuration_compiles_no_new_flare_kernel(lens, ghost, a, b):
    """The numbers a zoom, focus or f-number change moves (the tracer's vertex positions, the sensor and input
    planes, the stop's radius) are kernel inputs of the flare, not literals: a renderer of the lens in another
    configuration runs the kernels of the first (Dr.Jit's cache by source), and draws another flare."""
    images, hashes = [], []
    for sensor in (a, b):
        scene = make_scene(point((0.3, 0.2, 4.0), 100.0), lens=lens, w=48, h=32, **sensor)
        r = FlareRenderer(scene, 0, FlareOptions(mode="exact", ghosts=[ghost], samples=1 << 14, freeze=False))
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            dr.kernel_history()                                   # cleared
            images.append(r.render(seed=1).total)
            hashes.append({h["hash"] for h in dr.kernel_history() if h["type"] == dr.KernelType.JIT})
    assert hashes[0] and hashes[1] <= hashes[0], len(hashes[1] - hashes[0])
    assert images[0].max() > 0 and images[1].max() > 0
    assert float(np.abs(images[0] - images[1]).max()) > 0.05 * float(images[0].max())
