"""Symmetry reduction of lens transport (paper §4.1), for numpy and any Dr.Jit float type.

A rotationally symmetric lens commutes with every rotation about the optical axis (z) and with every
mirror in a plane containing it.  A ray on a plane z = const, given by its position (x, y) and unit
direction (dx, dy, dz), is therefore *reduced* to a canonical representative:

1. **rotate** about z by −φ, φ = atan2(y, x), so the position lies on +x: ``(r, 0)``, r = √(x²+y²) ≥ 0;
   the direction becomes ``(ωx, ω'y) = (c·dx + s·dy, −s·dx + c·dy)`` with c = cos φ, s = sin φ;
2. **reflect** in the x–z plane when ω'y < 0, so ``ωy = |ω'y| ≥ 0`` (``sgn`` = ±1 records it).

The reduced input is ``(r, ωx, ωy)`` (plus λ, which no symmetry touches); dz is unchanged and fixed by
the heading.  An output ray ``(x, y, dx, dy)`` computed in the reduced frame is mapped back by
:func:`undo`: reflect (y, dy → sgn·y, sgn·dy), then rotate by +φ.  On the axis (r = 0) the rotation
is the identity (c = 1, s = 0).  z components are untouched by both steps.

The frame numbers ``(c, s, sgn)`` are returned by :func:`reduce` and consumed by :func:`undo`, so the
pair is exactly the identity (up to rounding) and no trigonometric function is evaluated.
"""
from __future__ import annotations

import numpy as np


def _is_np(x) -> bool:
    return isinstance(x, (np.ndarray, float, int, np.floating))


def reduce(x, y, dx, dy):
    """(x, y, dx, dy) → ``(r, wx, wy), (c, s, sgn)``; numpy arrays or Dr.Jit floats (any backend)."""
    if _is_np(x):
        x, y, dx, dy = (np.asarray(v, dtype=np.float64) for v in (x, y, dx, dy))
        r = np.hypot(x, y)
        safe = r > 0
        rs = np.where(safe, r, 1.0)
        c = np.where(safe, x / rs, 1.0)
        s = np.where(safe, y / rs, 0.0)
        wx = c * dx + s * dy
        wy_ = c * dy - s * dx
        sgn = np.where(wy_ < 0, -1.0, 1.0)
        return (r, wx, wy_ * sgn), (c, s, sgn)
    import drjit as dr
    r2 = dr.fma(x, x, y * y)
    safe = r2 > 0
    inv = dr.select(safe, dr.rsqrt(dr.select(safe, r2, 1.0)), 0.0)
    r = r2 * inv
    c = dr.select(safe, x * inv, 1.0)
    s = y * inv
    wx = dr.fma(c, dx, s * dy)
    wy_ = dr.fma(c, dy, -s * dx)
    neg = wy_ < 0
    sgn = dr.select(neg, -1.0, 1.0)
    return (r, wx, dr.abs(wy_)), (c, s, sgn)


def undo(x, y, dx, dy, frame):
    """Map a reduced-frame output (position (x, y), direction (dx, dy)) back: reflect, then rotate."""
    c, s, sgn = frame
    y = y * sgn
    dy = dy * sgn
    if _is_np(x):
        return c * x - s * y, s * x + c * y, c * dx - s * dy, s * dx + c * dy
    import drjit as dr
    return (dr.fma(c, x, -s * y), dr.fma(s, x, c * y), dr.fma(c, dx, -s * dy), dr.fma(s, dx, c * dy))


def undo_point(x, y, frame):
    """Map a reduced-frame point (x, y) on any plane z = const (e.g. a stop-plane crossing) back:
    reflect, then rotate (the position part of :func:`undo`)."""
    c, s, sgn = frame
    y = y * sgn
    if _is_np(x):
        return c * x - s * y, s * x + c * y
    import drjit as dr
    return dr.fma(c, x, -s * y), dr.fma(s, x, c * y)


def reduced_ray(r, wx, wy, heading: int):
    """The reduced ray as lens-space numpy/Dr.Jit components: position (r, 0) and the unit direction
    (wx, wy, heading·√(1 − wx² − wy²)).  ``heading`` = +1 (forward, toward the sensor) or −1."""
    if _is_np(r):
        r = np.asarray(r, dtype=np.float64)
        dz = heading * np.sqrt(np.maximum(1.0 - wx * wx - wy * wy, 0.0))
        return (r, np.zeros_like(r)), (np.asarray(wx, dtype=np.float64), np.asarray(wy, dtype=np.float64), dz)
    import drjit as dr
    dz = heading * dr.sqrt(dr.maximum(1.0 - dr.fma(wx, wx, wy * wy), 0.0))
    return (r, r * 0.0), (wx, wy, dz)
