"""The regressor's outputs as its network learns them, and the weights of its loss.

* **Output standardisation**: a regressor predicts ``y = M · (shift + skip·xn + scale·network)`` of its
  normalised inputs ``xn``, with a least-squares linear part (the skip connection, kept in the model file) and
  the odd-y factor ``M`` (ωy / s_max on the outputs odd under the mirror ωy → −ωy, :data:`ODD_COLUMNS`), so the
  network's target has about unit variance (:func:`fit_output_transform`, :func:`odd_factor`); a fisheye's camera
  map regresses its exit position times |dz| (:func:`wants_position_cos`).
* **Loss weights**: per output column, from the column's spread against its accuracy goal (:func:`loss_weights`:
  positions in mm, directions in radians, T relative), and per sample near an aperture edge
  (:func:`edge_weights`).

Outputs are in the reduced frame (:mod:`mi_neurallens.trace.symmetry`): exit position (x, y) on the output plane
(mm), exit direction cosines (dx, dy), Fresnel throughput T.
"""
from __future__ import annotations

import math

import numpy as np

from ..constants import ARCSEC_PER_RAD
from ..errors import NeuralLensError
from .config import NetConfig

#: output columns that are odd under the mirror reduction ωy → −ωy (y and dy of the reduced frame)
ODD_COLUMNS = (1, 3)


def odd_factor(x_wy: np.ndarray, s_max: float | None, n_out: int = 5) -> np.ndarray:
    """(N, n_out) multiplier ``M`` of the odd-output parametrisation: ωy / s_max in the odd columns
    (:data:`ODD_COLUMNS`), 1 elsewhere; all ones when ``s_max`` is None (plain outputs).  ``x_wy``: ωy
    (direction cosine, ≥ 0 in the reduced domain)."""
    M = np.ones((len(x_wy), n_out))
    if s_max is not None:
        for j in ODD_COLUMNS:
            M[:, j] = np.asarray(x_wy, np.float64) / float(s_max)
    return M


#: rows per block of :func:`fit_output_transform`'s two passes (its temporaries stay in the cache)
FIT_BLOCK_ROWS = 1 << 16


#: ``exit_position = "auto"``: a regressor regresses its exit position times |dz|
#: (:func:`~mi_neurallens.neural.model.position_cos`) where its first pool's exit rays reach beyond this angle to the
#: axis: a fisheye's camera map (rays leaving the front at up to 90°); no bundled lens's maps come near it
POSITION_COS_FROM_DEG = 60.0


def wants_position_cos(setting: str, y: np.ndarray) -> bool:
    """Whether a regressor with ``NetConfig.exit_position = setting`` regresses position × |dz|, given reduced-frame
    outputs ``y`` (N, 5) of its first pool: ``"cos"`` yes, ``"plane"`` no, ``"auto"`` where an exit direction lies
    more than :data:`POSITION_COS_FROM_DEG` off the axis."""
    if setting in ("cos", "plane"):
        return setting == "cos"
    s = np.hypot(y[:, 2], y[:, 3]) if len(y) else np.zeros(1)
    return bool(s.max() > math.sin(math.radians(POSITION_COS_FROM_DEG)))


