"""The common back end of the readers of lens-design programs' files (Zemax ``.zmx``, CODE V ``.seq``).

Those programs describe a lens the same way: an object surface, numbered surfaces with a curvature,
a thickness to the next surface, a glass after the surface, a semi-diameter and optional conic and
polynomial terms, one surface flagged as the stop, an image surface, and a *system aperture* (entrance
pupil diameter, f-number or "float by stop size").  The format readers turn a file into a list of
:class:`SeqSurface` in millimetres with resolved media; :func:`build_lens` turns that into our
validated :class:`~mi_neurallens.optics.prescription.Lens`:

* **Dummy surfaces** (flat, no polynomial terms, the same medium on both sides, not the stop) do
  nothing to a ray in our model but cost a surface in the tracer and in every path id, so they are
  dropped and their thickness added to the gap they sit in.  The first vertex of the lens (z = 0) is
  therefore the first surface that refracts or the stop.
* **The stop** is its own flat surface in our model.  A stop on a flat dummy surface becomes that
  surface.  A stop on a lens surface (curved, aspheric or between two media, as in most catalogue
  singlets) becomes a flat stop in the plane of that surface's vertex — paraxially the same place —
  inserted in front of the surface when the surface's sag is ≥ 0 across its semi-diameter (it bulges
  toward the object, or is flat), behind it when the sag is ≤ 0, so that the two never cross.  When
  the sag has both signs (some aspheres), the stop goes in front, where the surface reaches farthest
  forward, and the metadata records that shift.
* **The stop radius** is chosen so that the paraxial entrance pupil at the primary wavelength matches
  the file's system aperture: ``("epd", D)`` gives an entrance-pupil radius D/2, ``("fno", N)`` an
  entrance-pupil diameter EFL/N (image-space f-number, object at infinity), ``("float", None)`` keeps
  the semi-diameter written on the stop surface, ``("radius", r)`` (the reader's ``stop_radius=``)
  sets it directly.
* **Errors** name the file, the file's own surface number and the file's keyword (``field``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
import math

import numpy as np

from ...errors import GlassError, LensError
from ..glass import AIR, Medium
from ..prescription import MAX_ASPHERIC, Lens, Surface, surfaces_cross
from ._common import Ctx

#: our Surface field -> a description used when the format gives no keyword for it
_FIELDS = ("radius", "thickness", "medium", "semi_diameter", "conic", "aspheric", "housing_radius", "stop")


@dataclass
class SeqSurface:
    """One surface of a design program's file, in millimetres, media resolved."""

    number: int                       # the file's surface number (object surface = 0)
    curvature: float = 0.0            # 1/mm
    thickness: float = 0.0            # mm to the next surface
    medium: Medium = AIR              # after the surface
    semi_diameter: float | None = None  # clear semi-diameter, mm
    housing: float | None = None      # mechanical semi-diameter, mm
    conic: float = 0.0
    aspheric: tuple = ()              # A4, A6, … A16
    stop: bool = False
    line: int | None = None           # line where the surface starts
    lines: dict = field(default_factory=dict)  # keyword -> line number

    def where(self, keyword: str) -> str:
        ln = self.lines.get(keyword, self.line)
        return f" (line {ln})" if ln else ""

    @property
    def is_plain(self) -> bool:
        """Flat with no polynomial terms."""
        return self.curvature == 0.0 and not any(a != 0.0 for a in self.aspheric)


def max_semi_diameter(curvature: float, conic: float) -> float:
    if curvature == 0.0 or 1.0 + conic <= 0.0:
        return math.inf
    return 1.0 / (abs(curvature) * math.sqrt(1.0 + conic))


def _surface(s: SeqSurface, **kw) -> Surface:
    args = dict(radius=math.inf if s.curvature == 0.0 else 1.0 / s.curvature, thickness=s.thickness,
                medium=s.medium, semi_diameter=s.semi_diameter, conic=s.conic, aspheric=tuple(s.aspheric),
                housing_radius=s.housing, label=str(s.number))
    args.update(kw)
    return Surface(**args)


