"""Where each map lives, as a training plans it: planes, supported sensor distances and sampled domains.

The functions live in :mod:`mi_neurallens.transport.planes` (render time needs them too: a baseline built with
no model file takes the planes and domains a neural map would have); this module is their name under
``training/``.  Which ghosts to learn is :func:`mi_neurallens.transport.planning.select_ghosts` over the
flare's ranking (:func:`mi_neurallens.flare.energy.ghost_energy_ranking`).
"""
from __future__ import annotations

from ..transport.planes import (AUTO_CLOSE_FOCUS_MAGNIFICATION, AUTO_CLOSE_FOCUS_MM,  # noqa: F401
                                backward_domain, close_focus_mm, default_field_half_angle, film_reach,
                                forward_domain, planes, sensor_distance_range, surface_extent)
