"""Optical media, the one entry point: :func:`resolve_medium` turns what a lens file says about a medium
(a name, a number, a dict) into a :class:`Medium`.

The media themselves (n(λ) formulas; constant, model, line and table glasses) are in :mod:`.media`;
vendor catalogs and the Open Optical Designer table in :mod:`.catalogs`.  Their public names are
re-exported here, so ``from mi_neurallens.optics.glass import ...`` stays the one import for glass.
"""
from __future__ import annotations

import math
import numbers

from ..errors import GlassError
from .catalogs import CATALOGS, catalog_glass, ood_material  # noqa: F401 (re-exported)
from .media import (AIR, FORMULAS, LAMBDA_C, LAMBDA_D, LAMBDA_E, LAMBDA_F, Medium,  # noqa: F401 (re-exported)
                    _real, constant, lines_glass, model_glass, table_glass)


# ====================================================================== the entry point
_SPEC_FORMS = ("'air'; a constant index n >= 1 (number); a catalog glass name (e.g. 'N-BK7'); "
               "or a dict: {'n'}, {'glass'[, 'catalog']}, {'nd', 'vd'}, "
               "{'nd', 'nC', 'nF'[, 'ng'][, 'ne']}, {'table': [[nm, n], ...]}, {'ood'}, "
               "{'formula', 'coefficients'[, 'source']} (each with an optional 'name')")

_DICT_FORMS = {  # kind → (required keys, optional keys)
    "constant": ({"n"}, {"name"}),
    "catalog": ({"glass"}, {"catalog", "name"}),
    "model": ({"nd", "vd"}, {"name", "model"}),
    "lines": ({"nd", "nC", "nF"}, {"ng", "ne", "name"}),
    "table": ({"table"}, {"name"}),
    "ood": ({"ood"}, {"name"}),
    "serialised": ({"formula", "coefficients"}, {"name", "source"}),
}
_DISCRIMINATORS = (("formula", "serialised"), ("coefficients", "serialised"), ("glass", "catalog"),
                   ("table", "table"), ("ood", "ood"), ("n", "constant"), ("vd", "model"),
                   ("nC", "lines"), ("nF", "lines"), ("ng", "lines"), ("ne", "lines"))

_FORMULA_SHAPES = {"constant": "1 value", "sellmeier": "pairs (B_i, C_i)",
                   "power_n2": "pairs (power, a_i) with integer powers",
                   "table": "pairs (λ_nm, n) with strictly increasing λ",
                   "buchdahl": "5 values (λ0_µm, n0, ν1, ν2, ν3)"}


def _validate_serialised(formula, coefficients) -> tuple[str, tuple[float, ...]]:
    if formula not in FORMULAS:
        raise GlassError(f"unknown formula {formula!r}; valid: {', '.join(FORMULAS)}")
    if isinstance(coefficients, (str, bytes, dict)) or not hasattr(coefficients, "__len__"):
        raise GlassError(f"'coefficients' must be a list of numbers, got {coefficients!r}")
    c = tuple(_real(v, f"coefficient {i}") for i, v in enumerate(coefficients))
    ok = {"constant": len(c) == 1 and c[0] > 0,
          "sellmeier": len(c) >= 2 and len(c) % 2 == 0,
          "power_n2": len(c) >= 2 and len(c) % 2 == 0 and all(p == int(p) for p in c[0::2]),
          "table": (len(c) >= 2 and len(c) % 2 == 0 and all(n > 0 for n in c[1::2])
                    and all(b > a for a, b in zip(c[0::2], c[2::2]))),
          "buchdahl": len(c) == 5}[formula]
    if not ok:
        raise GlassError(f"formula '{formula}' needs {_FORMULA_SHAPES[formula]}, got {list(c)}")
    return formula, c