def build_lens(ctx: Ctx, surfaces: list[SeqSurface], *, keywords: dict, object_medium: Medium = AIR,
               aperture: tuple, wavelength_nm: float, name: str, metadata: dict,
               stop_keyword: str) -> Lens:
    """Our :class:`Lens` from the optical surfaces of a design file (object and image surfaces
    excluded; the last surface's thickness is the image distance).  See the module docstring.

    ``keywords`` maps our field names (``radius``, ``thickness``, ``medium``, ``semi_diameter``,
    ``conic``, ``aspheric``, ``housing_radius``) to the file's keywords for error messages.
    ``aperture`` is ``("epd", D)``, ``("fno", N)``, ``("float", None)`` or ``("radius", r)``.
    ``metadata`` (the format's own dict) receives ``surface_numbers``, ``dropped_surfaces``,
    ``first_vertex_z_in_file`` and ``stop``.
    """
    kw = {f: keywords.get(f, f) for f in _FIELDS}
    if not surfaces:
        raise ctx.error("no surfaces between the object and the image surface", field=kw["radius"])
    stops = [s for s in surfaces if s.stop]
    if not stops:
        raise ctx.error(f"no aperture stop: no surface carries {stop_keyword} (exactly one must)",
                        field=stop_keyword)
    if len(stops) > 1:
        s = stops[1]
        raise ctx.error(f"a second aperture stop{s.where(stop_keyword)}; surface {stops[0].number} is already "
                        "the stop", surface=s.number, field=stop_keyword)

    # -- per-surface checks, in the file's numbering
    for s in surfaces:
        if s.thickness < 0 or not math.isfinite(s.thickness):
            raise ctx.error(f"thickness must be a finite number ≥ 0 (a negative thickness means a mirror or a "
                            f"folded system, which a refractive lens cannot have), got {s.thickness:g} mm"
                            f"{s.where(kw['thickness'])}", surface=s.number, field=kw["thickness"])
        if len(s.aspheric) > MAX_ASPHERIC:
            raise ctx.error(f"{len(s.aspheric)} polynomial terms; at most A4 … A16 ({MAX_ASPHERIC}) are supported"
                            f"{s.where(kw['aspheric'])}", surface=s.number, field=kw["aspheric"])
        if s.is_plain:
            continue  # a dummy, a flat stop or a flat refracting surface: checked below where it needs one
        _check_semi_diameter(ctx, s, kw)

    # -- the surfaces of our lens
    out: list[Surface] = []
    numbers: list[int] = []         # the file surface number of each of ours
    roles: list[str] = []           # "surface", "stop", "inserted stop"
    dropped = []
    z_first = 0.0                   # file z (from the first file surface's vertex) of our first vertex
    before = object_medium
    stop_info = {}
    for s in surfaces:
        plain_same = s.is_plain and s.medium == before
        if plain_same and not s.stop:
            rec = {"surface": s.number, "thickness_mm": s.thickness,
                   "reason": "dummy surface (flat, the same medium on both sides)"}
            if s.semi_diameter is not None:
                rec["semi_diameter_mm"] = s.semi_diameter
            dropped.append(rec)
            if out:
                out[-1] = _replace(out[-1], thickness=out[-1].thickness + s.thickness)
            else:
                z_first += s.thickness
            continue
        if s.is_plain and s.medium != before and s.semi_diameter is None:
            raise ctx.error(f"no semi-diameter{s.where(kw['semi_diameter'])}", surface=s.number,
                            field=kw["semi_diameter"])
        if s.stop and plain_same:
            out.append(_surface(s, semi_diameter=s.semi_diameter or 1.0, conic=0.0, aspheric=(), housing_radius=None,
                                is_stop=True, label="STO"))
            numbers.append(s.number)
            roles.append("stop")
            stop_info = {"placed": f"on surface {s.number}, a flat surface in {before.name}",
                         "file_semi_diameter_mm": s.semi_diameter}
            before = s.medium
            continue
        if s.semi_diameter is None:
            raise ctx.error(f"no semi-diameter{s.where(kw['semi_diameter'])}", surface=s.number,
                            field=kw["semi_diameter"])
        if s.is_plain:
            _check_semi_diameter(ctx, s, kw)
        surf = _surface(s)
        if s.stop:
            r = np.linspace(0.0, s.semi_diameter, 257)
            sag = surf.sag(r)
            lo, hi = float(np.nanmin(sag)), float(np.nanmax(sag))
            front = lo >= -1e-9 or hi > 1e-9     # sag ≥ 0, or of both signs: in front
            shift = 0.0 if lo >= -1e-9 or hi <= 1e-9 else -lo
            stop_info = {"placed": (f"a flat stop in the vertex plane of surface {s.number} (which carries the file's "
                                    f"stop), {'in front of' if front else 'behind'} it"),
                         "file_semi_diameter_mm": s.semi_diameter}
            if shift:
                # the sag changes sign: no plane through the vertex clears the surface; the stop goes
                # where the surface is farthest forward, and the gap in front of it gives way
                stop_info["placed"] = (f"a flat stop {shift:.6g} mm in front of the vertex of surface {s.number} (which "
                                       "carries the file's stop; its sag changes sign, so no plane through the "
                                       "vertex clears it)")
                stop_info["shift_mm"] = shift
                if out:
                    if out[-1].thickness < shift:
                        raise ctx.error(f"the stop on surface {s.number} cannot be placed: the surface's sag changes "
                                        f"sign and reaches {shift:.4g} mm in front of its vertex, farther than the "
                                        f"gap in front of it", surface=s.number, field=stop_keyword)
                    out[-1] = _replace(out[-1], thickness=out[-1].thickness - shift)
                else:
                    z_first -= shift
            stop_kw = dict(radius=math.inf, conic=0.0, aspheric=(), housing_radius=None, is_stop=True,
                           label="STO", semi_diameter=s.semi_diameter)
            if front:
                out += [_surface(s, thickness=shift, medium=before, **stop_kw), surf]
                roles += ["inserted stop", "surface"]
            else:
                out += [_replace(surf, thickness=0.0), _surface(s, **stop_kw)]
                roles += ["surface", "inserted stop"]
            numbers += [s.number, s.number]
        else:
            out.append(surf)
            numbers.append(s.number)
            roles.append("surface")
        before = s.medium

    if not any(not (r == "stop") for r in roles):
        raise ctx.error("the lens has no refracting surface (every surface is flat between equal media)",
                        field=kw["radius"])
    for i in range(len(out) - 1):
        if out[i].thickness == 0.0 and not (out[i].is_stop or out[i + 1].is_stop):
            raise ctx.error(f"thickness 0 between surfaces {numbers[i]} and {numbers[i + 1]}: two surfaces in one "
                            "place are not a lens", surface=numbers[i], field=kw["thickness"])

    # -- the stop radius for the file's system aperture
    si = next(i for i, s in enumerate(out) if s.is_stop)
    kind, value = aperture
    lens0 = _construct(ctx, out, numbers, roles, kw, object_medium, name)
    p0 = lens0.paraxial(wavelength_nm)
    epr1 = p0.entrance_pupil_radius / out[si].semi_diameter   # entrance-pupil radius per mm of stop radius
    stop_kwd = {"epd": keywords.get("epd", "EPD"), "fno": keywords.get("fno", "FNO"),
                "float": keywords.get("float", "FLOAT"), "radius": "stop_radius"}[kind]
    if kind == "epd":
        r = 0.5 * value / epr1
        rule = f"{stop_kwd} {value:g} mm: paraxial entrance-pupil diameter at {wavelength_nm:g} nm"
    elif kind == "fno":
        r = 0.5 * abs(p0.efl) / value / epr1
        rule = (f"{stop_kwd} {value:g}: image-space f-number EFL / entrance-pupil diameter at "
                f"{wavelength_nm:g} nm (EFL {p0.efl:.6g} mm)")
    elif kind == "float":
        if stop_info.get("file_semi_diameter_mm") is None:
            raise ctx.error(f"the stop radius floats with the stop's semi-diameter ({stop_kwd}), but the stop surface "
                            f"has none ({kw['semi_diameter']})", surface=numbers[si], field=kw["semi_diameter"])
        r = out[si].semi_diameter
        rule = f"{stop_kwd}: the semi-diameter written on the stop surface"
    elif kind == "radius":
        r = float(value)
        rule = "stop_radius= given to the reader"
    else:  # pragma: no cover - the readers pass one of the above
        raise AssertionError(kind)
    if not (math.isfinite(r) and r > 0):
        raise ctx.error(f"the system aperture gives a stop radius of {r!r} mm; it must be > 0",
                        surface=numbers[si], field=stop_kwd)
    out[si] = _replace(out[si], semi_diameter=float(r))
    lens = _construct(ctx, out, numbers, roles, kw, object_medium, name)
    p = lens.paraxial(wavelength_nm)
    stop_info.update({"surface": numbers[si], "rule": rule, "radius_mm": float(r),
                      "entrance_pupil_radius_mm": p.entrance_pupil_radius, "fnumber": p.fnumber,
                      "wavelength_nm": wavelength_nm})
    metadata.update({"surface_numbers": [None if ro == "inserted stop" else n for n, ro in zip(numbers, roles)],
                     "dropped_surfaces": dropped, "first_vertex_z_in_file": z_first, "stop": stop_info})
    return lens


