"""pbrt lens files (``.dat``): rows of ``radius  thickness  eta  aperture-diameter`` (mm).

What pbrt (v3 and v4, ``RealisticCamera``) does with them, and what we do:

* ``#`` starts a comment (to the end of the line).  Everything else is read as numbers; rows run
  from the scene side to the film side.  Stray ``"`` characters (present in the shipped files) are
  ignored, as pbrt's float reader ignores them; any other text is an error naming the line.
* column 1, radius: ``0`` marks the aperture stop (a flat iris) -> our stop surface.
* column 2, thickness to the next row.  pbrt ignores the value on the last row and focuses by moving
  the film; we set the image distance to the paraxial back focal length at 587.5618 nm (focus at
  infinity) and record that in ``metadata["pbrt"]``.
* column 3, eta: the index *after* the surface, one number: no dispersion in pbrt, so the media are
  ``constant(eta)``.  ``0`` means air (pbrt treats 0 as 1; the stop row has 0).
* column 4, aperture *diameter*; our semi-diameter is half of it.  On the stop row it is the
  largest iris diameter.

The 100 mm originals (``wide.dat`` ...) use another second column: ``axpos``, the distance from the
*previous* row, 0 on the first row (header ``radius axpos N aperture``).  They are detected and
converted (column 2 shifted up one row); see :func:`detect_layout`.
"""
from __future__ import annotations

import math
import os
from pathlib import Path
import re
import warnings

from ..glass import constant
from ..prescription import Lens, Surface
from ._common import LAMBDA_D_NM, Ctx

COLUMNS = ("radius", "thickness", "eta", "aperture")
LAYOUTS = ("auto", "thickness", "axpos")
_NUM = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$")


class PbrtLayoutWarning(UserWarning):
    """The file used the ``axpos`` layout and was converted to thicknesses."""


def looks_like_pbrt(text: str) -> bool:
    """True when the non-comment tokens are (mostly) numbers: at least 4, and ≥ 75 % numeric, so that
    a pbrt file with a typo is still read as pbrt and the reader can name the bad line."""
    n = bad = 0
    for line in text.splitlines():
        data = line.split("#", 1)[0].replace('"', " ")
        for tok in data.split():
            if _NUM.match(tok):
                n += 1
            else:
                bad += 1
    return n >= 4 and n >= 3 * bad


def load_pbrt(path: str | os.PathLike, **kw) -> Lens:
    raw = Path(path).read_bytes()
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")
    return read_pbrt(text, file=str(path), **kw)


