"""CODE V sequence files (``.seq``): the same subset as the Zemax reader, through the same back end.

A ``.seq`` file is a list of commands: ``;`` separates commands on a line, ``!`` starts a comment,
``&`` at the end of a line continues the command on the next one, commands and qualifiers are
case-insensitive and may be abbreviated to three letters (``TITLE`` = ``TIT``, ``STOP`` = ``STO``).
What is read (see ``docs/lens-format.md``, "CODE V .seq"):

system   ``RDM`` (radius mode: ``RDM``/``RDM Y`` radii, ``RDM N`` curvatures; a file without it is
         refused, because CODE V reads radii by default while hand-written files often mean
         curvatures; ``radius_mode=`` decides), ``DIM`` (M, C, I), ``WL`` + ``REF``, ``EPD``/``FNO``
         (the stop radius), ``TIT``, fields (``XAN``/``YAN``, ``XIM``/``YIM``, ``XRI``/``YRI``) for
         the default semi-diameters, ``PRV``/``PWL``/``END`` private glasses (index tables).
surfaces ``SO``, ``S`` and ``SI`` lines ``<radius or curvature> <thickness> [glass]``; ``STO``,
         ``CIR r`` (clear semi-diameter), ``CIR EDG r`` (edge -> housing radius), ``SPH``/``CON``/
         ``ASP``, ``K``, ``A``…``G`` (A4…A16), ``SLB``; solve and variable flags (``PIM``, ``CCY``,
         ``THC``, …) are noted, their saved values used.
glass    ``NAME_CATALOG`` (``NBK7_SCHOTT``, ``SLAL8_OHARA``), a name alone (searched in every
         catalogue), a private glass (``'E48'``), or a fictitious glass code ``nnnnnn.vvvv``
         (nd = 1.nnnnnn, Vd = vv.vv; ``517000.520000`` is nd 1.517, Vd 52).
zoom     ``ZOO`` rows and ``Zj`` qualifiers of gaps, the aperture and the fields: the positions become moving
         groups (:mod:`.codev_zoom`).

Refused, naming the file, the surface and the command: ``REFL`` (mirrors), decenters and tilts
(``XDE``/``YDE``/``ZDE``/``ADE``/``BDE``/``CDE``, ``DAR``, ``BEN``, ``REV``, ``RET``), other surface
types (``XTO``, ``YTO``, ``SPS``, ``DIF``, ``HOE``, …), obscurations and holes, non-circular
apertures, pickups (``PIK``), ``NAO``/``NA`` apertures, a curved image surface.

The image plane sits where CODE V puts it: the last surface's thickness plus the thickness on the
``SI`` line (CODE V's defocus of the image surface).  Surfaces without ``CIR`` get a semi-diameter
from a paraxial trace of each field's beam (chief ray plus the rim rays, shrunk by the file's
vignetting factors ``VUY``/``VLY``), + 2 % — CODE V computes such "default apertures" from the beam;
``metadata["codev"]["estimated_semi_diameters"]`` lists them.
"""
from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path
import re

import numpy as np

from ...errors import GlassError
from ..glass import AIR, CATALOGS, Medium, catalog_glass, model_glass, table_glass
from ..prescription import Lens
from ._common import Ctx
from ._sequential import SeqSurface, build_lens, max_semi_diameter, substitute_glass
from .codev_zoom import ZOOMABLE, ZoomData
from .zemax import _aperture as _zmx_aperture, _glass_subst

UNITS = {"M": 1.0, "MM": 1.0, "C": 10.0, "CM": 10.0, "I": 25.4, "IN": 25.4}
_ASP = {"A": 0, "B": 1, "C": 2, "D": 3, "E": 4, "F": 5, "G": 6, "H": 7, "J": 8}
#: commands that do not change the prescription (solves' saved values are used; flags, weights, titles)
_HARMLESS = {"LEN", "GO", "INI", "WTW", "WTF", "TEM", "PRE", "DER", "CCY", "THC", "GLC", "CUM", "THM", "PIM", "SLB",
             "VUX", "VUY", "VLX", "VLY", "WID", "CLS", "CWL", "NOT", "RSC", "SPH", "CON", "ASP", "EPD", "FNO",
             "NAO", "NA", "DIM", "RDM", "WL", "REF", "TIT", "XAN", "YAN", "XOB", "YOB", "XIM", "YIM", "XRI", "YRI",
             "PRV", "PWL", "END", "STO", "CIR", "K", "CUF"} | set(_ASP)
