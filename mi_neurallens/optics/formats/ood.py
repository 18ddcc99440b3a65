"""Open Optical Designer JSON (github.com/alexbock/open-optical-designer; "Save JSON File").

Mapping (see ``docs/lens-format.md``):

* ``radius_of_curvature``: signed R (mm); the string ``"<INFINITY>"`` or ``null`` = flat.
* ``aperture_radius``: clear semi-diameter; ``thickness``: to the next vertex (last: to the image
  plane, kept as written); ``conic_constant``: K (no polynomial terms exist in this format).
* ``material``: the medium after the surface, by name in the app's material list (linear
  interpolation of its index table) via ``resolve_medium({"ood": name})``; ``env_initial_material``
  is the object-space medium.  OOD air is Ciddor air (n ≈ 1.000278), not 1.
* The format has **no stop surface**: the app aims its beams through the axial point
  ``env_beam_cross_distance`` behind the first vertex.  We insert a flat stop there (splitting the
  air gap it falls in; inside glass or outside the lens is an error).  The file has no stop radius
  either: we choose it so that the paraxial entrance-pupil radius at ``center_wavelength`` equals
  ``env_beam_radius`` (the radius of the app's input beams, i.e. its working aperture), clipped to
  what the neighbouring surfaces allow (their clear semi-diameters, and the radius at which their
  sag reaches the stop plane).  ``stop_radius=`` overrides the choice.
"""
from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from ..prescription import Lens, Surface
from ._common import Ctx, is_number, loads_json, number, resolve, type_name

INFINITY = "<INFINITY>"
SURFACE_KEYS = ("radius_of_curvature", "aperture_radius", "thickness", "material", "conic_constant",
                "formula_properties")
AUTOFOCUS = ("off", "paraxial_ray", "marginal_ray", "paraxial_matrix")


def looks_like_ood(doc: Any) -> bool:
    if not isinstance(doc, dict) or not isinstance(doc.get("surfaces"), list):
        return False
    s = doc["surfaces"]
    return (bool(s) and isinstance(s[0], dict) and ("radius_of_curvature" in s[0] or "aperture_radius" in s[0])
            or any(k.startswith("env_") for k in doc))


def load_ood(path: str | os.PathLike, **kw) -> Lens:
    ctx = Ctx(str(path))
    doc = loads_json(ctx, Path(path).read_text(encoding="utf-8-sig"))
    return read_ood(doc, file=str(path), **kw)


def _material(ctx: Ctx, v: Any, *, surface=None, label=None, field="material"):
    if not isinstance(v, str) or not v.strip():
        raise ctx.error(f"must be a material name (e.g. \"Air\", \"PMMA\", \"N-BK7\"), got {type_name(v)} {v!r}",
                        surface=surface, label=label, field=field)
    return resolve(ctx, {"ood": v}, surface=surface, label=label, field=field)


