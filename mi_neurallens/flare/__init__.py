"""Lens flare: forward light tracing of ghost paths (exact or neural) and ghost energy ranking."""
from __future__ import annotations

from .energy import ghost_energy_ranking, select_ghosts  # noqa: F401
