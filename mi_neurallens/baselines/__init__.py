"""Baselines for the neural lens transport maps (docs/baselines.md): polynomial cores behind the
:class:`~mi_neurallens.transport.base.TransportMap` interface.

* ``abcd``   — paraxial 4×4 matrices (:mod:`.abcd`);
* ``taylor`` — Taylor polynomial optics, degree 3 or 5 (:mod:`.taylor`; ``taylor3``/``taylor5``);
* ``fitted`` — sparse polynomials fitted to traced rays (:mod:`.fitted`).

Build one by name with :func:`mi_neurallens.transport.make_map` (which also builds ``exact`` and
``neural``, the references they are compared with).
"""
from __future__ import annotations

from .abcd import ABCDMap
from .common import BaselineMap, default_domain, default_map_planes
from .fitted import FittedMap
from .taylor import TaylorMap

__all__ = ["ABCDMap", "TaylorMap", "FittedMap", "BaselineMap", "default_domain", "default_map_planes"]
