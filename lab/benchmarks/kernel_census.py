"""Which Dr.Jit kernels a training of ghost maps compiles and launches, per data step (issue 17: where a whole
lens's data set-up goes on a GPU).

    python benchmarks/kernel_census.py [--lens dgauss-50mm] [--paths 2560,96,80,1152] [--out census.json]

Runs ``mi-neurallens train LENS --paths PATHS`` in this process with a few hundred Adam steps and three
Levenberg–Marquardt iterations per network (the data steps are what is counted; the networks barely train) and no
flare verification, with Dr.Jit's kernel history on.  The data functions of ``training/data.py``,
``training/bounds.py``, ``training/outputs.py``, ``training/classifier.py``, ``training/levenberg.py`` and
``training/evaluate.py`` are wrapped; each kernel is counted
in the innermost wrapped call that launched it.  Per step: calls, kernels launched, distinct kernels (hashes),
in-run cache hits, compile seconds (code generation + the backend's compiler), execution seconds, wall seconds
(wrapped calls nest, so walls overlap).  The kernel cache is ``$HOME/.drjit``: run with ``HOME`` set to an empty
folder for a machine that never traced the lens.  Variant: ``$MI_NEURALLENS_VARIANT`` (the samplers use Dr.Jit's
LLVM backend wherever libLLVM is found, ``trace/api.py::float_type``).

On the 2-core AVX-512 VM, empty cache, dgauss-50mm's four ghosts: 62 distinct kernels (about 15 a ghost), 10.6 s
of LLVM compilation in a 65-s run (docs/results.md, "The fourth GPU session"); 49 since the stop heads' samplers
take the regressors' pilot and the held-out evaluation its networks as kernel parameters ("The data set-up").
"""
from __future__ import annotations

import argparse
import collections
import functools
import json
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

#: (module, attribute) of every wrapped step; "Class.method" wraps a method
STEPS = (("data", "PathSampler.random_valid"), ("data", "PathSampler.trace_u"), ("data", "PathSampler.trace_x"),
         ("data", "PathSampler.margin_u"), ("data", "valid_fraction"), ("data", "rejection_sample"),
         ("data", "classifier_samples"), ("data", "RegressorStream.sample"), ("bounds", "ValidBounds.build"),
         ("classifier", "calibrate_classifier"), ("outputs", "fit_output_transform"), ("levenberg", "finish_results"),
         ("evaluate", "evaluate_map"))


class Census:
    """Kernel history per wrapped step (innermost call first)."""

    def __init__(self, dr):
        self.dr = dr
        self.rows = collections.defaultdict(lambda: {"calls": 0, "kernels": 0, "hashes": set(), "cache_hits": 0,
                                                     "compile_s": 0.0, "exec_s": 0.0, "wall_s": 0.0})
        self.stack = ["(elsewhere)"]

    def flush(self, tag):
        dr = self.dr
        for h in dr.kernel_history():
            if h["type"] != dr.KernelType.JIT:
                continue
            r = self.rows[tag]
            r["kernels"] += 1
            r["hashes"].add(h["hash"])
            r["cache_hits"] += int(bool(h.get("cache_hit", False)))
            r["compile_s"] += (float(h.get("codegen_time", 0.0)) + float(h.get("backend_time", 0.0))) / 1e3
            r["exec_s"] += float(h.get("execution_time", 0.0)) / 1e3

    def wrap(self, module, name):
        owner = module
        if "." in name:
            cls, name = name.split(".")
            owner = getattr(module, cls)
        prefix = owner.__name__ if owner is not module else module.__name__.rsplit(".", 1)[-1]
        f, tag = getattr(owner, name), f"{prefix}.{name}"

        @functools.wraps(f)
        def counted(*a, **k):
            self.flush(self.stack[-1])
            self.stack.append(tag)
            t0 = time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                self.flush(tag)
                self.rows[tag]["calls"] += 1
                self.rows[tag]["wall_s"] += time.perf_counter() - t0
                self.stack.pop()
        setattr(owner, name, counted)

    def table(self) -> dict:
        hashes = set().union(*[r["hashes"] for r in self.rows.values()]) if self.rows else set()
        rows = {k: {**r, "hashes": len(r["hashes"])} for k, r in self.rows.items()}
        total = {"kernels": sum(r["kernels"] for r in rows.values()), "distinct": len(hashes),
                 "compile_s": sum(r["compile_s"] for r in rows.values()),
                 "exec_s": sum(r["exec_s"] for r in rows.values())}
        return {"rows": rows, "total": total}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lens", default="dgauss-50mm")
    ap.add_argument("--paths", default="2560,96,80,1152", help="ghost ids (or any --paths of `train`)")
    ap.add_argument("--steps", type=int, default=300, help="Adam steps per network (the data is what is counted)")
    ap.add_argument("--out", default=None, help="JSON file")
    a = ap.parse_args(argv)
    import tempfile
    import drjit as dr
    import mitsuba as mi
    from mi_neurallens.render_utils import default_variant
    mi.set_variant(default_variant())
    from mi_neurallens.training import bounds, classifier, data, evaluate, levenberg, outputs
    modules = {"data": data, "bounds": bounds, "classifier": classifier, "outputs": outputs, "levenberg": levenberg,
               "evaluate": evaluate}
    census = Census(dr)
    for mod, name in STEPS:
        census.wrap(modules[mod], name)
    from mi_neurallens.cli import main as cli
    sets = [f"{net}.{k}={v}" for net in ("forward_regressor", "forward_classifier", "forward_stop")
            for k, v in (("max_steps", a.steps), ("lm_iterations", 3))] + ["verify_flare=false"]
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        rc = cli(["train", a.lens, "--paths", a.paths, "--out", tmp, "--no-progress"]
                 + [x for s in sets for x in ("--set", s)])
    census.flush(census.stack[-1])
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    res = census.table()
    res["total"]["wall_s"] = time.perf_counter() - t0
    print(f"\nkernel census: {a.lens} --paths {a.paths}, {mi.variant()}, cache {os.path.expanduser('~/.drjit')}")
    print("| step | calls | kernels | distinct | cache hits | compile s | execution s | wall s |")
    print("|---|---|---|---|---|---|---|---|")
    for k, r in sorted(res["rows"].items(), key=lambda kv: -kv[1]["compile_s"]):
        print(f"| {k} | {r['calls']} | {r['kernels']} | {r['hashes']} | {r['cache_hits']} | {r['compile_s']:.2f} "
              f"| {r['exec_s']:.2f} | {r['wall_s']:.2f} |")
    t = res["total"]
    print(f"| **all** | | {t['kernels']} | {t['distinct']} | | {t['compile_s']:.2f} | {t['exec_s']:.2f} | "
          f"{t['wall_s']:.2f} (the run) |")
    if a.out:
        with open(a.out, "w") as f:
            json.dump({"benchmark": "kernel_census", "lens": a.lens, "paths": a.paths, "variant": mi.variant(),
                       "command": "python benchmarks/kernel_census.py " + " ".join(sys.argv[1:]), **res}, f, indent=1)
        print(f"wrote {a.out}")
    return rc


if __name__ == "__main__":
    sys.exit(main())