_REFUSE = {"XDE": "a decenter", "YDE": "a decenter", "ZDE": "a decenter", "ADE": "a tilt", "BDE": "a tilt",
           "CDE": "a tilt", "DAR": "a decenter-and-return", "BEN": "a bend (fold)", "REV": "a reverse decenter",
           "RET": "a coordinate return", "XTO": "a toroidal surface", "YTO": "a toroidal surface",
           "SPS": "a special surface", "DIF": "a diffractive surface", "HOE": "a holographic surface",
           "PIK": "a pickup (its value is not evaluated here)", "REX": "a rectangular aperture",
           "REY": "a rectangular aperture", "ELX": "an elliptical aperture", "ELY": "an elliptical aperture",
           "CUX": "an anamorphic (X) curvature", "RDX": "an anamorphic (X) radius", "GRN": "a gradient index",
           "ZRN": "a Zernike surface", "USR": "a user-defined surface", "IMP": "a surface import"}
_NUM = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)([eEdD][+-]?\d+)?$")
_ZPOS = re.compile(r"(?i)Z\d+")


def looks_like_codev(text: str) -> bool:
    """An object surface (``SO``) and a surface (``S <number> <number>``), each starting a command."""
    return bool(re.search(r"(?im)(^|;)\s*SO\s", text)) and bool(
        re.search(r"(?im)(^|;)\s*S\s+[-+.\d&]", text))


def load_codev(path: str | os.PathLike, **kw) -> Lens:
    raw = Path(path).read_bytes()
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")
    return read_codev(text, file=str(path), **kw)


# --------------------------------------------------------------------------------------------- lexing
def _strip_comment(line: str) -> str:
    q = None
    for i, ch in enumerate(line):
        if q:
            if ch == q:
                q = None
        elif ch in ("'", '"'):
            q = ch
        elif ch == "!":
            return line[:i]
    return line


def _split(body: str) -> list[str]:
    """Split at ``;`` outside quotes."""
    out, cur, q = [], [], None
    for ch in body:
        if q:
            cur.append(ch)
            if ch == q:
                q = None
        elif ch in ("'", '"'):
            q = ch
            cur.append(ch)
        elif ch == ";":
            out.append("".join(cur))
            cur = []
        else:
            cur.append(ch)
    out.append("".join(cur))
    return out


def _tokens(cmd: str) -> list[str]:
    return [t[1:-1] if t[:1] in ("'", '"') else t for t in re.findall(r"'[^']*'|\"[^\"]*\"|\S+", cmd)]


def commands(ctx: Ctx, text: str) -> list[tuple[int, list[str], bool]]:
    """(line, tokens, quoted-first-token) of every command, continuations joined."""
    lines = text.splitlines()
    out = []
    i = 0
    while i < len(lines):
        start = i + 1
        body = _strip_comment(lines[i])
        while body.rstrip().endswith("&"):
            if i + 1 >= len(lines):
                raise ctx.error(f"line {i + 1} ends with '&' (continued on the next line) but the file ends there: "
                                "it looks truncated", field="&")
            body = body.rstrip()[:-1] + _strip_comment(lines[i + 1])
            i += 1
        for part in _split(body):
            if part.strip():
                quoted = part.strip()[:1] in ("'", '"')
                out.append((start, _tokens(part), quoted))
        i += 1
    return out


def _key(tok: str) -> str:
    t = tok.upper()
    if t in ("SO", "SI", "S"):
        return t
    return t[:3]


