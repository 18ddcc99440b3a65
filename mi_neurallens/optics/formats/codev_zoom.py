"""CODE V zoom data (``ZOO``): the values a ``.seq`` file's zoomed items take at each zoom position.

CODE V stores a zoom lens (or a lens with focus positions) as one prescription whose zoomed items
carry a value per position.  What is read (the ``.seq`` reader hands each command here):

``ZOO n``                        the number of positions (optional; else the value count of the ``ZOO`` rows,
                                 which must agree)
``ZOO THI Sk v1 … vn``           surface k's thickness at each position (``SO``: the object distance, so a
                                 finite one makes that position a close-focus state; ``SI``: the image defocus)
``ZOO EPD v1 … vn``, ``ZOO FNO`` the system aperture at each position
``ZOO YAN Fj v1 … vn``           field j at each position (also ``XAN``, ``YIM``, ``XIM``, ``YRI``, ``XRI`` and the
                                 vignetting factors ``VUY``, ``VLY``, ``VUX``, ``VLX``): they size the beams that
                                 give surfaces without ``CIR`` their default semi-diameter
``THI Sk Zj v``, ``EPD Zj v``,   one position's value of an item a ``ZOO`` row zooms (the ``Zj`` qualifier)
``YAN Fi Zj v``, …

Zoomed wavelengths and weights (``WL``, ``REF``, ``WTW``, ``WTF``) and object heights (``YOB``, ``XOB``) are left
alone (counted in ``ignored_commands``).  Any other zoomed item (a radius or curvature, conic, polynomial term,
glass, ``CIR``, a decenter, …) is refused: only gaps and the aperture may differ between positions (moving
groups, :func:`~._sequential.moving_from_configurations`).  Values are in the file's unit (``DIM``).
"""
from __future__ import annotations

import re

from ._common import Ctx

#: zoomable field items (their lists are what the reader's ``fields`` holds)
FIELD_ITEMS = ("XAN", "YAN", "XIM", "YIM", "XRI", "YRI", "VUY", "VLY", "VUX", "VLX")
#: zoomable items that do not change the prescription or its default apertures
IGNORED_ITEMS = ("WL", "REF", "WTW", "WTF", "YOB", "XOB")
#: the commands whose ``Zj`` qualifier sets one position's value (others with one fall to the reader's refusals)
ZOOMABLE = ("THI", "EPD", "FNO") + FIELD_ITEMS
_SURF = re.compile(r"(?i)S(O|I|\d+)")
_FIELD = re.compile(r"(?i)F(\d+)")
_POS = re.compile(r"(?i)Z(\d+)")


