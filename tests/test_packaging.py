"""What a user gets from ``pip install``: the data the package carries and where it is found
(mi_neurallens/resources.py), and the clear errors of a machine that lacks something (an LLVM too old for
Dr.Jit, no torch for training).  The built wheel itself is exercised by scripts/wheel_smoke.sh in CI."""
from __future__ import annotations

import fnmatch
import os
import shutil
import subprocess
import sys

import pytest

from mi_neurallens import resources
from mi_neurallens.errors import NeuralLensError

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _pyproject() -> dict:
    try:
        import tomllib
    except ImportError:                 # Python 3.10
        import tomli as tomllib
    with open(os.path.join(ROOT, "pyproject.toml"), "rb") as f:
        return tomllib.load(f)


def _package_data_globs() -> list[str]:
    return _pyproject()["tool"]["setuptools"]["package-data"]["mi_neurallens"]


def test_every_import_of_the_tests_is_declared():
    """Each module the tests import is the standard library's, the package's, a test helper, or comes from a
    distribution pyproject.toml names itself (its dependencies or an extra), not one that merely happens to be
    installed with another.  (docs/ scripts the tests run count as the tests' own.)"""
    import ast
    import importlib.metadata as md
    import re
    norm = lambda n: re.sub(r"[-_.]+", "-", n).lower()            # noqa: E731
    proj = _pyproject()["project"]
    reqs = list(proj["dependencies"]) + [r for extra in proj["optional-dependencies"].values() for r in extra]
    declared = {norm(re.split(r"[<>=!~;\[ ]", r, maxsplit=1)[0]) for r in reqs}
    dists = md.packages_distributions()
    tests = os.path.join(ROOT, "tests")
    local = {f[:-3] for d in (tests, os.path.join(ROOT, "docs")) for f in os.listdir(d) if f.endswith(".py")}
    local.add("mi_neurallens")
    undeclared = set()
    for f in sorted(os.listdir(tests)):
        if not f.endswith(".py"):
            continue
        tree = ast.parse(open(os.path.join(tests, f), encoding="utf-8").read())
        for node in ast.walk(tree):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                     [node.module] if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module else [])
            for name in names:
                top = name.split(".")[0]
                if top in sys.stdlib_module_names or top in local or norm(top) in declared:
                    continue
                if not any(norm(d) in declared for d in dists.get(top, [])):
                    undeclared.add(f"{f}: {top} ({', '.join(dists.get(top, ['not installed']))})")
    assert not undeclared, sorted(undeclared)


def test_every_data_file_is_declared_package_data():
    """Every file under mi_neurallens/data (lenses, models and their evaluation records, recipes, scenes) matches
    a package-data pattern of pyproject.toml, so the wheel carries it; and the bundled data is all there."""
    globs = _package_data_globs()
    pkg = os.path.join(ROOT, "mi_neurallens")
    missing = []
    for dirpath, _, files in os.walk(os.path.join(pkg, "data")):
        for f in files:
            rel = os.path.relpath(os.path.join(dirpath, f), pkg).replace(os.sep, "/")
            if f.endswith(".work") or "/__pycache__/" in rel:
                continue
            if not any(fnmatch.fnmatch(rel, g) and rel.count("/") == g.count("/") for g in globs):
                missing.append(rel)
    assert not missing, f"not in [tool.setuptools.package-data]: {missing}"
    assert set(resources.model_names()) >= {"wide-22mm", "ood-59mm", "canon-ef-24mm-f1.4l", "dgauss-50mm",
                                             "canon-rf-24mm-f1.4l-vcm"}
    for name in resources.model_names():
        m = resources.find_model(name)
        assert m.with_name(m.name + ".eval.json").is_file(), name
    assert {"wide-22mm", "ood-59mm", "canon-ef-24mm-f1.4l"} <= {p.stem for p in
                                                                (resources.bundled_library().path / "recipes").glob("*.toml")}
    assert {"still_life", "night_point", "night", "chart", "bokeh"} <= set(resources.scene_names())


def test_a_user_library_comes_first_for_lenses_models_and_recipes(tmp_path, monkeypatch):
    """$MI_NEURALLENS_LENSES is searched before the bundled library, separately for each kind: a user's model of
    a bundled lens wins without a copy of its prescription, and `lens list` says where each lens comes from."""
    lib = tmp_path / "mylenses"
    (lib / "models").mkdir(parents=True)
    (lib / "recipes").mkdir()
    bundled_model = resources.find_model("wide-22mm")
    shutil.copy(bundled_model, lib / "models" / bundled_model.name)
    (lib / "recipes" / "wide-22mm.toml").write_text("seed = 7\n")
    shutil.copy(resources.find_lens("ood-59mm"), lib / "my-59mm.json")
    monkeypatch.setenv(resources.LENSES_ENV, str(lib))
    assert resources.find_model("wide-22mm") == lib / "models" / bundled_model.name
    assert resources.find_recipe("wide-22mm") == lib / "recipes" / "wide-22mm.toml"
    assert resources.find_lens("wide-22mm") == resources.bundled_library().lens("wide-22mm")
    assert resources.lens_origin("my-59mm").origin == "$" + resources.LENSES_ENV
    assert resources.find_model("my-59mm") is None


