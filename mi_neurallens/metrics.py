"""Image error metrics used in every comparison table (one definition, used everywhere).

``MAPE`` (mean absolute percentage error, the paper's metric), for an image ``a`` against a
reference ``b`` (H×W×C, linear radiance):

    MAPE(a, b) = mean over pixels and channels of  |a − b| / (|b| + ε),   ε = 0.01

ε keeps dark pixels from dominating (0.01 is 1 % of a white diffuse surface under unit
illumination).  ``relMSE`` = mean of (a − b)² / (b² + ε).
"""
from __future__ import annotations

import numpy as np

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