def _replace(s: Surface, **kw) -> Surface:
    import dataclasses
    return dataclasses.replace(s, **kw)


def _check_semi_diameter(ctx: Ctx, s: SeqSurface, kw: dict) -> None:
    sd = s.semi_diameter
    if sd is None:
        raise ctx.error(f"no semi-diameter{s.where(kw['semi_diameter'])}", surface=s.number, field=kw["semi_diameter"])
    if not (math.isfinite(sd) and sd > 0):
        raise ctx.error(f"semi-diameter must be > 0 mm, got {sd:g}{s.where(kw['semi_diameter'])}",
                        surface=s.number, field=kw["semi_diameter"])
    mx = max_semi_diameter(s.curvature, s.conic)
    if sd > mx * (1 + 1e-9):
        r = 1.0 / s.curvature
        raise ctx.error(f"semi-diameter {sd:.6g} mm is larger than the surface allows: {mx:.6g} mm for radius "
                        f"{r:.6g} mm and conic {s.conic:g} (1/(|c|·sqrt(1+K))){s.where(kw['semi_diameter'])}",
                        surface=s.number, field=kw["semi_diameter"])


def _check_crossing(ctx: Ctx, out: list[Surface], numbers: list[int], roles: list[str], kw: dict) -> None:
    z = np.concatenate([[0.0], np.cumsum([s.thickness for s in out[:-1]])])
    for i in range(len(out) - 1):
        hit = surfaces_cross(out[i], z[i], out[i + 1], z[i + 1])
        if hit is not None:
            na = "the stop" if roles[i] == "inserted stop" else f"surface {numbers[i]}"
            nb = "the stop" if roles[i + 1] == "inserted stop" else f"surface {numbers[i + 1]}"
            raise ctx.error(f"{na} and {nb} cross: at r = {hit[0]:.4g} mm {nb} lies {hit[1]:.4g} mm in front of "
                            f"{na} (the thickness between them is too small for their semi-diameters)",
                            surface=numbers[i], field=kw["thickness"])


