"""LensVisualizer lens data (github.com/ronbuening/LensVisualizer ``src/lens-data/<maker>/<Name>.data.ts``),
as the numeric JSON extracts in the shared lens data (``other/*.json``; key names unchanged).

Mapping (see ``docs/lens-format.md``):

* ``surfaces[]``: ``{label, R, d, nd, elemId, sd}``.  ``R`` signed radius (|R| ≥ 1e12, e.g. the
  file's 1e15, = flat); ``d`` to the next vertex (the last ``d`` is kept as the image distance);
  ``nd`` index after the surface (checked against the element); ``elemId`` the element that follows
  (0 = air); ``sd`` clear semi-diameter.  The surface labelled ``STO`` is the aperture stop.
* ``asph``: ``{label: {K, A4, A6, …}}`` -> conic and A4…A16 of that surface.  Non-zero odd terms,
  A2 or terms beyond A16 are refused (our sag has none of them).
* ``elements[]``: ``{id, nd, vd, nC?, nF?, ng?, indexReference?}`` -> the element's medium:
  patent line indices (nC, nF [, ng]) -> ``lines_glass``; otherwise ``model_glass(nd, vd)``.
  ``indexReference: "e"`` means the numbers are e-line values (ne, νe with F′, C′): with line
  indices they go to ``lines_glass`` as ne; without, a model glass is fitted so that it reproduces
  ne at 546.074 nm and νe = (ne − 1)/(nF′ − nC′) exactly (see :func:`eline_model_glass`).
* ``var`` (variable gaps): read as the lens's moving groups (:mod:`mi_neurallens.optics.moving`) — per labelled
  gap ``[d_inf, d_close]`` (primes) or one such pair per ``zoomPositions`` entry (zooms); ``closeFocusM`` the close
  focus (m from the sensor plane).  Whether the close-focus gaps are the patent's or the catalogue author's
  computation is not recorded in the files: close gaps written with more decimals than every infinity gap of the
  lens are taken as computed (``close_gaps: "modelled"``), the others as ``"published"``.  With ``focus="close"``
  and/or ``zoom=k`` the reader returns instead that one configuration, without moving groups.
"""
from __future__ import annotations

import math
import os
from pathlib import Path
import re
from typing import Any

import numpy as np

from ...errors import LensError
from ..glass import AIR, LAMBDA_C, LAMBDA_D, LAMBDA_F, Medium
from ..prescription import MAX_ASPHERIC, Lens, Surface
from ._common import Ctx, is_number, loads_json, number, resolve, type_name

FLAT_R = 1e12
LAMBDA_E = 546.0740
LAMBDA_F_PRIME = 479.9914
LAMBDA_C_PRIME = 643.8469
_ASPH_KEY = re.compile(r"^A(\d+)$")
#: top-level keys copied into Lens.metadata["lensvisualizer"]
_META_KEYS = ("key", "maker", "name", "subtitle", "specs", "focalLengthMarketing", "focalLengthDesign",
              "apertureMarketing", "apertureDesign", "nominalFno", "lensMounts", "imageFormat",
              "patentNumber", "patentAuthors", "patentAssignees", "patentYear", "elementCount",
              "groupCount", "closeFocusM", "projection", "zoomPositions", "zoomLabels", "var",
              "fstopSeries", "maxFstop")


def looks_like_lensvisualizer(doc: Any) -> bool:
    if not isinstance(doc, dict) or not isinstance(doc.get("surfaces"), list):
        return False
    s = doc["surfaces"]
    return isinstance(doc.get("elements"), list) and bool(s) and isinstance(s[0], dict) and (
        "elemId" in s[0] or ("R" in s[0] and "sd" in s[0]))


def load_lensvisualizer(path: str | os.PathLike, **kw) -> Lens:
    ctx = Ctx(str(path))
    doc = loads_json(ctx, Path(path).read_text(encoding="utf-8-sig"))
    return read_lensvisualizer(doc, file=str(path), **kw)


