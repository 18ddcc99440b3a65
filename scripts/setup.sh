#!/usr/bin/env bash
# One-time (idempotent, fast when already done) machine set-up for mi-neurallens.
#  1. Debian's libllvm19 when no LLVM >= 16 is present: Dr.Jit 1.5's LLVM backend crashes on LLVM 15
#     ("Cannot select fminimum").
#  2. torch==2.13.0 (CPU build) BEFORE anything that could pull an unpinned torch with CUDA wheels.
#  3. The package itself, editable, with the dev, train and cluster (Ray) extras.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

have_llvm16plus() {
  for f in /usr/lib/x86_64-linux-gnu/libLLVM-1[6-9]*.so* /usr/lib/x86_64-linux-gnu/libLLVM.so.[2-9]* \
           /usr/lib/x86_64-linux-gnu/libLLVM.so.1[6-9]* /usr/lib/aarch64-linux-gnu/libLLVM.so.1[6-9]* \
           /usr/lib/aarch64-linux-gnu/libLLVM-1[6-9]*.so* /usr/lib/llvm-1[6-9]/lib/libLLVM*.so*; do
    [ -e "$f" ] && return 0
  done
  return 1
}

if ! have_llvm16plus; then
  echo "[setup] installing Debian libllvm19 (Dr.Jit 1.5 needs LLVM >= 16)"
  SUDO=""; [ "$(id -u)" = 0 ] || SUDO=sudo
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libllvm19 >/dev/null
fi

stamp=.setup-done
want="$(cat pyproject.toml scripts/setup.sh | sha1sum | cut -c1-16)"
if [ -f "$stamp" ] && [ "$(cat $stamp)" = "$want" ] && $PY -c "import mi_neurallens, torch, mitsuba, ray" 2>/dev/null; then
  exit 0
fi
echo "[setup] installing Python packages (torch CPU pinned first)"
$PY -m pip install -q --disable-pip-version-check "torch==2.13.0"
$PY -m pip install -q --disable-pip-version-check -e ".[dev,train,cluster]"
echo "$want" > "$stamp"
echo "[setup] done"
