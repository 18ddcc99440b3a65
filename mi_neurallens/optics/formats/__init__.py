"""Readers and writers of lens prescription files.

:func:`load_lens` detects the format from the content (not the extension):

* project JSON (``{"format": "mi-neurallens-lens", ...}``) — :mod:`.project_json` (also the writer)
* pbrt ``.dat`` (the ``.NNmm.dat`` thickness layout and the ``axpos`` originals) — :mod:`.pbrt`
* Open Optical Designer JSON (``{"surfaces": [{"radius_of_curvature": ...}], "env_...": ...}``) — :mod:`.ood`
* LensVisualizer JSON (``{"surfaces": [{"label", "R", "d", "nd", "elemId", "sd"}], "elements": [...]}``)
  — :mod:`.lensvisualizer`
* Zemax OpticStudio sequential ``.zmx`` (UTF-16 or UTF-8; ``SURF n`` blocks) — :mod:`.zemax`
* CODE V sequence files ``.seq`` (``SO``/``S``/``SI`` commands) — :mod:`.codev`
* a lens name (``<name>.json`` in a lens library: :mod:`mi_neurallens.resources`) — :func:`bundled_lens_path`

:func:`convert_bundled` regenerates the bundled lenses from the shared lens data
(``python -m mi_neurallens.optics.formats convert /path/to/lens-data``).
"""
from __future__ import annotations

import inspect
import os
from pathlib import Path
from typing import Any, Callable

from ... import resources
from ...errors import LensError
from ..prescription import Lens
from ._common import Ctx, loads_json, sha256_file
from .codev import looks_like_codev, read_codev
from .lensvisualizer import looks_like_lensvisualizer, read_lensvisualizer
from .ood import looks_like_ood, read_ood
from .pbrt import looks_like_pbrt, read_pbrt
from .zemax import decode as _decode_zemax, looks_like_zemax, read_zemax
from .project_json import (FORMAT_ID, is_project_json, lens_from_dict, lens_to_dict, load_project_json,
                           save_lens)

LENSES_ENV = resources.LENSES_ENV

#: format id -> description (used in error messages and docs)
FORMATS = {
    "project": 'project JSON ({"format": "mi-neurallens-lens", "version": 1, ...}; docs/lens-format.md)',
    "pbrt": "pbrt lens file (.dat: rows of radius, thickness, eta, aperture diameter in mm; '#' comments)",
    "ood": "Open Optical Designer JSON (surfaces with radius_of_curvature/aperture_radius/material, env_* settings)",
    "lensvisualizer": "LensVisualizer JSON (surfaces {label, R, d, nd, elemId, sd} + elements[] + asph)",
    "zemax": "Zemax OpticStudio sequential .zmx (UTF-16 or UTF-8 text: SURF blocks with TYPE STANDARD/EVENASPH)",
    "codev": "CODE V sequence file .seq (RDM, DIM, EPD/FNO, WL, then SO / S ... / SI commands)",
}


# ------------------------------------------------------------------------------------------ bundled
def bundled_lenses() -> list[str]:
    """Names of the lenses on the search path (``$MI_NEURALLENS_LENSES``, then the bundled library), sorted:
    :func:`mi_neurallens.resources.lens_names`."""
    return resources.lens_names()


def bundled_lens_path(name: str) -> Path:
    """The prescription of the lens ``name`` on the search path (:func:`mi_neurallens.resources.lens_path`); the
    error names the lenses there are and the formats a file may have."""
    p = resources.find_lens(name)
    if p is None:
        names = resources.lens_names()
        raise LensError(f"no lens file or lens named '{name}'; lenses: {', '.join(names) or '(none)'} (searched "
                        f"{resources.search_path_text()}); or give the path of a file in one of these formats: "
                        f"{_format_list()}")
    return p


def _format_list() -> str:
    return "; ".join(FORMATS.values())


