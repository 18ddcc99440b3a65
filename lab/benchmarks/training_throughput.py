"""Training throughput: samples/s of the stacked trainer against the one-map-at-a-time trainer it replaced.

    python benchmarks/training_throughput.py                       # new trainer, K = 1, 4, 16 maps
    python benchmarks/training_throughput.py --baseline-tree DIR   # + the old trainer from a checkout
    python benchmarks/training_throughput.py --grid                # step time over maps × batch per stack

Same networks (forward regressor 5×32 and classifier 3×32, the recipe's settings otherwise; no
Levenberg–Marquardt finish), same data (ghost maps of ``wide-22mm`` streamed from the tracer, pools
refreshed every ``refresh_every`` steps, validation every ``eval_every`` steps — what training really
does), fixed step counts, goals off.  Samples/s counts
training samples (batch × steps × maps) per second of the training loop (set-up excluded: building the
samplers and held-out sets is the same for both).  ``--baseline-tree``: a checkout of the repository
before the stacked trainer (e.g. ``git worktree add /tmp/old c6c3982``), run in a subprocess with the
same settings, one map at a time, before and after the new trainer (ratios against the mean of the two).
``--steps-kinds``: the new trainer's CPU step, the fused kernel (``fused``, the default) and PyTorch's
operations (``pytorch``).  Every run also times the batched products alone at a stack's shape
(:func:`matmul_peak`, fp32 and bf16) and reports the fp32 ceiling: the samples/s a trainer would reach if
nothing but those products took time, and the fused kernel's forward and backward alone
(:func:`fused_kernel_rate`).  Writes ``benchmarks/results/training_throughput.json`` (``--out``).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if "--old" not in sys.argv:
    # the --old subprocess imports the baseline checkout (its PYTHONPATH and cwd), not this tree: before
    # 2026-11-28 this line ran there too, so its "old trainer" was this tree's trainer one map at a time
    sys.path.insert(0, ROOT)

LENS = "wide-22mm"
BENCH_NETWORKS = {"regressor": (5, 32), "classifier": (3, 32)}     # (hidden layers, width)


def problems(k, kind, heldout=20_000):
    """The first ``k`` ghosts of the lens's ranking as regressor or classifier problems."""
    import numpy as np
    from mi_neurallens import Lens
    from mi_neurallens.flare.energy import ghost_energy_ranking
    from mi_neurallens.training import plan
    from mi_neurallens.training.data import PathSampler, RegressorStream
    from mi_neurallens.training.evaluate import heldout_valid
    from mi_neurallens.transport.planning import select_ghosts
    lens = Lens.load(LENS)
    s0, _ = plan.sensor_distance_range(lens, 300.0)
    zf, zr = plan.planes(lens, s0)
    dom = plan.forward_domain(lens, zf, plan.default_field_half_angle(lens))
    ghosts = select_ghosts(ghost_energy_ranking(lens), 0.99, 32)[:k]
    center, scale = dom.norm_center_scale()
    out = []
    for pid in ghosts:
        ps = PathSampler(lens, pid, "forward", zf, zr, dom)
        stream = RegressorStream(ps, 7 + pid)
        if kind == "regressor":
            val = heldout_valid(lens, (pid, "forward", zf, zr), dom, heldout, 11 + pid)
            out.append(dict(stream=stream, val=val, heading=1, center=center, scale_in=scale, seed=7 + pid,
                            s_max=dom.s_max, key=f"forward.{pid}"))
        else:
            rng = np.random.default_rng(5)
            psv = PathSampler(lens, pid, "forward", zf, zr, dom, precision="float64")
            xcv = dom.u_to_x(rng.random((400_000, 4)))
            lcv, _ = psv.trace_x(xcv)
            out.append(dict(ps=ps, valid_u_source=(lambda n, s=stream: s.sample(n)[0]), val=(xcv, lcv),
                            center=center, scale_in=scale, seed=7 + pid, key=f"forward.{pid}"))
    return out


def net_config(kind, steps):
    from mi_neurallens.training.config import load_config
    # the recipe of the tree being measured (the --old subprocess runs in the baseline checkout)
    cfg = load_config(os.path.join(os.getcwd() if "--old" in sys.argv else ROOT, "training", f"{LENS}.toml"))
    nc = cfg.net(kind, "forward")
    # The networks the recorded rates were measured with (the recipe has since moved its ghost regressors to
    # 3 x 16), and no Levenberg-Marquardt finish: its wall-clock budget would count as loop time.
    hidden, width = BENCH_NETWORKS[kind]
    over = dict(max_steps=steps, max_minutes=1e6, patience=10 ** 9, hidden=hidden, width=width,
                lm_minutes=0.0, lm_iterations=0)
    if hasattr(nc, "stop_at_goals"):
        over["stop_at_goals"] = False
    import dataclasses
    known = {f.name for f in dataclasses.fields(nc)}        # the baseline's NetConfig has no finish
    return dataclasses.replace(nc, **{k: v for k, v in over.items() if k in known})


