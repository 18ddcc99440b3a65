"""Registration of every Mitsuba plugin of this package for the current variant."""
from __future__ import annotations


def register_all() -> list[str]:
    """Register ``realistic_lens``, ``neural_lens`` and ``lens_flare`` for the current variant."""
    import mitsuba as mi
    if mi.variant() is None:
        raise RuntimeError("mi_neurallens.register(): set a Mitsuba variant first (mi.set_variant(...))")
    if mi.variant().startswith("llvm_"):
        from .jit import check_llvm
        check_llvm()
    from .integrators import register as register_integrators
    from .sensors import register as register_sensors
    return register_sensors() + register_integrators()
