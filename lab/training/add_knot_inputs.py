"""Give a zoom lens's learned maps the knot inputs (transport/configurations.py, ``knot_monomials``) without
changing what they compute: the configurations' product monomials extended, every network's first layer and every
linear skip given zero columns for the new inputs, the input normalisation extended with the domain's.  A
finish-only run on the result (``mi-neurallens train LENS --finish-only maps --base OUT``) then learns to use them.

Written for issue 55: the EF 24-70's bundled map was trained before the knot inputs existed (27 inputs; a fresh
training now gives it 33).

    python lab/training/add_knot_inputs.py canon-ef-24-70mm-f2.8l /tmp/knot/base.model.safetensors
"""
from __future__ import annotations

import argparse
import dataclasses

import numpy as np


def pad(W, n_in):
    W = np.asarray(W, np.float64)
    return np.hstack([W, np.zeros((W.shape[0], n_in - W.shape[1]))])


def with_knot_inputs(tm):
    from mi_neurallens.transport.configurations import knot_monomials
    dom = tm.domain
    cond = dom.conditions
    if cond is None or "zoom" not in cond.names:
        return tm
    positions = int(round(cond.zoom_range[1] - cond.zoom_range[0])) + 1
    new = tuple(m for m in knot_monomials(positions) if m not in cond.monomials)
    if not new:
        return tm
    dom2 = dataclasses.replace(dom, conditions=dataclasses.replace(cond, monomials=cond.monomials + new))
    n_old, n_in = len(tm.input_center), dom2.n_inputs
    c, s = dom2.norm_center_scale()
    first = lambda layers: [(pad(layers[0][0], n_in), np.asarray(layers[0][1]))] + list(layers[1:])
    head = tm.stop_head
    if head is not None:
        head = dataclasses.replace(head, layers=first(head.layers), skip=pad(head.skip, n_in))
    print(f"{tm.key}: {n_old} -> {n_in} inputs (monomials {new})")
    return dataclasses.replace(tm, domain=dom2, input_center=np.concatenate([tm.input_center, c[n_old:]]),
                               input_scale=np.concatenate([tm.input_scale, s[n_old:]]),
                               classifier=first(tm.classifier), regressor=first(tm.regressor),
                               skip=pad(tm.skip, n_in), stop_head=head)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("lens")
    ap.add_argument("out")
    a = ap.parse_args()
    import mi_neurallens as nl
    from mi_neurallens.neural.model import bundled_model_path, load_model
    lens = nl.Lens.load(a.lens)
    model = load_model(bundled_model_path(a.lens), lens)
    model.maps = {k: with_knot_inputs(tm) for k, tm in model.maps.items()}
    model.save(a.out)
    from mi_neurallens.training.evaluate import map_outputs_np
    again = load_model(a.out, lens)
    base = load_model(bundled_model_path(a.lens), lens)
    for k, tm in again.maps.items():          # the same function, read back from the file
        u = np.random.default_rng(0).random((20000, tm.domain.dims))
        l0, y0 = map_outputs_np(base.maps[k], base.maps[k].domain.u_to_x(u))
        l1, y1 = map_outputs_np(tm, tm.domain.u_to_x(u))
        print(f"{k}: {tm.domain.n_inputs} inputs; max |logit diff| {np.abs(l1 - l0).max():.3g}, "
              f"max |output diff| {np.abs(y1 - y0).max():.3g}")
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
