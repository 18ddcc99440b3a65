"""The stacked trainer (training/stacked.py): K networks as one stack train as K independent networks
would — each map's gradient is its own, Adam is PyTorch's — and a map leaves the stack when it meets its
goals while the others go on."""
from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from mi_neurallens.training.config import NetConfig  # noqa: E402
from mi_neurallens.training.stacked import Problem, StackedAdam, StackedMLP, train_stack  # noqa: E402


def test_each_map_gets_its_own_gradient():
    """The summed loss of a stack differentiates into each map's own loss gradient (no cross-talk)."""
    net = StackedMLP(torch, "cpu", [1, 2, 3], 4, 5, 3, 16)
    x = torch.randn(3, 64, 4)
    y = torch.randn(3, 64, 5)
    ((net.forward(x) - y) ** 2).mean(-1).mean(-1).sum().backward()
    g_stack = [p.grad[1].clone() for p in net.params]
    for p in net.params:
        p.grad = None
    ((net.one(1)(x[1]) - y[1]) ** 2).mean().backward()
    for gs, p in zip(g_stack, net.params):
        torch.testing.assert_close(gs, p.grad[1], rtol=1e-5, atol=1e-7)
        assert float(p.grad[0].abs().max()) == 0.0 and float(p.grad[2].abs().max()) == 0.0


def test_stacked_adam_is_pytorch_adam_per_map():
    """A slice of the stack follows torch.optim.Adam's trajectory on the same gradients."""
    torch.manual_seed(0)
    w = torch.randn(2, 8, 4)
    ref = w[1].clone().requires_grad_()
    stacked = [w.clone().requires_grad_()]
    opt_ref = torch.optim.Adam([ref], lr=1e-2)
    opt = StackedAdam(stacked)
    for _ in range(20):
        g = torch.randn(2, 8, 4)
        stacked[0].grad = g.clone()
        opt.step(stacked, 1e-2)
        ref.grad = g[1].clone()
        opt_ref.step()
    torch.testing.assert_close(stacked[0][1].detach(), ref.detach(), rtol=1e-5, atol=1e-6)
    opt.take([1], torch)                 # a map leaving the stack keeps the others' moments
    assert opt.m[0].shape == (1, 8, 4)


class _Line(Problem):
    """A toy Problem: fit y = a·x (1 input, 1 output); goal: validation MSE."""

    POOL = {"X": "X", "Y": "Y"}

    def __init__(self, a, goal, seed):
        self.a, self.goal, self.net = a, goal, None
        self.rng = np.random.default_rng(seed)
        self.state = {"step": 0, "best_val": math.inf, "best_step": 0, "history": [], "evals_since_best": 0,
                      "seconds": 0.0, "samples": 0}
        x = torch.as_tensor(self.rng.uniform(-1, 1, (4096, 1)), dtype=torch.float32)
        self.X, self.Y = x, a * x
        self.xv = torch.linspace(-1, 1, 257)[:, None]

    def rows_loss(self, out, batch, const):
        return ((out - batch["Y"]) ** 2).mean(-1).mean(-1)

    def fresh_rows(self, k):
        x = torch.as_tensor(self.rng.uniform(-1, 1, (k, 1)), dtype=torch.float32)
        return {"X": x, "Y": self.a * x}

    def validate(self, step, loss, seconds):
        mse = float(((self.net(self.xv) - self.a * self.xv) ** 2).mean())
        self.state["history"].append({"step": step, "mse": mse})
        return mse, {}

    def goals_met(self):
        return self.state["history"][-1]["mse"] <= self.goal


