#!/usr/bin/env bash
# What a session with a lent GPU measures, in few calls: the maintained benchmarks and the GPU tests.
#
#   bash scripts/gpu_carry.sh                  # here, once: .whl/ = drjit + a trimmed mitsuba for Python 3.12
#   bash benchmarks/gpu_suite.sh STAGE [STAGE…]   # there (repository root), with .whl carried
#
# With the device tool: run(command="SUITE_DEADLINE=570 bash benchmarks/gpu_suite.sh bench flare tests equal",
# carry=[".whl"], timeout_s=600); results.tar.gz and suite.log come back under files_at.
#
# Stages (in the order given; `setup` always runs first):
#   setup   install .whl/*.whl into /tmp/site (pip --no-index), print the GPU and the Mitsuba variants
#   bench   mlp, then render
#   mlp     the learned maps' speed alone (bench_mlp.py on $PAPER_LENSES: both evaluation styles, cooperative vectors,
#           the tracer; each neural path's outputs against the CPU style's)
#   render  render time thinlens / realistic_lens / neural_lens (bench_render.py) on $PAPER_LENSES (overridable:
#           PAPER_LENSES="canon-ef-24mm-f1.4l"), each lens sensor with its camera rays inline in the integrator's
#           kernel and in a kernel of their own (ray_kernel), neural_lens also in the other backend's evaluation
#           style (neural/mlp.py MLP_STYLES), each frame's kernels timed (Dr.Jit's kernel history)
#   equal   equal render time, neural vs exact (equal_time.py), on every bundled lens with a model
#   flare   the 22 mm lens's flare benchmark (bench_flare.py: samples/s and equal-time MAPE, exact vs neural)
#   coatings  what a coating and the starburst cost a flare on this backend (bench_flare.py --coatings on the night
#           scene and on one point light, --starburst; ood-59mm, 2^24 samples a light: issue 57's cost goals, which
#           an exact per-ray stack misses on the 2-core CPU)
#   tests   the sensor, flare and aperture tests under cuda_ad_rgb ($MI_NEURALLENS_VARIANT)
#   train   a whole new lens with the defaults on the GPU: dgauss-50mm, transmit maps and the ghosts of the
#           default selection, then its held-out evaluation
#   costs   every bundled model's ghost maps timed against tracing them on this backend (evaluate --flare-cost
#           --write on copies, $RES/models): lens_flare's auto_max_cost then decides on the GPU too; copy each
#           model's metrics["flare_cost"]["cuda"] into the bundled one (the llvm records stay)
#   ghosts  every ghost of the default selection for $GHOST_LENSES (default: the three paper lenses; one
#           lens per call if they do not fit), with each lens's bundled recipe; each model comes back in
#           results.tar.gz, to be merged into the bundled one with `mi-neurallens merge`.  A zoom lens's ghosts
#           (GHOST_LENSES=canon-ef-24-70mm-f2.8l) are ranked over its configurations and each verified at three
#           zooms, the flare goals of issue 55.  That set needs more than one call on an H200 (docs/neural_lens.md):
#           a call cut short brings its checkpoints back (results/ghosts/*.work), and GHOST_RESUME=that folder, carried
#           with .whl, resumes them in the next
#   zoom    the zoom lens's one map at ten configurations training never drew (bench_zoom.py on the bundled
#           canon-ef-24-70mm-f2.8l: map accuracy, render MAPE ratio, and the render-time ratio neural ÷ realistic
#           on this backend; the CPU's figures are in docs/performance.md)
#
# Time: SUITE_DEADLINE=S (seconds from the start) makes every step stop by then (each Python step runs under
# `timeout` with what is left, and a step left with < 20 s is skipped), and results.tar.gz is rewritten after
# every stage, so a call cut short by the device tool still brings back what finished.  The device tool
# brings back at most 8 files: everything lands in results.tar.gz and suite.log.
#
# Results go to $OUT (the device tool's folder; ./gpu-results otherwise) as one results.tar.gz plus the
# logs, so they come back within the tool's 8-file limit.  Every stage also runs on a CPU:
# GPU_SUITE_VARIANT=llvm_ad_rgb GPU_SUITE_QUICK=1 (small sizes, a few training steps) is how it is tested.
set -uo pipefail
cd "$(dirname "$0")/.."
ROOT=$(pwd)
OUT="${OUT:-$ROOT/gpu-results}"
RES="$(mktemp -d)/results"          # outside $OUT: the device tool brings back at most 8 files from there
mkdir -p "$RES" "$OUT"
exec > >(tee -a "$OUT/suite.log") 2>&1
export PYTHONUNBUFFERED=1
export MI_NEURALLENS_VARIANT="${GPU_SUITE_VARIANT:-cuda_ad_rgb}"
export PYTHONPATH="$ROOT${PYTHONPATH:+:$PYTHONPATH}"
for d in /usr/local/nvidia/lib64 /usr/local/nvidia/lib; do      # the driver's OptiX, for Mitsuba's cuda variants
    [ -d "$d" ] && export LD_LIBRARY_PATH="$d${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
