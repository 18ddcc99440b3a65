#!/usr/bin/env python3
"""Speed of two source trees side by side, in one run: the no-regression check of a refactor.

    git worktree add /tmp/before <old commit>
    python benchmarks/before_after.py /tmp/before [--rounds 2] [--out out/before_after]

Runs ``bench_tracer``, ``bench_mlp``, ``bench_render`` and ``bench_flare`` of THIS tree on the code of
the other tree ("before") and of this tree ("after"), alternating before/after ``--rounds`` times so
that slow drifts of the machine fall on both, and prints every rate (``*per_s``) and time (``*_s``,
``seconds``) as before, after and after/before (best of the rounds: rates max, times min).  Run it
on an idle machine.  Each benchmark runs with the settings of ``BENCHES`` below (fewer rays and repeats
than its own defaults, so that both trees fit in one sitting).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

BENCHES = {
    "bench_tracer": ["--rays", "21", "--ref-rays", "12", "--repeats", "5"],
    "bench_mlp": ["--rays", "21", "--repeats", "5"],
    "bench_render": ["--res", "320x240", "--spp", "32", "--repeats", "3"],
    "bench_flare": ["--ghosts", "4", "--samples", str(1 << 20), "--ref-samples", str(1 << 21)],
}


def _flatten(o, prefix=""):
    if isinstance(o, dict):
        for k, v in o.items():
            yield from _flatten(v, f"{prefix}.{k}" if prefix else str(k))
    elif isinstance(o, list):
        for i, v in enumerate(o):
            yield from _flatten(v, f"{prefix}[{i}]")
    elif isinstance(o, (int, float)) and not isinstance(o, bool):
        yield prefix, float(o)


def _kind(key: str):
    last = key.rsplit(".", 1)[-1]
    if "per_s" in last:
        return "rate"
    if last in ("seconds", "best_s", "render_s", "first_call_s"):
        return "time"
    return None


def run(tree: str, name: str, args: list, out: str) -> dict:
    env = dict(os.environ, PYTHONPATH=tree)
    cmd = [sys.executable, os.path.join(ROOT, "benchmarks", f"{name}.py"), *args, "--out", out]
    subprocess.run(cmd, check=True, env=env, cwd=tree, stdout=subprocess.DEVNULL)
    with open(out) as f:
        return dict(_flatten(json.load(f)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("before", help="source tree of the old code (a git worktree)")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--only", nargs="*", default=list(BENCHES))
    ap.add_argument("--out", default=os.path.join(ROOT, "out", "before_after"))
    a = ap.parse_args(argv)
    os.makedirs(a.out, exist_ok=True)
    best: dict = {"before": {}, "after": {}}
    for r in range(a.rounds):
        for name in a.only:
            for label, tree in (("before", os.path.abspath(a.before)), ("after", ROOT)):
                vals = run(tree, name, BENCHES[name], os.path.join(a.out, f"{name}.{label}.{r}.json"))
                for k, v in vals.items():
                    kind = _kind(k)
                    if kind is None:
                        continue
                    key = f"{name}: {k}"
                    old = best[label].get(key)
                    best[label][key] = v if old is None else (max(old, v) if kind == "rate" else min(old, v))
                print(f"round {r + 1}: {name} ({label}) done", file=sys.stderr, flush=True)
    rows = ["| benchmark: quantity | before | after | after / before |", "|---|---|---|---|"]
    for key in sorted(set(best["before"]) & set(best["after"])):
        b, f = best["before"][key], best["after"][key]
        rows.append(f"| {key} | {b:.4g} | {f:.4g} | {f / b if b else float('nan'):.3f} |")
    table = "\n".join(rows)
    print(table)
    with open(os.path.join(a.out, "before_after.md"), "w") as f:
        f.write(table + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