def _float(ctx: Ctx, tok: str, *, surface, command: str, line: int) -> float:
    t = tok.replace("d", "e").replace("D", "E") if _NUM.match(tok) else tok
    try:
        x = float(t)
    except ValueError:
        raise ctx.error(f"expected a number, got {tok!r} (line {line})", surface=surface, field=command) from None
    if not math.isfinite(x):
        raise ctx.error(f"expected a finite number, got {tok!r} (line {line})", surface=surface, field=command)
    return x


# --------------------------------------------------------------------------------------------- reading
class _S:
    def __init__(self, number, line, rc, thickness, glass):
        self.number, self.line, self.rc, self.thickness, self.glass = number, line, rc, thickness, glass
        self.stop = False
        self.cir = None
        self.edg = None
        self.conic = 0.0
        self.asph = [0.0] * 9
        self.lines = {"S": line}


def read_codev(text: str, *, file: str | None = None, name: str | None = None, glasses: dict | None = None,
               stop_radius: float | None = None, radius_mode: bool | None = None) -> Lens:
    """Build a :class:`Lens` from the text of a CODE V ``.seq`` file.

    ``radius_mode``: ``True`` (radii) or ``False`` (curvatures) for a file without ``RDM``; a file
    with ``RDM`` must agree.  ``glasses``, ``stop_radius`` and ``name`` as for the Zemax reader.
    """
    ctx = Ctx(file or "<CODE V text>")
    rdm = None
    dim, wl, ref, title = None, None, None, ""
    aperture = None
    fields = {}
    private: dict[str, Medium] = {}
    pwl = None
    in_prv = False
    surfs: list[_S] = []
    obj = img = None
    notes: list[str] = []
    ignored: dict[str, int] = {}
    cur = None
    zoom = ZoomData(ctx, _float)

    for ln, toks, quoted in commands(ctx, text):
        if in_prv and quoted:
            gname = toks[0]
            if pwl is None:
                raise ctx.error(f"private glass {gname!r} (line {ln}) before its wavelengths (PWL)", field="PWL")
            vals = [_float(ctx, t, surface=None, command="PRV", line=ln) for t in toks[1:]]
            if len(vals) != len(pwl):
                raise ctx.error(f"private glass {gname!r} (line {ln}) has {len(vals)} indices for {len(pwl)} "
                                "wavelengths (PWL)", field="PRV")
            try:
                private[gname.upper()] = table_glass(sorted(zip(pwl, vals)), gname)
            except GlassError as e:
                raise ctx.error(f"private glass {gname!r} (line {ln}): {e.what}", field="PRV") from None
            continue
        k = _key(toks[0])
        args = toks[1:]
        where_s = None if cur is None else cur.number
        if k == "ZOO":
            zoom.command(toks, ln)
            continue
        if k in ZOOMABLE and any(_ZPOS.fullmatch(a) for a in args):
            zoom.qualified(toks, ln)
            continue
        if re.fullmatch(r"(?i)S\d+", toks[0]) or (args and re.fullmatch(r"(?i)S(\d+|O|I|A)", args[0])):
            raise ctx.error(f"{' '.join(toks)} (line {ln}): commands addressed to a numbered surface are not "
                            "supported; the reader follows the surfaces in file order", surface=where_s, field=k)
        if k in ("SO", "S", "SI"):
            if img is not None:
                raise ctx.error(f"{toks[0]} (line {ln}) after the image surface SI", surface=len(surfs) + 1, field=k)
            if k == "SO" and (obj is not None or surfs):
                raise ctx.error(f"a second object surface SO (line {ln})", surface=0, field="SO")
            if k != "SO" and obj is None:
                raise ctx.error(f"{toks[0]} (line {ln}) before the object surface SO", field="SO")
            number = 0 if k == "SO" else len(surfs) + 1
            if len(args) < 2:
                raise ctx.error(f"{k} needs a {'radius' if rdm else 'curvature'} and a thickness (line {ln}: "
                                f"{' '.join(toks)!r}); the file looks truncated", surface=number, field=k)
            rc = _float(ctx, args[0], surface=number, command=k, line=ln)
            t = _float(ctx, args[1], surface=number, command=k, line=ln)
            glass = args[2] if len(args) > 2 else None
            if len(args) > 3:
                raise ctx.error(f"unexpected {' '.join(args[3:])!r} after the glass (line {ln})", surface=number,
                                field=k)
            if glass is not None and glass.upper() == "REFL":
                raise ctx.error(f"REFL (line {ln}): mirrors are not supported; a lens here is a refractive, "
                                "sequential system along +z", surface=number, field="REFL")
            cur = _S(number, ln, rc, t, glass)
            if k == "SO":
                obj = cur
            elif k == "SI":
                img = cur
            else:
                surfs.append(cur)
            continue
        if k == "RDM":
            v = (args[0].upper() if args else "Y")
            if v[:1] not in ("Y", "N"):
                raise ctx.error(f"RDM {args[0]} (line {ln}): expected Y or N", field="RDM")
            rdm = v[:1] == "Y"
        elif k == "DIM":
            u = (args[0].upper() if args else "")
            if u not in UNITS:
                raise ctx.error(f"unknown unit DIM {u!r} (line {ln}); known: M (mm), C (cm), I (inches)", field="DIM")
            dim = u
        elif k == "WL":
            wl = [_float(ctx, t, surface=None, command="WL", line=ln) for t in args]
        elif k == "REF":
            ref = int(_float(ctx, args[0], surface=None, command="REF", line=ln)) if args else None
        elif k in ("EPD", "FNO"):
            aperture = (k, ln, args)
        elif k in ("NAO", "NA"):
            if stop_radius is None:
                raise ctx.error(f"the system aperture is a numerical aperture ({k} {' '.join(args)}, line {ln}), which "
                                "is not supported: EPD and FNO are; pass stop_radius= (mm) to set the stop yourself",
                                field=k)
        elif k == "TIT":
            title = " ".join(args)
        elif k in ("XAN", "YAN", "XIM", "YIM", "XRI", "YRI", "XOB", "YOB", "VUY", "VLY"):
            fields[k] = [_float(ctx, t, surface=None, command=k, line=ln) for t in args]
        elif k == "PRV":
            in_prv = True
        elif k == "PWL":
            pwl = [_float(ctx, t, surface=None, command="PWL", line=ln) for t in args]
        elif k == "END":
            in_prv = False
        elif k in _REFUSE:
            raise ctx.error(f"{_REFUSE[k]} ({' '.join(toks)}, line {ln}) is not supported: the lens must be a "
                            "rotationally symmetric refractive system", surface=where_s, field=k)
        elif cur is None and k in {"STO", "CIR", "K", "CUF"} | set(_ASP):
            raise ctx.error(f"{toks[0]} (line {ln}) before any surface", field=k)
        elif k == "STO":
            if cur is obj or cur is img:
                raise ctx.error(f"the {'object' if cur is obj else 'image'} surface cannot be the stop (line {ln})",
                                surface=cur.number, field="STO")
            cur.stop = True
            cur.lines["STO"] = ln
        elif k == "CIR":
            quals = [a.upper() for a in args if not _NUM.match(a)]
            nums = [a for a in args if _NUM.match(a)]
            if any(q[:3] in ("OBS", "HOL") for q in quals):
                raise ctx.error(f"an obscuration or hole ({' '.join(toks)}, line {ln}) is not supported",
                                surface=cur.number, field="CIR")
            if not nums:
                raise ctx.error(f"CIR without a radius (line {ln})", surface=cur.number, field="CIR")
            r = _float(ctx, nums[0], surface=cur.number, command="CIR", line=ln)
            if "EDG" in quals:
                cur.edg = r
                cur.lines["CIR EDG"] = ln
            else:
                cur.cir = r
                cur.lines["CIR"] = ln
        elif k == "K":
            cur.conic = _float(ctx, args[0] if args else "", surface=cur.number, command="K", line=ln)
            cur.lines["K"] = ln
        elif k in _ASP and len(toks[0]) == 1:
            v = _float(ctx, args[0] if args else "", surface=cur.number, command=k, line=ln)
            cur.asph[_ASP[k]] = v
            cur.lines.setdefault("ASP", ln)
            if v != 0.0 and _ASP[k] > 6:
                raise ctx.error(f"{k} = {v:g} (line {ln}): polynomial terms beyond r¹⁶ (G) are not supported",
                                surface=cur.number, field=k)
        elif k == "CUF":
            v = _float(ctx, args[0] if args else "", surface=cur.number, command="CUF", line=ln)
            if v != 0.0:
                raise ctx.error(f"CUF {v:g} (line {ln}) is not supported", surface=cur.number, field="CUF")
        elif k in _HARMLESS:
            ignored[k] = ignored.get(k, 0) + 1
        else:
            ignored[toks[0].upper()] = ignored.get(toks[0].upper(), 0) + 1

    # -- what must be there
    if obj is None:
        raise ctx.error("no object surface (SO)", field="SO")
    if img is None:
        raise ctx.error(f"no image surface (SI) after surface {len(surfs)}: the file looks truncated", field="SI")
    if not surfs:
        raise ctx.error("no surface between SO and SI", field="S")
    if rdm is None:
        if radius_mode is None:
            raise ctx.error("no RDM command: CODE V reads the first number of an S line as a radius by default, but "
                            "files written for other programs often mean a curvature; add RDM Y (radii) or RDM N "
                            "(curvatures), or pass radius_mode=True/False", field="RDM")
        rdm = bool(radius_mode)
        notes.append(f"no RDM in the file: radius_mode={rdm} given to the reader")
    elif radius_mode is not None and bool(radius_mode) != rdm:
        raise ctx.error(f"radius_mode={radius_mode} disagrees with the file's RDM {'Y' if rdm else 'N'}", field="RDM")
    scale = UNITS[dim] if dim else 1.0
    if dim is None:
        notes.append("no DIM in the file: millimetres")
    if wl:
        r = ref if ref is not None else (len(wl) + 1) // 2
        if not 1 <= r <= len(wl):
            raise ctx.error(f"REF {r} but WL lists {len(wl)} wavelengths", field="REF")
        primary = wl[r - 1]
        if ref is None and len(wl) > 1:
            notes.append(f"no REF: the middle wavelength ({primary:g} nm) is the reference")
    else:
        primary = 587.5618
        notes.append("no WL in the file: 587.5618 nm")

    def curv(s: _S) -> float:
        if rdm:
            return 0.0 if s.rc == 0.0 else 1.0 / (s.rc * scale)
        return s.rc / scale

    if curv(img) != 0.0:
        raise ctx.error(f"a curved image surface (line {img.line}) is not supported: the sensor is a plane",
                        surface=img.number, field="SI")
    subst = _glass_subst(ctx, glasses)
    used: set[str] = set()
    table: dict[str, dict] = {}
    object_medium = _medium(ctx, obj, subst, used, private, table) if obj.glass else AIR
    seq = []
    for s in surfs:
        medium = _medium(ctx, s, subst, used, private, table) if s.glass else AIR
        top = max([i for i, a in enumerate(s.asph) if a != 0.0] + [-1])
        asph = tuple(s.asph[i] * scale ** (-3 - 2 * i) for i in range(top + 1))
        lines = dict(s.lines)
        lines.setdefault("CIR", s.line)
        seq.append(SeqSurface(number=s.number, curvature=curv(s), thickness=s.thickness * scale, medium=medium,
                              semi_diameter=None if s.cir is None else s.cir * scale,
                              housing=None if s.edg is None else s.edg * scale, conic=s.conic, aspheric=asph,
                              stop=s.stop, line=s.line, lines=lines))
    unused = sorted(set(subst) - used)
    if unused:
        raise ctx.error(f"glasses= names {', '.join(map(repr, unused))}, which no surface of this file uses",
                        field="glasses")
    n_pos = zoom.positions(len(surfs))

    def image_gap(seq, defocus):
        seq[-1].thickness += defocus
        if seq[-1].thickness < 0:
            raise ctx.error(f"the image plane lies {-seq[-1].thickness:g} mm in front of the last surface (its "
                            f"thickness plus the SI thickness {defocus:g})", surface=img.number, field="SI")

    def system_aperture(kw, v, ln):
        if stop_radius is not None:
            return _zmx_aperture(ctx, [], 1.0, math.inf, stop_radius)[0]
        if kw is None:
            return ("float", None)
        if not v > 0:
            raise ctx.error(f"{kw} must be > 0, got {v:g} (line {ln})", field=kw)
        return ("epd", v * scale) if kw == "EPD" else ("fno", v)

    def distance(t):
        return math.inf if t * scale >= 1e10 else t * scale

    defocus = img.thickness * scale
    image_gap(seq, defocus)

    # -- the system aperture
    kw = v = ln = None
    if aperture is not None:
        kw, ln, args = aperture
        v = _float(ctx, args[0] if args else "", surface=None, command=kw, line=ln)
    elif stop_radius is None:
        notes.append("no EPD or FNO in the file: the stop's CIR is the stop radius")
    ap = system_aperture(kw, v, ln)

    if not any(s.stop for s in seq):
        raise ctx.error("no aperture stop: no surface carries STO (exactly one must)", field="STO")

    # -- zoom positions: each position's gaps, aperture and fields; the surfaces without CIR get the largest of
    # their positions' default semi-diameters (one clear aperture for the whole zoom)
    positions = []
    if zoom.rows:
        zoomed_ap = [k for k in ("EPD", "FNO") if (k, None) in zoom.rows]
        if len(zoomed_ap) > 1:
            raise ctx.error("both EPD and FNO are zoomed: one system aperture per file", field="ZOO")
        for p in range(n_pos):
            c_seq = [dataclasses.replace(b, thickness=zoom.value(("THI", f.number), p, f.thickness) * scale,
                                         lines=dict(b.lines)) for f, b in zip(surfs, seq)]
            image_gap(c_seq, zoom.value(("THI", "SI"), p, img.thickness) * scale)
            c_ap = ap
            if zoomed_ap:
                k_ap = zoomed_ap[0]
                c_ap = system_aperture(k_ap, zoom.value((k_ap, None), p, None), zoom.lines[(k_ap, None)])
            c_od = distance(zoom.value(("THI", 0), p, obj.thickness))
            c_est = _default_semi_diameters(ctx, c_seq, object_medium, c_ap, primary, zoom.fields_at(fields, p),
                                            scale, c_od)
            positions.append((c_seq, c_ap, c_od, c_est))
        widest = {}
        for *_, c_est in positions:
            for num, sd in c_est.items():
                widest[num] = max(sd, widest.get(num, 0.0))
        for c_seq in [seq] + [c[0] for c in positions]:
            for sf in c_seq:
                if str(sf.number) in widest:
                    sf.semi_diameter = widest[str(sf.number)]

    # -- default semi-diameters for surfaces without CIR
    object_distance = distance(obj.thickness)
    estimated = _default_semi_diameters(ctx, seq, object_medium, ap, primary, fields, scale, object_distance)
    if positions:
        estimated = widest
    ignored.update(zoom.ignored)

    md = {"unit": dim or "M", "mm_per_unit": scale, "radius_mode": rdm, "primary_wavelength_nm": primary,
          "wavelengths_nm": wl or [primary], "object_distance_mm": None if math.isinf(object_distance)
          else object_distance, "image_defocus_mm": defocus, "image_distance_mm": seq[-1].thickness,
          "aperture": list(ap), "glasses": table, "estimated_semi_diameters": estimated,
          "ignored_commands": dict(sorted(ignored.items()))}
    if notes:
        md["notes"] = notes
    lens_name = name or (Path(file).stem if file else "codev-lens")
    keywords = {"radius": "S", "thickness": "S", "medium": "S", "semi_diameter": "CIR", "conic": "K",
                "aspheric": "ASP", "housing_radius": "CIR EDG", "epd": "EPD", "fno": "FNO", "float": "CIR"}
    lens = build_lens(ctx, seq, keywords=keywords, object_medium=object_medium, aperture=ap, wavelength_nm=primary,
                      name=lens_name, metadata=md, stop_keyword="STO")
    if positions:
        from ._sequential import moving_from_positions
        lens = moving_from_positions(ctx, [c[:3] for c in positions], field="ZOO", keywords=keywords,
                                     object_medium=object_medium, wavelength_nm=primary, name=lens_name,
                                     stop_keyword="STO")
        md["zoom_positions"] = n_pos
    source = {"format": "CODE V .seq"}
    if file:
        source["file"] = Path(file).name
    return lens.replace(metadata={"description": title, "source": source, "codev": md})