def _resolve_dict(spec: dict) -> Medium:
    bad = [k for k in spec if not isinstance(k, str)]
    if bad:
        raise GlassError(f"medium dict keys must be strings, got {bad[0]!r} in {spec!r}")
    kinds = []
    for key, kind in _DISCRIMINATORS:
        if key in spec and kind not in kinds:
            kinds.append(kind)
    if not kinds:
        if "nd" in spec:
            raise GlassError(f"medium {spec!r} gives 'nd' without 'vd' (model glass) or "
                             f"'nC' and 'nF' (line indices)")
        raise GlassError(f"cannot resolve medium {spec!r}; expected {_SPEC_FORMS}")
    if len(kinds) > 1:
        raise GlassError(f"medium {spec!r} mixes the forms {' and '.join(kinds)}; give exactly "
                         f"one of {_SPEC_FORMS}")
    kind = kinds[0]
    required, optional = _DICT_FORMS[kind]
    unknown = sorted(set(spec) - required - optional)
    if unknown:
        raise GlassError(f"unknown key{'s' if len(unknown) > 1 else ''} "
                         f"{', '.join(repr(k) for k in unknown)} in {kind} medium {spec!r}; "
                         f"valid keys: {', '.join(sorted(required | optional))}")
    missing = sorted(required - set(spec))
    if missing:
        raise GlassError(f"{kind} medium {spec!r} is missing "
                         f"{', '.join(repr(k) for k in missing)}; it needs "
                         f"{', '.join(sorted(required))} (optional: {', '.join(sorted(optional))})")
    name = spec.get("name")
    if name is not None and (not isinstance(name, str) or not name.strip()):
        raise GlassError(f"medium 'name' must be a non-empty string, got {name!r}")

    if kind == "constant":
        n = _real(spec["n"], "constant index 'n'")
        if not n >= 1.0:
            raise GlassError(f"constant index 'n' must be ≥ 1, got {spec['n']!r}")
        return AIR if (n == 1.0 and name is None) else constant(n, name)
    if kind == "catalog":
        m = catalog_glass(spec["glass"], spec.get("catalog"))
    elif kind == "model":
        model = spec.get("model", "normal-line")
        if not isinstance(model, str):
            raise GlassError(f"model glass 'model' must be 'normal-line' or 'opticalglass', "
                             f"got {model!r}")
        return model_glass(spec["nd"], spec["vd"], name, model=model)
    elif kind == "lines":
        return lines_glass(spec["nd"], spec["nC"], spec["nF"], spec.get("ng"), spec.get("ne"), name)
    elif kind == "table":
        return table_glass(spec["table"], name or "table")
    elif kind == "ood":
        m = ood_material(spec["ood"])
    else:  # serialised Medium: no lookups
        formula, c = _validate_serialised(spec["formula"], spec["coefficients"])
        source = spec.get("source", {})
        if not isinstance(source, dict):
            raise GlassError(f"medium 'source' must be a dict, got {source!r}")
        return Medium(name or f"{formula} medium", formula, c, dict(source))
    if name is not None:
        m = Medium(name, m.formula, m.coefficients, dict(m.source))
    return m


def resolve_medium(spec, *, file: str | None = None, surface: int | None = None,
                   label: str | None = None, field: str | None = "medium") -> Medium:
    """Turn a file's medium description into a :class:`Medium` (the one entry point for readers).

    ``spec`` is ``"air"`` (any case) or ``1`` → :data:`AIR`; a number n ≥ 1 → constant; a string →
    :func:`catalog_glass`; or a dict ``{"n"}``, ``{"glass"[, "catalog"]}``, ``{"nd", "vd"}``,
    ``{"nd", "nC", "nF"[, "ng"][, "ne"]}``, ``{"table": [[nm, n], ...]}``, ``{"ood"}`` or a
    serialised Medium ``{"name", "formula", "coefficients"[, "source"]}``, each with an optional
    ``"name"``; a :class:`Medium` passes through unchanged.  Anything else raises :class:`GlassError` naming ``file``/``surface``/``field``.
    """
    try:
        if isinstance(spec, Medium):
            return spec
        if isinstance(spec, str):
            s = spec.strip()
            if not s:
                raise GlassError(f"empty medium name; expected {_SPEC_FORMS}")
            if s.casefold() == "air":
                return AIR
            return catalog_glass(s)
        if isinstance(spec, bool):
            raise GlassError(f"medium {spec!r} is a boolean; expected {_SPEC_FORMS}")
        if isinstance(spec, numbers.Real):
            n = float(spec)
            if not math.isfinite(n) or not n >= 1.0:
                raise GlassError(f"refractive index {spec!r} is not valid: a constant medium "
                                 f"needs a finite n ≥ 1")
            return AIR if n == 1.0 else constant(n)
        if isinstance(spec, dict):
            return _resolve_dict(spec)
        raise GlassError(f"cannot resolve medium {spec!r} ({type(spec).__name__}); "
                         f"expected {_SPEC_FORMS}")
    except GlassError as e:
        raise GlassError(e.what, file=file, surface=surface, label=label, field=field) from None