def _parse(ctx: Ctx, text: str):
    """-> (rows [(lineno, [4 floats])], comments [str], header_words or None)"""
    rows, comments, header = [], [], None
    for lineno, line in enumerate(text.splitlines(), start=1):
        data, _, comment = line.partition("#")
        if _:
            c = " ".join(comment.replace('"', " ").split())
            if c:
                words = c.lower().split()
                if header is None and "radius" in words and "aperture" in words:
                    header = (lineno, words)
                else:
                    comments.append(c)
        toks = data.replace('"', " ").split()
        if not toks:
            continue
        vals = []
        for k, tok in enumerate(toks):
            if not _NUM.match(tok):
                row = len(rows)
                raise ctx.error(f"line {lineno}: {tok!r} is not a number (rows are: radius thickness eta "
                                f"aperture-diameter, in mm)", surface=row + k // 4, field=COLUMNS[k % 4])
            vals.append(float(tok))
        if len(vals) % 4:
            row = len(rows) + len(vals) // 4
            got = len(vals) % 4
            raise ctx.error(f"line {lineno}: truncated row: {got} number(s) {vals[-got:]}, every row needs 4 "
                            f"(radius thickness eta aperture-diameter); '{COLUMNS[got]}' is missing",
                            surface=row, field=COLUMNS[got])
        for j in range(0, len(vals), 4):
            rows.append((lineno, vals[j:j + 4]))
    if not rows:
        raise ctx.error("no lens rows found (expected lines of: radius thickness eta aperture-diameter)")
    return rows, comments, header


def detect_layout(rows, header) -> tuple[str | None, str]:
    """Which second column: ``("thickness"|"axpos"|None, reason)``; ``None`` = ambiguous.

    * header names ``axpos`` and the first row's column 2 is 0 -> ``axpos`` (the MLD originals);
    * header names ``axpos`` but the first value is not 0 -> ``thickness`` (the header was copied
      from the original but the numbers were converted: ``dgauss.50mm.dat``);
    * no ``axpos`` header and the first value is not 0 -> ``thickness`` (what pbrt reads);
    * no ``axpos`` header but the first value is 0 -> ambiguous: in the thickness layout that
      would put the first two surfaces on the same vertex.
    """
    says_axpos = header is not None and "axpos" in header[1]
    first0 = rows[0][1][1] == 0.0 and len(rows) > 1
    if says_axpos and first0:
        return "axpos", (f"header line {header[0]} names 'axpos' and the first row's column 2 is 0: "
                         "column 2 is the distance from the previous surface (Modern Lens Design tables)")
    if says_axpos:
        return "thickness", (f"header line {header[0]} names 'axpos' but the first row's column 2 is "
                             f"{rows[0][1][1]:g}, not 0: the numbers are thicknesses (header left over from "
                             "the 100 mm original)")
    if first0:
        return None, ("the first row's column 2 is 0, which as a thickness puts the first two surfaces "
                      "on the same vertex (the 'axpos' layout starts with 0), but there is no header "
                      "naming 'axpos'")
    return "thickness", "column 2 is the thickness to the next surface (pbrt's layout)"


def read_pbrt(text: str, *, file: str | None = None, layout: str = "auto", name: str | None = None,
              wavelength_nm: float = LAMBDA_D_NM) -> Lens:
    """Parse pbrt lens text into a :class:`Lens` focused at infinity.

    ``layout``: ``"auto"`` (detect, see :func:`detect_layout`), ``"thickness"`` or ``"axpos"``.
    ``wavelength_nm``: wavelength of the paraxial back focal length used as image distance
    (irrelevant for the constant media of pbrt files, kept for clarity).
    """
    ctx = Ctx(file or "<pbrt text>")
    if layout not in LAYOUTS:
        raise ctx.error(f"layout must be one of {', '.join(LAYOUTS)}, got {layout!r}", field="layout")
    rows, comments, header = _parse(ctx, text)
    detected, reason = detect_layout(rows, header)
    if layout == "auto":
        if detected is None:
            raise ctx.error(f"cannot tell the column-2 layout: {reason}; load it with layout='axpos' (distance "
                            "from the previous surface) or layout='thickness' (distance to the next)",
                            surface=0, field="thickness")
        layout = detected
    else:
        reason = f"layout '{layout}' given by the caller (auto-detection: {reason})"

    n = len(rows)
    col2 = [r[1][1] for r in rows]
    if layout == "axpos":
        thick = col2[1:] + [0.0]
        file_last = None
        warnings.warn(f"{ctx.file}: 'axpos' layout detected ({reason}); converted to thicknesses by "
                      "shifting column 2 up one row", PbrtLayoutWarning, stacklevel=3)
    else:
        thick = col2[:-1] + [0.0]
        file_last = col2[-1]

    surfaces = []
    stop_rows = []
    for i, (lineno, (radius, _t, eta, aperture)) in enumerate(rows):
        where = dict(surface=i)
        for col, v in zip(COLUMNS, rows[i][1]):
            if not math.isfinite(v):
                raise ctx.error(f"line {lineno}: {col} must be a finite number, got {v}", field=col, **where)
        is_stop = radius == 0.0
        label = "STO" if is_stop else str(i + 1)
        where["label"] = label
        if is_stop:
            stop_rows.append(i)
            if len(stop_rows) > 1:
                raise ctx.error(f"line {lineno}: a second aperture stop (radius 0); row {stop_rows[0]} "
                                "(0-based) is already the stop and pbrt allows one", field="radius", **where)
        if thick[i] < 0 and not (i == n - 1):
            raise ctx.error(f"line {lineno}: thickness must be ≥ 0, got {thick[i]:g}", field="thickness",
                            **where)
        if eta < 0 or 0 < eta < 1:
            raise ctx.error(f"line {lineno}: eta must be ≥ 1 (0 means air), got {eta:g}", field="eta", **where)
        if not aperture > 0:
            raise ctx.error(f"line {lineno}: aperture diameter must be > 0 mm, got {aperture:g}",
                            field="aperture", **where)
        medium = constant(1.0 if eta == 0.0 else eta)  # pbrt: eta 0 is air
        surfaces.append(Surface(radius=math.inf if is_stop else radius, thickness=thick[i], medium=medium,
                                semi_diameter=aperture / 2.0, is_stop=is_stop, label=label))
    if not stop_rows:
        raise ctx.error("no aperture stop: pbrt marks the stop with a row whose radius is 0", field="radius")

    title = comments[0] if comments else ""
    meta_pbrt = {
        "layout": layout,
        "layout_reason": reason,
        "comments": comments,
        "header": None if header is None else " ".join(header[1]),
        "file_last_thickness": file_last,
        "image_distance": f"paraxial back focal length at {wavelength_nm} nm (focus at infinity); pbrt "
                          "ignores the last row's thickness and focuses by moving the film",
        "dispersion": "none: pbrt gives one index (eta) per medium, so every medium is a constant index",
        "aperture_column": "full diameter in the file; semi_diameter = diameter / 2",
    }
    if name is None:
        name = Path(file).stem if file else "pbrt-lens"
    lens = Lens(tuple(surfaces), name=name,
                metadata={"description": title, "source": {"format": "pbrt lens .dat"}, "pbrt": meta_pbrt},
                path=ctx.file)
    bfl = float(lens.bfl(wavelength_nm))
    if not (math.isfinite(bfl) and bfl > 0):
        raise ctx.error(f"the paraxial back focal length is {bfl:g} mm (no real image of an object at "
                        "infinity), so there is no image distance to put on the last row",
                        surface=n - 1, field="thickness")
    meta_pbrt["image_distance_mm"] = bfl
    return lens.with_sensor_distance(bfl)