def _medium(ctx: Ctx, s: _S, subst: dict, used: set, private: dict, table: dict) -> Medium:
    g = s.glass
    where = dict(surface=s.number, field="S")
    key = g.upper()
    m = substitute_glass(ctx, g, subst, used, table, surface=s.number, field="S")
    if m is not None:
        return m
    if key in private:
        table.setdefault(g, {"from": "private glass (PRV)"})
        return private[key]
    if _NUM.match(g):
        nd, vd = _glass_code(g)
        try:
            m = model_glass(nd, vd, name=f"{g} (nd={nd:.6g} vd={vd:.6g})")
        except GlassError as e:
            raise ctx.error(f"glass code {g} (line {s.line}): {e.what}", **where) from None
        table.setdefault(g, {"from": "glass code", "nd": nd, "vd": vd})
        return m
    gname, cat = g, None
    if "_" in g:
        head, _, tail = g.rpartition("_")
        if any(tail.upper() == c.upper() for c in CATALOGS):
            gname, cat = head, next(c for c in CATALOGS if c.upper() == tail.upper())
        elif tail.isalpha():
            raise ctx.error(f"glass {g!r} (line {s.line}) names the catalogue {tail!r}, which is not one of ours "
                            f"({', '.join(CATALOGS)}); give a substitute with glasses={{{g!r}: …}}", **where)
    try:
        m = catalog_glass(gname, cat)
    except GlassError as e:
        raise ctx.error(f"{e.what} (line {s.line}). Give a substitute with glasses={{{g!r}: 'N-BK7' or "
                        f"{{'nd': …, 'vd': …}}}} (CLI: --glass {g}=SPEC)", **where) from None
    table.setdefault(g, {"catalog": m.source.get("catalog"), "glass": m.source.get("glass")})
    return m