def eline_model_glass(ne: float, ve: float, name: str | None = None) -> Medium:
    """A model glass with n(546.074 nm) = ne and (ne − 1)/(n(F′) − n(C′)) = νe.

    ``model_glass`` is parameterised by (nd, Vd); this solves for the (nd, Vd) whose model glass has
    the requested e-line values (a few fixed-point steps; exact to ~1e-12).
    """
    nd, vd = float(ne), float(ve)
    m = None
    for _ in range(60):
        m = _model(nd, vd, name)
        ne_m = float(m.index(LAMBDA_E))
        dn = float(m.index(LAMBDA_F_PRIME) - m.index(LAMBDA_C_PRIME))
        ve_m = (ne_m - 1.0) / dn if dn else math.inf
        if abs(ne_m - ne) < 1e-13 and (math.isinf(ve) or abs(ve_m - ve) < 1e-10 * ve):
            break
        nd += ne - ne_m
        if math.isfinite(ve) and math.isfinite(ve_m):
            vd *= ve / ve_m
    return m


def _model(nd: float, vd: float, name: str | None) -> Medium:
    from ..glass import model_glass
    return model_glass(nd, vd, name=name)


def read_lensvisualizer(doc: Any, *, file: str | None = None, name: str | None = None,
                        focus: str = "infinity", zoom: int = 0, moving: bool = True) -> Lens:
    """Build a :class:`Lens` from a parsed LensVisualizer document.

    ``focus``: ``"infinity"`` (default; the file's ``d`` values) or ``"close"`` (the second value of each
    ``var`` entry).  ``zoom``: zoom position index for zoom lenses (``zoomPositions``), 0 = the file's.  With
    both defaults the lens carries the file's ``var`` as moving groups, unless ``moving`` is false; otherwise it is
    that one configuration.
    """
    ctx = Ctx(file or "<LensVisualizer dict>")
    if not isinstance(doc, dict):
        raise ctx.error(f"a LensVisualizer file is a JSON object, got {type_name(doc)}")
    rows = doc.get("surfaces")
    if not isinstance(rows, list) or len(rows) < 2:
        raise ctx.error("must be an array of at least two surfaces", field="surfaces")
    if focus not in ("infinity", "close"):
        raise ctx.error(f"focus must be 'infinity' or 'close', got {focus!r}", field="focus")

    elements = _elements(ctx, doc.get("elements", []))
    asph = doc.get("asph", {}) or {}
    if not isinstance(asph, dict):
        raise ctx.error(f"must be an object {{label: {{K, A4, …}}}}, got {type_name(asph)}", field="asph")
    var = _var(ctx, doc, focus, zoom)
    configured = bool(var) or focus != "infinity" or zoom != 0

    labels = []
    for i, s in enumerate(rows):
        if not isinstance(s, dict):
            raise ctx.error(f"a surface must be an object, got {type_name(s)}", surface=i)
        labels.append(str(s.get("label", i + 1)))
    for lab in asph:
        if lab not in labels:
            raise ctx.error(f"aspheric data for label '{lab}', but no surface has that label "
                            f"(labels: {', '.join(labels)})", field=f"asph.{lab}")
    for lab in var:
        if lab not in labels:
            raise ctx.error(f"variable gap for label '{lab}', but no surface has that label", field=f"var.{lab}")
    stops = [i for i, lab in enumerate(labels) if lab.upper() == "STO"]
    if not stops:
        raise ctx.error("no aperture stop: no surface is labelled 'STO'", field="label")
    if len(stops) > 1:
        raise ctx.error(f"a second surface labelled 'STO' (surface {stops[0]} is already the stop)",
                        surface=stops[1], label=labels[stops[1]], field="label")

    media: dict[int, Medium] = {}
    surfaces = []
    for i, s in enumerate(rows):
        label = labels[i]
        where = dict(surface=i, label=label)
        for k in ("R", "d", "nd", "sd"):
            if k not in s:
                raise ctx.error("required field is missing", field=k, **where)
        R = number(ctx, s["R"], field="R", **where)
        if R == 0:
            raise ctx.error("radius 0 is not a surface (flat is written as 1e15)", field="R", **where)
        radius = math.inf if abs(R) >= FLAT_R else R
        d = number(ctx, s["d"], field="d", minimum=0, **where)
        if label in var:
            d = var[label]
        nd = number(ctx, s["nd"], field="nd", minimum=1.0, **where)
        sd = number(ctx, s["sd"], field="sd", exclusive_minimum=0, **where)
        eid = s.get("elemId", 0 if nd == 1.0 else None)
        if not (is_number(eid) and float(eid) == int(eid)):
            raise ctx.error(f"must be an integer element id (0 = air), got {type_name(eid)} {eid!r}",
                            field="elemId", **where)
        eid = int(eid)
        if eid == 0:
            if abs(nd - 1.0) > 1e-9:
                raise ctx.error(f"elemId 0 means air, but nd is {nd:g}", field="nd", **where)
            medium = AIR
        else:
            if eid not in elements:
                raise ctx.error(f"element {eid} is not in elements[] (ids: {sorted(elements)})", field="elemId",
                                **where)
            el = elements[eid]
            if abs(float(el["nd"]) - nd) > 2e-6:
                raise ctx.error(f"nd {nd:.6f} disagrees with element {eid}'s nd {float(el['nd']):.6f}",
                                field="nd", **where)
            if eid not in media:
                media[eid] = _element_medium(ctx, el, i, label)
            medium = media[eid]
        conic, aspheric = 0.0, ()
        if label in asph:
            conic, aspheric = _asph(ctx, asph[label], i, label)
        elif re.fullmatch(r"\d+A", label):
            raise ctx.error(f"label '{label}' marks an aspheric surface but 'asph' has no entry for it",
                            field="asph", **where)
        is_stop = i == stops[0]
        if is_stop and (not math.isinf(radius) or conic or aspheric):
            raise ctx.error(f"the stop (STO) must be flat (R ≥ {FLAT_R:g}), got R = {R:g}", field="R", **where)
        surfaces.append(Surface(radius=radius, thickness=d, medium=medium, semi_diameter=sd, conic=conic,
                                aspheric=aspheric, is_stop=is_stop, label=label))

    meta = {k: doc[k] for k in _META_KEYS if k in doc}
    meta["focus"] = focus
    meta["zoom_position"] = zoom
    moving = None if (configured or not moving) else _moving(ctx, doc, labels)
    meta["media"] = {str(e): m.name for e, m in media.items()}
    notes = [f"surfaces with |R| ≥ {FLAT_R:g} are flat",
             "the last 'd' is kept as the image distance (as printed in the patent)",
             "element media: lines_glass from the patent's nC/nF(/ng) where given, else model_glass(nd, vd)"]
    if any(str(el.get("indexReference", "d")).lower() == "e" for el in elements.values()):
        notes.append("indexReference 'e': nd/vd hold ne/νe; model glasses reproduce ne at 546.074 nm and νe "
                     "(F′, C′) exactly")
    src = doc.get("_source") if isinstance(doc.get("_source"), dict) else {}
    source = {"format": "LensVisualizer JSON"}
    for a, b in (("repo", "repository"), ("path", "path"), ("commit", "commit")):
        if isinstance(src.get(a), str):
            source[b] = src[a]
    if isinstance(doc.get("patentNumber"), str):
        source["reference"] = doc["patentNumber"] + (f" — {doc['subtitle']}" if isinstance(doc.get("subtitle"), str)
                                                     else "")
    md = {"description": str(doc.get("name", "")), "source": source, "lensvisualizer": meta, "notes": notes}
    if name is None:
        name = str(doc.get("key") or (Path(file).stem if file else "lens"))
    return Lens(tuple(surfaces), name=name, object_medium=AIR, moving=moving, metadata=md, path=ctx.file)


