"""Mitsuba integrators: ``lens_flare`` (nested integrator + forward-traced lens ghosts).

:func:`register` defines and registers them for the current variant (called by
:func:`mi_neurallens.register`)."""
from __future__ import annotations


def register() -> list[str]:
    import mitsuba as mi
    if mi.variant() is None:
        raise RuntimeError("mi_neurallens.integrators.register(): set a Mitsuba variant first")
    from .lens_flare import PLUGIN, make_lens_flare
    cls = make_lens_flare()
    mi.register_integrator(PLUGIN, lambda props: cls(props))
    return [PLUGIN]
