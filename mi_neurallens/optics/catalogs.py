"""Glass catalogs: vendor glasses from the ``opticalglass`` spreadsheets (imported lazily) and the
material table of Open Optical Designer (``data/ood-materials.json``), both as :class:`~.media.Medium`.
"""
from __future__ import annotations

import functools

from ..errors import GlassError
from .media import Medium, table_glass


# ====================================================================== catalog glasses
#: Catalogs searched by :func:`catalog_glass`, in the order ambiguous names resolve.
CATALOGS = ("Schott", "Ohara", "Hoya", "CDGM", "Hikari", "Sumita")

# vendor → (our formula, powers of λ for power_n2 in the order of opticalglass' ``coefs``)
_VENDOR_FORMULA = {
    "Schott": ("sellmeier", None),
    "Ohara": ("sellmeier", None),
    "Hoya": ("power_n2", (0, 2, -2, -4, -6, -8)),
    "CDGM": ("power_n2", (0, 2, -2, -4, -6, -8)),
    "Sumita": ("power_n2", (0, 2, -2, -4, -6, -8)),
    "Hikari": ("power_n2", (0, 2, 4, -2, -4, -6, -8, -10, -12)),
}

# When a name is given without its vendor prefix and several glasses of one catalog match
# (Schott N-BK7 / P-BK7), the prefix listed first wins.
_PREFIX_PREFERENCE = {
    "Schott": ("N", "P"), "Ohara": ("S",), "Hoya": ("E", "M", "MP", "MC"),
    "CDGM": ("H", "D"), "Hikari": ("J", "Q"), "Sumita": ("K",),
}


def _norm(name: str) -> str:
    """Upper case, no white space: 'S-FSL 5' → 'S-FSL5'."""
    return "".join(str(name).split()).upper()


def _compact(name: str) -> str:
    return _norm(name).replace("-", "").replace("_", "")


def _split_prefix(name: str) -> tuple[str, str]:
    """('N', 'BK7') for 'N-BK7'; ('', name) when the name has no short alphabetic vendor prefix."""
    n = _norm(name)
    head, sep, tail = n.partition("-")
    if sep and 1 <= len(head) <= 2 and head.isalpha() and tail:
        return head, tail
    return "", n


@functools.lru_cache(maxsize=None)
def _catalog_names(catalog: str) -> dict:
    """Lookup tables of one catalog: exact (normalised), compact (no '-') and bare (no prefix)."""
    import warnings
    with warnings.catch_warnings():  # pandas deprecation noise from opticalglass' xls readers
        warnings.simplefilter("ignore")
        import opticalglass.glassfactory as gf
        names = [str(n) for n in gf.get_glass_catalog(catalog).get_glass_names()]
    pref = _PREFIX_PREFERENCE.get(catalog, ())
    exact, compact, bare = {}, {}, {}
    for n in names:
        exact.setdefault(_norm(n), n)
        compact.setdefault(_compact(n), n)
    for n in sorted(names, key=lambda n: (pref.index(_split_prefix(n)[0])
                                          if _split_prefix(n)[0] in pref else len(pref), n)):
        p, rest = _split_prefix(n)
        if p:
            bare.setdefault(rest.replace("-", "").replace("_", ""), n)
    return {"names": names, "exact": exact, "compact": compact, "bare": bare}


def _vendor_coefs(catalog: str, gname: str) -> list[float]:
    """The dispersion coefficients of ``gname`` exactly as opticalglass stores ``g.coefs``.

    Two Hikari sheets (J-PSKH8, J-KZFH9) write an unused term as '-', on which opticalglass'
    own ``create_glass`` fails; such a term is read as 0.
    """
    import opticalglass.glassfactory as gf
    cat = gf.get_glass_catalog(catalog)
    try:
        return [float(c) for c in cat.create_glass(gname, catalog).coefs]
    except ValueError:
        raw = list(cat.df.loc[gname]["dispersion coefficients"])
        vals = [0.0 if (isinstance(c, str) and c.strip() in ("-", "")) else float(c) for c in raw]
        if catalog == "Hoya":  # mantissa, exponent pairs (what HoyaCatalog.glass_coefs does)
            vals = [x * 10 ** y for x, y in zip(vals[::2], vals[1::2])]
        return vals


def _convert_vendor(catalog: str, coefs) -> tuple[str, tuple[float, ...]]:
    formula, powers = _VENDOR_FORMULA[catalog]
    c = [float(v) for v in coefs]
    if formula == "sellmeier":  # opticalglass: [B1, B2, B3, C1, C2, C3]
        k = len(c) // 2
        out = []
        for b, cc in zip(c[:k], c[k:]):
            out += [b, cc]
        return formula, tuple(out)
    if len(c) != len(powers):
        raise GlassError(f"{catalog}: expected {len(powers)} dispersion coefficients, got {len(c)}")
    out = []
    for p, a in zip(powers, c):
        if a != 0.0:  # unused terms cost kernel instructions and add nothing
            out += [float(p), a]
    return formula, tuple(out)