def test_lens_list_shows_origin_and_model(tmp_path, monkeypatch, capsys):
    lib = tmp_path / "lib"
    lib.mkdir()
    shutil.copy(resources.find_lens("ood-59mm"), lib / "my-59mm.json")
    monkeypatch.setenv(resources.LENSES_ENV, str(lib))
    from mi_neurallens.cli import main
    import json
    assert main(["lens", "list", "--json"]) == 0
    rows = {r["name"]: r for r in json.loads(capsys.readouterr().out)}
    assert rows["my-59mm"]["origin"] == "$MI_NEURALLENS_LENSES" and rows["my-59mm"]["model"] is None
    assert rows["wide-22mm"]["origin"] == "bundled" and rows["wide-22mm"]["model"].endswith(
        "wide-22mm.model.safetensors")
    assert main(["lens", "list"]) == 0
    text = capsys.readouterr().out
    assert "my-59mm" in text and str(lib) in text


def test_scenes_by_name_or_path(tmp_path):
    assert resources.scene_path("still_life") == resources.scenes_dir() / "still_life.xml"
    assert resources.scene_path("scenes/night_point.xml") == resources.scenes_dir() / "night_point.xml"
    mine = tmp_path / "still_life.xml"
    mine.write_text("<scene version='3.0.0'/>")
    assert resources.scene_path(str(mine)) == mine                  # an existing file wins over the name
    with pytest.raises(NeuralLensError, match="still_life"):
        resources.scene_path("nope")


def test_train_writes_beside_the_user_library_or_here():
    from mi_neurallens.commands.train import default_out_dir
    assert default_out_dir("wide-22mm", "wide-22mm") == "."           # never into the installed package
    assert default_out_dir("my/lens.json", "lens") == "."


def test_train_without_torch_says_how_to_get_it(monkeypatch, capsys):
    import importlib.util
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "torch" else real(name, *a))
    from mi_neurallens.cli import main
    assert main(["train", "wide-22mm"]) == 1
    err = capsys.readouterr().err
    assert "PyTorch" in err and "download.pytorch.org/whl/cpu" in err and "mi-neurallens[train]" in err


def test_an_llvm_too_old_for_drjit_is_a_clear_error(monkeypatch):
    import drjit as dr
    from mi_neurallens.jit import check_llvm
    check_llvm()                                                       # this machine's LLVM is fine
    monkeypatch.setattr(dr.detail, "llvm_version", lambda: (15, 0, 6))
    with pytest.raises(NeuralLensError, match=r"LLVM 15\.0\.6.*libllvm19.*DRJIT_LIBLLVM_PATH"):
        check_llvm()
    monkeypatch.setattr(dr.detail, "llvm_version", lambda: (-1, -1, -1))   # none found: Dr.Jit says so itself
    check_llvm()


LLVM15 = "/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1"


@pytest.mark.skipif(not os.path.exists(LLVM15), reason="no LLVM 15 on this machine to try")
def test_llvm15_stops_with_the_message_instead_of_aborting():
    """With Dr.Jit pointed at LLVM 15 (which aborts the process inside its first kernel), loading the plugins and
    the CLI end with the message and exit status 1, not SIGABRT."""
    env = {**os.environ, "DRJIT_LIBLLVM_PATH": LLVM15}
    r = subprocess.run([sys.executable, "-m", "mi_neurallens", "lens", "plot", "wide-22mm", "-o", os.devnull],
                       capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 1 and "libllvm19" in r.stderr, (r.returncode, r.stderr[-2000:])
    code = "import mitsuba as mi; mi.set_variant('llvm_ad_rgb'); import mi_neurallens; mi_neurallens.register()"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 1 and "LLVM 15" in r.stderr, (r.returncode, r.stderr[-2000:])


def test_reports_on_a_bundled_model_stay_out_of_the_package(tmp_path):
    """``evaluate`` writes its report beside a model file, except beside one inside the installed package, whose
    shipped evaluation record it must not overwrite: that report goes into the current folder."""
    from mi_neurallens.commands.evaluate import _beside
    assert _beside(str(resources.find_model("wide-22mm"))) == "wide-22mm.model.safetensors"
    mine = str(tmp_path / "my.model.safetensors")
    assert _beside(mine) == mine
