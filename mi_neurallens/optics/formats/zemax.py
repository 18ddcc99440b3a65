"""Zemax OpticStudio sequential lens files (``.zmx``), UTF-16 or UTF-8, as OpticStudio writes them.

A ``.zmx`` file is one keyword per line.  Header keywords describe the system; ``SURF n`` starts
surface n (0 = object, the last one = image) and the indented keywords after it describe that
surface.  What is read (see ``docs/lens-format.md``, "Zemax .zmx"):

header   ``UNIT`` (MM, CM, IN, M: every length is converted to mm), ``NAME``, ``NOTE``, ``MODE SEQ``,
         ``GCAT`` (catalogue search order), ``WAVM``/``WAVL`` + ``PWAV`` (the primary wavelength),
         ``ENPD``/``FNUM``/``FLOA`` (the system aperture, which sets the stop radius), ``MNUM`` with the
         multi-configuration lines ``THIC surface config value …`` and ``APER 0 config value …``: the
         configurations as moving groups (zoom positions at infinity, close focus at one finite object distance;
         :func:`~._sequential.moving_from_configurations`).
surface  ``TYPE STANDARD``/``EVENASPH``, ``CURV``, ``DISZ``, ``CONI``, ``PARM 2…8`` (A4…A16 of
         ``EVENASPH``), ``GLAS``, ``STOP``, ``DIAM`` (semi-diameter), ``FLAP``/``CLAP`` (a clear
         aperture, preferred to ``DIAM``), ``MEMA`` (mechanical semi-diameter -> housing radius).

Everything a rotationally symmetric refractive lens cannot be is refused with an error naming the
file, the surface number and the keyword: other surface types (``TYPE COORDBRK``, ``ODDASPHE``,
``TOROIDAL``, gradient index, ``NONSEQCO``, …), ``GLAS MIRROR``, tilts and decenters (``SCBD``),
obscurations and non-circular apertures, an ``EVENASPH`` r² term (``PARM 1``), ``MODE NSC``,
``OBNA`` (object-space NA; pass ``stop_radius=``), a curved image surface.  Other keywords (display,
tolerancing, coatings, solves, ray aiming, fields) do not change the prescription; they are counted
in ``metadata["zemax"]["ignored_keywords"]``.

The image distance is the last ``DISZ`` before the image surface, kept as the file says.
"""
from __future__ import annotations

import math
import os
from pathlib import Path
import re

from ...errors import GlassError
from ..glass import AIR, CATALOGS, Medium, catalog_glass, constant, model_glass
from ..prescription import Lens
from ._common import Ctx
from ._sequential import SeqSurface, build_lens, substitute_glass

#: mm per file length unit
UNITS = {"MM": 1.0, "CM": 10.0, "IN": 25.4, "INCH": 25.4, "INCHES": 25.4, "M": 1000.0, "METER": 1000.0,
         "METERS": 1000.0}
SURFACE_TYPES = ("STANDARD", "EVENASPH")
#: Zemax's default wavelength (µm) of an unused WAVM slot
_WAVM_DEFAULT = 0.55
#: surface keywords that change nothing in our model (display, solves, tolerancing, coatings, notes)
_HARMLESS_SURF = {"COMM", "HIDE", "MIRR", "SLAB", "POPS", "COAT", "FIMP", "PZUP", "MAZH", "OEMA", "VDSZ", "TCE",
                  "BLNK", "CCON", "CONF", "IGNR", "PPAR", "VPAR", "VCON", "PKUP", "EDGE", "THIC", "NOTE", "ZVDX",
                  "ZVDY", "ZVCX", "ZVCY", "ZVAN", "XDAT", "UDAD", "FLIP", "SQAR", "TOLE"}
#: apertures and obscurations other than a circular clear aperture
_OTHER_APERTURES = {"OBSC": "a circular obscuration", "SQAP": "a rectangular aperture",
                    "SQOB": "a rectangular obscuration", "ELAP": "an elliptical aperture",
                    "ELOB": "an elliptical obscuration", "SPID": "a spider", "UDAP": "a user-defined aperture",
                    "UDOB": "a user-defined obscuration"}
