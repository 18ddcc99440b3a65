"""Writing files so that nothing is ever left half-written (the one helper every writer uses), and the one
conversion of results to JSON-ready values."""
from __future__ import annotations

import math
import os
import tempfile


def atomic_write(path, write_fn) -> str:
    """Call ``write_fn(tmp_path)`` for a temporary file next to ``path`` (same extension, so writers
    that pick the format from the name work), give it the usual permissions (``mkstemp`` creates
    0600) and rename it over ``path``.  On any error the temporary file is removed and ``path`` is
    untouched.  Returns ``path``."""
    path = os.path.abspath(os.fspath(path))
    d, base = os.path.split(path)
    os.makedirs(d or ".", exist_ok=True)
    ext = os.path.splitext(base)[1]
    fd, tmp = tempfile.mkstemp(prefix=f".{base}.", suffix=f".tmp{ext}", dir=d or ".")
    os.close(fd)
    try:
        write_fn(tmp)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def atomic_write_text(path, text: str) -> str:
    """:func:`atomic_write` of a UTF-8 text file."""
    def w(tmp):
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
    return atomic_write(path, w)


def atomic_write_json(path, obj, indent: int = 1) -> str:
    """:func:`atomic_write_text` of ``obj`` as JSON (numpy scalars written as floats)."""
    import json
    return atomic_write_text(path, json.dumps(obj, indent=indent, default=float))


def jsonable(o, round_keys: dict | None = None, digits: int | None = None):
    """``o`` as JSON-ready Python values: numpy scalars and arrays to floats, ints and lists, non-finite floats
    to ``None``.  ``round_keys`` maps a key suffix to significant digits: floats anywhere under a key ending in
    that suffix are rounded to them (``digits`` is the rounding in force; callers leave it out)."""
    import numpy as np
    if isinstance(o, dict):
        out = {}
        for k, v in o.items():
            k = str(k)
            d = next((n for suffix, n in (round_keys or {}).items() if k.endswith(suffix)), digits)
            out[k] = jsonable(v, round_keys, d)
        return out
    if isinstance(o, (list, tuple)):
        return [jsonable(v, round_keys, digits) for v in o]
    if isinstance(o, (float, np.floating)):
        v = float(o)
        if not math.isfinite(v):
            return None
        return float(f"{v:.{digits}g}") if digits else v
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.ndarray):
        return jsonable(o.tolist(), round_keys, digits)
    return o
