"""Mitsuba sensors: ``realistic_lens`` (exact tracing) and ``neural_lens`` (learned transport map).

Shared pieces: :mod:`.common` (properties, lens setup, film mapping, frames), :mod:`.wavelengths`
(one λ per ray and its weight), :mod:`.pupil` (exit-pupil / rear-element sampling bounds).

**Registration is per Mitsuba variant.**  The plugin classes are module-level classes deriving from
the current variant's ``mi.Sensor``; :func:`register` re-imports their modules for the variant that
is currently set and registers them with Mitsuba; it returns the registered names.  It is called by
:func:`mi_neurallens.register` and automatically on ``import mi_neurallens`` when a variant is already
set.  Call ``mi_neurallens.register()`` after ``mi.set_variant(...)`` selects a variant for the first time; a
variant keeps its registration (and its own classes) when you switch away from it and back.
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
    # Each variant's constructor holds its own class: a lambda that looked the class up in the module at load time
    # would, after a later register() in another variant re-imported the module, build that variant's class here
    # (its base constructor ignores this variant's film and sampler: "unreferenced properties").
    for name, cls in ((realistic_lens.PLUGIN, realistic_lens.RealisticLens), (neural_lens.PLUGIN, neural_lens.NeuralLens)):
        mi.register_sensor(name, lambda props, cls=cls: cls(props))
    return [realistic_lens.PLUGIN, neural_lens.PLUGIN]
