"""The flare renderer with diffraction off, for the tests of the ghosts (the starburst has its own tests,
tests/test_diffraction.py, and check_equivalence renders without it too)."""
from __future__ import annotations

import functools

from mi_neurallens.flare.options import FlareOptions as _FlareOptions
from mi_neurallens.flare.render import render_flare as _render_flare

FlareOptions = functools.partial(_FlareOptions, diffraction=False)


def render_flare(*args, **kw):
    kw.setdefault("diffraction", False)
    return _render_flare(*args, **kw)