done
PY=python3
DEADLINE="${SUITE_DEADLINE:-}"
PAPER_LENSES="${PAPER_LENSES:-wide-22mm ood-59mm canon-ef-24mm-f1.4l canon-rf-24mm-f1.4l-vcm}"   # bench, render
ALL_LENSES="wide-22mm,ood-59mm,canon-ef-24mm-f1.4l,dgauss-50mm,canon-rf-24mm-f1.4l-vcm"
if [ -n "${GPU_SUITE_QUICK:-}" ]; then
    PAPER_LENSES="wide-22mm"; ALL_LENSES="wide-22mm"; RAYS=18; FILM=160x120; SPP=16
    FLARE="--ghosts 1 --samples 65536 --ref-samples 262144"
    EQUAL="--res 64x48 --spp 4,16 --reference-spp 64 --repeats 1"
    TRAIN="--paths backward-transmit --set regressor.max_steps=200 --set classifier.max_steps=200 --set stop.max_steps=200 --set regressor.lm_iterations=5 --set classifier.lm_iterations=5 --set stop.lm_iterations=5"
    GHOST_LENSES="${GHOST_LENSES:-wide-22mm}"
    GHOST_ARGS="--set max_ghosts=1 --set forward_regressor.max_steps=200 --set forward_classifier.max_steps=200 --set forward_stop.max_steps=200 --set forward_regressor.lm_iterations=5 --set forward_classifier.lm_iterations=5 --set forward_stop.lm_iterations=5"
    COAT="--ghosts 1 --samples 65536"
    ZOOM="--focal 35 --focus inf --rays 20000 --res 32x24 --spp 4 --reference-spp 16 --repeats 1"
    EVAL_N=2000; COST=14; COST_LENSES="${COST_LENSES:-wide-22mm}"
else
    RAYS=24; FILM=1280x960; SPP=64; FLARE="--ghosts 8 --samples $((1 << 24)) --ref-samples $((1 << 27))"
    EQUAL="--res 640x480 --spp 4,16,64 --reference-spp 1024 --repeats 2"
    COAT="--ghosts 4 --samples $((1 << 24))"
    ZOOM="--repeats 5"
    TRAIN="--paths transmit,ghosts"; EVAL_N=100000
    COST=22; COST_LENSES="${COST_LENSES:-$(echo $ALL_LENSES | tr , ' ')}"
fi
case "$MI_NEURALLENS_VARIANT" in cuda*) OTHER_STYLE=cpu ;; *) OTHER_STYLE=gpu ;; esac   # the learned maps' other style
status=0

left() {   # seconds left before SUITE_DEADLINE (a large number without one)
    if [ -n "$DEADLINE" ]; then echo $((DEADLINE - SECONDS)); else echo 100000; fi
}

py() {     # py BOX_SECONDS script args…: Python under `timeout`, within the box and the deadline
    local box=$1 l rc; shift
    l=$(left)
    [ "$l" -lt "$box" ] && box=$l
    if [ "$box" -lt 20 ]; then echo "skipped (deadline): $*"; return 1; fi
    timeout -k 5 "$box" $PY "$@"
    rc=$?
    { [ $rc -eq 124 ] || [ $rc -eq 137 ]; } && echo "stopped after ${box} s (timeout): $*"
    return $rc
}

stamp() {  # prefix each line with the seconds since the suite started (where a long training spends its time)
    local l
    while IFS= read -r l; do printf '%5d  %s\n' "$SECONDS" "$l"; done
}

