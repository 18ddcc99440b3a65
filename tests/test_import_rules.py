"""The house rules of docs/architecture.md hold: which folder may import which (import-linter's contracts in
pyproject.toml, over every import, lazy ones inside functions too), and importing the package or rendering
through it loads no torch and sets no Mitsuba variant."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_import_contracts_of_the_architecture_hold(capsys):
    cli = pytest.importorskip("importlinter.cli")
    rc = cli.lint_imports(config_filename=os.path.join(ROOT, "pyproject.toml"), no_cache=True)
    assert rc == 0, capsys.readouterr().out[-4000:]


def test_a_broken_contract_is_reported(tmp_path, capsys):
    """The check is not vacuous: a contract forbidding an import the package has (sensors use the tracer)
    is reported broken, with the import chain."""
    cli = pytest.importorskip("importlinter.cli")
    cfg = tmp_path / "contracts.toml"
    cfg.write_text('[tool.importlinter]\nroot_package = "mi_neurallens"\n\n'
                   '[[tool.importlinter.contracts]]\nname = "sensors without the tracer"\ntype = "forbidden"\n'
                   'source_modules = ["mi_neurallens.sensors"]\nforbidden_modules = ["mi_neurallens.trace"]\n')
    assert cli.lint_imports(config_filename=str(cfg), no_cache=True) != 0
    assert "mi_neurallens.sensors" in capsys.readouterr().out


_NO_TORCH = r"""
import sys
import mi_neurallens
assert "torch" not in sys.modules, "import mi_neurallens imported torch"
import mitsuba as mi
assert mi.variant() is None, f"import mi_neurallens set the variant {mi.variant()}"
mi.set_variant("llvm_ad_rgb")
mi_neurallens.register()
sensor = {"type": "neural_lens", "model": "wide-22mm", "film": {"type": "hdrfilm", "width": 8, "height": 6},
          "sampler": {"type": "independent", "sample_count": 1}}
scene = mi.load_dict({"type": "scene", "integrator": {"type": "lens_flare", "nested": {"type": "direct"},
                                                      "flare_samples": 1024, "ghosts": "2560"},
                      "sensor": sensor, "light": {"type": "point", "position": [0, 0, 5],
                                                  "intensity": {"type": "rgb", "value": 1.0}}})
mi.render(scene)
bad = sorted(m for m in sys.modules if m == "torch" or m.startswith(("torch.", "mi_neurallens.training")))
assert not bad, bad
print("ok")
"""


def test_importing_and_rendering_load_no_torch_and_no_training():
    """``import mi_neurallens`` and a neural_lens render with learned flare ghosts import neither torch nor
    ``mi_neurallens.training`` (the trainer and its recipes), in a fresh interpreter."""
    env = {k: v for k, v in os.environ.items() if k != "MI_NEURALLENS_VARIANT"}
    r = subprocess.run([sys.executable, "-c", _NO_TORCH], capture_output=True, text=True, env=env, cwd=ROOT,
                       timeout=600)
    assert r.returncode == 0 and r.stdout.strip().endswith("ok"), r.stderr[-3000:]
