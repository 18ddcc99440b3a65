"""Helpers shared by the format readers: error construction and strict value checks.

Every reader reports problems as :class:`~mi_neurallens.errors.LensError` naming the file, the
surface (0-based index in the file, plus its label when it has one) and the field.
"""
from __future__ import annotations

import difflib
import hashlib
import json
import math
from pathlib import Path
from typing import Any, Iterable

from ...errors import LensError

#: The d line (nm): the reference wavelength of nd/Vd and of the pbrt image distance.
from ...constants import LAMBDA_D as LAMBDA_D_NM  # noqa: F401 (re-exported)


class Ctx:
    """Where we are reading from (a file name for messages)."""

    def __init__(self, file: str | None):
        self.file = file

    def error(self, what: str, *, surface: int | None = None, label: str | None = None,
              field: str | None = None) -> LensError:
        return LensError(what, file=self.file, surface=surface, label=label or None, field=field)


def type_name(v: Any) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "boolean"
    if isinstance(v, (int, float)):
        return "number"
    if isinstance(v, str):
        return "string"
    if isinstance(v, list):
        return "array"
    if isinstance(v, dict):
        return "object"
    return type(v).__name__


def is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def number(ctx: Ctx, v: Any, *, field: str, surface: int | None = None, label: str | None = None,
           minimum: float | None = None, exclusive_minimum: float | None = None,
           what: str = "a number") -> float:
    """``v`` as a finite float, or a LensError naming ``field``."""
    if not is_number(v):
        raise ctx.error(f"must be {what}, got {type_name(v)} {v!r}", surface=surface, label=label,
                        field=field)
    x = float(v)
    if not math.isfinite(x):
        raise ctx.error(f"must be a finite number, got {x!r} (NaN and Infinity are not valid JSON numbers)",
                        surface=surface, label=label, field=field)
    if minimum is not None and x < minimum:
        raise ctx.error(f"must be ≥ {minimum:g}, got {x:g}", surface=surface, label=label, field=field)
    if exclusive_minimum is not None and not x > exclusive_minimum:
        raise ctx.error(f"must be > {exclusive_minimum:g}, got {x:g}", surface=surface, label=label,
                        field=field)
    return x


def check_keys(ctx: Ctx, obj: dict, allowed: Iterable[str], *, required: Iterable[str] = (),
               surface: int | None = None, label: str | None = None, prefix: str = "") -> None:
    """Unknown keys and missing required keys are errors (a typo must not pass silently)."""
    allowed = list(allowed)
    for k in obj:
        if k not in allowed:
            close = difflib.get_close_matches(str(k), allowed, n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            raise ctx.error(f"unknown key '{k}'{hint}; valid keys: {', '.join(allowed)}",
                            surface=surface, label=label, field=prefix + str(k))
    for k in required:
        if k not in obj:
            raise ctx.error("required field is missing", surface=surface, label=label, field=prefix + k)


def loads_json(ctx: Ctx, text: str) -> Any:
    """Parse JSON text; syntax errors and duplicate keys become LensErrors with line/column."""

    def pairs(items):
        d = {}
        for k, v in items:
            if k in d:
                raise ctx.error(f"duplicate key '{k}' in a JSON object", field=k)
            d[k] = v
        return d

    try:
        return json.loads(text, object_pairs_hook=pairs)
    except json.JSONDecodeError as e:
        raise ctx.error(f"not valid JSON: {e.msg} at line {e.lineno}, column {e.colno}") from None


def sha256_file(path: str | Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def resolve(ctx: Ctx, spec: Any, *, surface: int | None = None, label: str | None = None,
            field: str = "medium"):
    """``glass.resolve_medium`` with this file's location (imported lazily: it is written elsewhere)."""
    from ..glass import resolve_medium
    return resolve_medium(spec, file=ctx.file, surface=surface, label=label or None, field=field)