def measure_new(k, kind, steps, step="fused"):
    """The stacked trainer; ``step``: "fused" (its CPU default where a C compiler is, training/fused_mlp.c) or
    "pytorch" (PyTorch's batched products and the compiled rational tanh: MI_NEURALLENS_FUSED=0)."""
    from mi_neurallens.training import fused_cpu
    fused_cpu._KERNELS.clear()
    old_env = os.environ.get("MI_NEURALLENS_FUSED")
    os.environ["MI_NEURALLENS_FUSED"] = "1" if step == "fused" else "0"
    try:
        return _measure_new(k, kind, steps, step)
    finally:
        fused_cpu._KERNELS.clear()
        if old_env is None:
            os.environ.pop("MI_NEURALLENS_FUSED")
        else:
            os.environ["MI_NEURALLENS_FUSED"] = old_env


def _measure_new(k, kind, steps, step):
    from mi_neurallens.training import classifier, regressor
    from mi_neurallens.training.stacked import STEP_CHOICE
    STEP_CHOICE.clear()
    probs = problems(k, kind)
    nc = net_config(kind, steps)
    fn = regressor.train_regressors if kind == "regressor" else classifier.train_classifiers
    t = time.perf_counter()
    res = fn(probs, nc, progress=False)
    wall = time.perf_counter() - t
    st = [r["state"] for r in res]
    samples = sum(s["samples"] for s in st)
    loop = sum({s["stack"]: s["seconds"] for s in st}.values())      # the stacks run one after the other
    return {"maps": k, "kind": kind, "steps": steps, "samples": samples, "loop_seconds": loop,
            "stacks": len({s["stack"] for s in st}), "samples_per_s": samples / loop, "wall_seconds": wall,
            "step": step, "how": dict(STEP_CHOICE)}


def measure_old(k, kind, steps):
    """The pre-stack trainer: one map at a time with its own train_regressor / train_classifier."""
    from mi_neurallens.training import trainer      # the baseline checkout's module (this runs in its tree)
    nc = net_config(kind, steps)
    probs = problems(k, kind)
    samples = seconds = 0.0
    for p in probs:
        if kind == "regressor":
            r = trainer.train_regressor(p["stream"], p["val"], nc, heading=1, center=p["center"],
                                        scale_in=p["scale_in"], seed=p["seed"], ckpt=None, progress=False,
                                        s_max=p["s_max"])
        else:
            r = trainer.train_classifier(p["ps"], p["valid_u_source"], p["val"], nc, center=p["center"],
                                         scale_in=p["scale_in"], seed=p["seed"], ckpt=None, progress=False)
        samples += r["state"]["samples"]
        seconds += r["state"]["seconds"]
    import mi_neurallens
    return {"maps": k, "kind": kind, "steps": steps, "samples": samples, "loop_seconds": seconds,
            "samples_per_s": samples / seconds, "package": os.path.dirname(mi_neurallens.__file__)}


def matmul_peak(k=4, rows=8192, width=32, repeats=200):
    """What the CPU's batched products reach at a stack's shape — ``k`` maps × ``rows`` × ``width`` @ ``width`` ×
    ``width``, the hidden layers' product — in fp32 and bf16 (GFLOP/s, best of three timings), and the samples/s
    the benchmark's regressor and classifier could reach if *all* their time were such products at the fp32
    rate (forward and the two backward products per layer; no activation, loss or optimiser): the ceiling of
    an fp32 trainer built on PyTorch's batched products on this machine (not the CPU's FMA peak)."""
    import torch
    torch.set_num_threads(2)
    out = {"shape": [k, rows, width, width]}
    for name, dt in (("fp32", torch.float32), ("bf16", torch.bfloat16)):
        a, w = torch.randn(k, rows, width, dtype=dt), torch.randn(k, width, width, dtype=dt)
        for _ in range(20):
            torch.bmm(a, w)
        best = float("inf")
        for _ in range(3):
            t = time.perf_counter()
            for _ in range(repeats):
                torch.bmm(a, w)
            best = min(best, (time.perf_counter() - t) / repeats)
        out[f"{name}_gflops"] = 2.0 * k * rows * width * width / best / 1e9
    for kind, (hidden, width_) in BENCH_NETWORKS.items():
        n_out = 5 if kind == "regressor" else 1
        macs = 4 * width_ + (hidden - 1) * width_ * width_ + width_ * n_out
        out[f"{kind}_flop_per_sample"] = 3 * 2 * macs
        out[f"{kind}_fp32_ceiling_samples_per_s"] = out["fp32_gflops"] * 1e9 / (3 * 2 * macs)
    return out


