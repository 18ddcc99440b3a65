"""Mitsuba sensors: ``realistic_lens`` (exact tracing) and ``neural_lens`` (learned transport map).

Shared pieces: :mod:`.common` (properties, lens setup, film mapping, frames), :mod:`.wavelengths`
(one λ per ray and its weight), :mod:`.pupil` (exit-pupil / rear-element sampling bounds).

**Registration is per Mitsuba variant.**  The plugin classes are module-level classes deriving from
the current variant's ``mi.Sensor``; :func:`register` re-imports their modules for the variant that
is currently set and registers them with Mitsuba; it returns the registered names.  It is called by
:func:`mi_neurallens.register` and automatically on ``import mi_neurallens`` when a variant is already
set.  After every ``mi.set_variant(...)`` call ``mi_neurallens.register()`` again.
"""
from __future__ import annotations


def register() -> list[str]:
    """(Re-)import the sensor modules for the current variant and register them; returns their names.

    Mitsuba's own Python plugins do the same (``mitsuba/python/ad/integrators/__init__.py``): a plugin
    class derives from the ``mi.Sensor`` of the variant that was set when its module was imported, so
    the modules are re-imported after every variant change."""
    import importlib

    import mitsuba as mi
    if mi.variant() is None:
        raise RuntimeError("mi_neurallens.sensors.register(): set a Mitsuba variant first")
    from . import base, neural_lens, realistic_lens
    for module in (base, realistic_lens, neural_lens):
        importlib.reload(module)
    mi.register_sensor(realistic_lens.PLUGIN, lambda props: realistic_lens.RealisticLens(props))
    mi.register_sensor(neural_lens.PLUGIN, lambda props: neural_lens.NeuralLens(props))
    return [realistic_lens.PLUGIN, neural_lens.PLUGIN]
