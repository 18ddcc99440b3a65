#!/usr/bin/env bash
# Build .whl/: the Python packages a GPU machine without package access lacks (Dr.Jit and Mitsuba), as
# wheels for its Python, Mitsuba trimmed to the variants benchmarks/gpu_suite.sh uses so that wheels
# and the working tree together stay under a 64 MiB transfer limit.
#
#   bash scripts/gpu_carry.sh [PYTHON_VERSION]      (default 3.12; needs pip and the package index)
#
# Then, on the GPU machine, from the repository root:  bash benchmarks/gpu_suite.sh
# (it installs .whl/*.whl into /tmp/site with pip --no-index and puts it on PYTHONPATH).
#
# Kept Mitsuba variants: $KEEP_VARIANTS (default below).  Dropped: the other variants' extension
# modules, the C++ headers and the plugins in $DROP_PLUGINS (shapes, BSDFs and emitters nothing in this
# repository names; their data too), nothing the kept variants load; RECORD is rewritten to match.
set -euo pipefail
cd "$(dirname "$0")/.."
PYV="${1:-3.12}"
TAG="cp${PYV/./}"
# The GPU runs cuda_ad_*; Dr.Jit's own LLVM backend (the float64 numpy faces) is in the drjit wheel and needs no
# Mitsuba llvm variant.  With the llvm variants too the transfer was 65.4 of its 64 MiB (2026-11-28).
KEEP_VARIANTS="${KEEP_VARIANTS:-scalar_rgb cuda_ad_rgb cuda_ad_spectral}"
# With the tree at 28.6 MiB the three variants came to 64.5 of the 64 MiB (2026-11-28): these go (≈ 4 MiB packed)
DROP_PLUGINS="${DROP_PLUGINS:-ellipsoids ellipsoidsmesh sunsky timed_sunsky bsplinecurve linearcurve sdfgrid hair principled principledthin volpathmis}"
MITSUBA="${MITSUBA_VERSION:-3.9.1}"
DRJIT="${DRJIT_VERSION:-1.5.0}"
OUT=.whl
mkdir -p "$OUT"
grep -qx '/.whl/' .git/info/exclude 2>/dev/null || grep -qx '.whl/' .gitignore || echo '/.whl/' >> .git/info/exclude

tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
python3 -m pip download -q --no-deps --only-binary=:all: --python-version "$PYV" --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 -d "$tmp" "mitsuba==$MITSUBA" "drjit==$DRJIT"
rm -f "$OUT"/mitsuba-*.whl "$OUT"/drjit-*.whl
cp "$tmp"/drjit-*.whl "$OUT"/

python3 - "$tmp"/mitsuba-*.whl "$OUT" "$KEEP_VARIANTS" "$DROP_PLUGINS" <<'EOF'
"""Copy the Mitsuba wheel without the unused variants' modules and the headers, RECORD rewritten."""
import os, re, sys, zipfile
src, out, keep, drop = sys.argv[1], sys.argv[2], set(sys.argv[3].split()), set(sys.argv[4].split())
variant = re.compile(r"^mitsuba/((?:scalar|llvm|cuda)_[a-z_]+)\.cpython-[^/]+\.so$")
plugin = re.compile(r"^mitsuba/plugins/([a-z_0-9]+)\.so$")
drop_data = tuple(f"mitsuba/data/{d}/" for d in drop)
def dropped(name):
    m, p = variant.match(name), plugin.match(name)
    return ((m is not None and m.group(1) not in keep) or (p is not None and p.group(1) in drop)
            or name.startswith("mitsuba/include/") or name.startswith(drop_data))
dst = os.path.join(out, os.path.basename(src))
kept = gone = 0
with zipfile.ZipFile(src) as zi, zipfile.ZipFile(dst, "w", zipfile.ZIP_LZMA) as zo:
    for info in zi.infolist():
        if dropped(info.filename):
            gone += info.file_size
            continue
        data = zi.read(info)
        if info.filename.endswith(".dist-info/RECORD"):
            rows = [r for r in data.decode().splitlines() if r and not dropped(r.split(",")[0])]
            data = ("\n".join(rows) + "\n").encode()
        info.compress_type = zipfile.ZIP_LZMA   # pip extracts with zipfile, which reads LZMA
        zo.writestr(info, data)
        kept += info.file_size
print(f"{dst}: kept {kept / 2**20:.1f} MiB unpacked, dropped {gone / 2**20:.1f} MiB "
      f"(variants kept: {' '.join(sorted(keep))}; plugins dropped: {' '.join(sorted(drop))}); {os.path.getsize(dst) / 2**20:.1f} MiB on disk")
EOF
git ls-files -z | python3 -c '
import glob, os, sys
tree = sum(os.path.getsize(f) for f in sys.stdin.read().split("\0") if f and os.path.isfile(f))
whl = sum(os.path.getsize(f) for f in glob.glob(".whl/*.whl"))
print(f"tracked tree {tree / 2**20:.1f} MiB + wheels {whl / 2**20:.1f} MiB = {(tree + whl) / 2**20:.1f} MiB (limit 64 MiB)")'
