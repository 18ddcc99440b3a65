#!/usr/bin/env bash
# The product as a user installs it: build the wheel, install it into a fresh virtual environment (no system
# site packages, no torch) outside the checkout, and use it from a temporary directory — the bundled lenses,
# every bundled model in a small neural_lens render, a small flare, the demo, `lens convert` of a .zmx, and the
# error `train` gives without PyTorch.  .ci/run runs it after the tests; about two minutes on two cores.
#
#   bash scripts/wheel_smoke.sh            (PYTHON=python3.12 to build and test with another interpreter)
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
TMP=$(mktemp -d)
trap 'rm -rf "$TMP"' EXIT

echo "[wheel] building"
rm -rf build   # setuptools packs a stale build/lib too (a module since removed would ship)
$PY -m pip wheel -q --disable-pip-version-check --no-deps -w "$TMP/dist" . >/dev/null
ls -l "$TMP"/dist/*.whl
$PY -m venv "$TMP/venv"
echo "[wheel] installing into a fresh venv"
"$TMP/venv/bin/python" -m pip install -q --disable-pip-version-check "$TMP"/dist/*.whl
mkdir -p "$TMP/run"
cd "$TMP/run"
export PATH="$TMP/venv/bin:$PATH"
unset PYTHONPATH

echo "[wheel] mi-neurallens lens list"
mi-neurallens lens list | tee list.txt
grep -q "^wide-22mm .* yes  bundled" list.txt

echo "[wheel] train without torch says how to get it"
if mi-neurallens train wide-22mm 2> train.err; then echo "train ran without torch?"; exit 1; fi
grep -q "pip install" train.err && cat train.err

echo "[wheel] lens convert of a .zmx"
python - <<'EOF'
lines = ["VERS 140730 73 26155", "MODE SEQ", "NAME smoke singlet", "UNIT MM X W X CM MR CPMM", "ENPD 10",
         "WAVM 1 0.5875618 1", "PWAV 1",
         "SURF 0", "  TYPE STANDARD", "  CURV 0.0", "  DISZ INFINITY",
         "SURF 1", "  STOP", "  TYPE STANDARD", "  CURV 0.0", "  DISZ 5", "  DIAM 6 1 0 0 1 \"\"",
         "SURF 2", "  TYPE STANDARD", "  CURV 0.02", "  DISZ 6", "  GLAS N-BK7 0 0 1.5168 64.17 0 0 0 0 0 0",
         "  DIAM 12 1 0 0 1 \"\"",
         "SURF 3", "  TYPE STANDARD", "  CURV -0.005", "  DISZ 90", "  DIAM 12 1 0 0 1 \"\"",
         "SURF 4", "  TYPE STANDARD", "  CURV 0.0", "  DISZ 0", "  DIAM 10 0 0 0 1 \"\""]
open("singlet.zmx", "w").write("\r\n".join(lines) + "\r\n")
EOF
mi-neurallens lens convert singlet.zmx singlet.json
mi-neurallens lens info singlet.json | head -5

echo "[wheel] every bundled model in a small neural_lens render, and a small flare"
python - <<'EOF'
import os
import numpy as np
import mitsuba as mi
mi.set_variant("llvm_ad_rgb")
import mi_neurallens
from mi_neurallens import resources
assert "site-packages" in mi_neurallens.__file__ and not os.path.exists("mi_neurallens"), mi_neurallens.__file__
models = resources.model_names()
assert len(models) >= 5, models
for name in models:
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "path", "max_depth": 3},
        "sensor": {"type": "neural_lens", "model": name, "focus_distance": 2.0,
                   "film": {"type": "hdrfilm", "width": 32, "height": 24},
                   "sampler": {"type": "independent", "sample_count": 4}},
        "light": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}}})     # a white sky seen through the lens
    img = np.array(mi.render(scene))
    assert np.isfinite(img).all() and img.mean() > 0, name
    print(f"{name}: mean {img.mean():.4f}")
from mi_neurallens.commands.render import load_scene
from mi_neurallens.flare.render import render_flare
scene = load_scene("night_point", lens="wide-22mm", resolution=(48, 32), sensor_type="neural_lens",
                   sets=["model=wide-22mm"])
fr = render_flare(scene, 0, samples=1 << 16)
total = np.asarray(fr.total)
assert np.isfinite(total).all() and total.sum() > 0
print(f"flare: {len(fr.stats)} ghosts, total {total.sum():.4g}")
EOF

echo "[wheel] mi-neurallens demo (small)"
mi-neurallens demo --out demo --spp 4 --reference-spp 16 --resolution 64x48 --no-progress
test -s demo/compare.png && test -s demo/compare.md && test -s demo/wide-22mm-layout.png
echo "[wheel] ok"
