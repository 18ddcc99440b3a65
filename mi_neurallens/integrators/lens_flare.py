"""The ``lens_flare`` integrator: a nested integrator's image plus the ghosts of the scene's bright lights.

:class:`LensFlare` derives from the ``mi.SamplingIntegrator`` of the variant that was set when this
module was (re-)imported; :func:`mi_neurallens.integrators.register` re-imports it per variant.  The forward sampling and the radiometry live in
:mod:`mi_neurallens.flare.render`.
"""
from __future__ import annotations

import mitsuba as mi
import numpy as np

from ..constants import LUMINANCE_WEIGHTS
from ..flare.options import FlareError, FlareOptions, parse_id_list
from ..flare.render import FlareRenderer
from ..sensors.common import PropertyReader


PLUGIN = "lens_flare"

DOC = r"""
.. _integrator-lens_flare:

Lens flare (:monosp:`lens_flare`)
---------------------------------

Renders the nested integrator, then adds the flare of the scene's point, spot and directional
emitters (and, with ``small_emitters``, of the brightest small area emitters): for each light and
each kept ghost path (two internal reflections), points are sampled on the lens's entrance plane
over a pilot-found region that reaches the sensor, one wavelength per sample (CIE-weighted, like
the sensor), the path's transport map is evaluated (the tracer with ``realistic_lens``; classifier +
regressor with ``neural_lens``), continued to the sensor plane and the Fresnel-weighted flux splatted
(box filter) with the same radiometric normalisation as the backward image (docs/flares.md).  The
sensor must be ``realistic_lens`` or ``neural_lens``.

.. pluginparameters::

 * - (nested integrator)
   - |integrator|
   - The integrator that renders the scene (e.g. ``path``).  Without one only the flare is rendered.

 * - mode
   - |string|
   - ``auto``: a ghost's learned map where the sensor (or ``model``) has one that is accurate enough for this
     film (``auto_max_error``) and, where its verified flare error is recorded, within
     ``auto_max_flare_error`` (with its edges traced, at the ``boundary_band`` of the record that passes,
     where only such a record passes) and, where its cost against tracing is recorded, not slower than the tracer
     (``auto_max_cost``); the tracer otherwise; ``exact``: the tracer for every path; ``neural``:
     learned maps only (an error names a missing ghost); or a baseline for comparisons: ``abcd``,
     ``taylor3``, ``taylor5``, ``fitted`` (docs/baselines.md).  (Default: ``auto``)

 * - auto_max_error
   - |float|
   - ``auto`` uses a learned ghost map only if its held-out median exit-position error (recorded in the model
     file) is at most this many film pixels; a coarser map is traced instead, so a render never shows a
     learned ghost less sharp than its pixels.  (Default: 0.1)

 * - auto_max_flare_error
   - |float|
   - ``auto`` also requires, where the model file records one (``mi-neurallens evaluate MODEL --flare
     --write``), a map's verified flare error — its ghost against the tracer's on the same samples, paired
     MAPE — to be at most this.  Position alone does not see a classifier's edge.  The record is measured on a
     240×160 full-frame film, wide open: a necessary condition, not a proof at finer films or other irises
     (the position gate scales with the film; the iris needs a stop head).  (Default: 0.01, the per-ghost
     flare goal)

 * - auto_max_cost
   - |float|
   - ``auto`` also requires, where the model file records what a learned ghost costs against tracing it on
     this backend (``mi-neurallens evaluate MODEL --flare-cost --write``; ``train`` measures it), that its cost
     per sample be at most this × the tracer's: ``auto`` learns a ghost only where that is faster.  Costs
     measured on the CPU do not decide on the GPU (and back).  ``inf``: accuracy alone decides.  (Default: 1)

 * - boundary_band
   - |float|
   - Learned ghosts: a sample whose classifier logit lies within ±this of its decision is traced exactly
     instead, in a second pass over just those samples.  A learned ghost's flare error sits on its edges,
     where the classifier decides (its logit is about 40 × the aperture margin there), so 1.0 traces the rays
     within ≈ 0.025 of an aperture edge, a few percent of a ghost's samples: choose it for converged renders
     and fine films, where the learned edges' error would show (docs/flares.md, "Exact edges").  0: off.  In
     ``auto`` this is a floor: a ghost whose map is verified within ``auto_max_flare_error`` only with a wider
     band is rendered with that band.  (Default: 0)

 * - iris_band
   - |float|
   - Learned ghosts through an iris other than the trained one (``fstop`` stopped down, ``blades``: the iris is
     tested on each map's predicted stop-plane crossings): a sample whose predicted crossing lies within
     ``iris_band`` × 3 × the stop head's held-out p99 crossing error of the iris's edge is traced exactly
     instead, like ``boundary_band``'s, so the iris polygon's edge is the tracer's
     (docs/flares.md, "Exact edges").  0: off.  (Default: ``boundary_band`` in ``neural``, at least 1 in
     ``auto``, whose verified records were measured at the trained iris)

 * - model
   - |string|
   - Neural model whose ghost maps are used: a file, or a bundled lens name as the ``neural_lens`` sensor's
     ``model``.  (Default: the ``neural_lens`` sensor's model)

 * - mlp
   - |string|
   - How learned ghost maps are evaluated in their kernels: ``fused`` (every weight a literal: the fastest
     code once compiled, but one kernel to compile per ghost map), ``shared`` (every number of a map a kernel
     input, on a CPU the weights in packed cooperative-vector buffers: the ghost maps of one architecture
     share one kernel, compiled once), ``coopvec`` (Dr.Jit cooperative vectors on every backend, fp16 on
     CUDA), or ``auto``: ``shared`` when the render uses several learned maps, ``fused`` for one.
     (Default: ``auto``)

 * - freeze
   - |bool|
   - Replay each ghost's kernels instead of tracing them again in Python (Dr.Jit's frozen functions): the
     learned ghost maps of one architecture share one recording, and the integrator's later renders of the
     same sensor replay them all, the light and camera moved or not.  Off traces every kernel at every render
     (docs/flares.md, "Frozen kernels").  Spectral variants always trace.  (Default: ``true``)

 * - ghosts
   - |string|
   - Ghost path ids (or ``a:b`` optical-surface pairs: reflect at ``a``, then at ``b < a``) to render,
     space or comma separated.  (Default: the automatic selection below)

 * - exclude_ghosts
   - |string|
   - Ghost ids or pairs to leave out of the selection.  (Default: none)

 * - energy_fraction
   - |float|
   - Automatic selection: the strongest ghosts that together carry this share of the ghost energy.
     (Default: 0.99)

 * - max_ghosts
   - |int|
   - Automatic selection: at most this many ghosts.  (Default: 32)

 * - flare_samples
   - |int|
   - Forward samples per light, split over its ghosts in proportion to their pilot-estimated energy.
     (Default: 1048576)

 * - min_samples
   - |int|
   - Floor of the samples any one ghost gets, however dim.  (Default: 4096)

 * - coating
   - |string|
   - ``lens`` (the coatings of the sensor's lens file), ``none`` (bare surfaces), ``quarter_wave`` (a
     single layer, see below) or ``broadband`` (the quarter-half-quarter stack glass | Al₂O₃ λ/4 | ZrO₂ λ/2 |
     MgF₂ λ/4 | air at 550 nm; the lens format page lists its indices).  Changes the flare only, not the
     backward image.  (Default: ``lens``)

 * - coating_index
   - |float|
   - Refractive index of the ``quarter_wave`` layer.  (Default: 1.38, MgF₂)

 * - coating_wavelength
   - |float|
   - Design wavelength (nm) of the ``quarter_wave`` layer.  (Default: 550)

 * - coating_surfaces
   - |string|
   - Optical-surface indices that get the ``quarter_wave`` layer or the ``broadband`` stack.  (Default: all)

 * - blades
   - |int|
   - Polygonal aperture for the flare: the number of straight blades (0: circular).  Learned ghost
     maps with a stop head test it on their predicted stop-plane crossings (exactly as the tracer);
     in ``auto`` mode a map without one falls back to the tracer.  (Default: the sensor's iris)

 * - blade_rotation
   - |float|
   - Rotation of the blades in degrees.  (Default: the sensor's)

 * - visibility
   - |bool|
   - Shadow-test each light from the front of the lens.  (Default: |true|)

 * - small_emitters
   - |int|
   - Also flare the N brightest area emitters whose bounding box is smaller than
     ``small_emitter_size``.  (Default: 0)

 * - small_emitter_size
   - |float|
   - "Small": bounding-box diagonal below this (scene units).  (Default: 0.05)

 * - pilot_grid
   - |int|
   - Resolution of the pilot pass over the entrance disk (cells per side).  (Default: 64)

 * - pilot_spp
   - |int|
   - Pilot samples per cell.  (Default: 4)

 * - bounds
   - |string|
   - ``pilot``: sample only the cells the pilot found to reach the film (dilated by one cell);
     ``none``: the whole entrance disk (for comparisons).  (Default: ``pilot``)

 * - pilot_with
   - |string|
   - Who plans the sampling (pilot cells, per-ghost budgets): ``self`` (the render's own
     evaluator) or ``exact`` (the tracer in every mode, so exact and neural renders at one seed use
     identical samples and differ by the maps' error only; for comparisons).  (Default: ``self``)

 * - diffraction
   - |bool|
   - The aperture's diffraction starburst: each point, spot and directional light's own image, traced forward,
     is convolved with the far-field (Fraunhofer) pattern of the exit pupil (the iris at its f-number and blades,
     scaled by the pupil magnification, at the working f-number), per RGB channel with the sensor's colour
     matching; an area emitter the backward render already shows (``small_emitters``) gets the pattern minus a
     delta, so no light is counted twice.  It redistributes light and adds none: n spikes for an even number of
     blades, 2n for an odd one, none for a round iris (Airy rings).  (Default: |true|)

 * - diffraction_threshold
   - |float|
   - With a nested integrator and ``diffraction``: the pixels of its image whose luminance exceeds this are
     spread by the starburst too (the kernel minus a delta over the whole image), for bright speculars and
     emissive surfaces the flare does not trace.  0: off.  (Default: 0)

 * - aperture_mask
   - |string|
   - An image of the pupil's transmission (dust, scratches: grey values 0-1, any format Mitsuba reads) spanning
     the iris's circumscribed square, its top row up (+y): its diffraction joins the iris's in the starburst (the
     masked pupil's pattern by FFT near the light, the iris's beyond), and what it blocks is taken from the
     starburst.  (Default: none)

 * - include_transmit
   - |bool|
   - Also splat the transmit path (the lights' own images) forward; it gets one equal share of the
     budget.  For radiometric checks against the backward render.  (Default: |false|)

 * - transmit_only
   - |bool|
   - Splat only the transmit path.  (Default: |false|)

.. tabs::

    .. code-tab:: xml

        <integrator type="lens_flare">
            <string name="mode" value="auto"/>
            <integer name="flare_samples" value="4194304"/>
            <integer name="blades" value="6"/>
            <integrator type="path">
                <integer name="max_depth" value="6"/>
            </integrator>
        </integrator>

    .. code-tab:: python

        'type': 'lens_flare',
        'mode': 'auto',
        'flare_samples': 4194304,
        'blades': 6,
        'nested': {'type': 'path', 'max_depth': 6},
"""

