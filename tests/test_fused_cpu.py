"""The fused CPU training step (training/fused_mlp.c) against PyTorch's operations: the same outputs and
gradients to float32 rounding, for the shapes the trainer uses and for odd ones; and when it is not used."""
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from mi_neurallens.training import fused_cpu, stacked  # noqa: E402


def _kernel_or_skip(dims):
    kern = fused_cpu.kernel(torch, dims)
    if kern is None:
        pytest.skip(f"no fused kernel here: {fused_cpu.WHY_NOT.get(tuple(dims))}")
    return kern


def _reference(net, x, gout):
    """Outputs and parameter gradients of sum(gout · out) through PyTorch's operations (the rational tanh)."""
    fused, net.fused = net.fused, None
    try:
        for q in net.params:
            q.grad = None
        out = net.forward(x)
        (out * gout).sum().backward()
        return out.detach(), [q.grad.clone() for q in net.params]
    finally:
        net.fused = fused
        for q in net.params:
            q.grad = None


@pytest.mark.parametrize("n_in,hidden,width,n_out,K,B", [
    (4, 5, 32, 5, 3, 1000),     # the benchmark's regressor; B not a multiple of the tile or the row block
    (4, 3, 16, 5, 2, 4096),     # the defaults' ghost regressor
    (4, 2, 16, 1, 4, 37),       # the defaults' classifier, a batch smaller than a tile
    (5, 3, 48, 17, 1, 300),     # three vectors wide, more outputs than one vector holds
    (3, 1, 16, 2, 2, 8),        # one hidden layer
])
def test_forward_and_gradients_match_pytorch(n_in, hidden, width, n_out, K, B):
    net = stacked.StackedMLP(torch, "cpu", range(K), n_in, n_out, hidden, width)
    _kernel_or_skip(net.dims)
    assert net.fused is not None
    g = torch.Generator().manual_seed(3)
    x = torch.randn(K, B, n_in, generator=g) * 2.0
    gout = torch.randn(K, B, n_out, generator=g)
    ref_out, ref_grads = _reference(net, x, gout)
    out = net.forward(x)
    assert out.shape == (K, B, n_out)
    (out * gout).sum().backward()
    np.testing.assert_allclose(out.detach().numpy(), ref_out.numpy(), rtol=0, atol=2e-6 * float(ref_out.abs().max()))
    for q, r in zip(net.params, ref_grads):
        scale = float(r.abs().max())
        np.testing.assert_allclose(q.grad.numpy(), r.numpy(), rtol=0, atol=2e-5 * scale)


def test_each_map_its_own_gradient():
    """Map j's gradient depends only on map j's rows: changing map 1's targets leaves map 0's gradient."""
    net = stacked.StackedMLP(torch, "cpu", range(2), 4, 5, 3, 16)
    _kernel_or_skip(net.dims)
    x = torch.randn(2, 500, 4)
    grads = []
    for scale in (1.0, 7.0):
        gout = torch.ones(2, 500, 5)
        gout[1] *= scale
        for q in net.params:
            q.grad = None
        (net.forward(x) * gout).sum().backward()
        grads.append([q.grad.clone() for q in net.params])
    for a, b in zip(*grads):
        assert torch.equal(a[0], b[0])
        assert not torch.allclose(a[1], b[1])


def test_views_of_a_pool_are_read_as_their_rows():
    """A batch is a window of the stacked pools, a non-contiguous view: the kernel reads its rows."""
    net = stacked.StackedMLP(torch, "cpu", range(3), 4, 5, 3, 16)
    _kernel_or_skip(net.dims)
    pool = torch.randn(3, 2000, 4)
    view = pool[:, 700:1212]
    assert not view.is_contiguous()
    with torch.no_grad():
        assert torch.equal(net.forward(view), net.forward(view.contiguous()))


def test_not_used_where_it_cannot_run(monkeypatch):
    """Widths that are not whole vectors, and MI_NEURALLENS_FUSED=0, keep PyTorch's operations, with the reason."""
    assert fused_cpu.kernel(torch, [4, 24, 24, 5]) is None
    assert "multiple of 16" in fused_cpu.WHY_NOT[(4, 24, 24, 5)]
    net = stacked.StackedMLP(torch, "cpu", range(2), 4, 5, 2, 24)
    assert net.fused is None and "multiple of 16" in stacked.STEP_CHOICE["4-24-24-5"]
    monkeypatch.setenv("MI_NEURALLENS_FUSED", "0")
    monkeypatch.setattr(fused_cpu, "_KERNELS", {})
    assert fused_cpu.kernel(torch, [4, 16, 16, 5]) is None
    assert fused_cpu.WHY_NOT[(4, 16, 16, 5)] == "MI_NEURALLENS_FUSED=0"