def _construct(ctx, out, numbers, roles, kw, object_medium, name) -> Lens:
    _check_crossing(ctx, out, numbers, roles, kw)
    try:
        return Lens(tuple(out), name=name, object_medium=object_medium, metadata={}, path=ctx.file)
    except LensError as e:
        if e.surface is None or e.file != ctx.file:
            raise
        i = e.surface
        what = e.what + (" (the stop inserted at this surface's vertex)" if roles[i] == "inserted stop" else "")
        raise ctx.error(what, surface=numbers[i], field=kw.get(e.field, e.field)) from None


def substitute_glass(ctx: Ctx, name: str, subst: dict, used: set, table: dict, *, surface: int,
                     field: str):
    """The medium the caller substituted for glass ``name`` (``glasses=``/``--glass``), or None when
    none was given.  Records the use (an unused substitute is an error later) and the source in
    ``table``; a substitute that does not resolve is an error naming the surface and ``field``."""
    key = name.upper()
    if key not in subst:
        return None
    from ._common import resolve
    used.add(key)
    try:
        m = resolve(ctx, subst[key], surface=surface, field=field)
    except GlassError as e:
        raise ctx.error(f"glasses={{{name!r}: …}}: {e.what}", surface=surface, field=field) from None
    table.setdefault(name, {"from": "glasses= option", "medium": m.name})
    return m


def moving_from_positions(ctx: Ctx, positions: list, *, field: str, **build_kw) -> Lens:
    """A design file's configurations or zoom positions, ``[(surfaces, aperture, object distance (mm) in front of the
    file's first surface), ...]``, each built like a file of its own (:func:`build_lens` with ``build_kw``), as one
    lens with moving groups (:func:`moving_from_configurations`)."""
    mds = [{} for _ in positions]
    lenses = [build_lens(ctx, seq, aperture=ap, metadata=m, **build_kw) for (seq, ap, _), m in zip(positions, mds)]
    # each object distance in front of our first vertex: the file's, plus dummy surfaces dropped in front
    z0 = [float(m.get("first_vertex_z_in_file", 0.0) or 0.0) for m in mds]
    return moving_from_configurations(ctx, lenses, [od + z for (_, _, od), z in zip(positions, z0)], field=field)