def _elements(ctx: Ctx, els: Any) -> dict[int, dict]:
    if not isinstance(els, list):
        raise ctx.error(f"must be an array, got {type_name(els)}", field="elements")
    out = {}
    for j, e in enumerate(els):
        f = f"elements[{j}]"
        if not isinstance(e, dict):
            raise ctx.error(f"must be an object, got {type_name(e)}", field=f)
        eid = e.get("id")
        if not (is_number(eid) and float(eid) == int(eid) and int(eid) > 0):
            raise ctx.error(f"must be a positive integer, got {eid!r}", field=f"{f}.id")
        if int(eid) in out:
            raise ctx.error(f"duplicate element id {int(eid)}", field=f"{f}.id")
        number(ctx, e.get("nd"), field=f"{f}.nd", minimum=1.0)
        out[int(eid)] = e
    return out


def _element_medium(ctx: Ctx, el: dict, i: int, label: str) -> Medium:
    eid = int(el["id"])
    f = f"elements[id={eid}]"
    where = dict(surface=i, label=label)
    ref = str(el.get("indexReference", "d")).lower()
    if ref not in ("d", "e"):
        raise ctx.error(f"indexReference must be 'd' or 'e', got {el.get('indexReference')!r}",
                        field=f"{f}.indexReference", **where)
    n0 = number(ctx, el["nd"], field=f"{f}.nd", minimum=1.0, **where)
    lines = {}
    for k in ("nC", "nF", "ng"):
        if el.get(k) is not None:
            lines[k] = number(ctx, el[k], field=f"{f}.{k}", minimum=1.0, **where)
    nm = str(el.get("name") or f"element {eid}")
    if isinstance(el.get("glass"), str) and el["glass"].strip():
        nm += f": {el['glass'].strip()}"
    if "nC" in lines and "nF" in lines:
        if ref == "e":
            # lines_glass needs nd: interpolate it from C, e, F (n² = a + b/λ² + c/λ⁴), then fit all lines
            spec = {"nd": _nd_from_cef(lines["nC"], n0, lines["nF"]), "ne": n0, **lines, "name": nm}
        else:
            spec = {"nd": n0, **lines, "name": nm}
        return resolve(ctx, spec, field=f"{f}.nC", **where)
    v = number(ctx, el.get("vd"), field=f"{f}.vd", exclusive_minimum=0.0, **where)
    if ref == "e":
        try:
            return eline_model_glass(n0, v, name=nm)
        except LensError as e:  # GlassError from model_glass: add the location
            raise ctx.error(f"cannot build a model glass from ne={n0}, ve={v}: {e.what}", field=f"{f}.vd",
                            **where) from None
    return resolve(ctx, {"nd": n0, "vd": v, "name": nm}, field=f"{f}.vd", **where)