# ------------------------------------------------------------------------------------------ detection
def _read_text(ctx: Ctx, path: Path) -> tuple[str, str]:
    """The file as text: UTF-16 (with a byte-order mark, or the zero bytes of ASCII in UTF-16, as
    OpticStudio writes ``.zmx`` files), UTF-8 or Latin-1; anything else with zero bytes is binary.
    Returns the text and the encoding."""
    raw = path.read_bytes()
    head = raw[:4096]
    utf16 = head[:2] in (b"\xff\xfe", b"\xfe\xff") or (len(head) >= 4 and (
        head[1:4:2] == b"\x00\x00" or head[0:4:2] == b"\x00\x00"))
    if utf16:
        text, enc = _decode_zemax(ctx, raw)
        if "\x00" not in text[:2048]:
            return text, enc
    if b"\x00" in head:
        raise ctx.error(f"binary file, not a lens prescription; supported formats: {_format_list()}")
    try:
        return raw.decode("utf-8-sig"), "utf-8"
    except UnicodeDecodeError:
        return raw.decode("latin-1"), "latin-1"


def _detect_doc(ctx: Ctx, doc: Any) -> str:
    if isinstance(doc, dict) and "format" in doc and not is_project_json(doc):
        raise ctx.error(f"unknown format {doc['format']!r} (this reader knows \"{FORMAT_ID}\"); supported "
                        f"formats: {_format_list()}", field="format")
    if is_project_json(doc):
        return "project"
    if looks_like_lensvisualizer(doc):
        return "lensvisualizer"
    if looks_like_ood(doc):
        return "ood"
    if isinstance(doc, dict) and doc and all(isinstance(v, dict) for v in doc.values()) and any(
            any("optical-elements" in k for k in v) for v in doc.values()):
        raise ctx.error("this is the lentil lens database (many lenses in one file), which is not a supported "
                        f"format; supported formats: {_format_list()}")
    raise ctx.error(f"JSON, but not a lens format this package reads; supported formats: {_format_list()}")


def detect_format(path: str | os.PathLike) -> str:
    """The format id (a key of :data:`FORMATS`) of the file at ``path``, from its content."""
    ctx = Ctx(str(path))
    text, _ = _read_text(ctx, Path(path))
    return _detect_text(ctx, text)[0]


def _detect_text(ctx: Ctx, text: str):
    s = text.lstrip()
    if s[:1] in ("{", "["):
        doc = loads_json(ctx, text)
        return _detect_doc(ctx, doc), doc
    if looks_like_zemax(text):
        return "zemax", text
    if looks_like_codev(text):
        return "codev", text
    if looks_like_pbrt(text):
        return "pbrt", text
    raise ctx.error(f"not a recognised lens file (not JSON, not Zemax SURF blocks, not CODE V SO/S/SI commands, "
                    f"not rows of numbers); "
                    f"supported formats: "
                    f"{_format_list()}")


_READERS: dict[str, Callable[..., Lens]] = {
    "project": lambda doc, file, **kw: lens_from_dict(doc, path=file, **kw),
    "pbrt": lambda text, file, **kw: read_pbrt(text, file=file, **kw),
    "ood": lambda doc, file, **kw: read_ood(doc, file=file, **kw),
    "lensvisualizer": lambda doc, file, **kw: read_lensvisualizer(doc, file=file, **kw),
    "zemax": lambda text, file, **kw: read_zemax(text, file=file, **kw),
    "codev": lambda text, file, **kw: read_codev(text, file=file, **kw),
}
_OPTIONS = {"project": lens_from_dict, "pbrt": read_pbrt, "ood": read_ood, "lensvisualizer": read_lensvisualizer,
            "zemax": read_zemax, "codev": read_codev}
_TEXT_FORMATS = ("pbrt", "zemax", "codev")


def _check_options(ctx: Ctx, fmt: str, kw: dict) -> None:
    params = inspect.signature(_OPTIONS[fmt]).parameters
    allowed = [p for p, v in params.items() if v.kind == v.KEYWORD_ONLY and p not in ("file", "path", "encoding")]
    for k in kw:
        if k not in allowed:
            raise ctx.error(f"option '{k}' does not apply to a {fmt} file; its options: "
                            f"{', '.join(allowed) if allowed else '(none)'}", field=k)


