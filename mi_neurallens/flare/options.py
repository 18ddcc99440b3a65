"""Options of a flare render (the ``lens_flare`` properties as a dataclass) and ghost-id parsing."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import NeuralLensError
from ..neural.model import MLP_MODES

#: who evaluates the ghost paths (see the ``lens_flare`` docs)
MODES = ("auto", "exact", "neural")
#: baselines usable as ghost evaluators (docs/baselines.md), planes as the neural maps'
BASELINE_MODES = ("abcd", "taylor3", "taylor5", "fitted")
COATINGS = ("lens", "none", "quarter_wave", "broadband")
BOUNDS = ("pilot", "none")


class FlareError(NeuralLensError, ValueError):
    """Bad flare options (ghost ids, modes, missing ghost models...)."""


@dataclass
class FlareOptions:
    mode: str = "auto"                 #: auto | exact | neural | abcd | taylor3 | taylor5 | fitted
    #: mode auto: a learned ghost map is used where its held-out median exit-position error is at most this many
    #: film pixels, the tracer elsewhere
    auto_max_error_px: float = 0.1
    #: mode auto: and, where the model records a verified flare error for the map (``metrics["flare"]``,
    #: :mod:`mi_neurallens.flare.verify`), only if that paired MAPE is at most this (0.01: the per-ghost flare goal)
    auto_max_flare_error: float = 0.01
    #: mode auto: and, where the model records what the map costs against tracing its ghost on this backend
    #: (``metrics["flare_cost"]``, :func:`~mi_neurallens.flare.verify.record_flare_costs`), only if its cost per sample
    #: (at the band it would be rendered with) is at most this × the tracer's: so ``auto`` learns a ghost only where
    #: that is faster.  ``inf``: accuracy alone decides
    auto_max_cost: float = 1.0
    #: learned ghosts: a sample whose classifier logit lies within ±this of the decision (0) is traced exactly
    #: instead, in a second, compacted pass (0: off).  A learned ghost's flare error sits on its edges, where the
    #: classifier decides; the margin classifiers' logit is ≈ 40 × the aperture margin there, so 0.4 traces the
    #: rays within ≈ 0.01 of an aperture edge (docs/flares.md, "Exact edges").  In mode auto a floor: a ghost whose
    #: verified records pass the gate only with a wider band is rendered with that band
    #: (:meth:`~mi_neurallens.flare.policy.FlarePolicy.map_band`)
    boundary_band: float = 0.0
    #: learned ghosts rendered through an iris other than the trained one (stopped down, or bladed: the iris is
    #: tested on the maps' predicted stop-plane crossings): a sample whose predicted crossing lies within
    #: ``iris_band`` × 3 × its stop head's held-out p99 crossing error of the iris's edge is traced exactly
    #: instead, like the classifier's undecided ones (:func:`~mi_neurallens.flare.evaluator.iris_band_mm`).
    #: None: ``boundary_band`` in mode neural; in mode auto at least 1 (the verified records were measured at
    #: the trained iris); 0: off
    iris_band: float | None = None
    ghosts: list | None = None         #: ghost path ids to render (None: automatic selection)
    exclude_ghosts: list = field(default_factory=list)
    max_ghosts: int = 32               #: cap of the automatic selection
    energy_fraction: float = 0.99      #: automatic selection covers this share of ghost energy
    samples: int = 1 << 20             #: forward samples per light (split over its ghosts)
    min_samples: int = 1 << 12         #: floor per ghost
    pilot_grid: int = 64
    pilot_spp: int = 4
    bounds: str = "pilot"              #: pilot | none
    #: who plans the sampling (pilot cells and per-ghost budgets): "self" (the render's own evaluator)
    #: or "exact" (the tracer, whatever the mode).  Random numbers depend on the seed and the path only,
    #: so with "exact" renders of different modes at one seed use identical samples (common random
    #: numbers): their difference is the maps' error alone, without Monte Carlo noise between them.
    pilot_with: str = "self"
    coating: str = "lens"              #: lens (as the sensor's lens) | none | quarter_wave | broadband
    coating_index: float = 1.38
    coating_wavelength: float = 550.0
    coating_surfaces: list | None = None   #: optical-surface indices that get the coating (None: all)
    blades: int | None = None
    blade_rotation: float | None = None
    visibility: bool = True            #: shadow-test the light from the front of the lens
    small_emitters: int = 0            #: also flare the N brightest small area emitters
    small_emitter_size: float = 0.05   #: "small": bounding-box diagonal below this (scene units)
    include_transmit: bool = False     #: also splat the transmit path (radiometric checks)
    #: the aperture's diffraction starburst (flare/diffraction.py): each light's own image, traced forward, convolved
    #: with the exit pupil's Fraunhofer pattern (a light the backward render sees: with that pattern minus a delta)
    diffraction: bool = True
    #: with a nested render: its pixels whose luminance exceeds this (pixel units) are spread by the starburst too
    #: (bright speculars, emissive surfaces: the kernel minus a delta over the whole image); 0: off
    diffraction_threshold: float = 0.0
    #: an image of the pupil's transmission (dust, scratches; grey 0-1, over the iris's circumscribed square, its
    #: top row at +y) whose diffraction joins the iris's in the starburst; None: a clean pupil
    aperture_mask: str | None = None
    transmit_only: bool = False        #: splat only the transmit path
    model: object = None               #: NeuralLensModel or a file (default: the sensor's model)
    #: how learned ghost maps enter their kernels: "fused" (weights as literals: a kernel per map), "shared"
    #: (every number a kernel input, the weights in packed buffers on LLVM: one kernel per architecture),
    #: "coopvec", or "auto" (shared from SHARED_FROM learned maps of one render on: flare/policy.py says why)
    mlp: str = "auto"
    #: replay each ghost's kernels instead of tracing them again (``dr.freeze``): learned maps of one architecture
    #: share one recording, and a renderer's later renders replay all of them (FlareKernels.run, flare/kernels.py)
    freeze: bool = True

    def validate(self):
        if self.mode not in MODES + BASELINE_MODES:
            raise FlareError(f"lens_flare: 'mode' must be one of {', '.join(MODES + BASELINE_MODES)}, "
                             f"got {self.mode!r}")
        if self.coating not in COATINGS:
            raise FlareError(f"lens_flare: 'coating' must be one of {', '.join(COATINGS)}, got {self.coating!r}")
        if self.pilot_with not in ("self", "exact"):
            raise FlareError(f"lens_flare: 'pilot_with' must be 'self' or 'exact', got {self.pilot_with!r}")
        if self.bounds not in BOUNDS:
            raise FlareError(f"lens_flare: 'bounds' must be one of {', '.join(BOUNDS)}, got {self.bounds!r}")
        if not self.samples > 0:
            raise FlareError(f"lens_flare: 'flare_samples' must be > 0, got {self.samples}")
        if not 1 <= self.max_ghosts:
            raise FlareError(f"lens_flare: 'max_ghosts' must be >= 1, got {self.max_ghosts}")
        if not 0 < self.energy_fraction <= 1:
            raise FlareError(f"lens_flare: 'energy_fraction' must be in (0, 1], got {self.energy_fraction}")
        if self.blades is not None and self.blades != 0 and self.blades < 3:
            raise FlareError(f"lens_flare: 'blades' must be 0 (circular) or >= 3, got {self.blades}")
        if not self.auto_max_error_px >= 0:
            raise FlareError(f"lens_flare: 'auto_max_error' must be >= 0 (pixels), got {self.auto_max_error_px}")
        if not self.boundary_band >= 0:
            raise FlareError(f"lens_flare: 'boundary_band' must be >= 0 (a classifier logit), got {self.boundary_band}")
        if self.iris_band is not None and not self.iris_band >= 0:
            raise FlareError(f"lens_flare: 'iris_band' must be >= 0 (a multiple of the stop heads' p99 error, "
                             f"times 3), got {self.iris_band}")
        if not self.auto_max_cost > 0:
            raise FlareError(f"lens_flare: 'auto_max_cost' must be > 0 (learned / traced cost per sample; inf: off), "
                             f"got {self.auto_max_cost}")
        if not self.auto_max_flare_error >= 0:
            raise FlareError(f"lens_flare: 'auto_max_flare_error' must be >= 0, got {self.auto_max_flare_error}")
        if self.mlp not in ("auto",) + MLP_MODES:
            raise FlareError(f"lens_flare: 'mlp' must be one of auto, {', '.join(MLP_MODES)}, got {self.mlp!r}")
        if not self.diffraction_threshold >= 0:
            raise FlareError(f"lens_flare: 'diffraction_threshold' must be >= 0 (0: off), got "
                             f"{self.diffraction_threshold}")
        if not self.pilot_grid >= 4 or not self.pilot_spp >= 1:
            raise FlareError("lens_flare: 'pilot_grid' must be >= 4 and 'pilot_spp' >= 1")
        return self


def parse_id_list(text, what="ghosts"):
    """'12 40, 3' or [12, 40] → [12, 40, 3]; 'a:b' pairs (optical-surface indices) → ghost ids."""
    from ..trace.paths import ghost_id
    if text is None:
        return None
    if isinstance(text, (list, tuple)):
        items = list(text)
    else:
        items = [t for t in str(text).replace(",", " ").split() if t]
    out = []
    for t in items:
        if isinstance(t, (int, np.integer)):
            out.append(int(t))
            continue
        t = str(t)
        try:
            if ":" in t:
                a, b = (int(v) for v in t.split(":"))
                out.append(ghost_id(max(a, b), min(a, b)))
            else:
                out.append(int(t))
        except (ValueError, NeuralLensError):
            raise FlareError(f"lens_flare: '{what}': cannot read {t!r}: give integer path ids (e.g. 132) "
                             f"or optical-surface pairs 'a:b'") from None
    return out
