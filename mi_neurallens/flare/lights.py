"""The emitters that flare: point, spot and directional lights, and the brightest small area emitters."""
from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from .options import FlareOptions


@dataclass
class Light:
    emitter: object
    name: str
    kind: str          # point | spot | directional | area


def scene_lights(scene, opts: FlareOptions):
    """The emitters that flare: point, spot, directional; plus the brightest small area emitters."""
    import mitsuba as mi
    lights, areas = [], []
    for i, e in enumerate(scene.emitters()):
        cls = e.class_().name() if hasattr(e, "class_") else type(e).__name__
        name = f"{e.id() or cls}#{i}"
        fl = e.flags()
        if mi.has_flag(fl, mi.EmitterFlags.DeltaPosition):
            kind = "spot" if "spot" in cls.lower() or "Spot" in str(e) else "point"
            lights.append(Light(e, name, kind))
        elif mi.has_flag(fl, mi.EmitterFlags.DeltaDirection):
            lights.append(Light(e, name, "directional"))
        elif opts.small_emitters > 0 and mi.has_flag(fl, mi.EmitterFlags.Surface) and e.get_shape() is not None:
            sh = e.get_shape()
            bb = sh.bbox()
            diag = float(dr_norm(bb.max - bb.min))
            if diag <= opts.small_emitter_size:
                p = mi.traverse(e)
                val = None
                for k in p.keys():
                    if k.startswith("radiance"):
                        val = np.asarray(p[k], dtype=np.float64).ravel()
                        break
                lum = float(np.mean(val)) if val is not None and val.size else 1.0
                power = math.pi * lum * float(sh.surface_area()[0] if hasattr(sh.surface_area(), '__len__')
                                              else sh.surface_area())
                areas.append((power, Light(e, name, "area")))
    areas.sort(key=lambda t: -t[0])
    lights += [l for _, l in areas[:opts.small_emitters]]
    return lights


def dr_norm(v):
    return math.sqrt(sum(float(c) ** 2 for c in v))