def load_lens(path_or_name, *, format: str | None = None, **kw) -> Lens:
    """Read a lens: a file in any supported format (detected from the content) or a bundled name.

    ``format`` forces a reader (``"project"``, ``"pbrt"``, ``"ood"``, ``"lensvisualizer"``, ``"zemax"``,
    ``"codev"``).  Other keyword options go to the reader: pbrt ``layout=``; Open Optical Designer
    ``stop_radius=``; LensVisualizer ``focus=``, ``zoom=``; Zemax and CODE V ``glasses=``,
    ``stop_radius=``; CODE V ``radius_mode=``; every reader but the project one ``name=``.
    A :class:`Lens` is returned as is; a ``dict`` is read as a parsed JSON document.
    """
    if isinstance(path_or_name, Lens):
        return path_or_name
    if format is not None and format not in FORMATS:
        raise LensError(f"unknown format {format!r}; supported: {', '.join(FORMATS)}", field="format")
    if isinstance(path_or_name, dict):
        ctx = Ctx(None)
        fmt = format or _detect_doc(ctx, path_or_name)
        if fmt in _TEXT_FORMATS:
            raise LensError(f"a {fmt} lens is text, not a dict: pass the file path", field="format")
        _check_options(ctx, fmt, kw)
        return _READERS[fmt](path_or_name, None, **kw)
    if not isinstance(path_or_name, (str, os.PathLike)):
        raise LensError(f"expected a file path or bundled lens name, got {type(path_or_name).__name__}")
    p = Path(path_or_name)
    if not p.is_file():
        s = str(path_or_name)
        looks_like_path = isinstance(path_or_name, os.PathLike) or "/" in s or os.sep in s or p.suffix.lower() in (
            ".json", ".dat", ".txt", ".len", ".zmx", ".seq")
        if looks_like_path and resources.find_lens(s) is None:
            names = bundled_lenses()
            raise LensError(f"file not found: {s} (lenses by name: {', '.join(names) or 'none'})", file=s)
        p = bundled_lens_path(s)
    ctx = Ctx(str(p))
    text, encoding = _read_text(ctx, p)
    if format is None:
        fmt, payload = _detect_text(ctx, text)
    else:
        fmt = format
        payload = text if fmt in _TEXT_FORMATS else loads_json(ctx, text)
    _check_options(ctx, fmt, kw)
    if fmt == "zemax":
        kw["encoding"] = encoding
    return _READERS[fmt](payload, str(p), **kw)


# ------------------------------------------------------------------------------------------ conversion
def convert_file(src: str | os.PathLike, dst: str | os.PathLike, *, name: str | None = None, **options) -> Lens:
    """Read ``src`` in any supported format (reader ``options`` as for :func:`load_lens`) and write it as
    project JSON to ``dst``, atomically.  The source file's name, format and SHA-256 go into
    ``source``; the reader's decisions stay in ``metadata``.  Returns the lens written."""
    src_p = Path(src)
    lens = load_lens(src_p, **options)
    if not src_p.is_file():  # a bundled name
        src_p = bundled_lens_path(str(src))
    md = dict(lens.metadata)
    source = dict(md.get("source", {}))
    source.setdefault("file", src_p.name)
    source["sha256"] = sha256_file(src_p)
    conv = list(source.get("conversion", []))
    conv.append("converted by mi_neurallens.optics.formats.convert_file"
                + (f" with reader options {sorted(options)}" if options else ""))
    source["conversion"] = conv
    md["source"] = source
    lens = lens.replace(metadata=md, path=None, **({"name": name} if name else {}))
    save_lens(lens, dst)
    return lens


_PBRT_REPO = "mmp/pbrt-v4-scenes"
_MLD = "W. J. Smith, Modern Lens Design (1992)"