def _nd_from_cef(nC: float, ne: float, nF: float) -> float:
    lam = np.array([LAMBDA_C, LAMBDA_E, LAMBDA_F]) * 1e-3
    A = np.stack([np.ones(3), lam ** -2, lam ** -4], axis=1)
    a = np.linalg.solve(A, np.array([nC, ne, nF]) ** 2)
    ld = LAMBDA_D * 1e-3
    return float(np.sqrt(a[0] + a[1] * ld ** -2 + a[2] * ld ** -4))


def _asph(ctx: Ctx, a: Any, i: int, label: str) -> tuple[float, tuple[float, ...]]:
    where = dict(surface=i, label=label)
    if not isinstance(a, dict):
        raise ctx.error(f"must be an object {{K, A4, A6, …}}, got {type_name(a)}", field=f"asph.{label}", **where)
    k = 0.0
    coef = {}
    for key, v in a.items():
        f = f"asph.{label}.{key}"
        if key == "K":
            k = number(ctx, v, field=f, **where)
            continue
        m = _ASPH_KEY.match(key)
        if not m:
            raise ctx.error(f"unknown aspheric key '{key}' (expected K, A4, A6, …, A16)", field=f, **where)
        p = int(m.group(1))
        x = number(ctx, v, field=f, **where)
        if x == 0.0:
            continue
        if p % 2:
            raise ctx.error(f"odd aspheric term {key} = {x:g} is not supported (the sag has even terms "
                            "A4 … A16 only)", field=f, **where)
        if p < 4 or p > 2 * (MAX_ASPHERIC + 1):
            raise ctx.error(f"aspheric term {key} = {x:g} is not supported (even terms A4 … A16 only)",
                            field=f, **where)
        coef[p] = x
    top = max(coef) if coef else 2
    return k, tuple(coef.get(p, 0.0) for p in range(4, top + 1, 2))