_KEYWORDS = {"radius": "CURV", "thickness": "DISZ", "medium": "GLAS", "semi_diameter": "DIAM", "conic": "CONI",
             "aspheric": "PARM", "housing_radius": "MEMA", "epd": "ENPD", "fno": "FNUM", "float": "FLOA"}
_SURF_LINE = re.compile(r"^SURF\s+(\S+)\s*$")
#: multi-configuration operands that change the prescription beyond gaps and the aperture (refused), and all that
#: are recognised (the others set fields, wavelengths, weights, which do not change the lens)
_MCE_REFUSED = {"CRVT": "a curvature", "CONN": "a conic", "GLSS": "a glass", "PRAM": "a surface parameter",
                "PAR1": "a surface parameter", "PAR2": "a surface parameter", "PAR3": "a surface parameter",
                "SDIA": "a semi-diameter", "IGNR": "which surfaces are ignored", "TEMP": "the temperature",
                "PRES": "the pressure", "STPS": "the stop surface", "MCSD": "a semi-diameter", "COTN": "a coating"}
_MCE_OPERANDS = {"THIC", "APER", "WAVE", "WLWT", "XFIE", "YFIE", "FVDX", "FVDY", "FVCX", "FVCY", "FVAN", "FLWT",
                 "MOFF", "PWAV"} | set(_MCE_REFUSED)


def looks_like_zemax(text: str) -> bool:
    """A ``SURF n`` line and surface data (``CURV``/``DISZ``/``TYPE``) on indented lines."""
    return bool(re.search(r"(?m)^SURF\s+\d+\s*$", text)) and bool(
        re.search(r"(?m)^\s+(CURV|DISZ|TYPE)\s", text))


def decode(ctx: Ctx, raw: bytes) -> tuple[str, str]:
    """The text of a ``.zmx`` file and its encoding: UTF-16 (with or without a byte-order mark, as
    OpticStudio writes) or UTF-8 (older versions), with Latin-1 as the last resort."""
    if raw[:2] in (b"\xff\xfe", b"\xfe\xff"):
        enc = "utf-16"
    elif len(raw) >= 4 and raw[1:4:2] == b"\x00\x00" and raw[0] != 0:
        enc = "utf-16-le"
    elif len(raw) >= 4 and raw[0:4:2] == b"\x00\x00" and raw[1] != 0:
        enc = "utf-16-be"
    else:
        enc = None
    if enc:
        if (len(raw) - (2 if enc == "utf-16" else 0)) % 2:
            raise ctx.error(f"the file is {enc.upper()} text with an odd number of bytes ({len(raw)}): it is "
                            "truncated")
        try:
            return raw.decode(enc), enc
        except UnicodeDecodeError as e:
            raise ctx.error(f"not valid {enc.upper()} text at byte {e.start}") from None
    try:
        return raw.decode("utf-8-sig"), "utf-8"
    except UnicodeDecodeError:
        return raw.decode("latin-1"), "latin-1"


def load_zemax(path: str | os.PathLike, **kw) -> Lens:
    ctx = Ctx(str(path))
    text, enc = decode(ctx, Path(path).read_bytes())
    return read_zemax(text, file=str(path), encoding=enc, **kw)


class _Surf:
    def __init__(self, number: int, line: int):
        self.number, self.line = number, line
        self.data: dict[str, tuple[int, list[str]]] = {}   # keyword -> (line, tokens) (last one wins)
        self.parm: dict[int, tuple[int, float]] = {}
        self.stop = False
        self.type = "STANDARD"


def _num(ctx: Ctx, tok: str, *, surface, keyword: str, line: int, allow_inf: bool = False) -> float:
    t = tok
    if "," in t and "." not in t:
        t = t.replace(",", ".")  # decimal commas of some locales
    if allow_inf and t.upper() in ("INFINITY", "INF"):
        return math.inf
    try:
        x = float(t)
    except ValueError:
        raise ctx.error(f"expected a number, got {tok!r} (line {line})", surface=surface, field=keyword) from None
    if not math.isfinite(x):
        raise ctx.error(f"expected a finite number, got {tok!r} (line {line})", surface=surface, field=keyword)
    return x


