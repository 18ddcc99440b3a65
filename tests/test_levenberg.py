"""The Levenberg–Marquardt finish of small maps (mi_neurallens/training/levenberg.py): its Jacobian, its
residuals against the losses Adam minimises, what it buys over Adam, and the trainer's use of it."""
from __future__ import annotations

import math
import types

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from mi_neurallens.training import levenberg  # noqa: E402
from mi_neurallens.training.levenberg import MAX_PARAMS, FlatMLP, finish, finish_stack, n_params  # noqa: E402


def random_layers(dims, seed=0):
    g = np.random.default_rng(seed)
    return [(g.uniform(-1, 1, (b, a)) / math.sqrt(a), g.uniform(-1, 1, b) / math.sqrt(a))
            for a, b in zip(dims[:-1], dims[1:])]


def test_jacobian_is_autograds():
    """The closed-form Jacobian (one backward pass per output through the stored activations) equals
    PyTorch's autograd, weight by weight, and the forward pass equals the model file's layout."""
    layers = random_layers([4, 7, 6, 3], seed=1)
    net = FlatMLP(torch, layers)
    theta = net.flatten(layers)
    assert net.P == n_params(layers) == theta.numel() == 4 * 7 + 7 + 7 * 6 + 6 + 6 * 3 + 3
    X = torch.as_tensor(np.random.default_rng(2).normal(size=(11, 4)))
    z, J = net.jacobian(theta, X)
    ref = torch.func.jacrev(lambda th: net.forward(th, X))(theta)            # (n, out, P)
    np.testing.assert_allclose(J.numpy(), ref.numpy(), rtol=1e-12, atol=1e-12)
    h = X.numpy()
    for k, (W, b) in enumerate(layers):
        h = h @ W.T + b
        h = np.tanh(h) if k < len(layers) - 1 else h
    np.testing.assert_allclose(z.numpy(), h, rtol=1e-12, atol=1e-12)
    # the flat vector goes back to the same layers
    for (W, b), (W0, b0) in zip(net.layers(theta), layers):
        np.testing.assert_array_equal(W, W0)
        np.testing.assert_array_equal(b, b0)



def gauss_newton_problem(dims, lead, *, rows, seed, net_seed):
    """A (stacked, when ``lead``) random network of ``dims`` in float64 and a Gauss–Newton system on ``rows``
    random rows: (net, θ (…, P), X (…, rows, in), s and r (…, rows, out))."""
    rng = np.random.default_rng(seed)
    nets = [random_layers(dims, seed=net_seed + k) for k in range(max(int(np.prod(lead)), 1))]
    net = FlatMLP(torch, nets[0])
    theta = torch.stack([net.flatten(lay) for lay in nets]).reshape(lead + (net.P,))
    X = torch.as_tensor(rng.normal(size=lead + (rows, dims[0])))
    s = torch.as_tensor(rng.uniform(0.2, 2.0, lead + (rows, dims[-1])))
    r = torch.as_tensor(rng.normal(size=lead + (rows, dims[-1])))
    return net, theta, X, s, r


