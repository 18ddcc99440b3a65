"""The project's own lens format: strict JSON, read and written here.

Layout (see ``docs/lens-format.md`` and the JSON Schema ``mi_neurallens/data/lens.schema.json``)::

    {"format": "mi-neurallens-lens", "version": 1, "name": "...", "description": "...",
     "units": "mm", "object_medium": <medium spec>,
     "surfaces": [{"label", "radius", "thickness", "medium", "semi_diameter", "conic", "aspheric",
                   "housing_radius", "stop", "blades", "blade_rotation_deg", "coating"}, ...],
     "moving": {"gaps": {"<surface index>": [[d_inf, d_close] per position]}, "zoom_focal_lengths_mm",
                "close_focus_mm", "close_gaps", "note"},            (optional: zoom and focusing groups)
     "source": {provenance}, "metadata": {free-form}}

Unknown keys anywhere (except inside the free-form ``metadata`` and a medium's ``source``) are
errors, so a typo never passes silently.  Wrong types, NaN/Infinity, missing required fields raise
:class:`~mi_neurallens.errors.LensError` naming the file, the surface index and the field.

In memory, the file's ``description`` and ``source`` live in ``Lens.metadata["description"]`` and
``Lens.metadata["source"]``; the other keys of ``Lens.metadata`` are the file's ``metadata`` object.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path
import tempfile
from typing import Any

from ...errors import LensError
from ..glass import AIR, Medium
from ..coatings import COATING_MATERIALS, PRESETS, CoatingStack, Layer, preset
from ..prescription import MAX_ASPHERIC, Coating, Lens, Surface
from ._common import Ctx, check_keys, is_number, loads_json, number, resolve, type_name

FORMAT_ID = "mi-neurallens-lens"
VERSION = 1

TOP_KEYS = ("format", "version", "name", "description", "units", "object_medium", "surfaces",
            "moving", "source", "metadata")
#: the moving groups' keys (:mod:`mi_neurallens.optics.moving`)
MOVING_KEYS = ("gaps", "zoom_focal_lengths_mm", "close_focus_mm", "close_gaps", "stop_semi_diameters_mm", "note")
CLOSE_GAPS = ("published", "modelled")
TOP_REQUIRED = ("format", "version", "name", "surfaces")
SURFACE_KEYS = ("label", "radius", "thickness", "medium", "semi_diameter", "conic", "aspheric",
                "housing_radius", "stop", "blades", "blade_rotation_deg", "coating")
SURFACE_REQUIRED = ("radius", "thickness", "medium", "semi_diameter")
COATING_KEYS = ("index", "design_wavelength_nm")
#: a multilayer stack's keys (``layers`` from the glass outward), a layer's, or a preset's
STACK_KEYS = ("layers", "design_wavelength_nm", "name")
LAYER_KEYS = ("material", "thickness_nm", "waves")
#: provenance keys (all optional, all strings except ``conversion``: a list of strings)
SOURCE_KEYS = ("file", "format", "repository", "path", "commit", "url", "reference", "sha256",
               "conversion")
#: keys of ``Lens.metadata`` that map to top-level fields of the file
RESERVED_METADATA = ("description", "source")


# ---------------------------------------------------------------------------------------- reading
def is_project_json(doc: Any) -> bool:
    return isinstance(doc, dict) and doc.get("format") == FORMAT_ID


def load_project_json(path: str | os.PathLike, **kw) -> Lens:
    """Read a project JSON file."""
    ctx = Ctx(str(path))
    try:
        text = Path(path).read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as e:
        raise ctx.error(f"not UTF-8 text ({e.reason} at byte {e.start})") from None
    return lens_from_dict(loads_json(ctx, text), path=str(path), **kw)


def lens_from_dict(doc: Any, *, path: str | None = None) -> Lens:
    """Build a validated :class:`Lens` from a parsed project-JSON document."""
    ctx = Ctx(path or "<lens dict>")
    if not isinstance(doc, dict):
        raise ctx.error(f"a lens file must be a JSON object, got {type_name(doc)}")
    check_keys(ctx, doc, TOP_KEYS, required=TOP_REQUIRED)
    if doc["format"] != FORMAT_ID:
        raise ctx.error(f"must be \"{FORMAT_ID}\", got {doc['format']!r}", field="format")
    v = doc["version"]
    if not (is_number(v) and float(v) == int(v)):
        raise ctx.error(f"must be the integer {VERSION}, got {type_name(v)} {v!r}", field="version")
    if int(v) != VERSION:
        raise ctx.error(f"version {int(v)} is not supported by this mi-neurallens (it reads version "
                        f"{VERSION}){'; upgrade mi-neurallens' if int(v) > VERSION else ''}",
                        field="version")
    name = doc["name"]
    if not isinstance(name, str) or not name.strip():
        raise ctx.error(f"must be a non-empty string, got {type_name(name)} {name!r}", field="name")
    desc = doc.get("description", "")
    if not isinstance(desc, str):
        raise ctx.error(f"must be a string, got {type_name(desc)}", field="description")
    units = doc.get("units", "mm")
    if units != "mm":
        raise ctx.error(f"only \"mm\" is supported (every length is in millimetres), got {units!r}",
                        field="units")
    source = _read_source(ctx, doc.get("source", {}))
    meta = doc.get("metadata", {})
    if not isinstance(meta, dict):
        raise ctx.error(f"must be an object, got {type_name(meta)}", field="metadata")
    for k in RESERVED_METADATA:
        if k in meta:
            raise ctx.error(f"'{k}' is a top-level field of the lens file, not a metadata key",
                            field=f"metadata.{k}")
    obj = resolve(ctx, doc["object_medium"], field="object_medium") if "object_medium" in doc else AIR

    surfs = doc["surfaces"]
    if not isinstance(surfs, list):
        raise ctx.error(f"must be an array of surface objects, got {type_name(surfs)}", field="surfaces")
    if len(surfs) < 2:
        raise ctx.error(f"a lens needs at least one optical surface and a stop, got {len(surfs)} "
                        "surface(s)", field="surfaces")
    surfaces = [_read_surface(ctx, i, s) for i, s in enumerate(surfs)]
    stops = [i for i, s in enumerate(surfaces) if s.is_stop]
    if not stops:
        raise ctx.error("no surface is marked as the aperture stop: set \"stop\": true on exactly one "
                        "flat surface that sits in an air gap", field="stop")
    if len(stops) > 1:
        raise ctx.error(f"a second aperture stop (surface {stops[0]} is already the stop); exactly one "
                        "surface may have \"stop\": true", surface=stops[1],
                        label=surfaces[stops[1]].label, field="stop")
    metadata = {"description": desc, "source": source, **meta}
    moving = _read_moving(ctx, doc["moving"], len(surfaces)) if "moving" in doc else None
    return Lens(tuple(surfaces), name=name, object_medium=obj, moving=moving, metadata=metadata, path=path)


def _read_moving(ctx: Ctx, m: Any, n_surfaces: int):
    """The ``moving`` object: variable gaps by surface index, each a list of ``[d_infinity, d_close]`` per position."""
    from ..moving import MovingGroups
    if not isinstance(m, dict):
        raise ctx.error(f"must be an object, got {type_name(m)}", field="moving")
    check_keys(ctx, m, MOVING_KEYS, required=("gaps",), prefix="moving.")
    gaps = m["gaps"]
    if not isinstance(gaps, dict) or not gaps:
        raise ctx.error("must be an object {\"<surface index>\": [[d_inf, d_close], ...]} with at least one gap",
                        field="moving.gaps")
    out = {}
    for k, v in gaps.items():
        f = f"moving.gaps.{k}"
        if not (isinstance(k, str) and k.isdigit() and int(k) < n_surfaces):
            raise ctx.error(f"keys are surface indices 0-{n_surfaces - 1}, got {k!r}", field=f)
        if not (isinstance(v, list) and v and all(isinstance(p, list) and len(p) == 2 for p in v)):
            raise ctx.error("must be a list of [d_inf, d_close] pairs, one per position", field=f)
        out[int(k)] = [(number(ctx, a, field=f, exclusive_minimum=0), number(ctx, b, field=f, exclusive_minimum=0))
                       for a, b in v]
    zooms = m.get("zoom_focal_lengths_mm")
    if zooms is not None and not (isinstance(zooms, list) and all(is_number(z) and z > 0 for z in zooms)):
        raise ctx.error("must be a list of focal lengths in mm, one per position", field="moving.zoom_focal_lengths_mm")
    close = m.get("close_focus_mm")
    if close is not None:
        close = number(ctx, close, field="moving.close_focus_mm", exclusive_minimum=0)
    cg = m.get("close_gaps", "published")
    if cg not in CLOSE_GAPS and cg is not None:
        raise ctx.error(f"must be one of {list(CLOSE_GAPS)}, got {cg!r}", field="moving.close_gaps")
    note = m.get("note", "")
    if not isinstance(note, str):
        raise ctx.error(f"must be a string, got {type_name(note)}", field="moving.note")
    stops = m.get("stop_semi_diameters_mm")
    if stops is not None and not (isinstance(stops, list) and all(is_number(v) and v > 0 for v in stops)):
        raise ctx.error("must be a list of semi-diameters in mm, one per position", field="moving.stop_semi_diameters_mm")
    try:
        return MovingGroups(out, zoom_efl_mm=zooms, close_focus_mm=close, close_gaps=cg, focus_label=note,
                            stop_semi_diameters=stops)
    except LensError as e:
        raise ctx.error(str(e), field="moving") from e


def _read_source(ctx: Ctx, src: Any) -> dict:
    if not isinstance(src, dict):
        raise ctx.error(f"must be an object, got {type_name(src)}", field="source")
    check_keys(ctx, src, SOURCE_KEYS, prefix="source.")
    for k, v in src.items():
        if k == "conversion":
            if not (isinstance(v, list) and all(isinstance(x, str) for x in v)):
                raise ctx.error("must be an array of strings", field="source.conversion")
        elif not isinstance(v, str):
            raise ctx.error(f"must be a string, got {type_name(v)}", field=f"source.{k}")
    return dict(src)


def _read_surface(ctx: Ctx, i: int, s: Any) -> Surface:
    if not isinstance(s, dict):
        raise ctx.error(f"a surface must be a JSON object, got {type_name(s)}", surface=i)
    label = s.get("label", "")
    if not isinstance(label, str):
        raise ctx.error(f"must be a string, got {type_name(label)} {label!r}", surface=i, field="label")
    where = dict(surface=i, label=label or None)
    check_keys(ctx, s, SURFACE_KEYS, required=SURFACE_REQUIRED, **where)

    r = s["radius"]
    if r is None or r == "inf":
        radius = math.inf
    elif isinstance(r, str):
        raise ctx.error(f"must be a number (mm), or \"inf\" / null for a flat surface; got {r!r}",
                        field="radius", **where)
    else:
        radius = number(ctx, r, field="radius", what='a number (mm), or "inf" / null for a flat surface',
                        **where)
        if radius == 0.0:
            raise ctx.error('radius 0 is not a surface; write "inf" (or null) for a flat one',
                            field="radius", **where)
    thickness = number(ctx, s["thickness"], field="thickness", minimum=0.0, **where)
    sd = number(ctx, s["semi_diameter"], field="semi_diameter", exclusive_minimum=0.0, **where)
    conic = number(ctx, s.get("conic", 0.0), field="conic", **where)

    asph = s.get("aspheric", [])
    if not isinstance(asph, list):
        raise ctx.error(f"must be an array [A4, A6, …, A16], got {type_name(asph)}", field="aspheric",
                        **where)
    if len(asph) > MAX_ASPHERIC:
        raise ctx.error(f"at most {MAX_ASPHERIC} coefficients (A4 … A16), got {len(asph)}",
                        field="aspheric", **where)
    aspheric = tuple(number(ctx, a, field=f"aspheric[{k}]", **where) for k, a in enumerate(asph))

    h = s.get("housing_radius")
    housing = None if h is None else number(ctx, h, field="housing_radius", exclusive_minimum=0.0,
                                            what="a number (mm) or null", **where)
    stop = s.get("stop", False)
    if not isinstance(stop, bool):
        raise ctx.error(f"must be true or false, got {type_name(stop)} {stop!r}", field="stop", **where)
    b = s.get("blades", 0)
    if not (is_number(b) and math.isfinite(b) and float(b) == int(b)):
        raise ctx.error(f"must be an integer (0 = circular, or ≥ 3), got {type_name(b)} {b!r}",
                        field="blades", **where)
    blades = int(b)
    rot = number(ctx, s.get("blade_rotation_deg", 0.0), field="blade_rotation_deg", **where)

    coating = _read_coating(ctx, s.get("coating"), where)
    medium = resolve(ctx, s["medium"], field="medium", **where)
    return Surface(radius=radius, thickness=thickness, medium=medium, semi_diameter=sd, conic=conic,
                   aspheric=aspheric, housing_radius=housing, is_stop=stop, blades=blades,
                   blade_rotation_deg=rot, coating=coating, label=label)


def _read_coating(ctx: Ctx, c: Any, where: dict):
    """``null``; a single quarter-wave layer ``{"index", "design_wavelength_nm"}``; ``{"preset": name}``; or a
    stack ``{"layers": [{"material", "thickness_nm" | "waves"}, ...], "design_wavelength_nm"}``, glass outward."""
    if c is None:
        return None
    if not isinstance(c, dict):
        raise ctx.error(f"must be null or an object ({{\"index\", \"design_wavelength_nm\"}}, {{\"preset\"}} or "
                        f"{{\"layers\", \"design_wavelength_nm\"}}), got {type_name(c)}", field="coating", **where)
    if "preset" in c:
        check_keys(ctx, c, ("preset",), prefix="coating.", **where)
        if c["preset"] not in PRESETS:
            raise ctx.error(f"unknown preset {c['preset']!r}; presets: {', '.join(PRESETS)}",
                            field="coating.preset", **where)
        return preset(c["preset"])
    lam = number(ctx, c.get("design_wavelength_nm", 550.0), field="coating.design_wavelength_nm",
                 exclusive_minimum=0.0, **where)
    if "layers" not in c:
        check_keys(ctx, c, COATING_KEYS, prefix="coating.", **where)
        return Coating(index=number(ctx, c.get("index", Coating.index), field="coating.index",
                                    exclusive_minimum=0.0, **where), design_wavelength_nm=lam)
    check_keys(ctx, c, STACK_KEYS, prefix="coating.", **where)
    layers = c["layers"]
    if not (isinstance(layers, list) and layers):
        raise ctx.error(f"must be a non-empty array of layers (glass outward), got {type_name(layers)}",
                        field="coating.layers", **where)
    out = []
    for k, l in enumerate(layers):
        f = f"coating.layers[{k}]"
        if not isinstance(l, dict):
            raise ctx.error(f"must be an object {{\"material\", \"thickness_nm\" or \"waves\"}}, got {type_name(l)}",
                            field=f, **where)
        check_keys(ctx, l, LAYER_KEYS, required=("material",), prefix=f + ".", **where)
        if ("thickness_nm" in l) == ("waves" in l):
            raise ctx.error("give exactly one of thickness_nm (physical, nm) and waves (optical thickness in waves "
                            "at the design wavelength, 0.25 = a quarter wave)", field=f, **where)
        mat = l["material"]
        medium = (COATING_MATERIALS[mat] if isinstance(mat, str) and mat in COATING_MATERIALS
                  else resolve(ctx, mat, field=f + ".material", **where))
        if "waves" in l:
            waves = number(ctx, l["waves"], field=f + ".waves", exclusive_minimum=0.0, **where)
            t = waves * lam / float(medium.index(lam))
        else:
            t = number(ctx, l["thickness_nm"], field=f + ".thickness_nm", exclusive_minimum=0.0, **where)
        out.append(Layer(medium, t))
    name = c.get("name", "")
    if not isinstance(name, str):
        raise ctx.error(f"must be a string, got {type_name(name)}", field="coating.name", **where)
    return CoatingStack(tuple(out), lam, name)


def _coating_dict(c) -> dict:
    if isinstance(c, Coating):
        return {"index": _f(c.index), "design_wavelength_nm": _f(c.design_wavelength_nm)}
    if c.name in PRESETS and preset(c.name) == c:
        return {"preset": c.name}
    d = {"layers": [{"material": _medium_dict(l.medium), "thickness_nm": _f(l.thickness_nm)} for l in c.layers],
         "design_wavelength_nm": _f(c.design_wavelength_nm)}
    if c.name:
        d["name"] = c.name
    return d


# ---------------------------------------------------------------------------------------- writing
def _f(x: float):
    x = float(x)
    return int(x) if x.is_integer() and abs(x) < 1e15 else x


def lens_to_dict(lens: Lens) -> dict:
    """The project-JSON document of ``lens``.  Media are written in full (formula, coefficients and
    source), so reading the file back needs no glass catalogue.  Optional surface fields are written
    only when they differ from their defaults."""
    md = dict(lens.metadata or {})
    desc = md.pop("description", "") or ""
    source = md.pop("source", {}) or {}
    surfaces = []
    for s in lens.surfaces:
        d: dict[str, Any] = {}
        if s.label:
            d["label"] = s.label
        d["radius"] = "inf" if math.isinf(s.radius) else _f(s.radius)
        d["thickness"] = _f(s.thickness)
        d["semi_diameter"] = _f(s.semi_diameter)
        if s.conic:
            d["conic"] = _f(s.conic)
        if s.aspheric:
            d["aspheric"] = [_f(a) for a in s.aspheric]
        if s.housing_radius is not None:
            d["housing_radius"] = _f(s.housing_radius)
        if s.is_stop:
            d["stop"] = True
        if s.blades:
            d["blades"] = int(s.blades)
        if s.blade_rotation_deg:
            d["blade_rotation_deg"] = _f(s.blade_rotation_deg)
        if s.coating is not None:
            d["coating"] = _coating_dict(s.coating)
        d["medium"] = _medium_dict(s.medium)
        surfaces.append(d)
    out = {"format": FORMAT_ID, "version": VERSION, "name": lens.name, "description": str(desc),
           "units": "mm", "object_medium": _medium_dict(lens.object_medium), "surfaces": surfaces}
    if lens.moving is not None:
        out["moving"] = lens.moving.to_dict()
    out["source"], out["metadata"] = dict(source), md
    return out


def _medium_dict(m: Medium) -> dict:
    d = m.to_dict()
    d["coefficients"] = [_f(c) for c in d["coefficients"]]
    return d


def dumps_lens(doc: dict) -> str:
    """Format a project-JSON document: one line per surface, everything else indented."""
    parts = []
    for k, v in doc.items():
        if k == "surfaces":
            rows = ",\n".join("    " + json.dumps(s, ensure_ascii=False, allow_nan=False) for s in v)
            parts.append(f'  "surfaces": [\n{rows}\n  ]')
        elif k == "object_medium":
            parts.append(f"  {json.dumps(k)}: " + json.dumps(v, ensure_ascii=False, allow_nan=False))
        else:
            body = json.dumps(v, indent=2, ensure_ascii=False, allow_nan=False)
            parts.append(f"  {json.dumps(k)}: " + body.replace("\n", "\n  "))
    return "{\n" + ",\n".join(parts) + "\n}\n"


def _file_mode(path: Path) -> int:
    """Mode for the written file: the existing file's, else 0o666 minus the umask (like open())."""
    try:
        return path.stat().st_mode & 0o777
    except OSError:
        mask = os.umask(0)
        os.umask(mask)
        return 0o666 & ~mask


def save_lens(lens: Lens, path: str | os.PathLike) -> None:
    """Write ``lens`` as project JSON, atomically (temporary file in the same folder + rename).

    The text is read back and compared with ``lens`` before anything is written, so a file this
    function writes always loads to an equal lens.
    """
    path = Path(path)
    ctx = Ctx(str(path))
    doc = lens_to_dict(lens)
    try:
        text = dumps_lens(doc)
    except (TypeError, ValueError) as e:
        raise ctx.error(f"lens metadata/source is not JSON-serialisable: {e}", field="metadata") from None
    back = lens_from_dict(json.loads(text), path=str(path))
    if back != lens or back.fingerprint() != lens.fingerprint():
        raise ctx.error("internal error: the written lens would not read back equal; nothing written")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, _file_mode(path))
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


__all__ = ["FORMAT_ID", "VERSION", "lens_from_dict", "lens_to_dict", "save_lens", "load_project_json",
           "dumps_lens", "is_project_json"]
