"""Image error metrics used in every comparison table (one definition, used everywhere).

``MAPE`` (mean absolute percentage error, the paper's metric), for an image ``a`` against a
reference ``b`` (H×W×C, linear radiance):

    MAPE(a, b) = mean over pixels and channels of  |a − b| / (|b| + ε),   ε = 0.01

ε keeps dark pixels from dominating (0.01 is 1 % of a white diffuse surface under unit
illumination).  ``relMSE`` = mean of (a − b)² / (b² + ε).

Flare images (mostly black, with a dynamic range of many orders of magnitude) use a masked,
scale-free variant, :func:`mape_masked`: with Y the Rec. 709 luminance and b the reference,

    MAPE_flare(a, b) = mean over {p : Y_b(p) > 0.01 · max Y_b} of |Y_a − Y_b| / (|Y_b| + 0.001 · max Y_b)

Paired flare renders (the same samples: Monte Carlo noise cancels, what is left is where the light lands)
of a *compact* reference, one whose mask holds fewer than :data:`FLARE_COMPACT_PIXELS` pixels (a ghost
focused to a spot of a pixel or two), are compared after both are blurred by a Gaussian of
:data:`FLARE_COMPACT_SIGMA_PX` pixel (:func:`paired_flare_error_map`): per pixel, such a spot's error is how a
sub-µm shift splits it between two pixels (a learned spot whose image's centroid moved 0.0036 px read 0.065),
blurred it is its flux and its placement at the pixel's scale (a shift of δ pixels reads about 1.3 δ).
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


#: paired flare error: a reference whose mask holds fewer pixels than this is compact (a spot of a few pixels) and
#: compared blurred (:func:`paired_flare_error_map`)
FLARE_COMPACT_PIXELS = 16
#: paired flare error of a compact reference: the Gaussian's standard deviation both images are blurred with (pixels)
FLARE_COMPACT_SIGMA_PX = 1.0


def gaussian_blur(img, sigma_px: float):
    """``img`` (H×W or H×W×C) convolved over its two pixel axes with a normalised Gaussian of standard
    deviation ``sigma_px`` pixels, truncated at 4σ; zeros beyond the border (light spread past it is lost)."""
    img = np.asarray(img, np.float64)
    r = max(1, int(np.ceil(4.0 * sigma_px)))
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma_px) ** 2)
    k /= k.sum()
    out = img
    for axis in (0, 1):
        pad = [(0, 0)] * img.ndim
        pad[axis] = (r, r)
        p = np.pad(out, pad)
        n = out.shape[axis]
        out = sum(w * np.take(p, np.arange(i, i + n), axis=axis) for i, w in enumerate(k))
    return out


def paired_flare_error_map(a, b, compact_pixels: int = FLARE_COMPACT_PIXELS,
                           sigma_px: float = FLARE_COMPACT_SIGMA_PX):
    """:func:`flare_error_map` of paired renders ``a`` against the reference ``b`` (the same samples), with a
    compact reference (fewer than ``compact_pixels`` in its mask) compared after both are blurred by a Gaussian
    of ``sigma_px`` pixels (see the module docstring).  Returns (relative error (H×W), mask (H×W), compact)."""
    rel, mask = flare_error_map(a, b)
    if not 0 < int(mask.sum()) < compact_pixels:
        return rel, mask, False
    a, b = _prep(a, b)
    rel, mask = flare_error_map(gaussian_blur(a, sigma_px), gaussian_blur(b, sigma_px))
    return rel, mask, True


def mape_masked(a, b, mask_rel: float = FLARE_MASK_REL, eps_rel: float = FLARE_EPS_REL) -> float:
    """Luminance MAPE over the pixels where the reference is non-negligible (see module docstring)."""
    rel, m = flare_error_map(a, b, mask_rel, eps_rel)
    return float(np.mean(rel[m])) if m.any() else float("nan")