@pytest.mark.parametrize("dims, lead", [([4, 7, 6, 3], ()), ([4, 16, 16, 16, 6], (2,)), ([3, 300, 1], (1,))])
def test_normal_equations_are_the_jacobians(dims, lead):
    """JᵀJ and Jᵀr formed from the hidden layers' columns and the output layer's per-output blocks (what the
    finish solves each iteration) equal those of the whole scaled Jacobian J[n, o, :] = s[n, o] · ∂z_o/∂θ —
    unstacked and stacked, with one output, and with more hidden columns than one Gram panel
    (levenberg.GRAM_BLOCK) — and the activations end in the network's outputs."""
    net, theta, X, s, r = gauss_newton_problem(dims, lead, rows=37, seed=3, net_seed=4)
    z, J = net.jacobian(theta, X)
    Js = (J * s[..., None]).reshape(lead + (-1, net.P))
    want_A = Js.transpose(-1, -2) @ Js
    want_g = (Js.transpose(-1, -2) @ r.reshape(lead + (-1, 1)))[..., 0]
    hs = net.activations(theta, X)
    A, g = net.normal_equations(theta, hs, s, r)
    np.testing.assert_allclose(hs[-1].numpy(), z.numpy(), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(A.numpy(), want_A.numpy(), rtol=1e-10, atol=1e-10 * float(want_A.abs().max()))
    np.testing.assert_allclose(g.numpy(), want_g.numpy(), rtol=1e-10, atol=1e-10 * float(want_g.abs().max()))


@pytest.mark.parametrize("dims, lead", [([4, 16, 16, 16, 5], ()), ([4, 16, 16, 16, 6], (2,)), ([3, 300, 1], (1,))])
def test_float32_normal_equations_through_onednn(dims, lead, monkeypatch):
    """In float32 on a CPU the Jacobian is stored column by column and its Gram taken by oneDNN
    (levenberg._gram_columns): the same JᵀJ and Jᵀr as the float64 closed form, to float32 rounding, and as the
    row-major MKL path (MI_NEURALLENS_ONEDNN=0)."""
    if not levenberg._onednn_gram(torch, torch.zeros(1)):
        pytest.skip("no oneDNN linear in this PyTorch")
    net, theta, X, s, r = gauss_newton_problem(dims, lead, rows=300, seed=5, net_seed=8)
    A64, g64 = net.normal_equations(theta, net.activations(theta, X), s, r)
    hs32 = net.activations(theta, X.float())
    A32, g32 = net.normal_equations(theta, hs32, s.float(), r.float())
    for got, want in ((A32, A64), (g32, g64)):
        np.testing.assert_allclose(got.double().numpy(), want.numpy(), rtol=0, atol=2e-5 * float(want.abs().max()))
    monkeypatch.setenv("MI_NEURALLENS_ONEDNN", "0")
    A_mkl, g_mkl = net.normal_equations(theta, hs32, s.float(), r.float())
    np.testing.assert_allclose(A32.numpy(), A_mkl.numpy(), rtol=0, atol=2e-6 * float(A_mkl.abs().max()))
    np.testing.assert_allclose(g32.numpy(), g_mkl.numpy(), rtol=0, atol=2e-6 * float(g_mkl.abs().max()))


class SmoothMap:
    """A stand-in map problem: fit f(x) = (sin(x₀ + x₁²), x₂·x₃ + cos(x₀)) over [−1, 1]⁴ from fresh rows,
    validated on a fixed held-out set (RMS error)."""

    def __init__(self, goal=0.0, seed=7):
        self.rng = np.random.default_rng(seed)
        self.state = {"history": [], "step": 0, "seconds": 0.0, "samples": 0}
        self.goal = goal
        self.Xv = torch.as_tensor(self.rng.uniform(-1, 1, (4000, 4)), dtype=torch.float32)
        self.Yv = self.f(self.Xv)

    @staticmethod
    def f(X):
        return torch.stack([torch.sin(X[:, 0] + X[:, 1] ** 2), X[:, 2] * X[:, 3] + torch.cos(X[:, 0])], 1)

    def fresh_rows(self, n):
        X = torch.as_tensor(self.rng.uniform(-1, 1, (n, 4)), dtype=torch.float32)
        return {"X": X, "Y": self.f(X)}

    def lm_residual(self, z, batch):
        return z - batch["Y"].to(z.dtype), torch.ones_like(z)

    def validate(self, step, loss, seconds):
        rms = float(((self.net(self.Xv) - self.Yv) ** 2).mean().sqrt())
        self.state["history"].append({"step": step, "rms": rms})
        return rms, {}

    def goals_met(self):
        return self.state["history"][-1]["rms"] <= self.goal


def test_levenberg_marquardt_fits_far_beyond_adam():
    """From the same random 2×16 network, 60 Levenberg–Marquardt iterations on 1024 fresh rows each
    reach a held-out error far below 3000 Adam steps on batches of the same size (50× the iterations),
    and the history, samples and stop reason are recorded."""
    layers = random_layers([4, 16, 16, 2], seed=3)
    nc = types.SimpleNamespace(lm_rows=1024, lm_eval_every=10, stop_at_goals=True, patience=100)
    prob = SmoothMap()
    got = finish(torch, prob, layers, nc, seconds=1e9, max_iterations=60)
    lm = prob.state["history"][-1]["rms"]
    assert prob.state["history"][0]["rms"] > 0.3                   # the random start
    assert [h["phase"] for h in prob.state["history"]] == ["lm"] * 7
    assert prob.state["lm"]["iterations"] == 60 and prob.state["samples"] == 60 * 1024
    assert prob.state["lm"]["stop_reason"] == "max_iterations"
    # Adam, PyTorch's, same start, lr 3e-3 (the trainer's default), 3000 steps of 1024 fresh rows
    net = FlatMLP(torch, layers)
    theta = net.flatten(layers).float().requires_grad_()
    opt = torch.optim.Adam([theta], lr=3e-3)
    adam = SmoothMap()
    for _ in range(3000):
        b = adam.fresh_rows(1024)
        loss = ((net.forward(theta, b["X"]) - b["Y"]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    adam.net = lambda x: net.forward(theta.detach(), x)
    rms_adam, _ = adam.validate(0, None, 0.0)
    assert lm < 0.2 * rms_adam, (lm, rms_adam)
    assert lm < 2e-3
    # the returned layers are the best validated ones, and a goal stops it early
    best = FlatMLP(torch, got)
    np.testing.assert_allclose(float(((best.forward(best.flatten(got), prob.Xv.double()) - prob.Yv.double()) ** 2)
                                     .mean().sqrt()), min(h["rms"] for h in prob.state["history"]), rtol=1e-3)
    early = SmoothMap(goal=0.05)
    finish(torch, early, layers, nc, seconds=1e9, max_iterations=60)
    assert early.state["lm"]["stop_reason"] == "goals" and early.state["lm"]["iterations"] < 60


def test_a_stack_finishes_each_network_as_alone():
    """Three networks finished as one stack (batched Jacobians and solves, what a GPU runs) end where each
    ends finished alone: the same weights, validations, iterations and stop reasons — also when one meets
    its goal early and leaves the stack, and with a Jacobian of stacked networks equal to each one's."""
    nc = types.SimpleNamespace(lm_rows=512, lm_eval_every=5, stop_at_goals=True, patience=100)
    starts = [random_layers([4, 16, 16, 2], seed=s) for s in (3, 4, 5)]
    goals = [0.0, 0.08, 0.0]
    alone = [SmoothMap(goal=g, seed=10 + j) for j, g in enumerate(goals)]
    want = [finish(torch, m, lay, nc, seconds=1e9, max_iterations=25) for m, lay in zip(alone, starts)]
    stacked = [SmoothMap(goal=g, seed=10 + j) for j, g in enumerate(goals)]
    got = finish_stack(torch, stacked, starts, nc, seconds=1e9, max_iterations=25)
    assert alone[1].state["lm"]["stop_reason"] == "goals" and alone[1].state["lm"]["iterations"] < 25
    for a, b, w, g in zip(alone, stacked, want, got):
        assert a.state["lm"]["stop_reason"] == b.state["lm"]["stop_reason"]
        assert a.state["lm"]["iterations"] == b.state["lm"]["iterations"]
        assert b.state["lm"]["stacked_with"] == 3
        np.testing.assert_allclose([h["rms"] for h in b.state["history"]], [h["rms"] for h in a.state["history"]],
                                   rtol=1e-4)
        # the same function (float32 Jacobians summed in another order move the weights along flat
        # directions of the loss by ~1e-3, not the outputs)
        fw, fg = FlatMLP(torch, w), FlatMLP(torch, g)
        Xv = a.Xv.double()
        np.testing.assert_allclose(fg.forward(fg.flatten(g), Xv).numpy(), fw.forward(fw.flatten(w), Xv).numpy(),
                                   atol=2e-4)
    net = FlatMLP(torch, starts[0])
    theta = torch.stack([net.flatten(lay) for lay in starts])
    X = torch.as_tensor(np.random.default_rng(1).normal(size=(3, 9, 4)))
    z, J = net.jacobian(theta, X)
    for k in range(3):
        z1, J1 = net.jacobian(theta[k], X[k])
        np.testing.assert_allclose(J[k].numpy(), J1.numpy(), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(z[k].numpy(), z1.numpy(), rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="one shape"):
        finish_stack(torch, stacked[:2], [starts[0], random_layers([4, 8, 2])], nc, seconds=1.0)


def test_trainer_finishes_in_stacks_of_one_shape(monkeypatch):
    """:func:`finish_results` stacks the networks to finish by architecture (a finish-only run's base may mix 2×16 and
    2×8 maps), in stacks of :func:`lm_stack_size` (one on a CPU; several on a GPU, forced here), and each
    network ends as it would alone; a network that met its goals under Adam is left as it is."""
    assert levenberg.lm_stack_size("cpu", 8192, 5, 709) == 1
    assert levenberg.lm_stack_size("cuda:0", 8192, 5, 709) >= 32        # a lens's ghost regressors in one stack
    nc = types.SimpleNamespace(lm_minutes=1e6, lm_max_weights=MAX_PARAMS, lm_iterations=12, lm_rows=512,
                               lm_eval_every=4, stop_at_goals=True, patience=100)
    dims = [[4, 16, 16, 2], [4, 8, 8, 2], [4, 16, 16, 2], [4, 16, 16, 2]]
    starts = [random_layers(d, seed=20 + j) for j, d in enumerate(dims)]

    def run(stack):
        monkeypatch.setattr(levenberg, "lm_stack_size", lambda *a: stack)
        fits = [SmoothMap(seed=30 + j) for j in range(4)]
        res = [{"layers": lay, "state": fits[j].state} for j, lay in enumerate(starts)]
        res[3]["state"]["stop_reason"] = "goals"
        levenberg.finish_results(torch, fits, res, nc, [f"forward.{j}" for j in range(4)])
        return fits, res

    alone, res1 = run(1)
    stacked, res2 = run(8)
    assert [f.state["lm"]["stacked_with"] for f in stacked[:3]] == [2, 1, 2]
    assert "lm" not in stacked[3].state and res2[3]["layers"] is starts[3]
    for a, b in zip(alone[:3], stacked[:3]):
        assert a.state["lm"]["iterations"] == b.state["lm"]["iterations"] == 12
        np.testing.assert_allclose([h["rms"] for h in b.state["history"]], [h["rms"] for h in a.state["history"]],
                                   rtol=1e-4)


def test_residuals_are_the_losses_adam_minimises():
    """The regressor's residuals square to its weighted MSE (:meth:`RegressorFit.rows_loss` without the
    cosine term), edge weights included; the classifier's to its margin interval loss."""
    from mi_neurallens.training.classifier import ClassifierFit
    from mi_neurallens.training.regressor import RegressorFit
    g = np.random.default_rng(4)
    n = 500
    X = torch.as_tensor(g.normal(size=(n, 4)), dtype=torch.float64)
    batch = {"X": X, "Y": torch.as_tensor(g.normal(size=(n, 5))), "Yraw": torch.as_tensor(g.normal(size=(n, 5))),
             "W": torch.as_tensor(g.uniform(1, 3, n))}
    z = torch.as_tensor(g.normal(size=(n, 5)))
    fit = types.SimpleNamespace(torch=torch, W=torch.as_tensor(g.uniform(0.1, 2, 5)), odd_s=0.3, wy_c=0.1,
                                wy_s=0.2, nc=types.SimpleNamespace(direction_loss="mse"), huber_delta=None)
    fit.M_of = lambda xb, const=None: RegressorFit.M_of(fit, xb, const)
    const = {"W": fit.W[None], "wy_c": torch.tensor([0.1]), "wy_s": torch.tensor([0.2]), "odd_s": torch.tensor([0.3])}
    r, s = RegressorFit.lm_residual(fit, z, batch)
    loss = RegressorFit.rows_loss(fit, z, batch, const)
    np.testing.assert_allclose(float((r ** 2).sum(1).mean() / 5), float(loss), rtol=1e-7)   # float32 constants
    # ∂r/∂z is the column scale (the residual is linear in z)
    r2, _ = RegressorFit.lm_residual(fit, z + 1e-3, batch)
    np.testing.assert_allclose(((r2 - r) / 1e-3).numpy(), s.numpy(), rtol=1e-6)
    # classifier: the interval loss, 0 inside the band, one-sided at the clips
    cf = types.SimpleNamespace(torch=torch, margin=True, nc=types.SimpleNamespace(margin_clip=3.0))
    t = torch.as_tensor(np.concatenate([g.uniform(-2.9, 2.9, n - 100), np.full(50, 3.0), np.full(50, -3.0)]))
    logit = torch.as_tensor(g.normal(scale=4.0, size=n))
    r, s = ClassifierFit.lm_residual(cf, logit[:, None], {"L": t})
    np.testing.assert_allclose(float((r ** 2).mean()), float(ClassifierFit.margin_loss(cf, logit, t)), rtol=1e-12)
    assert set(np.unique(s.numpy())) <= {0.0, 1.0}
    cf.margin = False
    from mi_neurallens import NeuralLensError
    with pytest.raises(NeuralLensError, match="margin target"):
        ClassifierFit.lm_residual(cf, logit[:, None], {"L": t})


def test_huber_residuals_square_to_the_huber_loss():
    """``huber_residual``: r'² is ρ(r) (r² within δ, 2δ|r| − δ² beyond), its slope is ∂r'/∂r, continuous at δ;
    a regressor's residuals with ``lm_huber`` square to ρ of its weighted residuals, and its finish fixes δ at
    ``lm_huber`` × the held-out median and validates by the same loss."""
    from mi_neurallens.training.regressor import RegressorFit, huber_residual
    g = np.random.default_rng(5)
    r = torch.as_tensor(g.normal(scale=3.0, size=(400, 5)))
    delta = torch.as_tensor(g.uniform(0.5, 2.0, 5))
    rr, slope = huber_residual(torch, r, delta)
    a = r.abs()
    rho = torch.where(a <= delta, r * r, 2 * delta * a - delta * delta)
    np.testing.assert_allclose((rr ** 2).numpy(), rho.numpy(), rtol=1e-12)
    assert bool((torch.sign(rr) == torch.sign(r)).all())
    h = 1e-6
    fd = (huber_residual(torch, r + h, delta)[0] - huber_residual(torch, r - h, delta)[0]) / (2 * h)
    np.testing.assert_allclose(fd.numpy(), slope.numpy(), rtol=1e-5, atol=1e-8)
    at = huber_residual(torch, delta[None] * (1 + torch.tensor([[-1e-9], [1e-9]], dtype=torch.float64)), delta)
    np.testing.assert_allclose(at[0][0].numpy(), at[0][1].numpy(), rtol=1e-8)
    np.testing.assert_allclose(at[1].numpy(), 1.0, rtol=1e-7)
    # the regressor: δ from the held-out residuals at the finish's start, the residuals and score from it
    n = 600
    Xv = torch.as_tensor(g.normal(size=(n, 4)))
    Yv = torch.as_tensor(g.standard_t(2.0, size=(n, 5)))          # heavy tails, as a map's errors have
    fit = types.SimpleNamespace(torch=torch, W=torch.as_tensor(g.uniform(0.1, 2, 5)), odd_s=None, Xv=Xv, Yv=Yv,
                                nc=types.SimpleNamespace(lm_huber=1.5, direction_loss="mse"), state={},
                                huber_delta=None)
    fit.M_of = lambda xb, const=None: torch.ones(xb.shape[:-1] + (5,), dtype=xb.dtype)
    fit.predict = lambda xb: (fit.net(xb), fit.M_of(xb))
    fit.huber_medians = lambda pv: RegressorFit.huber_medians(fit, pv)
    RegressorFit.lm_start(fit, lambda x: 0.1 * x[:, :1].expand(-1, 5))
    rv = torch.sqrt(fit.W) * (0.1 * Xv[:, :1] - Yv)
    np.testing.assert_allclose(fit.huber_delta.numpy(), 1.5 * rv.abs().median(0).values.numpy(), rtol=1e-12)
    assert fit.state["lm_huber_delta"] == fit.huber_delta.tolist()
    pv = 0.1 * Xv[:, :1].expand(-1, 5)
    rho_v = huber_residual(torch, rv, fit.huber_delta)[0] ** 2
    np.testing.assert_allclose(RegressorFit.score(fit, pv), float(rho_v.mean()), rtol=1e-12)
    batch = {"X": Xv, "Y": Yv}
    z = torch.as_tensor(g.normal(size=(n, 5)))
    r1, s1 = RegressorFit.lm_residual(fit, z, batch)
    plain = torch.sqrt(fit.W) * (z - Yv)
    np.testing.assert_allclose((r1 ** 2).numpy(), huber_residual(torch, plain, fit.huber_delta)[0].numpy() ** 2,
                               rtol=1e-12)
    r2, _ = RegressorFit.lm_residual(fit, z + h, batch)
    r0, _ = RegressorFit.lm_residual(fit, z - h, batch)
    np.testing.assert_allclose(((r2 - r0) / (2 * h)).numpy(), s1.numpy(), rtol=1e-5, atol=1e-8)
    # without lm_huber nothing is fixed and the score is the mean square
    fit.nc.lm_huber, fit.huber_delta = 0.0, None
    RegressorFit.lm_start(fit, fit.net)
    assert fit.huber_delta is None
    np.testing.assert_allclose(RegressorFit.score(fit, pv), float(((pv - Yv) ** 2).mean()), rtol=1e-12)


class ContaminatedMap(SmoothMap):
    """:class:`SmoothMap` whose rows carry heavy-tailed noise (Student's t, 1.5 degrees of freedom, scale 0.02) in
    every target: its clean held-out targets judge the fit by the median error.  ``delta``: the finish minimises
    the Huber loss with that threshold (None: the squares)."""

    def __init__(self, delta=None, seed=7):
        super().__init__(seed=seed)
        self.delta = delta

    def fresh_rows(self, n):
        b = super().fresh_rows(n)
        b["Y"] = b["Y"] + 0.02 * torch.as_tensor(self.rng.standard_t(1.5, size=tuple(b["Y"].shape)), dtype=b["Y"].dtype)
        return b

    def lm_residual(self, z, batch):
        from mi_neurallens.training.regressor import huber_residual
        r = z - batch["Y"].to(z.dtype)
        if self.delta is None:
            return r, torch.ones_like(z)
        return huber_residual(torch, r, self.delta)

    def validate(self, step, loss, seconds):
        med = float((self.net(self.Xv) - self.Yv).abs().median())
        self.state["history"].append({"step": step, "rms": med})
        return med, {}


def test_a_huber_finish_fits_the_bulk_where_squares_chase_the_tail():
    """With heavy-tailed errors in the rows, the same 40 finish iterations from the same start reach a lower
    median error on the Huber loss (δ = 0.02, the noise's scale) than on the squares: what ``lm_huber`` does for a
    map whose goals are medians."""
    layers = random_layers([4, 16, 16, 2], seed=3)
    nc = types.SimpleNamespace(lm_rows=1024, lm_eval_every=10, stop_at_goals=False, patience=100)
    med = {}
    for name, delta in (("squares", None), ("huber", 0.02)):
        prob = ContaminatedMap(delta)
        got = finish(torch, prob, layers, nc, seconds=1e9, max_iterations=40)
        net = FlatMLP(torch, got)
        med[name] = float((net.forward(net.flatten(got), prob.Xv.double()) - prob.Yv.double()).abs().median())
    assert med["huber"] < 0.7 * med["squares"], med


class FollowingHuberMap(ContaminatedMap):
    """:class:`ContaminatedMap` whose finish runs on the regressor's own Huber machinery: δ fixed by
    ``RegressorFit.lm_start`` at ``lm_huber`` × the held-out median residual, the score, and, with ``refix`` > 0,
    δ fixed anew by ``RegressorFit.lm_refix`` as the residuals fall (unit column weights, the network's outputs the
    predictions)."""

    def __init__(self, refix, seed=7):
        super().__init__(seed=seed)
        self.torch, self.W = torch, torch.ones(2, dtype=torch.float64)
        self.nc = types.SimpleNamespace(lm_huber=0.5, lm_huber_refix=refix, lm_cell_weight=0.0)

    from mi_neurallens.training.regressor import RegressorFit as _R
    lm_start, lm_refix, huber_medians, score = _R.lm_start, _R.lm_refix, _R.huber_medians, _R.score
    scores_by_cell = _R.scores_by_cell
    huber_delta = last_pv = None
    cells: dict = {}
    del _R

    def predict(self, X):
        return self.net(X).double(), None

    def lm_residual(self, z, batch):
        from mi_neurallens.training.regressor import huber_residual
        return huber_residual(torch, z - batch["Y"].to(z.dtype), self.huber_delta.to(z.dtype))

    def validate(self, step, loss, seconds):
        pv, _ = self.predict(self.Xv)
        self.last_pv = pv
        med = float((pv - self.Yv).abs().median())
        self.state["history"].append({"step": step, "median": med, "delta": self.huber_delta.tolist()})
        return self.score(pv), {}


def test_a_huber_threshold_that_follows_the_residuals_fits_the_bulk_tighter():
    """``lm_huber_refix``: δ, fixed at the finish's start from a random network's residuals, lies far above the
    finished map's, where the Huber loss is the squares again; fixed anew whenever a column's median residual has
    fallen 1.5 times, the same 60 iterations from the same start reach a lower median error on the heavy-tailed rows
    (0.6x on this problem).  ``lm_refix`` leaves δ alone before the residuals have fallen that far, and with
    ``lm_huber_refix`` = 0; where it fixes δ anew it returns the score of the same predictions under the new δ."""
    layers = random_layers([4, 16, 16, 2], seed=3)
    nc = types.SimpleNamespace(lm_rows=1024, lm_eval_every=5, stop_at_goals=False, patience=100)
    med, probs = {}, {}
    for refix in (0.0, 1.5):
        probs[refix] = prob = FollowingHuberMap(refix)
        Yv = prob.Yv.double()
        prob.Yv = Yv
        got = finish(torch, prob, layers, nc, seconds=1e9, max_iterations=60)
        net = FlatMLP(torch, got)
        med[refix] = float((net.forward(net.flatten(got), prob.Xv.double()) - Yv).abs().median())
    fixed, follow = probs[0.0].state, probs[1.5].state
    assert "lm_huber_refixes" not in fixed
    assert len({tuple(h["delta"]) for h in fixed["history"]}) == 1
    assert follow["lm_huber_refixes"] >= 2
    d0, d1 = np.array(follow["history"][0]["delta"]), np.array(follow["lm_huber_delta"])
    assert (d1 < d0 / 1.5 ** 2).any(), (d0, d1)               # δ came down with the residuals
    assert med[1.5] < 0.8 * med[0.0], med
    # lm_refix itself: nothing until some column's median has fallen 1.5 times; then δ and the score anew
    prob = FollowingHuberMap(1.5)
    prob.Yv = prob.Yv.double()
    prob.net = lambda X: torch.zeros(X.shape[0], 2, dtype=torch.float64)
    prob.lm_start(prob.net)
    delta0 = prob.huber_delta.clone()
    prob.last_pv = prob.Yv * (1 - 1 / 1.4)                     # residuals 1/1.4 of the start's: not yet
    assert prob.lm_refix() is None and torch.equal(prob.huber_delta, delta0)
    prob.last_pv = prob.Yv * (1 - 1 / 1.6)
    s = prob.lm_refix()
    np.testing.assert_allclose(prob.huber_delta.numpy(), delta0.numpy() / 1.6, rtol=1e-9)
    assert s == prob.score(prob.last_pv) and prob.state["lm_huber_refixes"] == 1
    # kept by the worst cell (lm_cell_weight), the best score does not depend on δ: δ follows, the score stays
    prob.cells, prob.nc.lm_cell_weight = {"wide, inf": np.arange(10)}, 1.0
    prob.last_pv = prob.Yv * (1 - 1 / (1.6 * 1.6))
    assert prob.lm_refix() is None and prob.state["lm_huber_refixes"] == 2
    np.testing.assert_allclose(prob.huber_delta.numpy(), delta0.numpy() / 1.6 ** 2, rtol=1e-9)
    prob.nc.lm_huber_refix = 0.0
    prob.last_pv = prob.Yv * 0.9
    assert prob.lm_refix() is None


class WeightedMap(SmoothMap):
    """Two columns that one hidden unit cannot both fit, ``(tanh 2x₀, tanh 2x₁)``, the finish weighing them by ``w``
    (the regressor's column weights, ``RegressorFit.W``)."""

    def __init__(self, w, seed=7):
        super().__init__(seed=seed)
        self.sw = torch.sqrt(torch.as_tensor(w, dtype=torch.float64))

    @staticmethod
    def f(X):
        return torch.tanh(2 * X[:, :2])

    def lm_residual(self, z, batch):
        sw = self.sw.to(z.dtype)
        return sw * (z - batch["Y"].to(z.dtype)), sw.expand_as(z)

    def validate(self, step, loss, seconds):
        col = ((self.net(self.Xv) - self.Yv) ** 2).mean(0)
        self.state["history"].append({"step": step, "rms": float(col.max().sqrt())})
        return float((self.sw.float() ** 2 * col).sum()), {}


def test_direction_weight_trades_position_accuracy_for_direction_accuracy():
    """``NetConfig.direction_weight`` multiplies the direction columns' loss weights (and nothing else) before the
    weights are normalised; a finish whose network cannot fit every column then fits the heavier ones better and
    the others worse: how a zoom map whose position meets its goal with room to spare (0.8 of it) and whose
    direction misses it (1.2) is balanced."""
    from mi_neurallens.training.config import NetConfig
    from mi_neurallens.training.outputs import loss_weights
    assert NetConfig().direction_weight == 1.0
    oscale, y = np.array([0.5, 0.4, 0.01, 0.008, 0.02]), np.full((8, 5), 0.9)
    w1, w2 = loss_weights("goals", oscale, y), loss_weights("goals", oscale, y, 2.0)
    np.testing.assert_allclose(w2[2:4] / w2[:2], 2.0 * w1[2:4] / w1[:2], rtol=1e-12)   # directions over positions
    np.testing.assert_allclose(w2[0] / w2[1], w1[0] / w1[1], rtol=1e-12)
    assert w1[4] == w2[4] == 0.05                                                       # T keeps its floor
    np.testing.assert_allclose(loss_weights("uniform", oscale, y, 3.0), np.array([1, 1, 3, 3, 1]) / 1.8)
    # the trade, through the finish itself: a 4-1-2 network from the same start, either column weighed 8
    layers = random_layers([4, 1, 2], seed=3)
    nc = types.SimpleNamespace(lm_rows=1024, lm_eval_every=10, stop_at_goals=False, patience=100)
    cols = {}
    for heavy in (0, 1):
        prob = WeightedMap([8.0 if c == heavy else 1.0 for c in (0, 1)])
        got = finish(torch, prob, layers, nc, seconds=1e9, max_iterations=40)
        net = FlatMLP(torch, got)
        cols[heavy] = ((net.forward(net.flatten(got), prob.Xv.double()) - prob.Yv.double()) ** 2).mean(0).sqrt()
    assert cols[0][0] < 0.3 * cols[1][0] and cols[1][1] < 0.3 * cols[0][1], cols


def test_stop_head_residuals_are_its_weighted_loss():
    """The stop head's residuals square to its column-weighted MSE, stacked or not; ``goals`` weights follow
    each column's spread (mm), so the µm error of a wide column counts as much as a narrow one's."""
    from mi_neurallens import NeuralLensError
    from mi_neurallens.training.stop_head import StopFit, stop_loss_weights
    oscale = np.array([1.3, 0.05, 0.24, 0.13, 1.2, 0.42])
    w = stop_loss_weights("goals", oscale)
    np.testing.assert_allclose(w, np.maximum(oscale / oscale.mean(), 0.05))
    assert w[0] > 14 * w[1]
    assert stop_loss_weights("goals", [1.0, 1e-4])[1] == 0.05          # no column is ignored
    np.testing.assert_array_equal(stop_loss_weights("uniform", oscale), np.ones(6))
    with pytest.raises(NeuralLensError, match="loss_weights"):
        stop_loss_weights("physical", oscale)
    g = np.random.default_rng(5)
    n = 400
    fit = types.SimpleNamespace(torch=torch, W=torch.as_tensor(w), k=3, wy_c=0.1, wy_s=0.2, s_max=0.7,
                                f32=lambda a: torch.as_tensor(np.asarray(a, np.float64)))
    fit.M_of = lambda xb, const=None: StopFit.M_of(fit, xb, const)
    batch = {"X": torch.as_tensor(g.normal(size=(n, 4))), "Y": torch.as_tensor(g.normal(size=(n, 6)))}
    z = torch.as_tensor(g.normal(size=(n, 6)))
    r, s = StopFit.lm_residual(fit, z, batch)
    loss = StopFit.rows_loss(fit, z, batch, StopFit.constants(fit))
    np.testing.assert_allclose(float((r ** 2).sum(1).mean() / 6), float(loss), rtol=1e-12)
    r2, _ = StopFit.lm_residual(fit, z + 1e-3, batch)
    np.testing.assert_allclose(((r2 - r) / 1e-3).numpy(), s.numpy(), rtol=1e-6)
    # a stack of two maps: each map's loss with its own weights and its own ωy normalisation (input_box)
    other = types.SimpleNamespace(**{**vars(fit), "wy_c": 0.3, "wy_s": 0.05})
    const = {"W": torch.stack([fit.W[None], torch.ones(1, 6, dtype=torch.float64)]),
             "WY": torch.stack([StopFit.constants(fit)["WY"], StopFit.constants(other)["WY"]])}
    both = StopFit.rows_loss(fit, torch.stack([z, z]), {k: torch.stack([v, v]) for k, v in batch.items()}, const)
    np.testing.assert_allclose(float(both[0]), float(loss), rtol=1e-12)
    plain = ((z * StopFit.M_of(other, batch["X"]) - batch["Y"]) ** 2).mean()
    np.testing.assert_allclose(float(both[1]), float(plain), rtol=1e-12)
    assert abs(float(plain) - float(((z * fit.M_of(batch["X"]) - batch["Y"]) ** 2).mean())) > 1e-3


def test_a_stop_head_trained_on_its_input_box_folds_into_the_same_function():
    """input_box normalises over the valid rays' box (λ kept); fold_input_box turns a head on that box into the
    same function of the map's normalised inputs (first layer and skip absorb the affine change)."""
    from mi_neurallens.neural.mlp import mlp_np
    from mi_neurallens.training.input_box import INPUT_BOX_MARGIN, fold_input_box, input_box
    g = np.random.default_rng(8)
    c, s = np.array([16.8, 0.0, 0.35, 595.0]), np.array([16.8, 0.71, 0.35, 235.0])
    x = np.stack([g.uniform(0, 31.6, 5000), g.uniform(-0.7, 0.16, 5000), g.uniform(0, 0.17, 5000),
                  g.uniform(360, 830, 5000)], 1)
    cb, sb = input_box(x, c, s)
    assert cb[3] == c[3] and sb[3] == s[3]
    xb = (x - cb) / sb
    assert np.abs(xb[:, :3]).max() <= 1.0 / (1.0 + 2.0 * INPUT_BOX_MARGIN) + 1e-12
    assert np.abs(xb[:, :3]).max() > 0.95 / (1.0 + 2.0 * INPUT_BOX_MARGIN)
    layers = random_layers([4, 16, 16, 6])
    skip, shift = g.normal(size=(6, 4)), g.normal(size=6)
    head = lambda L, sk, sh, xn: mlp_np(xn, L) + xn @ sk.T + sh
    L2, sk2, sh2 = fold_input_box(layers, skip, shift, (cb, sb), (c, s))
    np.testing.assert_allclose(head(L2, sk2, sh2, (x - c) / s), head(layers, skip, shift, xb), rtol=1e-10, atol=1e-10)


def test_large_networks_are_left_to_adam(capsys):
    """A 5×32 regressor has more weights than the finish handles; the trainer records why it skipped, and says
    so (a recipe's lm_minutes for it buy nothing)."""
    from mi_neurallens.training.levenberg import finish_results
    layers = random_layers([4] + [32] * 5 + [5])
    assert n_params(layers) > MAX_PARAMS
    res = [{"layers": layers, "state": {"history": [], "stop_reason": "time_budget"}}]
    nc = types.SimpleNamespace(lm_minutes=1.0, lm_max_weights=MAX_PARAMS)
    finish_results(torch, [object()], res, nc, ["forward.12"])
    assert res[0]["state"]["lm"] == {"skipped": f"{n_params(layers)} weights > {MAX_PARAMS}"}
    assert "forward.12: the Levenberg-Marquardt finish skips this network" in capsys.readouterr().err


def test_trainer_finishes_small_networks_and_a_finish_only_run_finishes_a_model(tmp_path):
    """On a thick lens's camera map: the same Adam run, then 35 iterations of the finish, gives a regressor
    and a margin classifier far better than Adam's alone; ``finish_only = "maps"`` runs only the finish from a
    trained map (its stop head kept, its Adam history carried, the finish's validations after it); refining
    with no finish time is a clear error."""
    import dataclasses
    from mi_neurallens import NeuralLensError
    from mi_neurallens.transport import planes as plan
    from mi_neurallens.training.config import load_config
    from mi_neurallens.training.maps import train_map
    from test_training import thick_lens
    lens = thick_lens()
    s0, _ = plan.sensor_distance_range(lens, 500.0)
    z_front, z_rear = plan.planes(lens, s0)
    dom = plan.backward_domain(lens, 0, z_rear, z_front, np.random.default_rng(0), n=1 << 18)
    small = dict(hidden=2, width=16, batch=1024, pool=40000, refresh_every=200, eval_every=100, max_minutes=1.0,
                 warmup_steps=20, patience=100, lr=1e-2, lm_rows=2048, lm_eval_every=5, lm_minutes=0.0)
    over = {"regressor": dict(small, max_steps=400), "stop": dict(small, max_steps=200),
            "classifier": dict(small, max_steps=400, target="margin"), "heldout": 20000, "threads": 1}
    cfg = load_config(overrides=over)
    adam = train_map(lens, 0, "backward", z_rear, z_front, dom, cfg, None, progress=False, eval_n=20000)
    fin = dict(lm_minutes=10.0, lm_iterations=35)       # a count, not the clock: the same on every machine
    cfg_lm = load_config(overrides={**over, "regressor": dict(over["regressor"], **fin),
                                    "classifier": dict(over["classifier"], **fin)})
    # finish_only = "maps": only the finish, from the Adam map: what a whole run does after the same Adam run (one
    # run with both, Adam then the finish: test_commands_reports.py::test_train_command_keeps_the_bundled_regressor)
    ref = train_map(lens, 0, "backward", z_rear, z_front, dom, cfg_lm, str(tmp_path), progress=False, eval_n=20000,
                    finish_only="maps", base=adam)
    ra, rl = adam.metrics["regressor"], ref.metrics["regressor"]
    assert ref.training["regressor_lm"]["iterations"] <= 35 and "regressor_lm" not in adam.training
    assert ref.training["regressor_steps"] == adam.training["regressor_steps"] == 400
    assert rl["position_um_median"] < 0.3 * ra["position_um_median"], (rl, ra)
    assert rl["direction_arcsec_median"] < 0.5 * ra["direction_arcsec_median"]
    assert 0 < ref.training["classifier_lm"]["iterations"] <= 35
    assert ref.metrics["classifier"]["misclassification"] <= adam.metrics["classifier"]["misclassification"]
    assert ref.training["kept"]["network"] == "refine"
    hist = ref.training["regressor_history"]
    n_adam = len(adam.training["regressor_history"])
    assert hist[:n_adam] == adam.training["regressor_history"] and all(h.get("phase") == "lm" for h in hist[n_adam:])
    for (W, b), (W0, b0) in zip(ref.stop_head.layers, adam.stop_head.layers):
        np.testing.assert_array_equal(W, W0)
        np.testing.assert_array_equal(b, b0)
    # finish-only with a wider regressor configured: the map's 2×16 network is widened (the same function) and finished,
    # here on the Huber loss whose threshold follows the residuals (the model records its last δ and the refixes);
    # then, as widen_width asks, widened again and finished again (levenberg.widened_finish), both recorded
    wide_cfg = load_config(overrides={**over, "regressor": dict(over["regressor"], width=24, lm_huber=0.5,
                                                                lm_huber_refix=1.25, widen_width=28,
                                                                widen_minutes=10.0, **fin),
                                      "classifier": dict(over["classifier"], **fin)})
    wid = train_map(lens, 0, "backward", z_rear, z_front, dom, wide_cfg, str(tmp_path / "w"), progress=False,
                    eval_n=20000, finish_only="maps", base=adam)
    assert [W.shape for W, _ in wid.regressor] == [(28, 4), (28, 28), (5, 28)]
    assert [W.shape for W, _ in wid.classifier] == [W.shape for W, _ in adam.classifier]
    assert wid.training["regressor"]["widened_from"] == [16, 16] and wid.training["regressor"]["width"] == 24
    assert wid.training["regressor_widened"]["from"] == [24, 24] and wid.training["regressor_widened"]["to"] == 28
    assert wid.training["regressor_widened"]["first_finish"]["lm"]["iterations"] == 35
    assert "classifier_widened" not in wid.training
    assert wid.metrics["regressor"]["position_um_median"] < 0.3 * ra["position_um_median"]
    wlm = wid.training["regressor_lm"]
    assert wlm["lm_huber_refixes"] >= 1 and len(wlm["lm_huber_delta"]) == 5
    assert "lm_huber_refixes" not in ref.training["regressor_lm"]
    # finish_only = "stop-heads": only the stop head's finish, from its own weights widened to the configured width; the
    # classifier and regressor are the base's, bit for bit
    stop_cfg = load_config(overrides={**over, "stop": dict(over["stop"], width=24, lm_minutes=10.0, lm_iterations=30)})
    rs = train_map(lens, 0, "backward", z_rear, z_front, dom, stop_cfg, None, progress=False, finish_only="stop-heads",
                   base=adam)
    assert [W.shape[0] for W, _ in rs.stop_head.layers] == [24, 24, rs.stop_head.layers[-1][0].shape[0]]
    assert rs.stop_head.training["widened_from"] == [16, 16] and rs.stop_head.training["lm"]["iterations"] > 0
    assert rs.metrics["stop"]["stop_um_median"] < adam.metrics["stop"]["stop_um_median"]
    for (W, b), (W0, b0) in zip(rs.regressor + rs.classifier, adam.regressor + adam.classifier):
        np.testing.assert_array_equal(W, W0)
        np.testing.assert_array_equal(b, b0)
    with pytest.raises(NeuralLensError, match="lm_minutes is 0"):
        train_map(lens, 0, "backward", z_rear, z_front, dom, cfg, None, progress=False, finish_only="stop-heads", base=adam)
    # a rerun takes the finished networks from their checkpoints
    again = train_map(lens, 0, "backward", z_rear, z_front, dom, cfg_lm, str(tmp_path), progress=False, evaluate=False,
                      finish_only="maps", base=adam)
    np.testing.assert_array_equal(again.regressor[0][0], ref.regressor[0][0])
    with pytest.raises(NeuralLensError, match="lm_minutes is 0"):
        train_map(lens, 0, "backward", z_rear, z_front, dom, cfg, None, progress=False, finish_only="maps", base=adam)


def test_widening_keeps_the_function_and_lets_the_finish_go_lower():
    """``widen`` (what ``--finish-only maps`` does to a map configured wider than it is): the widened network computes
    the same outputs to rounding, and the finish continues from there below where the narrow network had
    stalled."""
    from mi_neurallens.training.levenberg import widen
    nc = types.SimpleNamespace(lm_rows=1024, lm_eval_every=10, stop_at_goals=True, patience=100)
    narrow = SmoothMap()
    small = finish(torch, narrow, random_layers([4, 3, 3, 2], seed=5), nc, seconds=1e9, max_iterations=120)
    stalled = min(h["rms"] for h in narrow.state["history"])
    wide = widen(small, 12, np.random.default_rng(0))
    assert [W.shape for W, _ in wide] == [(12, 4), (12, 12), (2, 12)] and n_params(wide) > 3 * n_params(small)
    a, b = FlatMLP(torch, small), FlatMLP(torch, wide)
    X = narrow.Xv.double()
    np.testing.assert_allclose(b.forward(b.flatten(wide), X).numpy(), a.forward(a.flatten(small), X).numpy(),
                               rtol=0, atol=1e-12)
    assert widen(wide, 8, np.random.default_rng(0))[1][0].shape == (12, 12)        # never narrower
    again = SmoothMap()
    finish(torch, again, wide, nc, seconds=1e9, max_iterations=40)
    assert again.state["history"][0]["rms"] == pytest.approx(stalled, rel=1e-3)    # it starts where it stalled
    assert min(h["rms"] for h in again.state["history"]) < 0.5 * stalled, (stalled, again.state["history"])


def test_a_widened_finish_continues_past_the_goals_from_the_same_function(tmp_path):
    """``widen_width`` / ``widen_minutes`` (:func:`widened_finish`, what a recipe asks of one ``train``): after the
    first finish, which stops at its goals, the network is widened (the same function: the widened finish's first
    validation is where the first finish ended), finished to its iteration budget past the goals, far lower; the
    state records both finishes, and a rerun takes the widened network from its checkpoint.  A widened network
    larger than the finish takes is refused before any training."""
    from mi_neurallens import NeuralLensError
    from mi_neurallens.training.levenberg import check_widenable, finish_results, widened_finish
    nc = types.SimpleNamespace(hidden=2, width=4, widen_width=12, widen_minutes=1e6, widen_iterations=50,
                               lm_minutes=1e6, lm_max_weights=MAX_PARAMS, lm_iterations=40, lm_rows=1024,
                               lm_eval_every=10, stop_at_goals=True, patience=100)

    def run(ckpt):
        fit = SmoothMap(goal=0.3)
        res = [{"layers": random_layers([4, 4, 4, 2], seed=5), "state": fit.state}]
        res[0]["state"]["stop_reason"] = "time_budget"            # Adam's
        finish_results(torch, [fit], res, nc, ["backward.0"], ckpt)
        first = [dict(h) for h in res[0]["state"]["history"]]
        widened_finish(torch, [fit], res, nc, ["backward.0"], ckpt)
        return fit, res[0], first

    fit, r, first = run(str(tmp_path / "stack"))
    st = r["state"]
    assert [np.shape(W) for W, _ in r["layers"]] == [(12, 4), (12, 12), (2, 12)]
    assert st["widened"]["from"] == [4, 4] and st["widened"]["to"] == 12
    assert st["widened"]["first_finish"]["lm"]["stop_reason"] == "goals"     # the first finish stopped at its goals
    assert st["widened"]["first_finish"]["lm"]["iterations"] < 40
    # the second did not, and ran its own count (widen_iterations; the clock would differ between machines)
    assert st["lm"]["stop_reason"] == "max_iterations" and st["lm"]["iterations"] == 50
    assert st["adam_stop_reason"] == "time_budget" and st["stop_reason"] == "goals"
    later = st["history"][len(first):]
    assert st["history"][:len(first)] == first and {h["phase"] for h in later} == {"widened"}
    assert later[0]["rms"] == pytest.approx(first[-1]["rms"], rel=1e-4)     # widened: the same function
    assert min(h["rms"] for h in later) < 0.5 * min(h["rms"] for h in first)
    best = FlatMLP(torch, r["layers"])
    got = float(((best.forward(best.flatten(r["layers"]), fit.Xv.double()) - fit.Yv.double()) ** 2).mean().sqrt())
    assert got == pytest.approx(min(h["rms"] for h in later), rel=1e-3)
    _, again, _ = run(str(tmp_path / "stack"))                     # a rerun: both finishes from their checkpoints
    for (W, b), (W0, b0) in zip(again["layers"], r["layers"]):
        np.testing.assert_array_equal(W, W0)
    check_widenable(nc, 4, 2, "regressor")
    with pytest.raises(NeuralLensError, match=r"regressor.widen_width = 40 makes a 2x40 network of 1922 weights.*"
                                              r"--set regressor.lm_max_weights=1922"):
        check_widenable(types.SimpleNamespace(**{**vars(nc), "widen_width": 40, "lm_max_weights": 1500}), 4, 2,
                        "regressor")


def test_row_feed_hands_out_each_fresh_row_once_in_chunks():
    """The finish's rows come ROW_CHUNK iterations at a time from one ``fresh_rows`` call, in order, each row
    once; a chunk that does not divide evenly is not reused past its end."""
    from mi_neurallens.training.levenberg import RowFeed

    class Counter:
        calls = 0
        next_id = 0

        def fresh_rows(self, n):
            Counter.calls += 1
            ids = np.arange(Counter.next_id, Counter.next_id + n)
            Counter.next_id += n
            return {"X": ids[:, None] * 1.0, "Y": ids * 2.0, "W": None}

    feed = RowFeed(Counter(), 100, chunk=4)
    got = [feed.next() for _ in range(10)]
    assert Counter.calls == 3                          # 4 + 4 + 2 of 4
    ids = np.concatenate([g["X"][:, 0] for g in got])
    np.testing.assert_array_equal(ids, np.arange(1000))
    assert all(len(g["Y"]) == 100 and g["W"] is None for g in got)
    np.testing.assert_array_equal(got[7]["Y"], 2.0 * np.arange(700, 800))


def test_finishing_a_network_larger_than_the_finish_takes_is_a_clear_error():
    """``finish_only = "maps"`` runs only the finish, which leaves networks above ``MAX_PARAMS`` alone: a 5×32 regressor
    (or a 3×16 one configured wider than the finish takes) is refused before any training, naming the way out; a
    3×16 one widened to 3×32 passes; a stop head widened past the limit by ``--finish-only stop-heads`` is refused the same way.
    A network given no time for the finish (``lm_minutes`` 0) is refused there too, before the other one's finish
    has run (it used to be found only then, minutes later)."""
    from mi_neurallens import NeuralLensError
    from mi_neurallens.training.config import NetConfig
    from mi_neurallens.training.keep import check_finish_only

    def base(widths):
        return types.SimpleNamespace(key="forward.10240", training={}, regressor=random_layers([4, *widths, 5]),
                                     classifier=random_layers([4, 16, 16, 1]), regressor_activation="tanh",
                                     classifier_activation="tanh")
    nets = lambda width, lm=1.0: (("regressor", NetConfig(hidden=3, width=width, lm_minutes=1.0)),
                                  ("classifier", NetConfig(hidden=2, width=16, lm_minutes=lm)))
    with pytest.raises(NeuralLensError, match=r"regressor of forward\.10240 \(4549 weights\).*--keep classifier "
                                              r"--set forward_regressor\.hidden=3"):
        check_finish_only([base([32] * 5)], nets(32), "forward")
    check_finish_only([base([16] * 3)], nets(32), "forward")           # 2 437 weights widened: the finish takes it
    with pytest.raises(NeuralLensError, match=r"larger than the Levenberg-Marquardt finish takes \(2500 weights, "
                                              r"forward_regressor\.lm_max_weights\)"):
        check_finish_only([base([16] * 3)], nets(48), "forward")
    # a recipe may raise the limit for one network (the EF 24-70's 4×27 camera regressor)
    raised = (("regressor", NetConfig(hidden=3, width=48, lm_minutes=1.0, lm_max_weights=5500)), nets(48)[1])
    check_finish_only([base([16] * 3)], raised, "forward")
    with pytest.raises(NeuralLensError, match=r"the classifier's lm_minutes is 0: .*--set classifier\.lm_minutes"):
        check_finish_only([base([16] * 3)], nets(16, lm=0.0), "backward")
    # the stop heads' finish-only run (``finish_only = "stop-heads"``) refuses the same, before it samples anything
    from mi_neurallens.training.stop_head import train_stop_heads
    tm = types.SimpleNamespace(key="forward.278528", direction="forward", path_id=278528)
    head = types.SimpleNamespace(layers=random_layers([4, 32, 32, 32, 6]))
    with pytest.raises(NeuralLensError, match=r"--finish-only stop-heads: forward\.278528 stop head \(\d+ weights\).*--keep networks"):
        train_stop_heads(None, [tm], NetConfig(hidden=3, width=48, lm_minutes=1.0), seeds=[0], start=[head])