#: property name -> (reader, FlareOptions field)
_PROPS = {
    "max_ghosts": ("int", "max_ghosts"), "flare_samples": ("int", "samples"), "min_samples": ("int", "min_samples"),
    "pilot_grid": ("int", "pilot_grid"), "pilot_spp": ("int", "pilot_spp"),
    "small_emitters": ("int", "small_emitters"), "blades": ("int", "blades"),
    "energy_fraction": ("float", "energy_fraction"), "coating_index": ("float", "coating_index"),
    "coating_wavelength": ("float", "coating_wavelength"), "blade_rotation": ("float", "blade_rotation"),
    "small_emitter_size": ("float", "small_emitter_size"), "auto_max_error": ("float", "auto_max_error_px"),
    "auto_max_flare_error": ("float", "auto_max_flare_error"), "boundary_band": ("float", "boundary_band"),
    "iris_band": ("float", "iris_band"), "auto_max_cost": ("float", "auto_max_cost"),
    "mode": ("string", "mode"), "model": ("string", "model"), "ghosts": ("string", "ghosts"),
    "exclude_ghosts": ("string", "exclude_ghosts"), "coating": ("string", "coating"),
    "coating_surfaces": ("string", "coating_surfaces"), "bounds": ("string", "bounds"),
    "pilot_with": ("string", "pilot_with"), "mlp": ("string", "mlp"),
    "visibility": ("bool", "visibility"), "freeze": ("bool", "freeze"),
    "include_transmit": ("bool", "include_transmit"), "diffraction": ("bool", "diffraction"),
    "diffraction_threshold": ("float", "diffraction_threshold"), "aperture_mask": ("string", "aperture_mask"),
    "transmit_only": ("bool", "transmit_only"),
}
#: properties read by Mitsuba's SamplingIntegrator base
_BASE_PROPS = ("samples_per_pass", "timeout", "hide_emitters", "max_depth", "rr_depth")


