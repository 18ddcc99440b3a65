"""Merging trained maps into one model file (a retrained map into a bundled model; the jobs of a
distributed training into the lens's model)."""
from __future__ import annotations

from ..errors import ModelError


def merge_models(src, dst, keys=None) -> list:
    """Copy the maps ``keys`` (default: all) of the model ``src`` into the model ``dst`` (both
    :class:`~mi_neurallens.neural.model.NeuralLensModel` of the same lens and planes; ``dst`` changes in
    place).  ``dst`` keeps its ghost ranking; its ``ghosts_trained`` becomes the ghost maps it now holds,
    in ranking order.  Returns the keys copied."""
    if src.fingerprint != dst.fingerprint:
        raise ModelError(f"a model of lens {src.lens_name} ({src.fingerprint}) cannot be merged into one of "
                         f"{dst.lens_name} ({dst.fingerprint})")
    if abs(src.z_front - dst.z_front) > 1e-9 or abs(src.z_rear - dst.z_rear) > 1e-9:
        raise ModelError("the two models use different planes (different close_focus_mm?)")
    keys = list(src.maps) if not keys else list(keys)
    for k in keys:
        if k not in src.maps:
            raise ModelError(f"the source model has no map {k!r}; it has {sorted(src.maps)}")
        dst.maps[k] = src.maps[k]
    for k, v in src.extra.items():
        dst.extra.setdefault(k, v)
    order = [int(d["path_id"]) for d in dst.extra.get("ghost_ranking", [])]
    have = set(dst.ghost_ids)
    dst.extra["ghosts_trained"] = [p for p in order if p in have] + sorted(have - set(order))
    return keys