def test_no_compiler_falls_back(monkeypatch):
    monkeypatch.setattr(fused_cpu, "_KERNELS", {})
    monkeypatch.setattr(fused_cpu, "_compiler", lambda: None)
    monkeypatch.setattr(fused_cpu, "_cache_dir", lambda: __import__("pathlib").Path("/nonexistent-cache"))
    assert fused_cpu.kernel(torch, [4, 16, 16, 5]) is None
    assert "no C compiler" in fused_cpu.WHY_NOT[(4, 16, 16, 5)]


def test_a_stack_trains_the_same_with_and_without_the_kernel():
    """Fifty Adam steps of a stack: the fused step and PyTorch's reach the same weights to float32 drift."""
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 2048, 4, generator=g)
    y = torch.sin(x.sum(-1, keepdim=True) * torch.tensor([1.0, 0.5, -0.7]))
    finals = []
    for use in (True, False):
        net = stacked.StackedMLP(torch, "cpu", range(2), 4, 3, 3, 16)
        if not use:
            net.fused = None
        elif net.fused is None:
            pytest.skip("no fused kernel here")
        opt = stacked.StackedAdam(net.params)
        for _ in range(50):
            ((net.forward(x) - y) ** 2).mean(dim=(1, 2)).sum().backward()
            opt.step(net.params, 3e-3)
        finals.append([q.detach().clone() for q in net.params])
    for a, b in zip(*finals):
        np.testing.assert_allclose(a.numpy(), b.numpy(), rtol=0, atol=1e-4)



def _regressor_problem(direction_loss, odd, heading, n_in=4):
    """A RegressorFit with just what its loss reads (no tracer): random transform, weights and constants."""
    from mi_neurallens.training.config import NetConfig
    from mi_neurallens.training.regressor import RegressorFit
    fit = RegressorFit.__new__(RegressorFit)
    rng = np.random.default_rng(11)
    fit.torch, fit.dev, fit.heading = torch, "cpu", heading
    fit.nc = NetConfig(direction_loss=direction_loss, cosine_weight=0.7)
    fit.odd_s = 3.0 if odd else None
    fit.wy_c, fit.wy_s = 0.2, 1.3
    fit.W = torch.as_tensor(rng.uniform(0.5, 2.0, 5), dtype=torch.float32)
    fit.T_shift = torch.as_tensor(rng.normal(0, 0.05, 5), dtype=torch.float32)
    fit.T_skip = torch.as_tensor(rng.normal(0, 0.1, (5, n_in)), dtype=torch.float32)
    fit.T_scale = torch.as_tensor(rng.uniform(0.05, 0.2, 5), dtype=torch.float32)
    fit.sig_d2 = 0.013
    return fit


@pytest.mark.parametrize("direction_loss,odd,edge,heading,n_in", [
    ("mse+cosine", True, False, 1, 4), ("cosine", False, True, 1, 4), ("none", True, True, -1, 4),
    ("mse+cosine", False, True, -1, 4), ("mse+cosine", True, True, -1, 6)])
def test_regressor_loss_and_gradient_match_autograd(direction_loss, odd, edge, heading, n_in):
    """The kernel's regressor loss (fused_mlp.c loss_regressor) against RegressorFit.rows_loss and autograd, on a
    window of stacked pools (strided rows), with exit directions near grazing (the dz clamp) among them; with the
    ray's four inputs, and with a zoom lens's six (zoom and focus as inputs: the skip term over every input)."""
    net = stacked.StackedMLP(torch, "cpu", range(3), n_in, 5, 3, 16)
    kern = _kernel_or_skip(net.dims)
    fit = _regressor_problem(direction_loss, odd, heading, n_in)
    g = torch.Generator().manual_seed(2)
    K, n, B = 3, 900, 700
    pools = {"X": torch.rand(K, n, n_in, generator=g) * 2 - 1, "Y": torch.randn(K, n, 5, generator=g) * 0.3,
             "Yraw": torch.randn(K, n, 5, generator=g) * 0.4}
    pools["Yraw"][:, :50, 2] = 0.9999                  # grazing targets: 1 - |d|² below the clamp
    if edge:
        pools["W"] = torch.rand(K, n, generator=g) + 0.5
    batch = {k: v[:, 100:100 + B] for k, v in pools.items()}
    const = {k: torch.stack([v] * K) for k, v in fit.constants().items()}
    out = (torch.randn(K, B, 5, generator=g) * 0.5).requires_grad_()
    ref = fit.rows_loss(out, batch, const)
    ref.sum().backward()
    loss, gout = fit.fused_loss(kern, out.detach(), batch, const)
    np.testing.assert_allclose(loss.numpy(), ref.detach().numpy(), rtol=2e-5, atol=1e-7)
    np.testing.assert_allclose(gout.numpy(), out.grad.numpy(), rtol=0, atol=1e-4 * float(out.grad.abs().max()))


