"""A learned ghost map's flare error, verified against the tracer on the same samples.

The held-out metrics of a map (exit position in µm, misclassification) do not say how wrong its *flare*
is: a ghost's image also depends on where its classifier's edge sits and on how its errors add up over
the film.  This module measures that directly, the protocol of ``benchmarks/flare_edges.py``:

* a point light in front of the lens (``scenes/night_point.xml``: 100 W/sr at ``light`` m, the camera at
  the origin looking down +z), a small film;
* the ghost rendered alone, once by the tracer and once by its learned map, **with the same samples**
  (``pilot_with = "exact"``, same seed: common random numbers), so Monte Carlo noise cancels and what is
  left is the map's own error;
* the paired MAPE: the mean relative luminance error over the pixels where the exact ghost is brighter
  than 1 % of its peak (:func:`mi_neurallens.metrics.flare_error_map`).

:func:`verify_model` measures every forward ghost map of a model at a few light positions and keeps the
largest error; ``mi-neurallens evaluate MODEL --flare --write`` records it in the model file
(``metrics["flare"]`` of each map), where the flare's mode ``auto`` reads it (``auto_max_flare_error``).
"""
from __future__ import annotations

#: light positions (m; x, y at z = 5 m in front of the lens): the night scene's (10° / 5° off axis) and one
#: near the axis, where the ghosts overlap most and the maps' errors showed most (docs/results.md)
LIGHTS = ((0.9, 0.45), (0.15, 0.1))
#: the film of the verification renders (pixels; 36 mm wide on a full-frame sensor: 150 µm pixels)
FILM = (240, 160)
#: default samples of each render (all on one ghost; 2^24 ≈ 440 per film pixel, more on the ghost's mask: the
#: paired error converges only with many samples per pixel, where a learned ray landing one pixel over no longer
#: shows)
SAMPLES_LOG2 = 24


def verification_scene(lens, model, light=LIGHTS[0], film=FILM):
    """The night_point scene as a dict: ``neural_lens`` with ``model`` (a file or bundled name) through
    ``lens``, one point light at ``(x, y, 5)`` m.  The current Mitsuba variant."""
    import mitsuba as mi
    import mi_neurallens
    mi_neurallens.register()
    return mi.load_dict({
        "type": "scene",
        "camera": {"type": "neural_lens", "lens": lens, "model": str(model),
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[0, 0, 1], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": int(film[0]), "height": int(film[1]),
                            "pixel_format": "rgb"}},
        "light": {"type": "point", "position": [float(light[0]), float(light[1]), 5.0],
                  "intensity": {"type": "rgb", "value": 100.0}},
    })


def paired_renders(scene, ghosts, samples, seed=1, sensor=0):
    """(exact, learned) flare images (H×W×3 numpy) of ``ghosts`` on the same samples."""
    from .render import render_flare
    ex = render_flare(scene, sensor, seed=seed, ghosts=list(ghosts), samples=samples, mode="exact").total
    ne = render_flare(scene, sensor, seed=seed, ghosts=list(ghosts), samples=samples, mode="neural",
                      pilot_with="exact").total
    return ex, ne


def paired_flare_error(scene, pid, samples=1 << SAMPLES_LOG2, seed=1) -> dict:
    """The learned map of ghost ``pid`` against the tracer on the same samples: ``paired_mape`` (None when
    the exact ghost leaves no pixel above the mask threshold: nothing to compare), ``pixels`` in the
    mask, ``flux_ratio`` (learned / exact luminance)."""
    import numpy as np
    from ..metrics import LUMINANCE, flare_error_map
    ex, ne = paired_renders(scene, [pid], samples, seed)
    rel, mask = flare_error_map(ne, ex)
    ye, yn = float(np.sum(ex[..., :3] @ LUMINANCE)), float(np.sum(ne[..., :3] @ LUMINANCE))
    return {"paired_mape": float(rel[mask].mean()) if mask.any() else None, "pixels": int(mask.sum()),
            "flux_ratio": yn / ye if ye > 0 else None}


def verify_model(model_path, lens=None, *, ghosts=None, lights=LIGHTS, samples_log2=SAMPLES_LOG2, film=FILM,
                 log=print) -> dict:
    """Every forward ghost map (or those of ``ghosts``) of the model at ``model_path`` against the tracer:
    {path_id: record}, the record ``metrics["flare"]`` keeps — ``paired_mape`` the largest over ``lights``
    (None if the ghost reached no pixel at any of them), the per-light values and flux ratios, and the
    protocol (samples, film, lights).  ``lens``: a bundled name or a lens file (default: the model's lens)."""
    from ..neural.model import load_model
    model = load_model(model_path)
    lens = lens or model.lens_name
    ids = [pid for pid in (model.ghost_ids if ghosts is None else ghosts) if model.has(pid, "forward")]
    per = {pid: [] for pid in ids}
    for light in lights:
        scene = verification_scene(lens, model_path, light, film)
        for k, pid in enumerate(ids):
            r = paired_flare_error(scene, pid, 1 << samples_log2)
            per[pid].append(r)
            if log:
                m = "no pixel" if r["paired_mape"] is None else f"{r['paired_mape']:.4f}"
                log(f"light {light}: ghost {pid} ({k + 1}/{len(ids)}) paired MAPE {m}")
    out = {}
    for pid, rs in per.items():
        vals = [r["paired_mape"] for r in rs if r["paired_mape"] is not None]
        out[pid] = {"paired_mape": max(vals) if vals else None,
                    "per_light": [r["paired_mape"] for r in rs],
                    "flux_ratio": [r["flux_ratio"] for r in rs],
                    "lights_m": [[float(x), float(y), 5.0] for x, y in lights],
                    "log2_samples": int(samples_log2), "film": [int(film[0]), int(film[1])],
                    "protocol": "paired (same samples, pilot_with=exact), mask > 1 % of the exact ghost's peak"}
    return out
