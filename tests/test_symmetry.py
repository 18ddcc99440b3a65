"""Symmetry reduction (paper §4.1): reduce→undo is the identity, and the exact tracer commutes with it."""
from __future__ import annotations

import numpy as np
import pytest

from mi_neurallens import Lens
from mi_neurallens.trace import symmetry
from mi_neurallens.trace.api import float_type


def _rays(n, seed=0, r_max=8.0, s_max=0.6):
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-r_max, r_max, (2, n))
    a = rng.uniform(0, 2 * np.pi, n)
    s = s_max * np.sqrt(rng.random(n))
    return x, y, s * np.cos(a), s * np.sin(a)


def test_reduce_undo_identity_numpy():
    x, y, dx, dy = _rays(10000)
    x[:3] = 0.0
    y[:3] = 0.0                       # on the axis
    dy[3:6] = 0.0                     # in the meridional plane
    (r, wx, wy), fr = symmetry.reduce(x, y, dx, dy)
    assert np.all(r >= 0) and np.all(wy >= 0)
    np.testing.assert_allclose(r, np.hypot(x, y), rtol=1e-12)
    np.testing.assert_allclose(wx ** 2 + wy ** 2, dx ** 2 + dy ** 2, rtol=1e-12, atol=1e-15)
    X, Y, DX, DY = symmetry.undo(r, np.zeros_like(r), wx, wy, fr)
    for a, b in ((X, x), (Y, y), (DX, dx), (DY, dy)):
        np.testing.assert_allclose(a, b, atol=1e-12)


def test_reduce_undo_drjit_matches_numpy():
    F = float_type("float32")
    x, y, dx, dy = _rays(4096, seed=1)
    (r, wx, wy), fr = symmetry.reduce(x, y, dx, dy)
    (rd, wxd, wyd), frd = symmetry.reduce(*(F(v.astype(np.float32)) for v in (x, y, dx, dy)))
    for a, b in ((rd, r), (wxd, wx), (wyd, wy)):
        np.testing.assert_allclose(a.numpy(), b, atol=2e-5)
    out = symmetry.undo(rd, rd * 0.0, wxd, wyd, frd)
    for a, b in zip(out, (x, y, dx, dy)):
        np.testing.assert_allclose(a.numpy(), b, atol=2e-5)


@pytest.mark.parametrize("name,direction,path", [("wide-22mm", "backward", "transmit"),
                                                  ("wide-22mm", "forward", "transmit"),
                                                  ("ood-59mm", "forward", 2560)])
def test_tracer_commutes_with_reduction(name, direction, path):
    """trace(reduce(x)) undone == trace(x), for validity, exit rays and throughput (float64)."""
    lens = Lens.load(name)
    if path != "transmit":
        from mi_neurallens.trace.paths import all_ghosts
        path = all_ghosts(lens)[7][0]
    z_in = lens.total_track + 2.0 if direction == "backward" else -1.0
    z_out = -1.0 if direction == "backward" else lens.total_track + 2.0
    heading = -1 if direction == "backward" else 1
    x, y, dx, dy = _rays(20000, seed=2, r_max=12.0, s_max=0.5)
    dz = heading * np.sqrt(1 - dx ** 2 - dy ** 2)
    o = np.stack([x, y, np.full_like(x, z_in)], 1)
    lam = np.random.default_rng(3).uniform(400, 700, len(x))
    full = lens.trace(o, np.stack([dx, dy, dz], 1), lam, direction=direction, path=path,
                      precision="float64", z_out=z_out)
    (r, wx, wy), fr = symmetry.reduce(x, y, dx, dy)
    (ro, _), (wdx, wdy, wdz) = symmetry.reduced_ray(r, wx, wy, heading)
    red = lens.trace(np.stack([ro, np.zeros_like(r), np.full_like(r, z_in)], 1), np.stack([wdx, wdy, wdz], 1),
                     lam, direction=direction, path=path, precision="float64", z_out=z_out)
    assert full.valid.sum() > 100
    np.testing.assert_array_equal(full.valid, red.valid)
    v = full.valid
    X, Y, DX, DY = symmetry.undo(red.position[v, 0], red.position[v, 1], red.direction[v, 0],
                                 red.direction[v, 1], tuple(f[v] for f in fr))
    np.testing.assert_allclose(X, full.position[v, 0], atol=1e-9)
    np.testing.assert_allclose(Y, full.position[v, 1], atol=1e-9)
    np.testing.assert_allclose(DX, full.direction[v, 0], atol=1e-12)
    np.testing.assert_allclose(DY, full.direction[v, 1], atol=1e-12)
    np.testing.assert_allclose(red.direction[v, 2], full.direction[v, 2], atol=1e-12)
    np.testing.assert_allclose(red.throughput[v], full.throughput[v], rtol=1e-12)