def _arg(ctx: Ctx, s: _Surf | None, keyword: str, k: int = 0, *, line=None, toks=None, allow_inf=False) -> float:
    if toks is None:
        line, toks = s.data[keyword]
    if len(toks) <= k:
        raise ctx.error(f"missing value {k + 1} (line {line}: {' '.join([keyword] + toks)!r}); the file looks "
                        "truncated", surface=None if s is None else s.number, field=keyword)
    return _num(ctx, toks[k], surface=None if s is None else s.number, keyword=keyword, line=line,
                allow_inf=allow_inf)


def read_zemax(text: str, *, file: str | None = None, name: str | None = None, glasses: dict | None = None,
               stop_radius: float | None = None, encoding: str | None = None) -> Lens:
    """Build a :class:`Lens` from the text of a ``.zmx`` file.

    ``glasses``: ``{name in the file: medium}`` replaces glasses by name before the catalogues are
    searched (any form :func:`~mi_neurallens.optics.glass.resolve_medium` takes: a catalogue name, a
    number, ``{"nd": …, "vd": …}``, …).  ``stop_radius``: the stop radius in mm, instead of the one
    the file's system aperture (``ENPD``/``FNUM``/``FLOA``) gives.  ``name``: the lens name (default:
    the file name without extension).
    """
    ctx = Ctx(file or "<zemax text>")
    header: dict[str, tuple[int, list[str]]] = {}
    wavm: dict[int, float] = {}
    wavl: list[float] | None = None
    gcat: list[str] = []
    ignored: dict[str, int] = {}
    notes: list[str] = []
    aperture_kw: list[tuple[str, int, list[str]]] = []
    surfs: list[_Surf] = []
    cur: _Surf | None = None
    mce: list[tuple] = []       # multi-configuration values: (operand, surface or slot, configuration, value, line)

    for ln, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line:
            continue
        toks = line.split()
        key, args = toks[0], toks[1:]
        m = _SURF_LINE.match(line)
        if key == "SURF":
            if not m or not m.group(1).isdigit():
                raise ctx.error(f"expected 'SURF <number>', got {line!r} (line {ln})", field="SURF")
            n = int(m.group(1))
            if n != len(surfs):
                raise ctx.error(f"SURF {n} at line {ln} follows SURF {len(surfs) - 1}; surfaces must be numbered "
                                f"0, 1, 2, … in order (the file is damaged or truncated)", surface=n, field="SURF")
            cur = _Surf(n, ln)
            surfs.append(cur)
            continue
        indented = raw[:1] in (" ", "\t")
        if cur is not None and indented:
            _surface_keyword(ctx, cur, key, args, ln, ignored)
            continue
        # header (and the trailing system lines after the last surface)
        if key == "MODE":
            if args[:1] != ["SEQ"]:
                raise ctx.error(f"MODE {' '.join(args)} (line {ln}): only sequential files (MODE SEQ) describe a "
                                "lens; non-sequential systems are not supported", field="MODE")
        elif key in ("ENPD", "FNUM", "FLOA", "OBNA"):
            if key == "OBNA" and stop_radius is None:
                _aperture(ctx, [(key, ln, args)], 1.0, math.inf, None)   # refuses it, naming the line
            aperture_kw.append((key, ln, args))
        elif key == "WAVM":
            if len(args) >= 2:
                k = int(_arg(ctx, None, key, 0, line=ln, toks=args))
                wavm[k] = _arg(ctx, None, key, 1, line=ln, toks=args)
        elif key == "WAVL":
            wavl = [_num(ctx, t, surface=None, keyword=key, line=ln) for t in args]
        elif key == "GCAT":
            gcat = args
        elif key in ("UNIT", "NAME", "NOTE", "PWAV", "MNUM", "VERS"):
            if key == "NOTE":
                notes.append(" ".join(args[1:] if args[:1] == ["0"] else args))
            else:
                header[key] = (ln, args)
        elif key in _MCE_OPERANDS and len(args) >= 3 and args[0].isdigit() and args[1].isdigit():
            mce.append((key, int(args[0]), int(args[1]), args[2], ln))      # a configuration's value
        elif key == "MIRR" or key in _HARMLESS_SURF:
            ignored[key] = ignored.get(key, 0) + 1
        elif cur is not None and key in ("TYPE", "CURV", "DISZ", "GLAS", "DIAM", "STOP", "CONI", "PARM"):
            _surface_keyword(ctx, cur, key, args, ln, ignored)   # unindented surface data
        else:
            ignored[key] = ignored.get(key, 0) + 1

    if len(surfs) < 3:
        raise ctx.error(f"{len(surfs)} SURF block(s): a lens file has an object surface, at least one lens "
                        "surface and an image surface" + ("; the file looks truncated" if surfs else ""),
                        field="SURF")

    # -- units
    scale, unit = 1.0, "MM"
    if "UNIT" in header:
        ln, args = header["UNIT"]
        unit = (args[:1] or [""])[0].upper()
        if unit not in UNITS:
            raise ctx.error(f"unknown lens unit {unit!r} (line {ln}); known: MM, CM, IN, M", field="UNIT")
        scale = UNITS[unit]

    # -- wavelengths (µm in the file, whatever UNIT says)
    if wavm:
        slots = sorted(wavm)
        used = [k for k in slots if wavm[k] != _WAVM_DEFAULT]
        last = max(used) if used else slots[0]
        pw = 1
        if "PWAV" in header:
            ln, args = header["PWAV"]
            pw = int(_arg(ctx, None, "PWAV", 0, line=ln, toks=args))
            if pw not in wavm:
                raise ctx.error(f"primary wavelength number {pw} (line {ln}) has no WAVM line", field="PWAV")
        wl_list = [round(wavm[k] * 1e3, 9) for k in slots if k <= max(last, pw)]
        primary = round(wavm[pw] * 1e3, 9)
    elif wavl:
        pw = 1
        if "PWAV" in header:
            ln, args = header["PWAV"]
            pw = int(_arg(ctx, None, "PWAV", 0, line=ln, toks=args))
            if not 1 <= pw <= len(wavl):
                raise ctx.error(f"primary wavelength number {pw} (line {ln}) but WAVL lists {len(wavl)}",
                                field="PWAV")
        wl_list = [round(w * 1e3, 9) for w in wavl]
        primary = round(wavl[pw - 1] * 1e3, 9)
    else:
        wl_list, primary = [550.0], 550.0
        notes.append("no wavelengths in the file: 550 nm (Zemax's default) is the primary wavelength")
    if not (math.isfinite(primary) and 100.0 < primary < 20000.0):
        raise ctx.error(f"primary wavelength {primary:g} nm is not a usable wavelength", field="WAVM")

    # -- object and image surfaces
    obj, img, lens_surfs = surfs[0], surfs[-1], surfs[1:-1]
    if obj.stop or img.stop:
        s = obj if obj.stop else img
        raise ctx.error(f"the {'object' if s is obj else 'image'} surface cannot be the stop", surface=s.number,
                        field="STOP")
    if "CURV" in img.data and _arg(ctx, img, "CURV") != 0.0:
        raise ctx.error(f"a curved image surface (CURV {img.data['CURV'][1][0]}, line {img.data['CURV'][0]}) is not "
                        "supported: the sensor is a plane", surface=img.number, field="CURV")
    if "DISZ" not in img.data:
        raise ctx.error(f"the last surface (SURF {img.number}, line {img.line}) has no DISZ, which OpticStudio writes "
                        "for every surface: the file looks truncated", surface=img.number, field="DISZ")
    if "GLAS" in img.data or _arg(ctx, img, "DISZ", allow_inf=True) != 0.0:
        k = "GLAS" if "GLAS" in img.data else "DISZ"
        raise ctx.error(f"the last surface (SURF {img.number}) has {k} {' '.join(img.data[k][1])} (line "
                        f"{img.data[k][0]}), so it is not an image surface: the file looks truncated",
                        surface=img.number, field=k)
    for s in surfs[:-1]:
        if "DISZ" not in s.data:
            raise ctx.error(f"SURF {s.number} (line {s.line}) has no DISZ (thickness): the file looks damaged or "
                            "truncated", surface=s.number, field="DISZ")
    object_distance = _arg(ctx, obj, "DISZ", allow_inf=True) * scale
    if object_distance >= 1e10:  # OpticStudio's "infinity" in some files
        object_distance = math.inf

    # -- glasses
    subst = _glass_subst(ctx, glasses)
    used_subst: set[str] = set()
    glass_table: dict[str, dict] = {}
    cats = _gcat_catalogs(gcat)
    object_medium = AIR
    if "GLAS" in obj.data:
        object_medium = _medium(ctx, obj, subst, used_subst, cats, glass_table, notes)

    seq = []
    for s in lens_surfs:
        medium = _medium(ctx, s, subst, used_subst, cats, glass_table, notes) if "GLAS" in s.data else AIR
        curv = _arg(ctx, s, "CURV") / scale if "CURV" in s.data else 0.0
        conic = _arg(ctx, s, "CONI") if "CONI" in s.data else 0.0
        asph = []
        if s.type == "EVENASPH":
            for k, (ln, v) in sorted(s.parm.items()):
                if v == 0.0:
                    continue
                if k == 1:
                    raise ctx.error(f"PARM 1 = {v:g} (line {ln}): the r² term of an even asphere is not supported "
                                    "(the sag has a conic and A4 … A16 only)", surface=s.number, field="PARM")
                if k > 8:
                    raise ctx.error(f"PARM {k} (line {ln}): EVENASPH has parameters 1 … 8", surface=s.number,
                                    field="PARM")
            top = max([k for k, (_, v) in s.parm.items() if v != 0.0] + [1])
            asph = [s.parm.get(k, (0, 0.0))[1] * scale ** (1 - 2 * k) for k in range(2, top + 1)]
        elif any(v != 0.0 for _, v in s.parm.values()):
            ignored["PARM (STANDARD)"] = ignored.get("PARM (STANDARD)", 0) + 1
        thick = _arg(ctx, s, "DISZ", allow_inf=True)
        if math.isinf(thick):
            raise ctx.error(f"DISZ INFINITY (line {s.data['DISZ'][0]}) on a lens surface", surface=s.number,
                            field="DISZ")
        sd, sd_kw = None, "DIAM"
        for k in ("CLAP", "FLAP"):
            if k in s.data:
                rmin = _arg(ctx, s, k, 0) if k == "CLAP" else 0.0
                if rmin != 0.0:
                    raise ctx.error(f"an annular aperture (inner radius {rmin:g}, line {s.data[k][0]}) is not "
                                    "supported", surface=s.number, field=k)
                sd, sd_kw = _arg(ctx, s, k, 1) * scale, k
                break
        if sd is None and "DIAM" in s.data:
            sd = _arg(ctx, s, "DIAM") * scale
        housing = None
        if "MEMA" in s.data:
            mema = _arg(ctx, s, "MEMA") * scale
            if mema > 0 and (sd is None or mema >= sd):
                housing = mema
        lines = {k: v[0] for k, v in s.data.items()}
        lines["DIAM"] = s.data.get(sd_kw, (s.line,))[0]
        if s.parm:
            lines["PARM"] = min(ln for ln, _ in s.parm.values())
        seq.append(SeqSurface(number=s.number, curvature=curv, thickness=thick * scale, medium=medium,
                              semi_diameter=sd, housing=housing, conic=conic, aspheric=tuple(asph), stop=s.stop,
                              line=s.line, lines=lines))
        if sd_kw != "DIAM":
            seq[-1].lines[sd_kw] = lines["DIAM"]
    unused = sorted(set(subst) - used_subst)
    if unused:
        raise ctx.error(f"glasses= names {', '.join(map(repr, unused))}, which no GLAS line of this file uses "
                        f"(its glasses: {', '.join(sorted(glass_table)) or 'none'})", field="glasses")

    # -- the system aperture
    aperture, ap_note = _aperture(ctx, aperture_kw, scale, object_distance, stop_radius)
    if ap_note:
        notes.append(ap_note)

    n_conf = int(header["MNUM"][1][0]) if "MNUM" in header and header["MNUM"][1][:1] and \
        header["MNUM"][1][0].isdigit() else 1
    configs = _configurations(ctx, n_conf, mce, seq, scale, aperture, object_distance, stop_radius) \
        if n_conf > 1 else None
    if n_conf > 1 and configs is None:
        notes.append(f"the file has {n_conf} configurations (MNUM, line {header['MNUM'][0]}) that change no gap or "
                     "aperture: the one saved in the surface data is read")
    title = " ".join(header["NAME"][1]) if "NAME" in header else ""
    md = {"encoding": encoding, "unit": unit, "mm_per_unit": scale, "primary_wavelength_nm": primary,
          "wavelengths_nm": wl_list, "object_distance_mm": object_distance if math.isfinite(object_distance) else None,
          "image_distance_mm": seq[-1].thickness if seq else None, "aperture": list(aperture),
          "gcat": gcat, "glasses": glass_table, "ignored_keywords": dict(sorted(ignored.items()))}
    if "VERS" in header:
        md["vers"] = " ".join(header["VERS"][1])
    if notes:
        md["notes"] = notes
    lens_name = name or (Path(file).stem if file else "zemax-lens")
    lens = build_lens(ctx, seq, keywords=_KEYWORDS, object_medium=object_medium, aperture=aperture,
                      wavelength_nm=primary, name=lens_name, metadata=md, stop_keyword="STOP")
    if configs is not None:
        from ._sequential import moving_from_positions
        lens = moving_from_positions(ctx, configs, field="MNUM", keywords=_KEYWORDS, object_medium=object_medium,
                                     wavelength_nm=primary, name=lens_name, stop_keyword="STOP")
        md["configurations"] = n_conf
    source = {"format": "Zemax OpticStudio .zmx"}
    if file:
        source["file"] = Path(file).name
    meta = {"description": title, "source": source, "zemax": md}
    return lens.replace(metadata=meta)