def _var(ctx: Ctx, doc: dict, focus: str, zoom: int) -> dict[str, float]:
    """label -> gap for the requested focus/zoom; empty for the default (file's d values)."""
    var = doc.get("var", {}) or {}
    if not isinstance(var, dict):
        raise ctx.error(f"must be an object, got {type_name(var)}", field="var")
    zooms = doc.get("zoomPositions")
    nz = len(zooms) if isinstance(zooms, list) else 1
    if not (isinstance(zoom, int) and 0 <= zoom < nz):
        raise ctx.error(f"zoom position must be an integer in 0 … {nz - 1} (zoomPositions: {zooms}), got {zoom!r}",
                        field="zoom")
    if focus == "infinity" and zoom == 0:
        return {}
    fi = 0 if focus == "infinity" else 1
    out = {}
    for lab, v in var.items():
        f = f"var.{lab}"
        if isinstance(zooms, list):
            if not (isinstance(v, list) and len(v) == nz):
                raise ctx.error(f"must list [d_inf, d_close] for each of the {nz} zoom positions", field=f)
            v = v[zoom]
        if not (isinstance(v, list) and len(v) == 2):
            raise ctx.error("must be [d_inf, d_close]", field=f)
        out[lab] = number(ctx, v[fi], field=f, minimum=0)
    return out


def _decimals(v: float) -> int:
    """Decimal places of ``v`` as written (at most 15)."""
    t = repr(float(v))
    return 0 if "e" in t or "." not in t else len(t.split(".")[1].rstrip("0"))


def _moving(ctx: Ctx, doc: dict, labels: list):
    """The file's ``var`` as :class:`~mi_neurallens.optics.moving.MovingGroups` (None without variable gaps)."""
    from ..moving import MovingGroups
    var = doc.get("var", {}) or {}
    if not var:
        return None
    zooms = doc.get("zoomPositions")
    pairs = {}
    for lab, v in var.items():
        rows = v if isinstance(zooms, list) else [v]
        pairs[labels.index(lab)] = [(number(ctx, a, field=f"var.{lab}", minimum=0),
                                     number(ctx, b, field=f"var.{lab}", minimum=0)) for a, b in rows]
    inf_digits = max(_decimals(a) for v in pairs.values() for a, _ in v)
    focuses = any(a != b for v in pairs.values() for a, b in v)
    modelled = any(_decimals(b) > inf_digits for v in pairs.values() for _, b in v)
    close = doc.get("closeFocusM")
    try:
        return MovingGroups(pairs, zoom_efl_mm=[float(z) for z in zooms] if isinstance(zooms, list) else None,
                            close_focus_mm=float(close) * 1000.0 if is_number(close) and focuses else None,
                            close_gaps=("modelled" if modelled else "published") if focuses else None,
                            focus_label="LensVisualizer var" + (" (close gaps written with more digits than the "
                                                                "infinity gaps: computed)" if modelled else ""))
    except LensError as e:
        raise ctx.error(str(e), field="var") from e
