"""Merging trained maps into one model file (a retrained map into a bundled model; the jobs of a
distributed training into the lens's model)."""
from __future__ import annotations

from ..errors import ModelError
from .whole_lens import has_run, runs_with_times


def merge_models(src, dst, keys=None) -> list:
    """Copy the maps ``keys`` (default: all) of the model ``src`` into the model ``dst`` (both
    :class:`~mi_neurallens.neural.model.NeuralLensModel` of the same lens and planes; ``dst`` changes in
    place).  ``dst`` keeps its ghost ranking; its ``ghosts_trained`` becomes the ghost maps it now holds,
    in ranking order, and its training runs gain ``src``'s (each marked with the maps merged from it:
    ``merged_maps``; the run that wrote ``src`` also with the time ``src`` records, ``seconds``), so the file
    still says how every map it holds was made.  A copied map without a stop
    head keeps the stop head of the map it replaces when both have the same path, planes and domain
    (:func:`keep_stop_head`), so retraining a map's classifier and regressor does not take away its
    render-time aperture.  Returns the keys copied."""
    if src.fingerprint != dst.fingerprint:
        raise ModelError(f"a model of lens {src.lens_name} ({src.fingerprint}) cannot be merged into one of "
                         f"{dst.lens_name} ({dst.fingerprint})")
    if abs(src.z_front - dst.z_front) > 1e-9 or abs(src.z_rear - dst.z_rear) > 1e-9:
        raise ModelError("the two models use different planes (different close_focus_mm?)")
    keys = list(src.maps) if not keys else list(keys)
    for k in keys:
        if k not in src.maps:
            raise ModelError(f"the source model has no map {k!r}; it has {sorted(src.maps)}")
        dst.maps[k] = keep_stop_head(src.maps[k], dst.maps.get(k))
    runs = [r for r in dst.extra.get("runs", []) if isinstance(r, dict)]
    for r in runs_with_times(src):          # the time src's file records is its own run's
        if not has_run(runs, r):
            runs.append({**r, "merged_maps": keys})
    for k, v in src.extra.items():
        dst.extra.setdefault(k, v)
    if runs:
        dst.extra["runs"] = runs
    order = [int(d["path_id"]) for d in dst.extra.get("ghost_ranking", [])]
    have = set(dst.ghost_ids)
    dst.extra["ghosts_trained"] = [p for p in order if p in have] + sorted(have - set(order))
    return keys


def keep_stop_head(new, old):
    """``new`` (a :class:`~mi_neurallens.neural.model.NeuralMap`) with the stop head of ``old`` when ``new``
    has none and ``old`` has one for the same path, direction, planes and domain: the stop head maps the
    same input rays to their stop-plane crossings, whatever the classifier and regressor beside it, so it
    stays valid (its held-out metrics come with it; ``training["stop_head_kept_from"]`` says so).
    Otherwise ``new`` unchanged."""
    import dataclasses
    if new.stop_head is not None or old is None or getattr(old, "stop_head", None) is None:
        return new
    same = (new.path_id == old.path_id and new.direction == old.direction
            and abs(new.z_in - old.z_in) < 1e-9 and abs(new.z_out - old.z_out) < 1e-9
            and new.domain.to_dict() == old.domain.to_dict())
    if not same:
        return new
    metrics = dict(new.metrics)
    if "stop" in old.metrics:
        metrics["stop"] = old.metrics["stop"]
    training = {**new.training, "stop_head_kept_from": old.training.get("config_digest")}
    return dataclasses.replace(new, stop_head=old.stop_head, metrics=metrics, training=training)