def _configurations(ctx: Ctx, n: int, mce: list, seq: list, scale: float, aperture: tuple, object_distance: float,
                    stop_radius):
    """The file's ``n`` configurations as ``[(surfaces, aperture, object distance (mm)), ...]`` from its
    multi-configuration values (``THIC surface configuration value …``: a gap, surface 0 the object distance;
    ``APER 0 configuration value …``: the system aperture, in the unit of the file's ``ENPD``/``FNUM``), or None
    when they change no gap and no aperture.  Operands that only set fields, wavelengths or weights are left
    alone; one that changes the prescription otherwise (a curvature, conic, glass, parameter, …) is an error."""
    import dataclasses
    changes = False
    thick = {}      # (surface, config) -> mm
    aper = {}       # config -> value
    for key, a, c, v, ln in mce:
        if key in _MCE_REFUSED:
            raise ctx.error(f"the configurations change {_MCE_REFUSED[key]} ({key} {a} {c}, line {ln}): only gaps "
                            "(THIC) and the aperture (APER) may differ between configurations (moving groups)",
                            field=key)
        if not 1 <= c <= n:
            raise ctx.error(f"{key} {a} {c} (line {ln}) names configuration {c}, but MNUM gives {n}", field=key)
        if key == "THIC":
            if a > len(seq):
                raise ctx.error(f"THIC {a} {c} (line {ln}): no surface {a} before the image", field="THIC")
            thick[(a, c)] = _num(ctx, v, surface=a, keyword="THIC", line=ln, allow_inf=True) * scale
            changes = True
        elif key == "APER":
            aper[c] = _num(ctx, v, surface=None, keyword="APER", line=ln)
            changes = True
    if not changes:
        return None
    out = []
    for c in range(1, n + 1):
        c_seq = [dataclasses.replace(s, thickness=thick.get((s.number, c), s.thickness)) for s in seq]
        od = thick.get((0, c), object_distance)
        od = math.inf if od >= 1e10 else od
        ap = aperture
        if c in aper and stop_radius is None and aperture[0] in ("epd", "fno"):
            if not aper[c] > 0:
                raise ctx.error(f"configuration {c}'s aperture must be > 0, got {aper[c]:g}", field="APER")
            ap = (aperture[0], aper[c] * (scale if aperture[0] == "epd" else 1.0))
        out.append((c_seq, ap, od))
    return out


