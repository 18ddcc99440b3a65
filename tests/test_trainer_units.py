"""Unit tests of the trainer's pieces (RegressorFit, ClassifierFit): the target transform, the odd-y
factor and the margin loss, which lived in closures no test could reach."""
from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from mi_neurallens.training.config import NetConfig  # noqa: E402
from mi_neurallens.training.classifier import ClassifierFit  # noqa: E402
from mi_neurallens.training.outputs import ODD_COLUMNS, odd_factor  # noqa: E402
from mi_neurallens.training.regressor import RegressorFit  # noqa: E402


def _regressor_fit(odd_s, rng):
    """A RegressorFit carrying only what its transform methods read (no sampler, no pool)."""
    fit = RegressorFit.__new__(RegressorFit)
    fit.torch, fit.dev = torch, "cpu"
    fit.skip = rng.normal(size=(5, 4))
    fit.shift = rng.normal(size=5)
    fit.oscale = rng.uniform(0.5, 3.0, 5)
    fit.odd_s = odd_s
    fit.center = np.array([3.0, 0.0, 0.2, 595.0])
    fit.scale_in = np.array([3.0, 0.4, 0.2, 235.0])
    fit.wy_c, fit.wy_s = float(fit.center[2]), float(fit.scale_in[2])
    return fit


@pytest.mark.parametrize("odd_s", [None, 0.4])
def test_regressor_outputs_invert_targets(odd_s):
    rng = np.random.default_rng(1)
    fit = _regressor_fit(odd_s, rng)
    x = np.c_[rng.uniform(0, 6, 500), rng.uniform(-0.4, 0.4, 500), rng.uniform(0, 0.4, 500),
              rng.uniform(360, 830, 500)]
    xn = (x - fit.center) / fit.scale_in
    y = rng.normal(size=(500, 5))
    t = fit.targets(x, xn, y)
    np.testing.assert_allclose(fit.outputs(x, xn, t), y, atol=1e-12)
    # the transform is not the identity: the network learns a residual of the skip connection
    assert np.abs(t - y).max() > 0.1


def test_odd_factor_of_a_batch_matches_numpy():
    """M_of (torch, from normalised inputs) equals odd_factor (numpy, from ωy) on the odd columns."""
    rng = np.random.default_rng(2)
    fit = _regressor_fit(0.4, rng)
    wy = rng.uniform(0, 0.4, 64)
    xn = np.zeros((64, 4))
    xn[:, 2] = (wy - fit.wy_c) / fit.wy_s
    M = fit.M_of(torch.as_tensor(xn, dtype=torch.float64)).numpy()
    ref = odd_factor(wy, 0.4)
    for j in ODD_COLUMNS:
        np.testing.assert_allclose(M[:, j], ref[:, j], rtol=1e-6)
    others = [j for j in range(5) if j not in ODD_COLUMNS]
    assert np.all(M[:, others] == 1.0)
    assert np.all(_regressor_fit(None, rng).M_of(torch.zeros((3, 4))).numpy() == 1.0)


def test_margin_loss_is_an_interval_regression():
    fit = ClassifierFit.__new__(ClassifierFit)
    fit.torch, fit.nc = torch, NetConfig(margin_clip=4.0)
    c = 4.0
    t = torch.tensor([-c, -1.0, 0.5, c])
    # inside the band the target is matched exactly; at the clip only the side counts
    assert float(fit.margin_loss(torch.tensor([-9.0, -1.0, 0.5, 9.0]), t)) == 0.0
    # a logit on the wrong side of a clipped target, or off an in-band target, costs its squared miss
    assert float(fit.margin_loss(torch.tensor([-c, -1.0, 0.5, c - 1.0]), t)) == pytest.approx(1.0 / 4)
    assert float(fit.margin_loss(torch.tensor([-c, 1.0, 0.5, c]), t)) == pytest.approx(4.0 / 4)
    assert math.isfinite(float(fit.margin_loss(torch.tensor([1e3, -1e3, 0.0, 0.0]), t)))
