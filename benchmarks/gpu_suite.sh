#!/usr/bin/env bash
# Everything a session with a lent GPU should measure, in few calls (issues 17 and 18).
#
#   bash scripts/gpu_carry.sh                  # here, once: .whl/ = drjit + a trimmed mitsuba for Python 3.12
#   bash benchmarks/gpu_suite.sh STAGE [STAGE…]   # there (repository root), with .whl carried
#
# With the device tool: run(command="bash benchmarks/gpu_suite.sh tests bench", carry=[".whl"],
# timeout_s=600), then the same with "train" and with "ghosts"; results.tar.gz comes back under files_at.
#
# Stages (each fits one 10-minute call; run `tests bench` in one call, `train` in another):
#   setup   install .whl/*.whl into /tmp/site (pip --no-index), print the GPU and the Mitsuba variants
#   tests   the sensor, flare and aperture tests under cuda_ad_rgb ($MI_NEURALLENS_VARIANT)
#   bench   fused literals vs cooperative vectors (bench_mlp.py) and render time thinlens / realistic_lens /
#           neural_lens (bench_render.py) on the three paper lenses and the 27-surface RF 24 mm; the flare
#           benchmark (bench_flare.py: samples/s and equal-time MAPE, exact vs neural) on wide-22mm
#   train   a whole new lens with the defaults on the GPU: dgauss-50mm, transmit maps and the ghosts of the
#           default selection (issue 17: <= 10 min), then its held-out evaluation
#   ghosts  every ghost of the default selection for $GHOST_LENSES (default: the three paper lenses; one
#           lens per call if they do not fit), recipe as in training/<lens>.toml; each model comes back in
#           results.tar.gz, to be merged into the bundled one with training/merge_maps.py
#
# Results go to $OUT (the device tool's folder; ./gpu-results otherwise) as one results.tar.gz plus the
# logs, so they come back within the tool's 8-file limit.  Every stage also runs on a CPU:
# GPU_SUITE_VARIANT=llvm_ad_rgb GPU_SUITE_QUICK=1 (small sizes, a few training steps) is how it is tested.
set -uo pipefail
cd "$(dirname "$0")/.."
ROOT=$(pwd)
OUT="${OUT:-$ROOT/gpu-results}"
RES="$OUT/results"
mkdir -p "$RES"
export PYTHONUNBUFFERED=1
export MI_NEURALLENS_VARIANT="${GPU_SUITE_VARIANT:-cuda_ad_rgb}"
export PYTHONPATH="$ROOT${PYTHONPATH:+:$PYTHONPATH}"
PY=python3
PAPER_LENSES="wide-22mm ood-59mm canon-ef-24mm-f1.4l canon-rf-24mm-f1.4l-vcm"
if [ -n "${GPU_SUITE_QUICK:-}" ]; then
    PAPER_LENSES="wide-22mm"; RAYS=18; FILM=160x120; SPP=16; FLARE="--ghosts 1 --samples 65536 --ref-samples 262144"
    TRAIN="--paths backward-transmit --set regressor.max_steps=200 --set classifier.max_steps=200 --set stop.max_steps=200"
    GHOST_LENSES="${GHOST_LENSES:-wide-22mm}"
    GHOST_ARGS="--set max_ghosts=1 --set forward_regressor.max_steps=200 --set forward_classifier.max_steps=200 --set forward_stop.max_steps=200"
    EVAL_N=2000
else
    RAYS=24; FILM=1280x960; SPP=64; FLARE="--ghosts 8 --samples $((1 << 24)) --ref-samples $((1 << 27))"
    TRAIN="--paths transmit,ghosts"; EVAL_N=100000
fi
status=0

stage_setup() {
    if ls .whl/*.whl >/dev/null 2>&1; then
        $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
            || return 1
        export PYTHONPATH="/tmp/site:$PYTHONPATH"
    fi
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>/dev/null | tee "$RES/gpu.txt"
    $PY - <<'EOF' 2>&1 | tee "$RES/setup.txt"
import os, platform, sys
import drjit as dr, mitsuba as mi
v = os.environ["MI_NEURALLENS_VARIANT"]
print("python", sys.version.split()[0], platform.platform())
print("mitsuba", mi.__version__, "from", os.path.dirname(mi.__file__), "drjit", dr.__version__)
mi.set_variant(v)
x = mi.Float(1.0) + 1.0
print("variant", v, "ok:", float(x[0]) == 2.0)
try:
    import torch
    print("torch", torch.__version__, "cuda:", torch.cuda.is_available(),
          torch.cuda.get_device_name(0) if torch.cuda.is_available() else "")
except ImportError:
    print("torch: not installed")
EOF
}

stage_tests() {
    $PY -m pytest -q -ra -p no:cacheprovider tests/test_sensor_realistic.py tests/test_sensor_neural.py \
        tests/test_flare.py tests/test_aperture.py 2>&1 | tee "$RES/tests.log"
    return "${PIPESTATUS[0]}"
}

stage_bench() {
    local rc=0
    for lens in $PAPER_LENSES; do
        $PY benchmarks/bench_mlp.py --lens "$lens" --rays $RAYS --out "$RES/mlp_$lens.json" 2>&1 | tee -a "$RES/bench.log" || rc=1
        $PY benchmarks/bench_render.py --lens "$lens" --res $FILM --spp $SPP --repeats 3 \
            --out "$RES/render_$lens.json" 2>&1 | tee -a "$RES/bench.log" || rc=1
    done
    $PY benchmarks/bench_flare.py --lens wide-22mm $FLARE --out "$RES/flare_wide-22mm.json" 2>&1 | tee -a "$RES/bench.log" || rc=1
    return $rc
}

stage_train() {
    local t0=$SECONDS rc=0
    $PY -m mi_neurallens train dgauss-50mm $TRAIN --out "$RES/train" --no-progress \
        2>&1 | tee "$RES/train.log" || rc=1
    echo "wall: $((SECONDS - t0)) s for dgauss-50mm ($TRAIN) with data on $MI_NEURALLENS_VARIANT" | tee -a "$RES/train.log"
    $PY -m mi_neurallens evaluate "$RES/train/dgauss-50mm.model.safetensors" -n $EVAL_N --seed 4242 \
        2>&1 | tee -a "$RES/train.log" || rc=1
    rm -rf "$RES/train/"*.work
    return $rc
}

stage_ghosts() {
    local rc=0 t0
    for lens in ${GHOST_LENSES:-wide-22mm ood-59mm canon-ef-24mm-f1.4l}; do
        t0=$SECONDS
        $PY -m mi_neurallens train "$lens" --paths ghosts ${GHOST_ARGS:-} --out "$RES/ghosts" --no-progress \
            2>&1 | tee "$RES/ghosts_$lens.log" || rc=1
        echo "wall: $((SECONDS - t0)) s for the ghosts of $lens" | tee -a "$RES/ghosts_$lens.log"
        rm -rf "$RES/ghosts/"*.work
    done
    return $rc
}

[ $# -gt 0 ] || set -- setup tests bench
case " $* " in *" setup "*) ;; *) set -- setup "$@" ;; esac   # every call installs the wheels first
for stage in "$@"; do
    echo "=== $stage ($(date -u +%H:%M:%S))"
    t=$SECONDS
    if "stage_$stage"; then echo "=== $stage ok, $((SECONDS - t)) s"; else echo "=== $stage FAILED, $((SECONDS - t)) s"; status=1; fi
done
tar -czf "$OUT/results.tar.gz" -C "$OUT" results && echo "results: $OUT/results.tar.gz"
exit $status
