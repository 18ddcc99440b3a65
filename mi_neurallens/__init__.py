"""mi-neurallens: real camera lenses for Mitsuba 3.

* :class:`Lens` — validated prescriptions (``Lens.load``), paraxial numbers, exact tracing.
* Mitsuba plugins (``realistic_lens``, ``neural_lens`` sensors, ``lens_flare`` integrator) are
  registered for the current Mitsuba variant by :func:`register`, which ``import mi_neurallens``
  calls automatically when a variant is already set.  Registration is per variant: call
  :func:`register` after ``mi.set_variant`` selects a variant for the first time (switching back to a
  registered variant keeps its plugins).

Importing this package never imports torch and never sets a Mitsuba variant.
"""
from __future__ import annotations

from .errors import GlassError, LensError, ModelError, NeuralLensError
from .optics.glass import Medium
from .optics.prescription import Coating, Lens, Surface

__version__ = "0.1.0"

__all__ = ["Lens", "Surface", "Medium", "Coating", "LensError", "GlassError", "ModelError",
           "NeuralLensError", "register", "project_valid", "__version__"]


def register() -> list[str]:
    """Register this package's Mitsuba plugins for the *current* variant; returns their names."""
    from .plugins import register_all
    return register_all()


def project_valid(params, sensor: str = "sensor", opt=None) -> dict:
    """Move the prescription parameters of the ``realistic_lens`` loaded under key ``sensor`` in ``params`` (a
    ``mi.SceneParameters``, and an optimiser ``opt`` holding them) back into the valid region; see
    :func:`mi_neurallens.sensors.live.project_valid`."""
    from .sensors.live import project_valid as _project
    return _project(params, sensor, opt)


def _auto_register():
    try:
        import sys
        mi = sys.modules.get("mitsuba")
        if mi is not None and mi.variant() is not None:
            register()
    except NeuralLensError:     # e.g. an LLVM too old for Dr.Jit: say so now, not as "unknown plugin" later
        raise
    except Exception:  # pragma: no cover - registration problems surface on load instead
        pass


_auto_register()