def _glass_code(code: str) -> tuple[float, float]:
    """CODE V's fictitious glass code: ``517000.520000`` -> (1.517, 52.0), ``500.700`` -> (1.5, 70.0):
    the integer part is the decimals of nd, the fraction × 100 is Vd."""
    ip, _, fp = code.partition(".")
    ip = ip.lstrip("+")
    nd = 1.0 + int(ip) / 10 ** len(ip)
    vd = round(float("0." + (fp or "0")) * 100.0, 9)
    return nd, vd


def _default_semi_diameters(ctx, seq, object_medium, ap, wavelength, fields, scale, object_distance):
    """Fill in the semi-diameter of surfaces without CIR: 1.02 × the largest paraxial height of the
    fields' beams (chief ray ± the marginal height shrunk by VUY/VLY), for an object at infinity,
    capped at 99.9 % of what the surface allows.  A flat stop between equal media needs none (its
    radius comes from the aperture).  Returns {surface: semi-diameter}."""
    before, missing = object_medium, []
    for s in seq:
        if s.semi_diameter is None and not (s.stop and s.is_plain and s.medium == before):
            missing.append(s)
        before = s.medium
    if not missing:
        return {}
    # paraxial y-nu trace with the file's thicknesses; the stop sits at its surface's vertex
    n0 = float(object_medium.index(wavelength))
    ns = [float(s.medium.index(wavelength)) for s in seq]
    si = next(i for i, s in enumerate(seq) if s.stop)

    def trace(y, nu):
        ys, n_prev = [], n0
        for i, s in enumerate(seq):
            ys.append(y)
            nu = nu - y * s.curvature * (ns[i] - n_prev)
            if i < len(seq) - 1:
                y = y + s.thickness * nu / ns[i]
            n_prev = ns[i]
        return np.array(ys)

    # unit rays to locate the entrance pupil (image of the stop in object space)
    ya, yb = trace(1.0, 0.0), trace(0.0, n0)
    # a ray (y0, u0) at z=0 crosses the stop at ya[si]*y0 + yb[si]*u0 = 0 for the chief ray
    kind, value = ap
    epr = None
    if ya[si] != 0.0:
        # marginal: object at infinity -> u0 = 0, y0 = EPR; the stop radius scales linearly
        r_stop = None
        if kind == "epd":
            epr = 0.5 * value
        elif kind == "fno":
            A = _efl(seq, n0, ns, wavelength)
            epr = 0.5 * abs(A) / value
        else:
            st = seq[si]
            r_stop = st.semi_diameter if kind == "float" else float(value)
            epr = None if r_stop is None else abs(r_stop / ya[si])
    if epr is None:
        raise ctx.error("cannot estimate the semi-diameters of surfaces without CIR: the entrance pupil is undefined",
                        surface=missing[0].number, field="CIR")
    ym = ya * epr
    # each field's beam: chief ray through the stop centre, rim rays at (1 - VUY) and (1 - VLY) of the
    # marginal height above and below it (CODE V's vignetting factors)
    rim = np.abs(ym)
    vuy, vly = fields.get("VUY", []), fields.get("VLY", [])
    for j, theta in enumerate(_field_angles(fields, seq, n0, ns, wavelength, scale)):
        u = math.tan(theta)
        y0 = -yb[si] * u / ya[si]               # height at z = 0 of the chief ray aimed at the stop centre
        yc = trace(y0, n0 * u)
        up = 1.0 - (vuy[j] if j < len(vuy) else 0.0)
        lo = 1.0 - (vly[j] if j < len(vly) else 0.0)
        rim = np.maximum(rim, np.maximum(np.abs(yc + up * ym), np.abs(yc - lo * ym)))
    out = {}
    for i, s in enumerate(seq):
        if s in missing:
            sd = 1.02 * rim[i]
            lim = max_semi_diameter(s.curvature, s.conic)
            sd = min(sd, 0.999 * lim)
            s.semi_diameter = float(sd)
            out[str(s.number)] = float(sd)
    return out


