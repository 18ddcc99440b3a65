"""Mitsuba integrators: ``lens_flare`` (nested integrator + forward-traced lens ghosts) and, in AD variants,
``lens_ad`` (path tracing differentiable in the camera's rays).

:func:`register` re-imports and registers them for the current variant (called by
:func:`mi_neurallens.register`)."""
from __future__ import annotations


def register() -> list[str]:
    """(Re-)import ``lens_flare`` for the current variant and register it (see
    :func:`mi_neurallens.sensors.register`)."""
    import importlib

    import mitsuba as mi
    if mi.variant() is None:
        raise RuntimeError("mi_neurallens.integrators.register(): set a Mitsuba variant first")
    from . import lens_flare
    importlib.reload(lens_flare)
    mi.register_integrator(lens_flare.PLUGIN, lambda props, cls=lens_flare.LensFlare: cls(props))
    names = [lens_flare.PLUGIN]
    if "_ad_" in mi.variant():
        from . import lens_ad
        importlib.reload(lens_ad)
        mi.register_integrator(lens_ad.PLUGIN, lambda props, cls=lens_ad.LensAD: cls(props))
        names.append(lens_ad.PLUGIN)
    return names