def _surface_keyword(ctx: Ctx, s: _Surf, key: str, args: list[str], ln: int, ignored: dict) -> None:
    if key == "STOP":
        s.stop = True
        s.data["STOP"] = (ln, args)
    elif key == "TYPE":
        if not args:
            raise ctx.error(f"TYPE without a surface type (line {ln})", surface=s.number, field="TYPE")
        if args[0] not in SURFACE_TYPES:
            raise ctx.error(f"TYPE {args[0]} (line {ln}) is not supported: a lens here is rotationally symmetric and "
                            f"made of {' and '.join(SURFACE_TYPES)} surfaces (spheres, conics and even aspheres "
                            "A4…A16)", surface=s.number, field="TYPE")
        s.type = args[0]
        s.data["TYPE"] = (ln, args)
    elif key == "PARM":
        if len(args) < 2:
            raise ctx.error(f"PARM needs a number and a value (line {ln}); the file looks truncated",
                            surface=s.number, field="PARM")
        k = int(_num(ctx, args[0], surface=s.number, keyword="PARM", line=ln))
        s.parm[k] = (ln, _num(ctx, args[1], surface=s.number, keyword="PARM", line=ln))
    elif key == "GLAS":
        if not args:
            raise ctx.error(f"GLAS without a glass name (line {ln})", surface=s.number, field="GLAS")
        if args[0].upper() == "MIRROR":
            raise ctx.error(f"GLAS MIRROR (line {ln}): mirrors are not supported; a lens here is a refractive, "
                            "sequential system along +z", surface=s.number, field="GLAS")
        s.data["GLAS"] = (ln, args)
    elif key == "SCBD":
        vals = [_num(ctx, t, surface=s.number, keyword=key, line=ln) for t in args[3:]]
        if any(v != 0.0 for v in vals):
            raise ctx.error(f"a surface tilt or decenter (SCBD {' '.join(args)}, line {ln}) is not supported: the "
                            "lens must be rotationally symmetric about one axis", surface=s.number, field="SCBD")
        ignored[key] = ignored.get(key, 0) + 1
    elif key == "OBDC":
        vals = [_num(ctx, t, surface=s.number, keyword=key, line=ln) for t in args[:2]]
        if any(v != 0.0 for v in vals):
            raise ctx.error(f"a decentered aperture (OBDC {' '.join(args)}, line {ln}) is not supported",
                            surface=s.number, field="OBDC")
    elif key in _OTHER_APERTURES:
        raise ctx.error(f"{_OTHER_APERTURES[key]} ({key}, line {ln}) is not supported: a surface's aperture is a "
                        "centred circle (DIAM, FLAP or CLAP)", surface=s.number, field=key)
    elif key in ("CURV", "DISZ", "CONI", "DIAM", "MEMA", "FLAP", "CLAP"):
        if not args:
            raise ctx.error(f"{key} without a value (line {ln}); the file looks truncated", surface=s.number,
                            field=key)
        s.data[key] = (ln, args)
    else:
        ignored[key] = ignored.get(key, 0) + 1