def _efl(seq, n0, ns, wavelength):
    M = np.eye(2)
    n_prev = n0
    for i, s in enumerate(seq):
        M = np.array([[1.0, 0.0], [-s.curvature * (ns[i] - n_prev), 1.0]]) @ M
        if i < len(seq) - 1:
            M = np.array([[1.0, s.thickness / ns[i]], [0.0, 1.0]]) @ M
        n_prev = ns[i]
    power = -M[1, 0]
    return ns[-1] / power if power else math.inf


def _field_angles(fields, seq, n0, ns, wavelength, scale) -> list[float]:
    """The field angles (radians) of the file's field list: angles, or image heights / EFL."""
    for xk, yk in (("XAN", "YAN"), ("XIM", "YIM"), ("XRI", "YRI")):
        xs, ys = fields.get(xk, []), fields.get(yk, [])
        n = max(len(xs), len(ys))
        if not n:
            continue
        xs = xs + [0.0] * (n - len(xs))
        ys = ys + [0.0] * (n - len(ys))
        h = [math.hypot(x, y) for x, y in zip(xs, ys)]
        if xk == "XAN":
            return [math.radians(a) for a in h]
        efl = _efl(seq, n0, ns, wavelength)
        return [math.atan(a * scale / abs(efl)) if math.isfinite(efl) else 0.0 for a in h]
    return [0.0]
