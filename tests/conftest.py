"""Shared fixtures: a few lenses built by hand (independent of the file readers) and the bundled set."""
from __future__ import annotations

import math
import os
import sys

import pytest

sys.path.insert(0, os.path.dirname(__file__))  # test modules import helpers from conftest

# Under pytest-xdist (`make test` runs two workers) each worker's PyTorch keeps to one thread: two workers' OpenMP
# teams of two on two cores spin against each other (a 5 s test of 3000 small Adam steps took 60 s).
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ.setdefault("OMP_NUM_THREADS", "1")

from mi_neurallens.optics.glass import AIR, constant  # noqa: E402
from mi_neurallens.optics.prescription import Lens, Surface  # noqa: E402

# pbrt wide.22mm.dat (Nakamura, MLD p.360, scaled to 22 mm): radius, thickness, eta, aperture diameter
WIDE22 = [
    (35.98738, 1.21638, 1.54, 23.716), (11.69718, 9.9957, 1, 17.996), (13.08714, 5.12622, 1.772, 12.364),
    (-22.63294, 1.76924, 1.617, 9.812), (71.05802, 0.8184, 1, 9.152), (0, 2.27766, 0, 8.756),
    (-9.58584, 2.43254, 1.617, 8.184), (-11.28864, 0.11506, 1, 9.152), (-166.7765, 3.09606, 1.713, 10.648),
    (-7.5911, 1.32682, 1.805, 11.44), (-16.7662, 3.98068, 1, 12.276), (-7.70286, 1.21638, 1.617, 13.42),
    (-11.97328, 14.3183, 1, 17.996),
]


def lens_from_rows(rows, name="test"):
    surfs = []
    for r, t, n, a in rows:
        stop = r == 0
        surfs.append(Surface(radius=math.inf if stop else r, thickness=t,
                             medium=AIR if n in (0, 1) else constant(n), semi_diameter=a / 2, is_stop=stop))
    return Lens(tuple(surfs), name=name)


@pytest.fixture(scope="session")
def wide22():
    """The 22 mm wide-angle lens built directly from the pbrt numbers (last thickness = BFL)."""
    return lens_from_rows(WIDE22, "wide22-by-hand")


def plate(thickness=5.0, n=1.5, semi=20.0, gap=2.0):
    """A plane-parallel glass plate with a stop in front of it."""
    return Lens((
        Surface(radius=math.inf, thickness=gap, medium=AIR, semi_diameter=semi, is_stop=True),
        Surface(radius=math.inf, thickness=thickness, medium=constant(n), semi_diameter=semi),
        Surface(radius=math.inf, thickness=10.0, medium=AIR, semi_diameter=semi),
    ), name="plate")


def bundled_names():
    try:
        from mi_neurallens.optics.formats import bundled_lenses
        return list(bundled_lenses())
    except Exception:
        return []


@pytest.fixture(scope="session", autouse=True)
def _default_mitsuba_variant():
    """Start the tests in the default variant with the plugins registered, whichever module was imported last."""
    try:
        import mitsuba as mi
        import mi_neurallens as nl
        from mi_neurallens.render_utils import default_variant
    except ImportError:
        return
    mi.set_variant(default_variant())
    nl.register()


@pytest.fixture(autouse=True)
def _restore_mitsuba_variant():
    """Give each test back the Mitsuba variant it started with.

    Test modules choose their variant when they are imported (and register the plugins there); a test that switches
    variant (to compare RGB with spectral, say) would otherwise leave the next test, on the same xdist worker, in a
    variant where `realistic_lens` was never registered -- a failure that depends on how tests are distributed."""
    mi = sys.modules.get("mitsuba")
    before = mi.variant() if mi is not None else None
    yield
    mi = sys.modules.get("mitsuba")
    if before is not None and mi is not None and mi.variant() != before:
        mi.set_variant(before)