def _glass_subst(ctx: Ctx, glasses) -> dict:
    if glasses is None:
        return {}
    if not isinstance(glasses, dict):
        raise ctx.error(f"glasses= must be a dict {{glass name in the file: medium}}, got {type(glasses).__name__}",
                        field="glasses")
    out = {}
    for k, v in glasses.items():
        if not isinstance(k, str) or not k.strip():
            raise ctx.error(f"glasses= keys must be glass names, got {k!r}", field="glasses")
        out[k.strip().upper()] = v
    return out


def _gcat_catalogs(gcat: list[str]) -> list[str]:
    """Our catalogues named by GCAT, in its order (SUMITA_AUG2011 -> Sumita)."""
    out = []
    for g in gcat:
        for c in CATALOGS:
            if g.upper().startswith(c.upper()) and c not in out:
                out.append(c)
    return out


def _medium(ctx: Ctx, s: _Surf, subst: dict, used: set, cats: list[str], table: dict, notes: list) -> Medium:
    ln, args = s.data["GLAS"]
    gname = args[0]
    where = dict(surface=s.number, field="GLAS")
    key = gname.upper()
    m = substitute_glass(ctx, gname, subst, used, table, surface=s.number, field="GLAS")
    if m is not None:
        return m
    if key == "___BLANK":
        if len(args) < 5:
            raise ctx.error(f"a model glass (GLAS ___BLANK, line {ln}) needs nd and Vd in fields 4 and 5; the file "
                            "looks truncated", **where)
        nd = _num(ctx, args[3], surface=s.number, keyword="GLAS", line=ln)
        vd = _num(ctx, args[4], surface=s.number, keyword="GLAS", line=ln)
        dpgf = _num(ctx, args[5], surface=s.number, keyword="GLAS", line=ln) if len(args) > 5 else 0.0
        label = f"model nd={nd:.6g} vd={vd:.6g}"
        try:
            if vd == 0.0:  # Zemax: Vd = 0 means no dispersion
                m = AIR if nd == 1.0 else constant(nd, f"n={nd:.6g}")
            else:
                m = model_glass(nd, vd, name=label)
        except GlassError as e:
            raise ctx.error(f"model glass (line {ln}): {e.what}", **where) from None
        rec = {"from": "model glass (___BLANK)", "nd": nd, "vd": vd}
        if dpgf:
            rec["dPgF_ignored"] = dpgf
            note = "model glasses ignore their ΔPgF (the partial-dispersion offset on GLAS ___BLANK lines)"
            if note not in notes:
                notes.append(note)
        table.setdefault(label, rec)
        return m
    try:
        m = _catalog(gname, cats)
    except GlassError as e:
        fields = ""
        if len(args) >= 5:
            fields = (f" The GLAS line also holds nd {args[3]}, Vd {args[4]}: Zemax keeps these for model-glass "
                      "solves and does not use them for a catalogue glass (they are often stale defaults such as "
                      "1.5/40), so they are not used here.")
        raise ctx.error(f"{e.what} (line {ln}; the file's GCAT: {' '.join(cats) or 'none of ours'}).{fields} Give a "
                        f"substitute with glasses={{{gname!r}: 'N-BK7' or {{'nd': …, 'vd': …}}}} (CLI: --glass "
                        f"{gname}=SPEC)", **where) from None
    rec = {"catalog": m.source.get("catalog"), "glass": m.source.get("glass")}
    if len(args) >= 5:
        try:
            fnd, fvd = float(args[3]), float(args[4])
            if (fnd, fvd) not in ((1.5, 40.0), (0.0, 0.0)):
                rec.update({"file_nd": fnd, "file_vd": fvd, "catalog_nd": m.nd})
        except ValueError:
            pass
    table.setdefault(gname, rec)
    return m