#: name -> how the bundled lens is made from the shared lens data
BUNDLED: dict[str, dict] = {
    "wide-22mm": dict(
        file="pbrt/wide.22mm.dat", repository=_PBRT_REPO, path="sanmiguel/lenses/wide.22mm.dat",
        commit="fd7a5f25dc00",
        description="Wide-angle (38°) lens, Nakamura, scaled to 22 mm; the pbrt/Kolb lens the paper calls "
                    "'Nakamura'",
        reference=f"{_MLD}, p. 360"),
    "dgauss-50mm": dict(
        file="pbrt/dgauss.50mm.dat", repository=_PBRT_REPO, path="lenses/dgauss.50mm.dat", commit="304287dfcf96",
        description="Double-Gauss 50 mm f/2, 22° half field (US 2,673,491, Tronnier), scaled to 50 mm",
        reference=f"US 2,673,491 (Tronnier); {_MLD}, p. 312"),
    "fisheye-10mm": dict(
        file="pbrt/fisheye.10mm.dat", repository=_PBRT_REPO, path="lenses/fisheye.10mm.dat", commit="304287dfcf96",
        description="Muller 16 mm f/4 155.9° fisheye, scaled to 10 mm",
        reference=f"{_MLD}, p. 164"),
    "telephoto-250mm": dict(
        file="pbrt/telephoto.250mm.dat", repository=_PBRT_REPO, path="lenses/telephoto.250mm.dat",
        commit="304287dfcf96",
        description="Sigler super-achromat telephoto (EFL 254 mm, f/5.6), scaled to 250 mm",
        reference=f"{_MLD}, p. 175"),
    "ood-59mm": dict(
        file="open-optical-designer/default-sample-lens.json", repository="alexbock/open-optical-designer",
        path="src/data/default-sample-lens.js (DEFAULT_SAMPLE_LENS_JSON)", commit="6e7dcc7d3de1",
        description="Open Optical Designer's built-in sample lens: 59.5 mm, 7 plastic (PMMA/PC) elements, "
                    "7 conics; the paper's '59 mm' lens",
        reference="Open Optical Designer default sample design"),
    "canon-ef-24mm-f1.4l": dict(
        file="other/CanonEF24mmf14L.json", repository="ronbuening/LensVisualizer",
        path="src/lens-data/canon/CanonEF24mmf14L.data.ts", commit="bf55b14f5ebdf8234ffb11cbace476fddb39b236",
        description="Canon EF 24mm f/1.4L USM (JP H11-030743 A, Numerical Example 6); a candidate for the "
                    "paper's 'Canon 24 mm', whose own prescription is not public",
        reference="JP 1999-030743 A (JP H11-030743 A), Numerical Example 6, Canon / M. Misaka"),
    "canon-rf-24mm-f1.4l-vcm": dict(
        file="other/CanonRF24mmF14LVCM.json", repository="ronbuening/LensVisualizer",
        path="src/lens-data/canon/CanonRF24mmF14LVCM.data.ts", commit="bf55b14f5ebdf8234ffb11cbace476fddb39b236",
        description="Canon RF 24mm F1.4 L VCM (JP 2025-15010 A, Numerical Example 3): a modern many-element "
                    "lens, 15 elements in 27 surfaces, two aspheres; internal focusing by two groups to 0.24 m (moving "
                    "groups)",
        reference="JP 2025-15010 A, Numerical Example 3, Canon / K. Shinohara, Y. Matsuba"),
    "canon-ef-24-70mm-f2.8l": dict(
        file="other/CanonEF2470mmf28L.json", repository="ronbuening/LensVisualizer",
        path="src/lens-data/canon/CanonEF2470mmf28L.data.ts", commit="bf55b14f5ebdf8234ffb11cbace476fddb39b236",
        description="Canon EF 24-70mm f/2.8L USM (JP 2014-041222 A, Numerical Example 1): a zoom lens, 16 elements "
                    "in 31 surfaces, two aspheres; zoom positions 24.9 / 35.13 / 68.14 mm and internal focusing to "
                    "0.38 m (moving groups)",
        reference="JP 2014-041222 A, Numerical Example 1, Canon / H. Endo"),
}