def read_ood(doc: Any, *, file: str | None = None, name: str | None = None,
             stop_radius: float | None = None) -> Lens:
    """Build a :class:`Lens` from a parsed Open Optical Designer document."""
    ctx = Ctx(file or "<Open Optical Designer dict>")
    if not isinstance(doc, dict):
        raise ctx.error(f"an Open Optical Designer file is a JSON object, got {type_name(doc)}")
    rows = doc.get("surfaces")
    if not isinstance(rows, list) or not rows:
        raise ctx.error("must be a non-empty array of surfaces", field="surfaces")

    # ---- environment
    lam_um = number(ctx, doc.get("center_wavelength", 0.55), field="center_wavelength", exclusive_minimum=0)
    if lam_um > 20:
        raise ctx.error(f"is in micrometres (e.g. 0.55), got {lam_um:g}", field="center_wavelength")
    lam_nm = lam_um * 1000.0
    if "env_beam_cross_distance" not in doc:
        raise ctx.error("missing: the format's only stop definition is the axial distance from the first "
                        "vertex where the chief rays cross (\"Aperture Distance\")", field="env_beam_cross_distance")
    z_stop = number(ctx, doc["env_beam_cross_distance"], field="env_beam_cross_distance")
    beam = None
    if stop_radius is None:
        if "env_beam_radius" not in doc:
            raise ctx.error("missing: it sets the working aperture (pass stop_radius= to choose the stop "
                            "radius yourself)", field="env_beam_radius")
        beam = number(ctx, doc["env_beam_radius"], field="env_beam_radius", exclusive_minimum=0)
    obj = _material(ctx, doc.get("env_initial_material", "Air"), field="env_initial_material")
    autofocus = doc.get("env_last_surface_autofocus", "off")
    if autofocus not in AUTOFOCUS:
        raise ctx.error(f"must be one of {', '.join(AUTOFOCUS)}, got {autofocus!r}",
                        field="env_last_surface_autofocus")

    # ---- surfaces as written
    surfs, mats = [], []
    for i, s in enumerate(rows):
        label = str(i + 1)
        where = dict(surface=i, label=label)
        if not isinstance(s, dict):
            raise ctx.error(f"a surface must be an object, got {type_name(s)}", **where)
        for k in ("radius_of_curvature", "aperture_radius", "thickness", "material"):
            if k not in s:
                raise ctx.error("required field is missing", field=k, **where)
        r = s["radius_of_curvature"]
        if r is None or r == INFINITY:
            radius = math.inf
        elif isinstance(r, str):
            raise ctx.error(f"must be a number or \"{INFINITY}\", got {r!r}", field="radius_of_curvature", **where)
        else:
            radius = number(ctx, r, field="radius_of_curvature", **where)
            if radius == 0:
                raise ctx.error(f"radius 0 is not a surface; flat is \"{INFINITY}\"", field="radius_of_curvature",
                                **where)
        sd = number(ctx, s["aperture_radius"], field="aperture_radius", exclusive_minimum=0, **where)
        t = number(ctx, s["thickness"], field="thickness", minimum=0, **where)
        k = number(ctx, s.get("conic_constant", 0.0), field="conic_constant", **where)
        m = _material(ctx, s["material"], **where)
        mats.append(s["material"].strip())
        surfs.append(Surface(radius=radius, thickness=t, medium=m, semi_diameter=sd, conic=k, label=label))
    n = len(surfs)
    if n < 2:
        raise ctx.error("needs at least two surfaces", field="surfaces")

    # ---- insert the stop
    z = np.concatenate([[0.0], np.cumsum([s.thickness for s in surfs[:-1]])])
    if not (0.0 < z_stop < z[-1]):
        raise ctx.error(f"the stop plane z = {z_stop:g} mm lies outside the lens (the vertices run from z = 0 to "
                        f"z = {z[-1]:g} mm); this reader needs a stop between the first and the last surface",
                        field="env_beam_cross_distance")
    k = int(np.searchsorted(z, z_stop, side="right") - 1)  # z[k] <= z_stop < z[k+1]
    if mats[k].lower() != "air":
        raise ctx.error(f"the stop plane z = {z_stop:g} mm falls inside {mats[k]} (between surface {k} at "
                        f"z = {z[k]:g} and surface {k + 1} at z = {z[k + 1]:g}); an aperture stop must sit in "
                        "an air gap", surface=k, label=str(k + 1), field="env_beam_cross_distance")
    front, back = surfs[k], surfs[k + 1]
    limit, limited_by = _stop_limit(front, z[k], back, z[k + 1], z_stop)
    if not limit > 0:
        raise ctx.error(f"no room for a stop at z = {z_stop:g} mm: the neighbouring surfaces reach that plane on "
                        "the axis", surface=k, label=str(k + 1), field="env_beam_cross_distance")
    t_front = _clean(z_stop - z[k])
    stop = Surface(radius=math.inf, thickness=_clean(front.thickness - t_front), medium=front.medium,
                   semi_diameter=limit, is_stop=True, label="STO")
    front = dataclasses.replace(front, thickness=t_front)
    all_s = surfs[:k] + [front, stop] + surfs[k + 1:]

    meta_ood = {
        "center_wavelength_nm": lam_nm,
        "short_wavelength_nm": _um(doc, "short_wavelength", 0.44) * 1000.0,
        "long_wavelength_nm": _um(doc, "long_wavelength", 0.62) * 1000.0,
        "env_beam_radius": beam if beam is not None else doc.get("env_beam_radius"),
        "env_fov_angle_deg": doc.get("env_fov_angle"),
        "env_image_radius": doc.get("env_image_radius"),
        "env_beam_cross_distance": z_stop,
        "env_initial_material": doc.get("env_initial_material", "Air"),
        "env_last_surface_autofocus": autofocus,
        "formula_properties": any(isinstance(s, dict) and s.get("formula_properties") for s in rows),
        "surface_labels": "labels '1'..'N' are the app's surface numbers; 'STO' is the inserted stop",
    }
    if autofocus != "off":
        meta_ood["note_autofocus"] = ("the app overwrites the last thickness when autofocus is on; the "
                                      "thickness stored in the file is kept")
    md = {"description": "Open Optical Designer design", "source": {"format": "Open Optical Designer JSON"},
          "ood": meta_ood}
    if name is None:
        name = Path(file).stem if file else "ood-lens"
    lens = Lens(tuple(all_s), name=name, object_medium=obj, metadata=md, path=ctx.file)

    si = k + 1
    if stop_radius is not None:
        r = number(ctx, stop_radius, field="stop_radius", exclusive_minimum=0)
        if r > limit * (1 + 1e-12):
            raise ctx.error(f"stop radius {r:g} mm is larger than the neighbouring surfaces allow ({limit:.6g} mm, "
                            f"{limited_by})", surface=si, label="STO", field="stop_radius")
        rule = "stop_radius given by the caller"
    else:
        epr_at_limit = float(lens.paraxial(lam_nm).entrance_pupil_radius)
        r = min(limit, limit * beam / epr_at_limit)
        rule = (f"chosen so that the paraxial entrance-pupil radius at {lam_nm:g} nm equals env_beam_radius "
                f"({beam:g} mm)" + (f", clipped to {limit:.6g} mm ({limited_by})" if r >= limit else ""))
    lens = lens.with_stop_radius(r)
    epr = float(lens.paraxial(lam_nm).entrance_pupil_radius)
    meta_ood["stop"] = {"z_mm": z_stop, "radius_mm": r, "rule": rule, "limit_mm": limit,
                        "limited_by": limited_by, "entrance_pupil_radius_mm": epr,
                        "clipped": stop_radius is None and r >= limit}
    return lens


