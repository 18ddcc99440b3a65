"""``mi-neurallens render``: scene loading with overrides, passes, EXR + PNG output, errors."""
from __future__ import annotations

import os

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")

from mi_neurallens.cli import main  # noqa: E402
from mi_neurallens.render_utils import apply_sensor_overrides, default_variant, tonemap  # noqa: E402
from mi_neurallens.neural.model import bundled_model_path  # noqa: E402
from mi_neurallens.resources import scenes_dir  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENES = str(scenes_dir())


def read_exr(path):
    return np.array(mi.Bitmap(path), dtype=np.float32)


@pytest.mark.parametrize("name", ["chart", "bokeh", "still_life"])
def test_bundled_scenes_render(tmp_path, name, capsys):
    out = tmp_path / f"{name}.exr"
    rc = main(["render", os.path.join(SCENES, f"{name}.xml"), "-o", str(out), "--spp", "4",
               "--resolution", "40x30", "--no-progress"])
    assert rc == 0
    img = read_exr(str(out))
    assert img.shape[:2] == (30, 40) and np.isfinite(img).all() and img.max() > 0.01
    png = tmp_path / f"{name}.png"
    assert png.exists()
    from PIL import Image
    assert Image.open(png).size == (40, 30)
    assert "render time" in capsys.readouterr().out
    assert not [p for p in os.listdir(tmp_path) if ".tmp" in p]     # nothing half-written left


def test_overrides_reach_the_sensor(tmp_path):
    """--lens / --set change the sensor: stopping the chart down to f/16 without Fresnel loss makes
    the (uniformly lit, exposure-normalised) chart brighter than wide open with Fresnel loss."""
    a, b = tmp_path / "a.exr", tmp_path / "b.exr"
    common = [os.path.join(SCENES, "chart.xml"), "--spp", "16", "--resolution", "24x18", "--no-progress"]
    assert main(["render", *common, "-o", str(a), "--lens", "dgauss-50mm", "--set", "fstop=16",
                 "--set", "fresnel=false", "--passes", "2"]) == 0
    assert main(["render", *common, "-o", str(b), "--lens", "dgauss-50mm"]) == 0
    ia, ib = read_exr(str(a)), read_exr(str(b))
    assert ia.mean() > 1.3 * ib.mean()
    scene = __import__("mi_neurallens.commands.render", fromlist=["load_scene"]).load_scene(
        os.path.join(SCENES, "chart.xml"), variant=default_variant(), lens="dgauss-50mm", sets=["fstop=16"])
    s = str(scene.sensors()[0])
    assert "dgauss-50mm" in s and "f/16" in s


def test_xml_parameter_and_film_set(tmp_path):
    out = tmp_path / "c.exr"
    assert main(["render", os.path.join(SCENES, "chart.xml"), "-o", str(out), "-D", "spp=4",
                 "--set", "film.width=20", "--set", "film.height=10", "--no-progress"]) == 0
    assert read_exr(str(out)).shape[:2] == (10, 20)


