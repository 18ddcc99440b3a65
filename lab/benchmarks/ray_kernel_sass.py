"""What the GPU runs for one camera ray: each lens sensor's camera-ray kernel compiled to machine code, counted.

    python benchmarks/ray_kernel_sass.py [--lens wide-22mm ...] [--styles cpu,gpu] [--out sass.json] [--keep DIR]

For each lens: ``realistic_lens`` and ``neural_lens`` (each evaluation style of the learned map in ``--styles``:
neural/mlp.py ``MLP_STYLES``) make 2^20 camera rays with ``ray_kernel = separate``, so the rays are one kernel
of their own; Dr.Jit's kernel history gives that kernel's source (PTX on CUDA).  Where ``ptxas`` is found (on
``PATH``, in ``$CUDA_HOME/bin`` or ``/usr/local/cuda/bin``, or in Triton's wheel, which PyTorch's CUDA builds
install) the PTX is compiled for the GPU's architecture (``ptxas -v``: registers, spills) and ``nvdisasm`` /
``cuobjdump`` counts its instructions by opcode (FFMA, MOV, MUFU, ...).  On the CPU (LLVM) only the Dr.Jit operation counts are
reported.  Issue 18: the learned map's instruction count and register use against the tracer's, per lens.
"""
from __future__ import annotations

import argparse
import collections
import glob
import os
import re
import shutil
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def find_tool(name):
    """A CUDA tool: PATH, $CUDA_HOME/bin, /usr/local/cuda/bin, or Triton's bundled copy."""
    hit = shutil.which(name)
    if hit:
        return hit
    cands = [os.path.join(os.environ.get("CUDA_HOME", "/usr/local/cuda"), "bin", name)]
    try:
        import triton
        cands += glob.glob(os.path.join(os.path.dirname(triton.__file__), "backends", "nvidia", "bin", name))
    except Exception:
        pass
    for c in cands:
        if os.path.isfile(c) and os.access(c, os.X_OK):
            return c
    return None


def ray_kernel_ir(mi, dr, sensor, n=1 << 20):
    """(operation count, source) of the largest kernel that sample_ray + dr.eval launches: the camera rays."""
    import numpy as np
    rng = np.random.default_rng(0)
    s = [mi.Float(rng.random(n).astype(np.float32)) for _ in range(5)]
    dr.eval(s)
    dr.kernel_history()
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        ray, w = sensor.sample_ray(mi.Float(0.0) + 0 * s[0], s[0], mi.Point2f(s[1], s[2]), mi.Point2f(s[3], s[4]))
        dr.eval(ray.o, ray.d, w)
        dr.sync_thread()
        hist = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    k = max(hist, key=lambda k: k["operation_count"])
    ir = k.get("ir", "")
    return int(k["operation_count"]), ir.getvalue() if hasattr(ir, "getvalue") else str(ir)   # io.StringIO on CUDA


def sass_report(ptx, arch, ptxas, disasm, work, tag):
    """ptxas -v (registers, spills) and an opcode histogram of the compiled kernel."""
    src = os.path.join(work, f"{tag}.ptx")
    cub = os.path.join(work, f"{tag}.cubin")
    with open(src, "w") as f:
        f.write(ptx)
    r = subprocess.run([ptxas, f"-arch={arch}", "-v", src, "-o", cub], capture_output=True, text=True)
    out = {"ptxas_rc": r.returncode}
    info = r.stderr + r.stdout
    m = re.search(r"Used (\d+) registers", info)
    out["registers"] = int(m.group(1)) if m else None
    m = re.search(r"(\d+) bytes spill stores, (\d+) bytes spill loads", info)
    out["spill_bytes"] = [int(m.group(1)), int(m.group(2))] if m else None
    if r.returncode != 0:
        out["ptxas_error"] = info[-800:]
        return out
    if disasm:
        args = [disasm, "-c", cub] if os.path.basename(disasm).startswith("nvdisasm") else [disasm, "-sass", cub]
        d = subprocess.run(args, capture_output=True, text=True)
        ops = collections.Counter()
        for line in d.stdout.splitlines():
            m = re.search(r"/\*[0-9a-f]{4,}\*/\s+(?:@!?U?P\w+\s+)?([A-Z][A-Z0-9_]*)(?:\.[\w.]+)?\s", line)
            if m:
                ops[m.group(1)] += 1
        out["instructions"] = sum(ops.values())
        out["opcodes"] = dict(ops.most_common())
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lens", nargs="+", default=["wide-22mm"])
    ap.add_argument("--styles", default="cpu,gpu")
    ap.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "ray_kernel_sass.json"))
    ap.add_argument("--keep", help="folder to keep the PTX and cubins in")
    a = ap.parse_args(argv)
    import drjit as dr
    import mitsuba as mi
    from mi_neurallens.render_utils import default_variant
    mi.set_variant(default_variant())
    import mi_neurallens
    from mi_neurallens.fileio import atomic_write_json
    from mi_neurallens.neural.mlp import forced_style
    mi_neurallens.register()
    cuda = mi.variant().startswith("cuda")
    ptxas = find_tool("ptxas") if cuda else None
    disasm = (find_tool("nvdisasm") or find_tool("cuobjdump")) if ptxas else None
    arch = None
    if ptxas:
        try:
            cc = subprocess.run(["nvidia-smi", "--query-gpu=compute_cap", "--format=csv,noheader"],
                                capture_output=True, text=True).stdout.split()
        except OSError:
            cc = []
        arch = "sm_" + cc[0].replace(".", "") if cc else "sm_90"
    print(f"variant {mi.variant()}; ptxas {ptxas}; disassembler {disasm}; arch {arch}")
    work = a.keep or tempfile.mkdtemp()
    os.makedirs(work, exist_ok=True)
    styles = [s for s in a.styles.split(",") if s]
    rows = []
    for lens in a.lens:
        film = {"type": "hdrfilm", "width": 1024, "height": 1024, "pixel_format": "rgb"}
        base = {"lens": lens, "ray_kernel": "separate", "film": film}
        cases = [("realistic_lens", None)] + [("neural_lens", s) for s in styles]
        for kind, style in cases:
            with forced_style(style):
                sensor = mi.load_dict({"type": kind, **base})
                ops, ir = ray_kernel_ir(mi, dr, sensor)
            tag = f"{lens}_{kind}" + (f"_{style}" if style else "")
            row = {"lens": lens, "sensor": kind, "style": style, "drjit_operations": ops}
            if ptxas and ir:
                row.update(sass_report(ir, arch, ptxas, disasm, work, tag))
            rows.append(row)
            extra = ""
            if "instructions" in row:
                extra = (f", {row['instructions']} SASS instructions, {row['registers']} registers, spills "
                         f"{row['spill_bytes']}: " + ", ".join(f"{k} {v}" for k, v in row["opcodes"].items()))
            elif "registers" in row:
                extra = f", {row['registers']} registers"
            print(f"{tag}: {ops} Dr.Jit operations{extra}", flush=True)
    atomic_write_json(a.out, {"variant": mi.variant(), "arch": arch, "ptxas": ptxas, "rows": rows}, indent=2)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