def fit_output_transform(xn: np.ndarray, y: np.ndarray, residual: str, M: np.ndarray | None = None):
    """(skip (c, k), out_shift (c,), out_scale (c,)) of the regressor's output transform
    ``y = M · (shift + skip·xn + scale·network)`` (``M`` from :func:`odd_factor`; None = ones), for inputs
    ``xn`` (N, k) and targets ``y`` (N, c): the linear part is the least-squares fit of y (``residual =
    "linear"``) or the mean (``"none"``), and ``scale`` the spread of what is left, so the network's target
    has about unit variance.

    The fit solves the normal equations, accumulated in float64 over blocks of :data:`FIT_BLOCK_ROWS` rows
    (a (k+1)² system per column: the columns are the normalised inputs, about [−1, 1], and a constant, so it
    is well conditioned), and a second blocked pass takes the residuals' spread.  ``np.linalg.lstsq`` on
    the whole (N, k+1) design matrix cost 0.11 s a column on a map's two million pool rows, mostly memory
    traffic through full-size temporaries: 15 s of a lens's 28 forward maps' set-up."""
    n, k = xn.shape
    c = y.shape[1]
    if residual not in ("linear", "none"):
        raise NeuralLensError(f"unknown residual mode {residual!r}: use 'linear' or 'none'")
    p = k + 1 if residual == "linear" else 1

    def base(sl):
        m = sl.stop - sl.start
        return np.concatenate([xn[sl], np.ones((m, 1))], 1) if p > 1 else np.ones((m, 1))

    blocks = [slice(a, min(a + FIT_BLOCK_ROWS, n)) for a in range(0, n, FIT_BLOCK_ROWS)]
    G, b = np.zeros((c, p, p)), np.zeros((c, p))
    for sl in blocks:
        B = base(sl)
        for j in range(c):
            A = B if M is None else B * M[sl, j:j + 1]
            G[j] += A.T @ A
            b[j] += A.T @ y[sl, j]
    coef = np.stack([np.linalg.lstsq(G[j], b[j], rcond=None)[0] for j in range(c)])   # rank-safe
    s1, s2 = np.zeros(c), np.zeros(c)
    for sl in blocks:
        B = base(sl)
        for j in range(c):
            A = B if M is None else B * M[sl, j:j + 1]
            r = y[sl, j] - A @ coef[j]
            s1[j] += r.sum()
            s2[j] += r @ r
    scale = np.sqrt(np.maximum(s2 / max(n, 1) - (s1 / max(n, 1)) ** 2, 0.0))
    skip = coef[:, :-1] if p > 1 else np.zeros((c, k))
    shift = coef[:, -1]
    scale = np.where(scale > 1e-9, scale, 1e-9)
    return skip, shift, scale


#: accuracy goals per output column (x, y in mm; dx, dy; T relative), used by loss_weights="goals"
GOAL_UNITS = (0.002, 0.002, 5.0 / ARCSEC_PER_RAD, 5.0 / ARCSEC_PER_RAD, 0.005)


def loss_weights(mode: str, oscale, y, direction_weight: float = 1.0) -> np.ndarray:
    """Per-column weights of the standardised MSE.  ``goals``: ∝ std / goal, i.e. columns whose
    residual spread is large compared with their accuracy goal (directions, usually) get more weight;
    normalised to mean 1 and floored at 0.05 so no column is ignored.  ``uniform``: all 1.

    ``direction_weight`` (``NetConfig.direction_weight``) multiplies the direction columns' (dx, dy) weights before
    the normalisation: equal weights in goal units leave a map that meets one goal with room to spare and misses the
    other (a zoom map's position at 0.8 of its goal where its direction is at 1.2), and the loss trades one for the
    other."""
    if mode == "uniform":
        w = np.ones(5)
    elif mode == "goals":
        goal = np.array(GOAL_UNITS, dtype=np.float64)
        goal[4] *= max(float(np.mean(np.abs(y[:, 4]))), 1e-6)
        w = np.asarray(oscale, np.float64) / goal
    else:
        raise NeuralLensError(f"unknown loss_weights {mode!r}: use 'goals' or 'uniform'")
    w[2:4] *= float(direction_weight)
    w = w / w.mean()
    return np.maximum(w, 0.05)


def edge_weights(ps, u: np.ndarray, nc: NetConfig) -> np.ndarray:
    """Per-sample loss weights of valid regressor samples (unit-cube ``u``): ``1 + edge_weight ·
    exp(−margin / edge_margin)``, with the tracer's aperture margin (1 − r²/R² at the tightest aperture,
    :attr:`~mi_neurallens.trace.tracer.TraceResult.margin`).  Rays that graze an aperture land on the
    sharp edge of a ghost, where a few µm of position error is a visible shift of the edge."""
    _, m, _ = ps.margin_u(u)
    return 1.0 + nc.edge_weight * np.exp(-np.maximum(m, 0.0) / nc.edge_margin)