def test_bad_input_gives_clear_errors(tmp_path, capsys):
    chart = os.path.join(SCENES, "chart.xml")
    out = str(tmp_path / "x.exr")
    assert main(["render", chart, "-o", out, "--set", "fstop=1.0", "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert "fstop" in err and "wider than" in err
    assert main(["render", chart, "-o", out, "--set", "bogus=1", "--no-progress"]) == 1
    assert "bogus" in capsys.readouterr().err
    assert main(["render", chart, "-o", out, "--resolution", "12by5"]) == 1
    assert "WxH" in capsys.readouterr().err
    assert main(["render", str(tmp_path / "missing.xml"), "-o", out]) == 1
    assert "not found" in capsys.readouterr().err
    assert not os.path.exists(out)


def test_apply_sensor_overrides_types():
    xml = '<scene version="3.0.0"><sensor type="realistic_lens"><float name="fstop" value="4"/></sensor></scene>'
    t = apply_sensor_overrides(xml, sets=["fstop=8", "fresnel=false", "film.width=64"], lens="x.json",
                               spp=16)
    assert '<float name="fstop" value="8"' in t and 'value="4"' not in t
    assert '<boolean name="fresnel" value="false"' in t
    assert '<string name="lens" value="x.json"' in t
    assert '<integer name="width" value="64"' in t and '<integer name="sample_count" value="16"' in t


def test_tonemap_is_srgb():
    t = tonemap(np.array([[[0.0, 0.0031308, 1.0], [0.5, 2.0, -1.0]]]))
    assert t[0, 0].tolist() == [0, 10, 255] and t[0, 1].tolist() == [188, 255, 0]


def test_spectral_variant(tmp_path):
    out = tmp_path / "s.exr"
    assert main(["render", os.path.join(SCENES, "still_life.xml"), "-o", str(out), "--spp", "4",
                 "--resolution", "24x18", "--variant", "llvm_ad_spectral", "--lens", "canon-ef-24mm-f1.4l",
                 "-D", "focus=2", "--no-progress"]) == 0
    img = read_exr(str(out))
    assert np.isfinite(img).all() and img.mean() > 0.02
    assert main(["render", os.path.join(SCENES, "chart.xml"), "-o", str(out), "--variant", "nope"]) == 1


def test_focus_overrides_replace_each_other():
    """Setting sensor_distance on a scene that gives focus_distance (or the reverse) replaces it:
    the two are exclusive properties of the lens sensors."""
    from mi_neurallens.render_utils import apply_sensor_overrides
    xml = ('<scene version="3.0.0"><sensor type="realistic_lens">'
           '<float name="focus_distance" value="1.5"/></sensor></scene>')
    out = apply_sensor_overrides(xml, sets=["sensor_distance=15"])
    assert 'name="sensor_distance"' in out and "focus_distance" not in out
    back = apply_sensor_overrides(out, sets=["focus_distance=2"])
    assert 'name="focus_distance"' in back and "sensor_distance" not in back


def test_variant_env_sets_the_default_of_commands_benchmarks_and_tests(monkeypatch):
    """$MI_NEURALLENS_VARIANT (how benchmarks/gpu_suite.sh runs everything on cuda_ad_rgb) is the default
    --variant of the rendering commands, and its spectral sibling follows it."""
    from mi_neurallens.cli import build_parser
    from mi_neurallens.errors import NeuralLensError
    monkeypatch.delenv("MI_NEURALLENS_VARIANT", raising=False)
    assert (default_variant(), default_variant("spectral")) == ("llvm_ad_rgb", "llvm_ad_spectral")
    monkeypatch.setenv("MI_NEURALLENS_VARIANT", "cuda_ad_rgb")
    assert (default_variant(), default_variant("spectral")) == ("cuda_ad_rgb", "cuda_ad_spectral")
    for cmd in (["render", "s.xml"], ["compare", "s.xml"], ["flare", "s.xml"]):
        assert build_parser().parse_args(cmd).variant == "cuda_ad_rgb", cmd
    with pytest.raises(NeuralLensError):
        default_variant("polarized")


def test_flare_neural_on_a_realistic_lens_scene_takes_the_lens_bundled_model(tmp_path, capsys):
    """``flare --mode neural`` on a ``realistic_lens`` scene without ``--model`` uses the bundled model of
    the scene's lens when there is one (the learned ghosts, not an error asking for a model); a lens whose
    bundled model lacks the ghost gets an error that says how to train it."""
    import json
    if not os.path.exists(bundled_model_path("wide-22mm")):
        pytest.skip("no bundled wide-22mm model")
    scene = os.path.join(SCENES, "night_point.xml")
    js = tmp_path / "flare.json"
    rc = main(["flare", scene, "--lens", "wide-22mm", "--mode", "neural", "--ghost", "2560", "--samples", "65536",
               "--resolution", "48x32", "-o", str(tmp_path / "f.png"), "--json", str(js)])
    assert rc == 0
    rows = json.loads(js.read_text())["neural"]["ghosts"]
    ghosts = [g for g in rows if g["path_id"]]         # path 0: the light's own image, which diffraction spreads
    assert ghosts and all(g["evaluator"] == "neural" and g["path_id"] == 2560 for g in ghosts)
    assert [g["path_id"] for g in rows if not g["path_id"]] == [0]
    assert "wide-22mm.model.safetensors" in capsys.readouterr().err
    rc = main(["flare", scene, "--lens", "canon-rf-24mm-f1.4l-vcm", "--mode", "neural", "--ghost", "2560",
               "--samples", "65536", "--resolution", "48x32", "-o", str(tmp_path / "g.png")])
    err = capsys.readouterr().err
    assert rc != 0 and "no forward map for path 2560" in err and "mi-neurallens train canon-rf-24mm-f1.4l-vcm" in err


def test_render_benchmark_times_both_mlp_styles_and_each_frames_kernels(tmp_path):
    """``benchmarks/bench_render.py`` as ``make bench`` and benchmarks/gpu_suite.sh run it, here at a tiny size:
    it times neural_lens also in the other evaluation style (rows neural_lens{gpu}) with each frame's kernels (the
    separate ray kernel one kernel more than inline).  The GPU suite's script parses."""
    import json
    import subprocess
    import sys
    assert subprocess.run(["bash", "-n", os.path.join(ROOT, "benchmarks", "gpu_suite.sh")]).returncode == 0
    out = tmp_path / "render.json"
    subprocess.run([sys.executable, os.path.join(ROOT, "benchmarks", "bench_render.py"), "--res", "32x24", "--spp",
                    "2", "--repeats", "1", "--ray-kernels", "inline,separate", "--mlp-styles", "gpu",
                    "--kernel-history", "--out", str(out)], check=True, stdout=subprocess.DEVNULL)
    rows = json.loads(out.read_text())["results"]
    assert {"neural_lens{gpu}", "neural_lens{gpu}[separate]", "realistic_lens[separate]"} <= set(rows)
    for name in ("realistic_lens", "neural_lens", "neural_lens{gpu}"):
        inline, sep = rows[name]["kernels"], rows[f"{name}[separate]"]["kernels"]
        assert len(sep) == len(inline) + 1 and all(k["execution_ms"] >= 0 for k in sep)
    # the two styles trace different kernels (the integrator's, inline, holds the network)
    assert rows["neural_lens"]["kernels"][0]["operations"] != rows["neural_lens{gpu}"]["kernels"][0]["operations"]
