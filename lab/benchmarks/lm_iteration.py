"""What one Levenberg–Marquardt iteration's normal equations cost: the whole Jacobian against the blocks.

    python benchmarks/lm_iteration.py [--rows 8192] [--repeats 5] [--json OUT]

For the networks the finish polishes (``mi_neurallens/training/levenberg.py``) — a 3×16 ghost regressor (4 inputs,
5 outputs: 709 weights), 3×16 stop heads of ghosts crossing the stop plane three times and once (6 and 2 outputs),
a 2×16 classifier (1 output: 369 weights) and the camera map's 2×32 stop head — it times forming ``JᵀJ`` and ``Jᵀr`` on
``--rows`` rows two ways, in float32 as the finish does, best of ``--repeats``:

* ``jacobian``: the whole scaled Jacobian (``FlatMLP.jacobian``, scaled by ∂r/∂z, then ``JᵀJ`` as one product), what
  the finish did before;
* ``blocks``: ``FlatMLP.normal_equations`` — the hidden layers' columns and the residuals in one buffer, its Gram
  matrix by panels (its upper triangle), the output layer per output.

and checks that both give the same matrix (relative difference, float32).  Run it on an idle machine.
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

#: (name, layer widths, in → out)
NETWORKS = (("ghost regressor 3x16", [4, 16, 16, 16, 5]),
            ("ghost stop head 3x16, three crossings", [4, 16, 16, 16, 6]),
            ("ghost stop head 3x16, one crossing", [4, 16, 16, 16, 2]),
            ("classifier 2x16", [4, 16, 16, 1]),
            ("camera stop head 2x32", [4, 32, 32, 2]))


def best_of(fn, repeats):
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=8192)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    import torch
    from mi_neurallens.training.levenberg import FlatMLP
    torch.set_num_threads(a.threads)
    rng = np.random.default_rng(0)
    out = []
    print(f"| network | weights | jacobian, s | blocks, s | speed-up | max relative difference |")
    print("|---|---|---|---|---|---|")
    for name, dims in NETWORKS:
        layers = [(rng.normal(size=(b, i)) / np.sqrt(i), rng.normal(size=b) * 0.1) for i, b in zip(dims[:-1], dims[1:])]
        net = FlatMLP(torch, layers)
        theta = torch.stack([net.flatten(layers)])
        X = torch.as_tensor(rng.normal(size=(1, a.rows, dims[0])), dtype=torch.float32)
        s = torch.as_tensor(rng.uniform(0.5, 2.0, (1, a.rows, dims[-1])), dtype=torch.float32)
        r = torch.as_tensor(rng.normal(size=(1, a.rows, dims[-1])), dtype=torch.float32)

        def whole():
            _, J = net.jacobian(theta, X)
            Js = (J * s[..., None]).reshape(1, -1, net.P)
            return Js.transpose(1, 2) @ Js, (Js.transpose(1, 2) @ r.reshape(1, -1, 1))[..., 0]

        def blocks():
            return net.normal_equations(theta, net.activations(theta, X), s, r)

        with torch.no_grad():
            A0, _ = whole()
            A1, _ = blocks()
            diff = float((A1 - A0).abs().max() / A0.abs().max())
            t0 = best_of(whole, a.repeats)
            t1 = best_of(blocks, a.repeats)
        out.append({"network": name, "dims": dims, "weights": net.P, "rows": a.rows, "jacobian_s": t0, "blocks_s": t1,
                    "max_rel_diff": diff})
        print(f"| {name} | {net.P} | {t0:.3f} | {t1:.3f} | {t0 / t1:.2f}× | {diff:.1e} |")
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"threads": a.threads, "rows": a.rows, "results": out}, f, indent=1)


if __name__ == "__main__":
    main()