def fused_kernel_rate(k=4, rows=8192, repeats=30):
    """The fused CPU step alone (training/fused_mlp.c: forward and backward of a stack, no loss, optimiser or
    data) at a stack's shape, for the benchmark's two networks: samples/s and GFLOP/s of its products (the
    same count as :func:`matmul_peak`'s); None where the kernel does not compile."""
    import torch
    from mi_neurallens.training import fused_cpu, stacked
    torch.set_num_threads(2)
    out = {}
    for kind, (hidden, width) in BENCH_NETWORKS.items():
        n_out = 5 if kind == "regressor" else 1
        net = stacked.StackedMLP(torch, "cpu", range(k), 4, n_out, hidden, width)
        if net.fused is None:
            return None
        x, g = torch.randn(k, rows, 4), torch.randn(k, rows, n_out)
        params = [q.detach() for q in net.params]

        def step():
            _, acts = net.fused.forward(torch, x, params)
            net.fused.backward(torch, x, params, acts, g)
        for _ in range(3):
            step()
        best = float("inf")
        for _ in range(3):
            t = time.perf_counter()
            for _ in range(repeats):
                step()
            best = min(best, (time.perf_counter() - t) / repeats)
        macs = 4 * width + (hidden - 1) * width * width + width * n_out
        out[kind] = {"shape": [k, rows], "samples_per_s": k * rows / best,
                     "gflops": k * rows * 3 * 2 * macs / best / 1e9}
    return out