def moving_from_configurations(ctx: Ctx, lenses: list, object_distances: list, *, field: str) -> Lens:
    """A design file's configurations as one lens with moving groups (:mod:`mi_neurallens.optics.moving`).

    ``lenses``: the lens of each configuration (built like the file's own, each with that configuration's
    thicknesses and aperture); ``object_distances``: each configuration's object distance in front of its first
    vertex (mm, ``inf``).  Configurations with the object at infinity are zoom positions (ordered by focal
    length); configurations with the object at one finite distance are their close-focus states, each paired with
    the zoom position whose gaps differ least from it (as many as there are positions).  The gaps that differ
    between configurations become the variable gaps, and a stop radius that differs between positions (a
    per-configuration aperture) is kept per position.  Anything else — other object distances, configurations
    that differ in anything but gaps and the stop — is a :class:`LensError` naming ``field``.  Returns the first
    position's lens with the moving groups (its name, path and metadata those of ``lenses[0]``)."""
    from ..moving import MovingGroups
    n = len(lenses)
    shape = [(s.radius, s.medium, s.conic, s.aspheric, s.is_stop, s.label) for s in lenses[0].surfaces]
    for k, L in enumerate(lenses[1:], 2):
        if [(s.radius, s.medium, s.conic, s.aspheric, s.is_stop, s.label) for s in L.surfaces] != shape:
            raise ctx.error(f"configuration {k} differs from configuration 1 in more than its gaps and aperture (a "
                            "surface, glass or shape changes): only moving groups (gaps) and the stop's size may "
                            "change between configurations", field=field)
    inf = [k for k in range(n) if math.isinf(object_distances[k])]
    fin = [k for k in range(n) if not math.isinf(object_distances[k])]
    if not inf:
        raise ctx.error("no configuration has the object at infinity: the zoom positions (or the infinity focus) "
                        "must be given with the object at infinity", field=field)
    dists = sorted({round(object_distances[k], 6) for k in fin})
    if len(dists) > 1:
        raise ctx.error(f"configurations at {len(dists)} finite object distances ({', '.join(f'{d:g}' for d in dists)} "
                        "mm): one close-focus distance is supported", field=field)
    if fin and len(fin) != len(inf):
        raise ctx.error(f"{len(inf)} configuration(s) with the object at infinity but {len(fin)} at "
                        f"{dists[0]:g} mm: each zoom position needs its close-focus state", field=field)
    gaps = lambda k: np.array([s.thickness for s in lenses[k].surfaces])
    inf.sort(key=lambda k: lenses[k].efl())
    partner = {}
    free = list(fin)
    for k in inf:
        if not free:
            break
        j = min(free, key=lambda f: float(np.abs(gaps(f) - gaps(k)).sum()))
        partner[k] = j
        free.remove(j)
    base = lenses[inf[0]]
    table = {}
    for i in range(len(base.surfaces)):
        rows = [(lenses[k].surfaces[i].thickness,
                 lenses[partner.get(k, k)].surfaces[i].thickness) for k in inf]
        if any(a != rows[0][0] or b != rows[0][0] for a, b in rows):
            table[i] = rows
    stops = [lenses[k].stop.semi_diameter for k in inf]
    stop_sd = stops if any(abs(v - stops[0]) > 1e-12 for v in stops) else None
    if not table and stop_sd is None:
        return base
    close = None
    if fin:
        j = partner[inf[0]]
        close = object_distances[j] + lenses[j].image_z          # from the sensor plane
    try:
        mg = MovingGroups(table, zoom_efl_mm=[lenses[k].efl() for k in inf] if len(inf) > 1 else None,
                          close_focus_mm=close, close_gaps="published" if fin else None, stop_semi_diameters=stop_sd,
                          focus_label=f"{n} configurations of the file: {len(inf)} position(s)"
                                      + (f", close focus {close:g} mm from the sensor" if fin else ""))
        return base.replace(moving=mg)
    except LensError as e:
        raise ctx.error(f"the configurations do not make a lens with moving groups: {e}", field=field) from e
