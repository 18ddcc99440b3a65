"""PyTorch at hand for the trainers: the torch module (imported lazily, with its thread count), the device, a
plain ``torch.nn`` MLP and its layers in the model file's layout, and a network's training state before its
first step."""
from __future__ import annotations

import math


def load_torch(threads: int = 2):
    """``torch``, imported here (never at the package's import), using ``threads`` CPU threads (0: as it is)."""
    import torch
    if threads:
        torch.set_num_threads(int(threads))
    return torch


def pick_device(torch, want: str = "auto"):
    """The ``torch.device`` to train on: ``"auto"`` is CUDA where there is one, else the CPU."""
    if want == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(want)


def make_net(torch, n_in: int, n_out: int, hidden: int, width: int, activation: str):
    """A ``torch.nn.Sequential`` MLP: ``hidden`` layers of ``width`` units (``"tanh"`` or ``"relu"``), linear
    output."""
    nn = torch.nn
    act = {"tanh": nn.Tanh, "relu": nn.ReLU}[activation]
    layers, w = [], n_in
    for _ in range(hidden):
        layers += [nn.Linear(w, width), act()]
        w = width
    layers.append(nn.Linear(w, n_out))
    return nn.Sequential(*layers)


def net_layers(net) -> list:
    """[(W (out, in), b (out,)) float64 numpy] of a :func:`make_net` network: the model file's layout."""
    import torch
    return [(m.weight.detach().cpu().double().numpy(), m.bias.detach().cpu().double().numpy())
            for m in net if isinstance(m, torch.nn.Linear)]


def new_state() -> dict:
    """A network's training state before its first step (steps, best validation score, history, evaluations
    since the best, seconds, samples): what :func:`~mi_neurallens.training.stacked.train_stack` and the
    finish (:mod:`~mi_neurallens.training.levenberg`) update."""
    return {"step": 0, "best_val": math.inf, "best_step": 0, "history": [], "evals_since_best": 0,
            "seconds": 0.0, "samples": 0}
