"""Mitsuba sensors: ``realistic_lens`` (exact tracing) and ``neural_lens`` (learned transport map).

Shared pieces: :mod:`.common` (properties, lens setup, film mapping, frames), :mod:`.wavelengths`
(one λ per ray and its weight), :mod:`.pupil` (exit-pupil / rear-element sampling bounds).

**Registration is per Mitsuba variant.**  :func:`register` defines the plugin classes for the variant
that is currently set and registers them with Mitsuba; it returns the registered names.  It is called by
:func:`mi_neurallens.register` and automatically on ``import mi_neurallens`` when a variant is already
set.  After every ``mi.set_variant(...)`` call ``mi_neurallens.register()`` again.
"""
from __future__ import annotations


def register() -> list[str]:
    """Register the sensors for the current variant; returns their plugin names."""
    import mitsuba as mi
    if mi.variant() is None:
        raise RuntimeError("mi_neurallens.sensors.register(): set a Mitsuba variant first")
    from . import neural_lens, realistic_lens
    mi.register_sensor(realistic_lens.PLUGIN, realistic_lens.make_realistic_lens())
    mi.register_sensor(neural_lens.PLUGIN, neural_lens.make_neural_lens())
    return [realistic_lens.PLUGIN, neural_lens.PLUGIN]