def convert_bundled(source_dir: str | os.PathLike, out_dir: str | os.PathLike | None = None) -> dict[str, Path]:
    """Regenerate the bundled lenses (project JSON) from the shared lens data at ``source_dir``.

    Each file is read with the readers of this package, given its name, description and provenance
    (original file, repository, path, commit, SHA-256, conversion decisions) and written with
    :func:`save_lens` into ``out_dir`` (default: the bundled library, ``mi_neurallens/data/lenses``).  Returns name -> written path.
    """
    src = Path(source_dir)
    out = Path(out_dir) if out_dir is not None else resources.bundled_library().path
    written = {}
    for name, info in BUNDLED.items():
        f = src / info["file"]
        if not f.is_file():
            raise LensError(f"missing source file for bundled lens '{name}'", file=str(f))
        lens = load_lens(f, name=name, **info.get("read", {}))
        md = dict(lens.metadata)
        fmt_src = dict(md.get("source", {}))
        conv = _conversion_notes(lens)
        source = {
            "file": Path(info["file"]).name,
            "format": fmt_src.get("format", ""),
            "repository": info["repository"],
            "path": info["path"],
            "commit": info["commit"],
            "url": f"https://github.com/{info['repository']}/blob/{info['commit']}/{info['path'].split(' ')[0]}",
            "reference": info["reference"],
            "sha256": sha256_file(f),
            "conversion": conv,
        }
        md["source"] = source
        md["description"] = info["description"]
        lens = lens.replace(metadata=md, path=None)
        target = out / f"{name}.json"
        save_lens(lens, target)
        written[name] = target
    return written


def _conversion_notes(lens: Lens) -> list[str]:
    md = lens.metadata
    notes = [f"converted by mi_neurallens.optics.formats.convert_bundled from the '{md['source'].get('format')}' file"]
    if "pbrt" in md:
        p = md["pbrt"]
        last = p["file_last_thickness"]
        notes += [
            f"column-2 layout: {p['layout']}: {p['layout_reason']}",
            "radius 0 row -> flat aperture stop 'STO'; eta 0 -> air; semi_diameter = aperture diameter / 2",
            f"dispersion: {p['dispersion']}",
            f"last thickness (image distance) = {p['image_distance_mm']:.6f} mm, the {p['image_distance']}"
            + ("" if last is None else f" (the file's value, {last:g}, is not used)"),
        ]
    if "ood" in md:
        o = md["ood"]
        st = o["stop"]
        notes += [
            "materials by name from the app's material list (piecewise-linear index tables); object space "
            f"= {o['env_initial_material']} (Ciddor air, n ≈ 1.000278, not 1)",
            f"flat stop 'STO' inserted at z = {st['z_mm']:g} mm (env_beam_cross_distance), splitting the air gap",
            f"stop radius {st['radius_mm']:.6f} mm: {st['rule']}; paraxial entrance-pupil radius "
            f"{st['entrance_pupil_radius_mm']:.6f} mm",
            "aperture_radius -> clear semi_diameter; no housing; last thickness kept as written",
        ]
    if "lensvisualizer" in md:
        notes += list(md.get("notes", []))
        notes.append("label 'STO' -> aperture stop; asph K/A4…A16 by label; no coatings, no housings")
        mg = lens.moving
        if mg is not None:
            notes.append(f"var -> moving groups: the gaps after surfaces {', '.join(map(str, mg.gaps))} at "
                         f"{mg.positions} position(s)" + (f" (zoomPositions {', '.join(f'{z:g}' for z in mg.zoom_efl_mm)} mm)"
                                                          if mg.zoom_efl_mm else "")
                         + (f", close focus {mg.close_focus_mm / 1000:g} m (closeFocusM), close gaps {mg.close_gaps}"
                            if mg.close_focus_mm else ""))
        elif md["lensvisualizer"].get("var"):
            notes.append("var (variable gaps) not read: the lens is the file's infinity-focus configuration")
    return notes


__all__ = ["load_lens", "save_lens", "lens_to_dict", "lens_from_dict", "load_project_json", "bundled_lenses",
           "bundled_lens_path", "detect_format", "convert_bundled", "convert_file", "FORMATS", "BUNDLED",
           "read_pbrt", "read_ood", "read_lensvisualizer", "read_zemax", "read_codev"]