def test_a_map_leaves_the_stack_at_its_goal_and_the_others_go_on(tmp_path):
    nc = NetConfig(hidden=2, width=16, lr=1e-2, batch=256, max_steps=600, eval_every=50, patience=10 ** 6,
                   warmup_steps=10, refresh_every=100, max_minutes=5.0, pool=4096)
    fits = [_Line(0.5, 1e-2, 1), _Line(-0.8, 0.0, 2)]          # the second goal is unreachable
    res = train_stack(torch, "cpu", fits, nc, seeds=[1, 2], n_in=1, n_out=1, keys=["a", "b"],
                      ckpt=str(tmp_path / "s.ckpt"), progress=False)
    a, b = (r["state"] for r in res)
    assert a["stop_reason"] == "goals" and a["step"] < nc.max_steps
    assert b["stop_reason"] == "max_steps" and b["step"] == nc.max_steps
    assert b["history"][-1]["mse"] < 1e-3                     # it kept learning after the first left
    # the best weights come back as model-file layers, (out, in) per layer
    assert [W.shape for W, _ in res[1]["layers"]] == [(16, 1), (16, 16), (1, 16)]
    # a rerun of the finished stack resumes from its checkpoint and does not train again
    again = train_stack(torch, "cpu", [_Line(0.5, 1e-2, 1), _Line(-0.8, 0.0, 2)], nc, seeds=[1, 2], n_in=1,
                        n_out=1, keys=["a", "b"], ckpt=str(tmp_path / "s.ckpt"), progress=False)
    for r0, r1 in zip(res, again):
        for (W0, _), (W1, _) in zip(r0["layers"], r1["layers"]):
            np.testing.assert_array_equal(W0, W1)


def test_a_cpu_splits_many_maps_into_stacks_that_fit_its_cache(monkeypatch, tmp_path):
    """On a CPU, maps × batch rows per step are capped (CPU_STACK_ROWS): more maps train as several stacks,
    one after the other, each map with the same result semantics."""
    import mi_neurallens.training.stacked as st
    monkeypatch.setattr(st, "CPU_STACK_ROWS", 256)
    assert st.stack_size("cpu", 256) == 1 and st.stack_size("cuda:0", 8192) > 1000
    nc = NetConfig(hidden=2, width=16, lr=1e-2, batch=256, max_steps=300, eval_every=50, patience=10 ** 6,
                   warmup_steps=10, refresh_every=100, max_minutes=5.0, pool=4096)
    res = train_stack(torch, "cpu", [_Line(0.5, 1e-2, 1), _Line(-0.8, 0.0, 2)], nc, seeds=[1, 2], n_in=1, n_out=1,
                      keys=["a", "b"], ckpt=str(tmp_path / "s.ckpt"), progress=False)
    assert [r["state"]["stack"] for r in res] == [0, 1]
    # a resume finds every map's state across the stacks' checkpoints (s.ckpt.0, s.ckpt.1)
    from mi_neurallens.training.stacked import peek_stack
    got = peek_stack(str(tmp_path / "s.ckpt"), ["a", "b"])
    assert sorted(got) == ["a", "b"] and got["b"]["stop_reason"] == "max_steps"
    assert res[0]["state"]["stop_reason"] == "goals" and res[1]["state"]["stop_reason"] == "max_steps"


def test_a_diverged_map_leaves_the_stack_with_its_best_weights_and_the_others_go_on(tmp_path):
    """A map whose loss turns non-finite stops ("diverged") at the next validation instead of holding its place
    in the stack until its patience runs out; its neighbours' gradients never see its NaNs."""
    nc = NetConfig(hidden=2, width=16, lr=1e-2, batch=256, max_steps=600, eval_every=50, patience=10 ** 6,
                   warmup_steps=10, refresh_every=100, max_minutes=5.0, pool=4096)
    bad = _Line(0.5, 1e-2, 3)
    bad.X[7, 0] = math.inf                        # one poisoned row: the first batch holding it gives NaN
    bad.rng = np.random.default_rng(3)
    fits = [_Line(0.5, 1e-2, 1), bad]
    res = train_stack(torch, "cpu", fits, nc, seeds=[1, 2], n_in=1, n_out=1, keys=["a", "b"], progress=False)
    a, b = (r["state"] for r in res)
    assert b["stop_reason"] == "diverged" and b["step"] < nc.max_steps
    assert a["stop_reason"] == "goals" and a["history"][-1]["mse"] <= 1e-2
    assert all(np.isfinite(W).all() and np.isfinite(c).all() for W, c in res[1]["layers"])
