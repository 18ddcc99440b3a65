"""The bokeh test scene and its measurements: the blur disc of a small on-axis light, seen out of focus,
whose image is the iris's shape (tests/test_aperture.py)."""
from __future__ import annotations

import numpy as np

#: the point light of the bokeh scene: on axis, this far from the sensor plane (m), its radius (m) and radiance
BOKEH_LIGHT_M, BOKEH_LIGHT_RADIUS_M, BOKEH_RADIANCE = 4.0, 0.004, 1e3


def bokeh_scene(kind: str, lens: str, fstop: float, blades: int, focus_m: float, width_mm: float, res: int,
                spp: int, *, rotation_deg: float = 0.0, model: str | None = None, light_m: float = BOKEH_LIGHT_M,
                radius_m: float = BOKEH_LIGHT_RADIUS_M) -> dict:
    """A ``mi.load_dict`` scene whose image is the iris's shape: a small bright sphere (``radius_m``, radiance
    :data:`BOKEH_RADIANCE`) on the axis ``light_m`` from the sensor, seen out of focus by the sensor ``kind``
    (``"realistic_lens"`` or ``"neural_lens"``, with ``model``: default the lens's bundled one) focused at
    ``focus_m``, at ``fstop`` with ``blades`` blades turned by ``rotation_deg``; a ``res``² film ``width_mm``
    wide (crop it to the blur disc), box filter, ``spp`` independent samples, a path tracer of depth 2."""
    s = {"type": kind, "lens": lens, "focus_distance": focus_m, "fstop": fstop, "blades": blades,
         "blade_rotation": rotation_deg, "sensor_width": width_mm,
         "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
         "sampler": {"type": "independent", "sample_count": spp}}
    if kind == "neural_lens":
        s["model"] = model or lens
    return {"type": "scene", "integrator": {"type": "path", "max_depth": 2}, "sensor": s,
            "light": {"type": "sphere", "center": [0, 0, light_m], "radius": radius_m,
                      "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [BOKEH_RADIANCE] * 3}}}}


def disc_mask(image) -> np.ndarray:
    """The blur disc of a :func:`bokeh_scene` image (H×W or H×W×3, then its green channel): the pixels above 10 %
    of the mean of the non-zero ones (the issue-16 bokeh protocol)."""
    g = np.asarray(image, np.float64)
    g = g[..., 1] if g.ndim == 3 else g
    return g > 0.1 * g[g > 0].mean()


def mask_iou(a, b) -> float:
    """Intersection over union of two boolean masks (1 when both are empty)."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    union = (a | b).sum()
    return float((a & b).sum() / union) if union else 1.0