def _clean(x: float) -> float:
    """Drop float noise from sums of decimal thicknesses (33.7 − 30 → 3.7, not 3.700000000000003)."""
    return float(f"{float(x):.12g}")


def _um(doc, key, default):
    v = doc.get(key, default)
    return float(v) if is_number(v) else default


def _stop_limit(front: Surface, z0: float, back: Surface, z1: float, zs: float) -> tuple[float, str]:
    """Largest stop radius at zs that neither neighbour's clear aperture nor sag forbids."""
    cands = [(front.semi_diameter, f"clear semi-diameter of the surface in front ({front.semi_diameter:g} mm)"),
             (back.semi_diameter, f"clear semi-diameter of the surface behind ({back.semi_diameter:g} mm)")]
    # front surface must stay at or before the stop plane: z0 + sag(r) <= zs
    r = _first_crossing(lambda rr: zs - (z0 + front.sag(rr)), front.semi_diameter)
    if r is not None:
        cands.append((r, f"the surface in front reaches the stop plane at r = {r:.6g} mm"))
    r = _first_crossing(lambda rr: (z1 + back.sag(rr)) - zs, back.semi_diameter)
    if r is not None:
        cands.append((r, f"the surface behind reaches the stop plane at r = {r:.6g} mm"))
    return min(cands, key=lambda c: c[0])


def _first_crossing(gap, rmax: float) -> float | None:
    """Smallest r in [0, rmax] where gap(r) < 0 (bisection), or None."""
    rs = np.linspace(0.0, rmax, 4097)
    g = np.asarray(gap(rs))
    bad = np.nonzero(~(g >= 0))[0]
    if not bad.size:
        return None
    j = bad[0]
    if j == 0:
        return 0.0
    lo, hi = rs[j - 1], rs[j]
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if gap(mid) >= 0:
            lo = mid
        else:
            hi = mid
    return float(lo)
