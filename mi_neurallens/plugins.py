"""Registration of every Mitsuba plugin of this package for the current variant."""
from __future__ import annotations


def register_all() -> list[str]:
    import mitsuba as mi
    if mi.variant() is None:
        raise RuntimeError("mi_neurallens.register(): set a Mitsuba variant first (mi.set_variant(...))")
    names = []
    try:
        from .sensors import register as reg_sensors
    except ImportError:
        reg_sensors = None
    if reg_sensors is not None:
        names += reg_sensors()
    from .integrators import register as reg_integrators
    names += reg_integrators()
    return names
