"""A network trained on its valid rays' bounding box, folded back into the map's own input normalisation.

A learned map normalises its reduced inputs (r, ωx, ωy, λ) over its whole sampled domain
(:meth:`~mi_neurallens.transport.planning.Domain.norm_center_scale`): its classifier must see every ray.  The
regressor and the stop head only ever see the *valid* rays, and a ghost's may fill a corner of that domain
(the Canon EF's ghost 278528: ωy in the lowest quarter of its range, ωx in 60 %), so the network resolves its
function inside a small part of its inputs' range.  With ``NetConfig.input_box`` such a network trains on
inputs normalised over its valid rays' bounding box (:func:`input_box`), and at the end the affine change of
inputs is folded into its first layer and its linear skip (:func:`fold_input_box`): the same function of the
map's normalised inputs, so the model file, the render kernel and the network's cost do not change.
"""
from __future__ import annotations

import numpy as np

#: the margin of :func:`input_box`, a fraction of the valid rays' extent on each side
INPUT_BOX_MARGIN = 0.02


def input_box(x, center, scale):
    """(center, scale) normalising the valid reduced inputs ``x`` (N, 4) over their bounding box widened by
    :data:`INPUT_BOX_MARGIN` of its extent each side, λ (and any column the rays do not spread) left as the
    map's ``center``/``scale``.  Measured for the stop heads (``FORWARD_STOP``): 278528's head reached
    3.98–5.19 µm median on its box where the map's normalisation gave 5.35–5.81 (three runs each, the same
    cost), dgauss-50mm's 28 heads met their goals in 0.83× the time, and the Canon EF's seven three-crossing
    heads came out 5–46 % lower."""
    x = np.asarray(x, np.float64)
    c, s = np.array(center, np.float64), np.array(scale, np.float64)
    lo, hi = x.min(0), x.max(0)
    half = 0.5 * (hi - lo) * (1.0 + 2.0 * INPUT_BOX_MARGIN)
    use = (half > 1e-9 * s) & (np.arange(len(c)) < 3)
    c[use], s[use] = 0.5 * (lo + hi)[use], half[use]
    return c, s


def fold_input_box(layers, skip, shift, box, to):
    """A network trained on inputs normalised by ``box`` = (c_b, s_b) — its ``layers`` ([(W (out, in), b), …])
    and linear ``skip`` (n_out, 4), ``shift`` (n_out,) — as the same function of inputs normalised by ``to`` =
    (c, s): x_b = (c − c_b)/s_b + (s/s_b)·x, absorbed by the first layer and the skip.  Returns (layers, skip,
    shift), float64."""
    (cb, sb), (c, s) = (np.asarray(v, np.float64) for v in box), (np.asarray(v, np.float64) for v in to)
    a, d = s / sb, (c - cb) / sb
    W0, b0 = (np.asarray(v, np.float64) for v in layers[0])
    skip, shift = np.asarray(skip, np.float64), np.asarray(shift, np.float64)
    return ([(W0 * a[None, :], b0 + W0 @ d)] + [(np.asarray(W, np.float64), np.asarray(b, np.float64))
                                                for W, b in layers[1:]], skip * a[None, :], shift + skip @ d)


def is_box(box, center, scale) -> bool:
    """Whether ``box`` = (c_b, s_b) differs from the map's normalisation (``center``, ``scale``)."""
    return not (np.array_equal(np.asarray(box[0], np.float64), np.asarray(center, np.float64))
                and np.array_equal(np.asarray(box[1], np.float64), np.asarray(scale, np.float64)))