stage_setup() {
    if ls .whl/*.whl >/dev/null 2>&1; then
        $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
            || return 1
        export PYTHONPATH="/tmp/site:$PYTHONPATH"
    fi
    nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.sm --format=csv 2>/dev/null | tee "$RES/gpu.txt"
    ldconfig -p 2>/dev/null | grep -i optix | head -3
    $PY - <<'EOF' 2>&1 | tee "$RES/setup.txt"
import os, platform, sys
import drjit as dr, mitsuba as mi
v = os.environ["MI_NEURALLENS_VARIANT"]
print("python", sys.version.split()[0], platform.platform())
print("mitsuba", mi.__version__, "from", os.path.dirname(mi.__file__), "drjit", dr.__version__)
mi.set_variant(v)
x = mi.Float(1.0) + 1.0
print("variant", v, "ok:", float(x[0]) == 2.0)
scene = mi.load_dict({"type": "scene", "s": {"type": "sphere"}})      # OptiX (cuda) or Embree (llvm)
print("scene ok:", scene.ray_intersect(mi.Ray3f([0, 0, -3], [0, 0, 1])).is_valid())
from mi_neurallens.trace.api import float_type     # the training data's and numpy faces' backend: LLVM when present
print("Dr.Jit backends: llvm", dr.has_backend(dr.JitBackend.LLVM), "cuda", dr.has_backend(dr.JitBackend.CUDA),
      "-> training data on", float_type("float32").__module__)
try:
    import torch
    print("torch", torch.__version__, "cuda:", torch.cuda.is_available(),
          torch.cuda.get_device_name(0) if torch.cuda.is_available() else "")
except ImportError:
    print("torch: not installed")
EOF
    return "${PIPESTATUS[0]}"
}

stage_bench() {
    local rc=0
    stage_mlp || rc=1
    stage_render || rc=1
    return $rc
}

stage_mlp() {      # the learned maps alone, both evaluation styles and cooperative vectors, against the tracer
    local rc=0
    for lens in $PAPER_LENSES; do
        py 60 benchmarks/bench_mlp.py --lens "$lens" --rays $RAYS --out "$RES/mlp_$lens.json" || rc=1
    done
    return $rc
}

stage_render() {   # bench's render times alone (a call with little time left): PAPER_LENSES="…" picks the lenses
    local rc=0
    for lens in $PAPER_LENSES; do
        py 120 benchmarks/bench_render.py --lens "$lens" --res $FILM --spp $SPP --repeats 3 --ray-kernels inline,separate \
            --mlp-styles $OTHER_STYLE --kernel-history --out "$RES/render_$lens.json" || rc=1
    done
    return $rc
}

stage_equal() {
    py 150 benchmarks/equal_time.py --lenses $ALL_LENSES $EQUAL --out "$RES/equal_time.json"
}

stage_flare() {
    py 90 benchmarks/bench_flare.py --lens wide-22mm $FLARE --out "$RES/flare_wide-22mm.json"
}

stage_coatings() {
    local rc=0
    py 150 benchmarks/bench_flare.py --lens ood-59mm $COAT --coatings none,quarter_wave,broadband --scene night \
        --out "$RES/coatings_night_ood-59mm.json" || rc=1
    py 90 benchmarks/bench_flare.py --lens ood-59mm $COAT --coatings none,quarter_wave,broadband \
        --out "$RES/coatings_point_ood-59mm.json" || rc=1
    py 90 benchmarks/bench_flare.py --lens ood-59mm $COAT --starburst --out "$RES/starburst_ood-59mm.json" || rc=1
    return $rc
}

stage_zoom() {
    py 400 benchmarks/bench_zoom.py $ZOOM --variant "$MI_NEURALLENS_VARIANT" --out "$RES/bench_zoom.json"
}

stage_tests() {
    local box=240 l; l=$(left); [ "$l" -lt "$box" ] && box=$l
    [ "$box" -lt 30 ] && { echo "skipped (deadline): tests"; return 1; }
    # $GPU_SUITE_TESTS: other test ids (what a call cut short did not reach)
    timeout -k 5 "$box" $PY -m pytest -q -ra -p no:cacheprovider ${GPU_SUITE_TESTS:-tests/test_sensor_realistic.py \
        tests/test_sensor_neural.py tests/test_flare.py tests/test_flare_freeze.py tests/test_aperture.py} 2>&1 \
        | tee "$RES/tests.log"
    return "${PIPESTATUS[0]}"
}

stage_train() {
    local t0=$SECONDS rc=0
    py 100000 -m mi_neurallens train dgauss-50mm $TRAIN --out "$RES/train" --no-progress 2>&1 \
        | stamp | tee "$RES/train.log"
    [ "${PIPESTATUS[0]}" -eq 0 ] || rc=1
    echo "wall: $((SECONDS - t0)) s for dgauss-50mm ($TRAIN) (MI_NEURALLENS_VARIANT=$MI_NEURALLENS_VARIANT; the samplers' backend: setup.txt)" | tee -a "$RES/train.log"
    py 300 -m mi_neurallens evaluate "$RES/train/dgauss-50mm.model.safetensors" -n $EVAL_N --seed 4242 \
        2>&1 | tee -a "$RES/train.log" || rc=1
    rm -rf "$RES/train/"*.work
    return $rc
}

stage_costs() {
    local rc=0
    mkdir -p "$RES/models"
    for lens in $COST_LENSES; do
        cp "mi_neurallens/data/lenses/models/$lens.model.safetensors" "$RES/models/" || { rc=1; continue; }
        py 300 -m mi_neurallens evaluate "$RES/models/$lens.model.safetensors" --recorded --flare-cost --write \
            --flare-cost-samples $COST --json "$RES/models/$lens.eval.json" --markdown "$RES/models/$lens.eval.md" \
            2>&1 | tee "$RES/costs_$lens.log"
        [ "${PIPESTATUS[0]}" -eq 0 ] || rc=1
    done
    return $rc
}

stage_ghosts() {   # GHOST_RESUME=DIR: resume from the work folders a cut-short call brought back (results/ghosts/)
    local rc=0 t0 work
    mkdir -p "$RES/ghosts"
    if [ -n "${GHOST_RESUME:-}" ]; then   # a wrong folder stops here, not after a fresh start has spent the call
        local saved=("$GHOST_RESUME"/*.work)
        if [ ! -d "${saved[0]}" ]; then
            echo "GHOST_RESUME=$GHOST_RESUME holds no <lens>.model.safetensors.work folder: give the results/ghosts/" \
                 "folder a cut-short call brought back" | tee "$RES/ghosts_resume.log" >&2
            return 1
        fi
        cp -r "${saved[@]}" "$RES/ghosts/"
    fi
    for lens in ${GHOST_LENSES:-wide-22mm ood-59mm canon-ef-24mm-f1.4l}; do
        t0=$SECONDS
        py 100000 -m mi_neurallens train "$lens" --paths ghosts ${GHOST_ARGS:-} --out "$RES/ghosts" --no-progress \
            2>&1 | tee "$RES/ghosts_$lens.log" || rc=1
        echo "wall: $((SECONDS - t0)) s for the ghosts of $lens" | tee -a "$RES/ghosts_$lens.log"
        work="$RES/ghosts/$lens.model.safetensors.work"
        if [ -f "$RES/ghosts/$lens.model.safetensors" ]; then
            rm -rf "$work"
        elif [ -d "$work" ]; then      # cut short: its checkpoints come back in results.tar.gz, for GHOST_RESUME
            echo "kept $(du -sh "$work" | cut -f1) of checkpoints: carry results/ghosts/ and set GHOST_RESUME to resume" \
                | tee -a "$RES/ghosts_$lens.log"
        fi
    done
    return $rc
}

[ $# -gt 0 ] || set -- setup bench flare tests equal
case " $* " in *" setup "*) ;; *) set -- setup "$@" ;; esac   # every call installs the wheels first (setup named: where named)
for stage in "$@"; do
    echo "=== $stage ($(date -u +%H:%M:%S), ${SECONDS} s in)"
    t=$SECONDS
    if "stage_$stage"; then echo "=== $stage ok, $((SECONDS - t)) s"; else echo "=== $stage FAILED, $((SECONDS - t)) s"; status=1; fi
    tar -czf "$OUT/results.tar.gz.part" -C "$(dirname "$RES")" results && mv "$OUT/results.tar.gz.part" "$OUT/results.tar.gz"
done
echo "results: $OUT/results.tar.gz"
exec >&- 2>&-      # let tee finish writing suite.log before the tool collects $OUT
wait
exit $status
