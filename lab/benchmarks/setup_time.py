"""How long a training's data set-up takes before its first network trains: this tree against another.

    python benchmarks/setup_time.py [--lens dgauss-50mm] [--paths forward] [--baseline-tree DIR] [--json OUT]

Runs ``python -m mi_neurallens train LENS --paths PATHS --no-verify`` in a subprocess, on an empty Dr.Jit kernel
cache and an empty PyTorch compile cache (a fresh ``HOME`` and ``TORCHINDUCTOR_CACHE_DIR``: what a new lens on a
new machine sees), stamps every line of its log with the seconds since the start, and stops it at the first
"regressor step=" line: everything before is set-up (planning, ghost ranking, samplers, pilot bounds, pools,
held-out sets, output transforms, the training activation's compilation).  Reported: seconds to the "map(s) to
train" line (planning and ranking) and from there to the first step (the maps' data set-up).  With
``--baseline-tree`` (e.g. ``git worktree add /tmp/old HEAD~3``) the same command runs from that checkout first,
in the same invocation, so the ratio is measured on one machine state.  This 2-core VM's speed drifts by tens
of per cent between minutes: compare runs of one invocation only.
"""
from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def run_once(tree: str, lens: str, paths: str, timeout: float, log_path: str | None = None) -> dict:
    """Set-up times (s) of one training started from the checkout ``tree``."""
    with tempfile.TemporaryDirectory(prefix="setup_time_") as tmp:
        env = dict(os.environ, HOME=os.path.join(tmp, "home"), TORCHINDUCTOR_CACHE_DIR=os.path.join(tmp, "inductor"),
                   PYTHONPATH=tree, PYTHONUNBUFFERED="1")
        os.makedirs(env["HOME"])
        cmd = [sys.executable, "-m", "mi_neurallens", "train", lens, "--paths", paths, "--out",
               os.path.join(tmp, "out"), "--no-verify", "--no-progress"]
        t0 = time.perf_counter()
        p = subprocess.Popen(cmd, cwd=tree, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        planned = first = None
        lines = []
        try:
            for line in p.stdout:
                t = time.perf_counter() - t0
                lines.append(f"[{t:.1f}s] {line}")
                if planned is None and "map(s) to train" in line:
                    planned = t
                if "regressor step=" in line:
                    first = t
                    break
                if t > timeout:
                    break
        finally:
            p.kill()
            p.wait()
        if log_path:
            with open(log_path, "w") as f:
                f.writelines(lines)
        if first is None:
            raise SystemExit(f"{tree}: no training step within {timeout:.0f} s; its log:\n" + "".join(lines[-20:]))
        planned = 0.0 if planned is None else planned
        return {"to_plan_s": round(planned, 2), "data_setup_s": round(first - planned, 2),
                "to_first_step_s": round(first, 2)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lens", default="dgauss-50mm")
    ap.add_argument("--paths", default="forward", help="what `train --paths` takes (default: the forward maps)")
    ap.add_argument("--baseline-tree", help="another checkout, run first in the same invocation")
    ap.add_argument("--timeout", type=float, default=900.0, help="give up on a run after this many seconds")
    ap.add_argument("--logs", help="folder for the stamped logs of each run")
    ap.add_argument("--json", help="write the results here")
    a = ap.parse_args(argv)
    trees = ([("baseline", os.path.abspath(a.baseline_tree))] if a.baseline_tree else []) + [("this tree", ROOT)]
    rows = {}
    for name, tree in trees:
        log = os.path.join(a.logs, f"setup_{name.replace(' ', '_')}.log") if a.logs else None
        if a.logs:
            os.makedirs(a.logs, exist_ok=True)
        rows[name] = run_once(tree, a.lens, a.paths, a.timeout, log)
        rows[name]["commit"] = subprocess.run(["git", "-C", tree, "describe", "--always", "--dirty"],
                                              capture_output=True, text=True).stdout.strip()
        print(f"{name} ({rows[name]['commit']}): planning {rows[name]['to_plan_s']:.1f} s, data set-up "
              f"{rows[name]['data_setup_s']:.1f} s, first step at {rows[name]['to_first_step_s']:.1f} s", flush=True)
    if "baseline" in rows:
        r = rows["this tree"]["data_setup_s"] / max(rows["baseline"]["data_setup_s"], 1e-9)
        print(f"data set-up, this tree / baseline: {r:.2f}")
    if a.json:
        sys.path.insert(0, ROOT)
        from mi_neurallens.fileio import atomic_write_json
        atomic_write_json(a.json, {"benchmark": "setup_time", "lens": a.lens, "paths": a.paths,
                                   "machine": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
                                   "command": " ".join(["python"] + sys.argv), "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
