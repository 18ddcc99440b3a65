#!/usr/bin/env bash
# Retrain every bundled model (lenses/models/*.model.safetensors) from its recipe training/<lens>.toml.
# Resumable: rerun after an interruption (checkpoints live in lenses/models/<lens>.model.safetensors.work/).
# Extra arguments are passed to every `mi-neurallens train` call, e.g. --set seed=2 or --no-progress.
set -euo pipefail
cd "$(dirname "$0")/.."
for lens in wide-22mm ood-59mm canon-ef-24mm-f1.4l; do
  echo "=== $lens ==="
  /usr/bin/time -v python -m mi_neurallens train "$lens" --config "training/$lens.toml" --out lenses/models "$@" \
      2> >(tee "training/logs/$lens.train.log" >&2)
done
for lens in wide-22mm ood-59mm canon-ef-24mm-f1.4l; do
  python -m mi_neurallens evaluate "lenses/models/$lens.model.safetensors" -n 200000
done