def options_from_props(props, nested_names=()):
    """Read every lens_flare property into :class:`~mi_neurallens.flare.render.FlareOptions`, with the
    sensors' :class:`~mi_neurallens.sensors.common.PropertyReader` (clear errors naming the property)."""
    rd = PropertyReader(props, PLUGIN)
    rd.refuse_unknown(tuple(_PROPS), skip=tuple(nested_names) + _BASE_PROPS)
    kw = {}
    for k, (kind, field) in _PROPS.items():
        if not rd.has(k):
            continue
        v = rd.bool(k, None) if kind == "bool" else getattr(rd, kind)(k)
        if k in ("ghosts", "exclude_ghosts"):
            v = parse_id_list(v, k)
            if k == "exclude_ghosts":
                v = v or []
        elif k == "coating_surfaces":
            v = [int(t) for t in v.replace(",", " ").split()]
        elif k in ("model", "aperture_mask"):
            v = v or None
        kw[field] = v
    return FlareOptions(**kw).validate()


class LensFlare(mi.SamplingIntegrator):
    __doc__ = DOC

    def __init__(self, props):
        super().__init__(props)
        self.nested = None
        nested_names = []
        for k in props.keys():
            v = props.get(k) if k not in ("samples_per_pass", "timeout", "hide_emitters") else None
            if isinstance(v, mi.Integrator):
                if self.nested is not None:
                    raise FlareError("lens_flare: give at most one nested integrator")
                self.nested = v
                nested_names.append(k)
        self.opts = options_from_props(props, nested_names)
        self.last_result = None
        self._cached = None         # (key, FlareRenderer) of the last render (see _renderer)

    def flare(self, scene, sensor, seed=0, per_ghost=False):
        """The flare alone as a :class:`~mi_neurallens.flare.render.FlareResult` (numpy)."""
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        res = self._renderer(scene, sensor).render(seed=int(seed), per_ghost=per_ghost)
        self.last_result = res
        return res

    def _renderer(self, scene, sensor):
        """The :class:`~mi_neurallens.flare.render.FlareRenderer` of ``(scene, sensor)``, kept from one render to
        the next while the sensor's lens set-up, model and film are the same objects and sizes, so that later
        renders replay its frozen kernels instead of recording them again (the lights and the camera's pose are
        read at every render; the renderer holds the objects whose ids make the key)."""
        film = sensor.film()
        key = (id(scene), id(sensor), id(sensor.setup), id(getattr(sensor, "model", None)), tuple(film.size()),
               tuple(film.crop_size()), tuple(film.crop_offset()))
        if self._cached is None or self._cached[0] != key:
            self._cached = (key, FlareRenderer(scene, sensor, self.opts))
        return self._cached[1]

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        res = self.flare(scene, sensor, seed)
        fl = mi.TensorXf(res.total)
        if self.nested is None:
            return fl
        img = self.nested.render(scene, sensor, seed, spp, develop, evaluate)
        if not develop:
            return img
        if self.opts.diffraction and self.opts.diffraction_threshold > 0 and img.shape[2] >= 3:
            img = mi.TensorXf(self._spread_bright(np.array(img.numpy() if hasattr(img, "numpy") else img), scene,
                                                  sensor))
        C = img.shape[2]
        if C == 3:
            return img + fl
        arr = img.numpy() if hasattr(img, "numpy") else img
        out = np.array(arr, copy=True)
        if C >= 3:
            out[..., :3] += res.total
        else:
            out[..., 0] += res.total @ np.array(LUMINANCE_WEIGHTS, np.float32)
        return mi.TensorXf(out)

    def _spread_bright(self, arr, scene, sensor):
        """``arr`` (H, W, C) with its RGB pixels above ``diffraction_threshold`` in luminance spread by the starburst
        (their values convolved with the kernel minus a delta)."""
        rgb = np.asarray(arr[..., :3], np.float64)
        lum = rgb @ np.asarray(LUMINANCE_WEIGHTS, np.float64)
        bright = np.where((lum > self.opts.diffraction_threshold)[..., None], rgb, 0.0)
        if bright.any():
            K = self._renderer(scene, sensor).diffraction_kernel()
            arr = np.array(arr, np.float32, copy=True)
            arr[..., :3] += (K.convolve(bright) - bright).astype(np.float32)
        return arr

    def aov_names(self):
        return []

    def traverse(self, cb):
        if self.nested is not None:
            cb.put("nested", self.nested, mi.ParamFlags.NonDifferentiable)

    def to_string(self):
        o = self.opts
        return (f"LensFlare[mode={o.mode}, flare_samples={o.samples}, max_ghosts={o.max_ghosts}, "
                f"ghosts={o.ghosts}, coating={o.coating}, blades={o.blades}, nested={self.nested}]")