def grid(maps=(1, 2, 4, 8, 16, 32), batches=(1024, 2048, 4096, 8192), hidden=5, width=32):
    """Step time of one stack of K regressors (``hidden`` × ``width``) at batch B (pools in memory, no
    validation or refresh), with the trainer's CPU step (the fused kernel where it compiles): what
    :data:`~mi_neurallens.training.stacked.CPU_STACK_ROWS` is chosen from."""
    import copy
    import numpy as np
    import torch
    from mi_neurallens.training import nets, outputs, regressor, stacked
    torch.set_num_threads(2)
    probs = problems(max(maps), "regressor", heldout=2000)
    nc = net_config("regressor", 10)
    fits = []
    for p in probs:
        u0, x0, y0 = p["stream"].sample(300_000)
        xn0 = (x0 - p["center"]) / p["scale_in"]
        tr = outputs.fit_output_transform(xn0, y0, nc.residual, outputs.odd_factor(x0[:, 2], p["s_max"]))
        fits.append(regressor.RegressorFit(torch, "cpu", None, nc, p["stream"], p["val"], (u0, x0, y0),
                                           state=nets.new_state(), heading=1,
                                           center=p["center"], scale_in=p["scale_in"], transform=tr,
                                           odd_s=p["s_max"]))
    rng = np.random.default_rng(0)
    rows = []
    for k in maps:
        for b in batches:
            fs = [copy.copy(f) for f in fits[:k]]
            net = stacked.StackedMLP(torch, "cpu", range(k), 4, 5, hidden, width)
            opt = stacked.StackedAdam(net.params)
            pools = stacked.PoolStack(torch, fs)

            def step():
                batch = pools.batch(int(rng.integers(0, pools.n - b)), b)
                if stacked.fused_step(net, fs[0], batch, pools.const) is None:     # as the trainer steps
                    fs[0].rows_loss(net.forward(batch["X"]), batch, pools.const).sum().backward()
                opt.step(net.params, 1e-3)
            for _ in range(3):
                step()
            n = max(5, int(2e6 / (k * b)))
            t = time.perf_counter()
            for _ in range(n):
                step()
            dt = (time.perf_counter() - t) / n
            rows.append({"maps": k, "batch": b, "step_ms": 1e3 * dt, "samples_per_s": k * b / dt,
                         "network": f"{hidden}x{width}", "fused": net.fused is not None})
            print(f"K={k:2d} B={b:5d}: {1e3 * dt:6.1f} ms/step, {k * b / dt / 1e6:.2f} M samples/s", flush=True)
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline-tree", help="checkout of the one-map-at-a-time trainer (run in a subprocess)")
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--maps", default="1,4,16")
    ap.add_argument("--kinds", default="regressor,classifier")
    ap.add_argument("--steps-kinds", default="fused,pytorch",
                    help="the stacked trainer's CPU steps to measure: fused (the default), pytorch (its operations)")
    ap.add_argument("--grid", action="store_true", help="only the stack-size grid (maps × batch)")
    ap.add_argument("--grid-network", default="5x32", help="the grid's regressor: hidden layers x width")
    ap.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "training_throughput.json"))
    ap.add_argument("--old", action="store_true", help=argparse.SUPPRESS)   # the subprocess's mode
    args = ap.parse_args()
    if args.grid:
        out = {"machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
               "command": " ".join(sys.argv),
               "grid": grid(hidden=int(args.grid_network.split("x")[0]), width=int(args.grid_network.split("x")[1]))}
        from mi_neurallens.fileio import atomic_write_json
        atomic_write_json(args.out if args.out != ap.get_default("out") else
                          os.path.join(ROOT, "benchmarks", "results", "training_stack_grid.json"), out)
        return
    kinds = args.kinds.split(",")
    if args.old:
        print(json.dumps([measure_old(int(args.maps), kind, args.steps) for kind in kinds]))
        return
    rows = {"machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
            "command": " ".join(sys.argv), "new": [], "old": []}
    def run_old(when):
        env = dict(os.environ, PYTHONPATH=os.path.abspath(args.baseline_tree))
        out = subprocess.run([sys.executable, os.path.abspath(__file__), "--old", "--maps", "2", "--steps",
                              str(args.steps), "--kinds", args.kinds], env=env, cwd=args.baseline_tree,
                             capture_output=True, text=True, check=True)
        got = json.loads(out.stdout.strip().splitlines()[-1])
        if any(not os.path.abspath(r["package"]).startswith(os.path.abspath(args.baseline_tree)) for r in got):
            raise SystemExit(f"the baseline run imported {got[0]['package']}, not {args.baseline_tree}")
        for r in got:
            print(f"old  {r['kind']:10s} one at a time ×{r['maps']} ({when}): {r['samples_per_s'] / 1e6:.2f} M samples/s",
                  flush=True)
        return got

    if args.baseline_tree:
        # The old trainer runs first and again last: this VM's speed drifts by tens of per cent over minutes,
        # so each ratio is against the mean of the two (both are in the JSON)
        rows["old"] = run_old("first")
    rows["matmul_peak"] = peak = matmul_peak()
    print(f"batched products {peak['shape']}: fp32 {peak['fp32_gflops']:.0f} GFLOP/s, bf16 {peak['bf16_gflops']:.0f}")
    rows["fused_kernel"] = fused = fused_kernel_rate()
    for kind, r in (fused or {}).items():
        print(f"fused kernel alone {kind:10s} {r['shape']}: {r['samples_per_s'] / 1e6:.2f} M samples/s, "
              f"{r['gflops']:.0f} GFLOP/s")
    for kind in kinds:
        ceil = peak[f"{kind}_fp32_ceiling_samples_per_s"]
        base = next((o["samples_per_s"] for o in rows["old"] if o["kind"] == kind), None)
        print(f"fp32 ceiling {kind:10s}: {ceil / 1e6:.2f} M samples/s"
              + (f"  {ceil / base:.2f}× the old trainer" if base else ""))
    for kind in kinds:
        for step in args.steps_kinds.split(","):
            for k in map(int, args.maps.split(",")):
                r = measure_new(k, kind, args.steps, step)
                rows["new"].append(r)
                base = next((o["samples_per_s"] for o in rows["old"] if o["kind"] == kind), None)
                ratio = f"  {r['samples_per_s'] / base:.2f}× the old trainer" if base else ""
                print(f"new  {kind:10s} {step:7s} {k:2d} maps ({r['stacks']} stacks): "
                      f"{r['samples_per_s'] / 1e6:.2f} M samples/s{ratio}", flush=True)
    if args.baseline_tree:
        rows["old_last"] = run_old("last")
        for kind in kinds:
            a, b = (next(o["samples_per_s"] for o in rows[w] if o["kind"] == kind) for w in ("old", "old_last"))
            base = 0.5 * (a + b)
            for r in rows["new"]:
                if r["kind"] == kind:
                    r["vs_old_mean"] = r["samples_per_s"] / base
            best = max(r["samples_per_s"] for r in rows["new"] if r["kind"] == kind)
            print(f"{kind}: the old trainer {a / 1e6:.2f} then {b / 1e6:.2f} M samples/s; the best new row is "
                  f"{best / base:.2f}× their mean")
    from mi_neurallens.fileio import atomic_write_json
    atomic_write_json(args.out, rows)


if __name__ == "__main__":
    main()