def _canonical_catalog(catalog) -> str:
    if not isinstance(catalog, str):
        raise GlassError(f"glass catalog must be a string, one of {', '.join(CATALOGS)}; "
                         f"got {catalog!r}")
    for c in CATALOGS:
        if c.upper() == catalog.strip().upper():
            return c
    raise GlassError(f"unknown glass catalog '{catalog}'; valid catalogs: {', '.join(CATALOGS)}")


@functools.lru_cache(maxsize=4096)
def _catalog_lookup(name: str, catalog: str | None) -> tuple[str, str, str, tuple[float, ...]]:
    cats = CATALOGS if catalog is None else (catalog,)
    q_exact, q_compact = _norm(name), _compact(name)
    # Match levels first, catalogs second: an exact spelling in any catalog beats a prefix-less
    # match in an earlier one ('F1' is CDGM F1, not Hoya E-F1).
    for level, q in (("exact", q_exact), ("compact", q_compact), ("bare", q_compact)):
        for c in cats:
            hit = _catalog_names(c)[level].get(q)
            if hit is not None:
                formula, coefs = _convert_vendor(c, _vendor_coefs(c, hit))
                return c, hit, formula, coefs
    import difflib
    cand = {}
    for c in cats:
        t = _catalog_names(c)
        for key in ("compact", "bare"):
            for k, n in t[key].items():
                cand.setdefault(k, f"{n} ({c})")
    close = []
    for k in difflib.get_close_matches(q_compact, list(cand), n=12, cutoff=0.5):
        if cand[k] not in close:
            close.append(cand[k])
    hint = ("; close names: " + ", ".join(close[:3])) if close else ""
    raise GlassError(f"unknown glass '{name}' (searched catalog{'s' if len(cats) > 1 else ''} "
                     f"{', '.join(cats)}){hint}")


def catalog_glass(name: str, catalog: str | None = None) -> Medium:
    """A vendor catalog glass, e.g. ``catalog_glass("S-LAL14", "Ohara")``.

    ``catalog`` is one of :data:`CATALOGS` (any case); ``None`` searches all of them, and a name
    found in several resolves in the order of :data:`CATALOGS`.  Names match case-insensitively,
    ignoring white space ('S-FSL5' is Ohara's 'S-FSL 5'), with or without '-', and with or without
    the vendor prefix ('LAL14' → S-LAL14, 'BK7' → Schott N-BK7).  An exact spelling in any catalog
    wins over a prefix-less match.  Unknown names raise :class:`GlassError` with close names.
    """
    if not isinstance(name, str) or not name.strip():
        raise GlassError(f"glass name must be a non-empty string, got {name!r}")
    cat = None if catalog is None else _canonical_catalog(catalog)
    c, gname, formula, coefs = _catalog_lookup(name.strip(), cat)
    return Medium(gname, formula, coefs, {"catalog": c, "glass": gname})


# ====================================================================== Open Optical Designer
@functools.lru_cache(maxsize=1)
def _ood_data() -> tuple:
    import json
    from importlib import resources
    text = resources.files("mi_neurallens").joinpath("data", "ood-materials.json").read_text("utf-8")
    return tuple(json.loads(text))


@functools.lru_cache(maxsize=None)
def _ood_medium(key: str) -> Medium | None:
    mats = _ood_data()
    for fold in (False, True):
        for m in mats:
            names = [m.get("name"), m.get("alternate_name")]
            names = [n for n in names if n]
            hit = (key in names) if not fold else (key.casefold() in [n.casefold() for n in names])
            if hit:
                pairs = [(round(float(row[0]) * 1000.0, 9), float(row[1]))
                         for row in m["refractive_index"]]
                med = table_glass(pairs, m["name"])
                return Medium(med.name, med.formula, med.coefficients,
                              {"catalog": "Open Optical Designer", "glass": m["name"],
                               "reference": m.get("reference", "")})
    return None


def ood_material(name: str) -> Medium:
    """A material of Open Optical Designer by ``name`` or ``alternate_name`` (exact first, then
    case-insensitive), as its ``table`` (k ignored).  Its "Air" is Ciddor air, not n = 1."""
    if not isinstance(name, str):
        raise GlassError(f"Open Optical Designer material name must be a string, got {name!r}")
    m = _ood_medium(name.strip())
    if m is None:
        avail = [x["name"] + (f" ({x['alternate_name']})" if x.get("alternate_name") else "")
                 for x in _ood_data()]
        raise GlassError(f"unknown Open Optical Designer material '{name}'; available: "
                         f"{', '.join(avail)}")
    return Medium(m.name, m.formula, m.coefficients, dict(m.source))
