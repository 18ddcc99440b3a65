"""Image error metrics used in every comparison table (one definition, used everywhere).

``MAPE`` (mean absolute percentage error, the paper's metric), for an image ``a`` against a
reference ``b`` (H×W×C, linear radiance):

    MAPE(a, b) = mean over pixels and channels of  |a − b| / (|b| + ε),   ε = 0.01

ε keeps dark pixels from dominating (0.01 is 1 % of a white diffuse surface under unit
illumination).  ``relMSE`` = mean of (a − b)² / (b² + ε).

Flare images (mostly black, with a dynamic range of many orders of magnitude) use a masked,
scale-free variant, :func:`mape_masked`: with Y the Rec. 709 luminance and b the reference,

    MAPE_flare(a, b) = mean over {p : Y_b(p) > 0.01 · max Y_b} of |Y_a − Y_b| / (|Y_b| + 0.001 · max Y_b)
"""
from __future__ import annotations

import numpy as np

from .constants import LUMINANCE_WEIGHTS

EPSILON = 0.01


def _prep(a, b):
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"images differ in shape: {a.shape} vs {b.shape}")
    if a.ndim == 3 and a.shape[2] == 4:   # drop alpha
        a, b = a[..., :3], b[..., :3]
    return a, b


def mape(a, b, eps: float = EPSILON) -> float:
    a, b = _prep(a, b)
    return float(np.mean(np.abs(a - b) / (np.abs(b) + eps)))


def rel_mse(a, b, eps: float = EPSILON) -> float:
    a, b = _prep(a, b)
    return float(np.mean((a - b) ** 2 / (b * b + eps)))


def error_map(a, b, eps: float = EPSILON) -> np.ndarray:
    """Per-pixel relative error |a − b| / (|b| + ε), averaged over channels (H×W)."""
    a, b = _prep(a, b)
    e = np.abs(a - b) / (np.abs(b) + eps)
    return e.mean(axis=2) if e.ndim == 3 else e


#: Rec. 709 luminance weights
LUMINANCE = np.array(LUMINANCE_WEIGHTS, np.float64)
#: flare MAPE: mask threshold and epsilon, relative to the reference's maximum luminance
FLARE_MASK_REL, FLARE_EPS_REL = 1e-2, 1e-3


def flare_error_map(a, b, mask_rel: float = FLARE_MASK_REL, eps_rel: float = FLARE_EPS_REL):
    """The per-pixel terms of :func:`mape_masked`: (relative luminance error (H×W), mask (H×W)); the mask
    is empty when the reference is black."""
    ya = np.asarray(a, np.float64)[..., :3] @ LUMINANCE
    yb = np.asarray(b, np.float64)[..., :3] @ LUMINANCE
    mx = float(yb.max()) if yb.size else 0.0
    if not mx > 0:
        return np.zeros(yb.shape), np.zeros(yb.shape, bool)
    return np.abs(ya - yb) / (np.abs(yb) + eps_rel * mx), yb > mask_rel * mx


def mape_masked(a, b, mask_rel: float = FLARE_MASK_REL, eps_rel: float = FLARE_EPS_REL) -> float:
    """Luminance MAPE over the pixels where the reference is non-negligible (see module docstring)."""
    rel, m = flare_error_map(a, b, mask_rel, eps_rel)
    return float(np.mean(rel[m])) if m.any() else float("nan")