class ZoomData:
    """The ``ZOO`` rows of one file: ``rows[(item, qualifier)]`` = [value per position] (None: not given yet) with
    ``item`` THI (``qualifier`` the surface: 0 for ``SO``, k, or ``"SI"``), EPD/FNO (None) or a field item (the
    field's index, 0-based); ``lines`` the line of each row."""

    def __init__(self, ctx: Ctx, parse_float):
        self.ctx, self._float = ctx, parse_float
        self.declared = None        # (n, line) of a ``ZOO n`` command
        self.rows: dict = {}
        self.lines: dict = {}
        self.ignored: dict = {}

    # ------------------------------------------------------------------ commands
    def command(self, toks: list[str], ln: int) -> None:
        """A ``ZOO`` command: ``toks`` its tokens (``ZOO`` first)."""
        ctx = self.ctx
        if len(toks) == 2 and re.fullmatch(r"\d+", toks[1]):
            self.declared = (int(toks[1]), ln)
            return
        if len(toks) < 3:
            raise ctx.error(f"{' '.join(toks)} (line {ln}): ZOO needs an item and its value at each position "
                            "(ZOO THI S5 10 20 30)", field="ZOO")
        item = _item(toks[1])
        key, rest = self._key(item, toks[2:], toks, ln)
        if key is None:
            return
        vals = [self._float(ctx, t, surface=_surface_number(key), command="ZOO", line=ln) for t in rest]
        if not vals:
            raise ctx.error(f"{' '.join(toks)} (line {ln}): no values", field="ZOO")
        if key in self.rows:
            raise ctx.error(f"{' '.join(toks)} (line {ln}) zooms {_describe(key)} a second time (first on line "
                            f"{self.lines[key]})", field="ZOO")
        self.rows[key], self.lines[key] = vals, ln

    def qualified(self, toks: list[str], ln: int) -> None:
        """A command with a ``Zj`` qualifier: position j's value of a zoomed item."""
        ctx = self.ctx
        z = [t for t in toks[1:] if _POS.fullmatch(t)]
        rest = [t for t in toks[1:] if not _POS.fullmatch(t)]
        if len(z) != 1:
            raise ctx.error(f"{' '.join(toks)} (line {ln}): expected one zoom position Zj", field="ZOO")
        j = int(_POS.fullmatch(z[0]).group(1))
        key, vals = self._key(_item(toks[0]), rest, toks, ln)
        if key is None:
            return
        if len(vals) != 1:
            raise ctx.error(f"{' '.join(toks)} (line {ln}): expected one value for position {j}", field="ZOO")
        if key not in self.rows:
            raise ctx.error(f"{' '.join(toks)} (line {ln}) sets position {j} of {_describe(key)}, which no ZOO command "
                            "zooms (ZOO THI S5 v1 … vn first)", field="ZOO")
        row = self.rows[key]
        if not 1 <= j <= len(row):
            raise ctx.error(f"{' '.join(toks)} (line {ln}): position {j}, but the ZOO row on line {self.lines[key]} "
                            f"has {len(row)}", field="ZOO")
        row[j - 1] = self._float(ctx, vals[0], surface=_surface_number(key), command=toks[0].upper(), line=ln)

    def _key(self, item: str, args: list[str], toks: list[str], ln: int):
        """(row key, the remaining value tokens) of a zoomed ``item`` with qualifiers ``args``; (None, …) for an
        item left alone."""
        ctx = self.ctx
        if item == "THI":
            if not args or not _SURF.fullmatch(args[0]):
                raise ctx.error(f"{' '.join(toks)} (line {ln}): a zoomed thickness names its surface (SO, Sk or SI)",
                                field="ZOO")
            s = _SURF.fullmatch(args[0]).group(1).upper()
            return ("THI", 0 if s == "O" else ("SI" if s == "I" else int(s))), args[1:]
        if item in ("EPD", "FNO"):
            return (item, None), args
        if item in FIELD_ITEMS:
            if not args or not _FIELD.fullmatch(args[0]) or int(_FIELD.fullmatch(args[0]).group(1)) < 1:
                raise ctx.error(f"{' '.join(toks)} (line {ln}): a zoomed field names its field (F1, F2, …)",
                                field="ZOO")
            return (item, int(_FIELD.fullmatch(args[0]).group(1)) - 1), args[1:]
        if item in IGNORED_ITEMS:
            self.ignored[f"ZOO {item}"] = self.ignored.get(f"ZOO {item}", 0) + 1
            return None, []
        raise ctx.error(f"{' '.join(toks)} (line {ln}) zooms {toks[1] if toks[0].upper() == 'ZOO' else toks[0]}: "
                        "only gaps (THI), the aperture (EPD, FNO) and the fields may differ between zoom positions "
                        "(moving groups); a radius, glass, conic, aperture size or decenter that changes is not "
                        "supported", field="ZOO")

    # ------------------------------------------------------------------ positions
    def positions(self, n_surfaces: int) -> int:
        """How many positions the rows give (1 without rows); checks the rows against each other, ``ZOO n`` and
        the file's ``n_surfaces`` (S1 … Sn)."""
        ctx = self.ctx
        if not self.rows:
            return 1
        counts = {len(v) for v in self.rows.values()}
        n = self.declared[0] if self.declared else max(counts)
        for key, v in self.rows.items():
            if len(v) != n:
                why = f"ZOO {self.declared[0]} (line {self.declared[1]})" if self.declared else "the other ZOO rows"
                raise ctx.error(f"the ZOO row of {_describe(key)} (line {self.lines[key]}) has {len(v)} values, but "
                                f"{why} give {n} positions", field="ZOO")
            if key[0] == "THI" and isinstance(key[1], int) and key[1] > n_surfaces:
                raise ctx.error(f"ZOO THI S{key[1]} (line {self.lines[key]}): the file has surfaces S1 … "
                                f"S{n_surfaces}", field="ZOO")
        return n

    def value(self, key, p: int, default):
        """The value of row ``key`` at position ``p`` (0-based), ``default`` for an item no row zooms."""
        row = self.rows.get(key)
        return default if row is None else row[p]

    def fields_at(self, fields: dict, p: int) -> dict:
        """The file's ``fields`` with the zoomed ones at position ``p`` (0-based)."""
        out = {k: list(v) for k, v in fields.items()}
        for (item, j), row in self.rows.items():
            if item in FIELD_ITEMS:
                vals = out.setdefault(item, [])
                vals.extend([0.0] * (j + 1 - len(vals)))
                vals[j] = row[p]
        return out


def _item(tok: str) -> str:
    """A command's name as the reader keys it: upper case, abbreviated to three letters (``THICKNESS`` = ``THI``)."""
    return tok.upper()[:3]


def _surface_number(key):
    return key[1] if key[0] == "THI" and isinstance(key[1], int) else None


def _describe(key) -> str:
    item, q = key
    if item == "THI":
        return "the object distance (THI SO)" if q == 0 else ("the image defocus (THI SI)" if q == "SI"
                                                              else f"the thickness of S{q}")
    if item in ("EPD", "FNO"):
        return f"the aperture ({item})"
    return f"field F{q + 1}'s {item}"
