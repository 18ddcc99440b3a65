"""The ``lens_flare`` integrator: a nested integrator's image plus the ghosts of the scene's bright lights.

Defined per Mitsuba variant by :func:`make_lens_flare` and registered by
:func:`mi_neurallens.integrators.register`.  The forward sampling and the radiometry live in
:mod:`mi_neurallens.flare.render`.
"""
from __future__ import annotations

PLUGIN = "lens_flare"

DOC = r"""
Lens flare (:monosp:`lens_flare`)
---------------------------------

Renders the nested integrator, then adds the flare of the scene's point, spot and directional
emitters (and, with ``small_emitters``, of the brightest small area emitters): for each light and
each kept ghost path (two internal reflections), points are sampled on the lens's entrance plane
over a pilot-found region that reaches the sensor, one wavelength per sample (CIE-weighted, like
the sensor), the path is evaluated (exactly with ``realistic_lens``; classifier + regressor with
``neural_lens``), continued to the sensor plane and the Fresnel-weighted flux splatted (box filter)
with the same radiometric normalisation as the backward image.  The sensor must be
``realistic_lens`` or ``neural_lens``.

.. pluginparameters::

 * - (nested integrator)
   - |integrator|
   - The integrator that renders the scene (e.g. ``path``).  Without one only the flare is rendered.
 * - mode
   - |string|
   - ``auto`` (neural maps where the sensor/``model`` has them, exact otherwise), ``exact``, ``neural``,
     or a baseline for comparisons: ``abcd``, ``taylor3``, ``taylor5``, ``fitted`` (docs/baselines.md).
 * - model
   - |string|
   - Neural model file to use for ghosts (default: the ``neural_lens`` sensor's model).
 * - ghosts / exclude_ghosts
   - |string|
   - Ghost path ids (or ``a:b`` optical-surface pairs) to render / to leave out, space separated.
 * - max_ghosts, energy_fraction
   - |int|, |float|
   - Automatic selection: the strongest ghosts covering ``energy_fraction`` of the ghost energy
     (default 0.99), at most ``max_ghosts`` (default 32).
 * - flare_samples
   - |int|
   - Forward samples per light, split over its ghosts in proportion to their energy (default 2^20).
 * - coating, coating_index, coating_wavelength, coating_surfaces
   - |string|, |float|, |float|, |string|
   - ``lens`` (as the sensor's lens, default), ``none`` (bare surfaces) or ``quarter_wave``
     (single layer of index ``coating_index`` (1.38), quarter wave at ``coating_wavelength`` nm
     (550), on the optical surfaces listed in ``coating_surfaces`` (default all)).  Flare only.
 * - blades, blade_rotation
   - |int|, |float|
   - Polygonal aperture for the flare (straight blades, rotation in degrees).  Flare only.
 * - visibility
   - |bool|
   - Shadow-test each light from the front of the lens (default true).
 * - small_emitters, small_emitter_size
   - |int|, |float|
   - Also flare the N brightest area emitters whose bounding box is smaller than the size.
 * - pilot_grid, pilot_spp, bounds
   - |int|, |int|, |string|
   - Pilot pass resolution (64) and samples per cell (4); ``bounds=none`` samples the whole
     entrance disk (for comparisons).
 * - pilot_with
   - |string|
   - Who plans the sampling (pilot cells, per-ghost budgets): ``self`` (default: the render's own
     evaluator) or ``exact`` (the tracer in every mode, so exact and neural renders at one seed
     use identical samples and differ by the maps' error only; for comparisons).
"""

_INT_PROPS = ("max_ghosts", "flare_samples", "min_samples", "pilot_grid", "pilot_spp", "small_emitters",
              "blades")
_FLOAT_PROPS = ("energy_fraction", "coating_index", "coating_wavelength", "blade_rotation", "small_emitter_size")
_STR_PROPS = ("mode", "model", "ghosts", "exclude_ghosts", "coating", "coating_surfaces", "bounds", "pilot_with")
_BOOL_PROPS = ("visibility", "include_transmit", "transmit_only")


def options_from_props(props, nested_names=()):
    """Read every lens_flare property into :class:`~mi_neurallens.flare.render.FlareOptions`."""
    from ..flare.render import FlareError, FlareOptions, parse_id_list
    kw = {}
    for k in props.keys():
        if k in nested_names:
            continue
        v = props.get(k)
        if k in _INT_PROPS:
            if isinstance(v, bool) or not isinstance(v, (int, float)) or int(v) != v:
                raise FlareError(f"lens_flare: property '{k}' must be an integer, got {v!r}")
            kw[{"flare_samples": "samples"}.get(k, k)] = int(v)
        elif k in _FLOAT_PROPS:
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise FlareError(f"lens_flare: property '{k}' must be a number, got {v!r}")
            kw[k] = float(v)
        elif k in _BOOL_PROPS:
            if not isinstance(v, bool):
                raise FlareError(f"lens_flare: property '{k}' must be a boolean, got {v!r}")
            kw[k] = v
        elif k in _STR_PROPS:
            if not isinstance(v, str):
                raise FlareError(f"lens_flare: property '{k}' must be a string, got {v!r}")
            if k in ("ghosts", "exclude_ghosts", "coating_surfaces"):
                kw[k] = parse_id_list(v, k) if k != "coating_surfaces" else [int(t) for t in
                                                                            v.replace(",", " ").split()]
                if k == "exclude_ghosts":
                    kw[k] = kw[k] or []
            else:
                kw[k] = v or None if k == "model" else v
        elif k in ("samples_per_pass", "timeout", "hide_emitters", "max_depth", "rr_depth"):
            continue   # consumed by the SamplingIntegrator base
        else:
            raise FlareError(f"lens_flare: unknown property '{k}'; known: "
                             f"{', '.join(_INT_PROPS + _FLOAT_PROPS + _STR_PROPS + _BOOL_PROPS)}")
    return FlareOptions(**kw).validate()


def make_lens_flare():
    """Define the ``lens_flare`` class for the CURRENT Mitsuba variant."""
    import mitsuba as mi

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
                        from ..flare.render import FlareError
                        raise FlareError("lens_flare: give at most one nested integrator")
                    self.nested = v
                    nested_names.append(k)
            self.opts = options_from_props(props, nested_names)
            self.last_result = None

        def flare(self, scene, sensor, seed=0, per_ghost=False):
            """The flare alone as a :class:`~mi_neurallens.flare.render.FlareResult` (numpy)."""
            from ..flare.render import FlareRenderer
            if isinstance(sensor, int):
                sensor = scene.sensors()[sensor]
            res = FlareRenderer(scene, sensor, self.opts).render(seed=int(seed), per_ghost=per_ghost)
            self.last_result = res
            return res

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
            C = img.shape[2]
            if C == 3:
                return img + fl
            arr = img.numpy() if hasattr(img, "numpy") else img
            import numpy as np
            out = np.array(arr, copy=True)
            if C >= 3:
                out[..., :3] += res.total
            else:
                out[..., 0] += res.total @ np.array([0.2126, 0.7152, 0.0722], np.float32)
            return mi.TensorXf(out)

        def aov_names(self):
            return []

        def traverse(self, cb):
            if self.nested is not None:
                cb.put("nested", self.nested, mi.ParamFlags.NonDifferentiable)

        def to_string(self):
            o = self.opts
            return (f"LensFlare[mode={o.mode}, flare_samples={o.samples}, max_ghosts={o.max_ghosts}, "
                    f"ghosts={o.ghosts}, coating={o.coating}, blades={o.blades}, nested={self.nested}]")

    LensFlare.__name__ = "LensFlare"
    return LensFlare