def _catalog(name: str, cats: list[str]) -> Medium:
    """The file's GCAT catalogues first (exact spelling), then every catalogue (any spelling we accept)."""
    from ..catalogs import _norm
    for c in cats:
        try:
            m = catalog_glass(name, c)
        except GlassError:
            continue
        if _norm(m.source["glass"]) == _norm(name):
            return m
    return catalog_glass(name)


def _aperture(ctx: Ctx, entries, scale: float, object_distance: float, stop_radius):
    if stop_radius is not None:
        if isinstance(stop_radius, bool) or not isinstance(stop_radius, (int, float)) or not (
                math.isfinite(stop_radius) and stop_radius > 0):
            raise ctx.error(f"stop_radius must be a positive number of mm, got {stop_radius!r}", field="stop_radius")
        return ("radius", float(stop_radius)), None
    if not entries:
        return ("float", None), "no system aperture (ENPD, FNUM, FLOA) in the file: the stop's DIAM is the stop radius"
    key, ln, args = entries[-1]
    note = None
    if len(entries) > 1:
        note = f"several system apertures; the last one ({key}, line {ln}) is used"
    if key == "FLOA":
        return ("float", None), note
    v = _arg(ctx, None, key, 0, line=ln, toks=args)
    if key == "ENPD":
        if not v > 0:
            raise ctx.error(f"entrance pupil diameter must be > 0, got {v:g} (line {ln})", field=key)
        return ("epd", v * scale), note
    if key == "FNUM":
        flag = int(_arg(ctx, None, key, 1, line=ln, toks=args)) if len(args) > 1 else 0
        if not v > 0:
            raise ctx.error(f"f-number must be > 0, got {v:g} (line {ln})", field=key)
        if flag == 1 and math.isfinite(object_distance):
            raise ctx.error(f"a paraxial working f-number (FNUM {' '.join(args)}, line {ln}) with an object at a finite "
                            "distance is not supported; pass stop_radius=", field=key)
        return ("fno", v), note
    raise ctx.error(f"the system aperture is an object-space numerical aperture or cone angle (OBNA "
                    f"{' '.join(args)}, line {ln}), which is not supported: ENPD, FNUM and FLOA are; pass "
                    "stop_radius= (mm) to set the stop yourself", field=key)