def test_margin_loss_and_gradient_match_autograd():
    from mi_neurallens.training.config import NetConfig
    from mi_neurallens.training.classifier import ClassifierFit
    net = stacked.StackedMLP(torch, "cpu", range(2), 4, 1, 2, 16)
    kern = _kernel_or_skip(net.dims)
    fit = ClassifierFit.__new__(ClassifierFit)
    fit.torch, fit.margin, fit.nc = torch, True, NetConfig(target="margin", margin_clip=2.5)
    assert fit.has_fused_loss()
    g = torch.Generator().manual_seed(4)
    t = torch.randn(2, 3000, generator=g) * 3.0                       # inside, beyond both clips
    batch = {"L": t[:, 500:2500]}
    out = (torch.randn(2, 2000, 1, generator=g) * 3.0).requires_grad_()
    ref = fit.rows_loss(out, batch, {})
    ref.sum().backward()
    loss, gout = fit.fused_loss(kern, out.detach(), batch, {})
    np.testing.assert_allclose(loss.numpy(), ref.detach().numpy(), rtol=1e-5)
    np.testing.assert_allclose(gout.numpy(), out.grad.numpy(), rtol=0, atol=1e-6 * float(out.grad.abs().max()))


def test_a_fused_step_leaves_the_gradients_autograd_would():
    """stacked.fused_step (network and loss in C, no autograd) against forward + rows_loss + backward."""
    net = stacked.StackedMLP(torch, "cpu", range(3), 4, 5, 3, 16)
    _kernel_or_skip(net.dims)
    fit = _regressor_problem("mse+cosine", True, 1)
    g = torch.Generator().manual_seed(6)
    batch = {"X": torch.rand(3, 512, 4, generator=g) * 2 - 1, "Y": torch.randn(3, 512, 5, generator=g) * 0.3,
             "Yraw": torch.randn(3, 512, 5, generator=g) * 0.4}
    const = {k: torch.stack([v] * 3) for k, v in fit.constants().items()}
    loss = stacked.fused_step(net, fit, batch, const)
    got = [q.grad.clone() for q in net.params]
    for q in net.params:
        q.grad = None
    ref = fit.rows_loss(net.forward(batch["X"]), batch, const)      # the fused network, autograd's loss
    ref.sum().backward()
    np.testing.assert_allclose(loss.numpy(), ref.detach().numpy(), rtol=2e-5)
    for a, q in zip(got, net.params):
        np.testing.assert_allclose(a.numpy(), q.grad.numpy(), rtol=0, atol=1e-4 * float(q.grad.abs().max()))


def test_a_maps_gradient_is_the_same_alone_and_in_a_stack():
    """Each map's tiles are shared among the threads the same way whatever the stack's size: map 1 of a stack of
    three has, bit for bit, the gradient it has alone (the stacked trainer's promise of the Adam trajectory a map
    would follow alone)."""
    net = stacked.StackedMLP(torch, "cpu", range(3), 4, 5, 3, 16)
    kern = _kernel_or_skip(net.dims)
    g = torch.Generator().manual_seed(9)
    x, gout = torch.randn(3, 8192, 4, generator=g), torch.randn(3, 8192, 5, generator=g)
    params = [q.detach() for q in net.params]
    _, acts = kern.forward(torch, x, params)
    stack = kern.backward(torch, x, params, acts, gout)
    one = [q[1:2].contiguous() for q in params]
    _, acts1 = kern.forward(torch, x[1:2].contiguous(), one)
    alone = kern.backward(torch, x[1:2].contiguous(), one, acts1, gout[1:2].contiguous())
    for a, b in zip(stack, alone):
        assert torch.equal(a[1:2], b)


def test_shapes_and_dtypes_are_checked_before_the_kernel_reads_them():
    net = stacked.StackedMLP(torch, "cpu", range(2), 4, 5, 3, 16)
    kern = _kernel_or_skip(net.dims)
    params = [q.detach() for q in net.params]
    with pytest.raises(ValueError):
        kern.forward(torch, torch.randn(2, 10, 3), params)                       # 3 inputs, not 4
    with pytest.raises(ValueError):
        kern.forward(torch, torch.randn(3, 10, 4), params)                       # 3 maps, parameters of 2
    with pytest.raises(ValueError):
        kern.forward(torch, torch.randn(2, 10, 4), [q.double() for q in params])
    assert fused_cpu.kernel(torch, [4, 272, 272, 5]) is None                      # wider than the registers hold
