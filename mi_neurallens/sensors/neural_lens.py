"""The ``neural_lens`` sensor: the learned lens transport map (classifier → regressor) in the kernel.

Same conventions, properties and sampling as ``realistic_lens`` (both derive from
:mod:`.base`); only the transport differs: instead of tracing the prescription, the backward
transmit map of a trained model (:mod:`mi_neurallens.neural.model`) is evaluated inside the Dr.Jit
kernel — the symmetry reduction, the classifier (is the ray blocked?), the regressor (exit ray and
Fresnel throughput) with literal weights and a float32 tanh (per backend: ``neural/mlp.py``), and the undo of
the reduction.
"""
from __future__ import annotations

import dataclasses
import os

from .. import resources
from ..errors import ModelError
from ..jit import untraversed
from ..neural.model import MLP_MODES, load_model
from ..trace.iris import Iris
from .base import LensSensorBase
from .common import SensorPropertyError, load_lens

PLUGIN = "neural_lens"

#: transport of the camera rays: the learned map, or a baseline between the same planes
METHODS = ("neural", "exact", "abcd", "taylor3", "taylor5", "fitted")

DOC = r"""
.. _sensor-neural_lens:

Neural lens camera (:monosp:`neural_lens`)
------------------------------------------

.. pluginparameters::

 * - model
   - |string|
   - A model file (``*.model.safetensors``, written by ``mi-neurallens train``) or a lens name whose model is
     found in a lens library: a bundled lens (``mi-neurallens lens list``; which ship a model:
     docs/lenses.md), or a lens of ``$MI_NEURALLENS_LENSES`` with a ``models/<name>.model.safetensors``.
     (Default: the model of ``lens`` when ``lens`` is given, else ``wide-22mm``)

 * - lens
   - |string|
   - The prescription the model was trained for (file or bundled name).  It gives the paraxial
     focus, pupil bounds and normalisation; its fingerprint must match the model's.  (Default: the
     bundled lens named in the model)

 * - use_classifier
   - |bool|
   - Evaluate the classifier and drop rays it calls blocked.  ``false`` reproduces the paper's
     ablation: every ray inside the trained domain is passed through the regressor, and the image
     gets over-exposed and blurred.  (Default: |true|)

 * - mlp
   - |string|
   - How the networks are evaluated in the kernel.  ``fused``: every weight is a literal in the generated
     kernel and tanh is accurate to float32 (a rational approximation on the CPU, the GPU's exp2 and
     reciprocal on CUDA); the fastest evaluation once compiled, but every new weight set compiles a kernel
     of its own.  ``shared``: every number of the map is a kernel input (on the CPU the networks through
     packed cooperative-vector buffers, fp32, equal to ``fused`` to ~1e-6; on CUDA fp32 kernel parameters),
     so maps of one architecture share one compiled kernel: for many maps in one render, as ``lens_flare``'s
     ghosts.  ``coopvec``: Dr.Jit cooperative vectors (``drjit.nn``) on every backend, no recompilation when
     weights change, tensor cores on CUDA but fp16 there (coarser exit rays).  Keep ``fused`` for camera
     rays (rates of each: docs/performance.md).  (Default: ``fused``)

 * - method
   - |string|
   - ``neural`` (default): the learned map.  For comparisons, the same planes and sampling with another
     transport: ``exact`` (the tracer), ``abcd`` (paraxial matrices), ``taylor3``/``taylor5``
     (Taylor polynomial optics), ``fitted`` (sparse polynomials fitted to traced rays; built when the
     scene loads, ~20–40 s).  See docs/baselines.md.  (Default: ``neural``)

 * - focus_distance, sensor_distance, fstop, blades, blade_rotation, sensor_width, scene_unit_mm,
     fresnel, pupil_sampling, ray_kernel, to_world, film, sampler, shutter_open, shutter_close
   - 
   - As for :ref:`realistic_lens <sensor-realistic_lens>`, so the two sensors are interchangeable in a
     scene.  Manual focusing (``sensor_distance`` / ``focus_distance``) moves the sensor with the same
     model, within the sensor-distance range the model was trained for (a clear error outside it).
     ``fstop`` (any value from the widest up) and ``blades``/``blade_rotation`` work without retraining
     when the model has a stop head: the map was learned wide open and also predicts where each ray
     crosses the stop plane, and that crossing is tested against the requested iris, exactly as the
     tracer tests it (a model without one is fixed at its trained aperture, with a clear error).
     ``fresnel=false`` replaces the learned throughput by 1.

The evaluation order per camera ray: film point and pupil sample (as ``realistic_lens``), then the
ray is moved to the model's input plane, reduced by the lens's rotational and mirror symmetry to
(r, ωx, ωy ≥ 0, λ), the classifier decides whether it is blocked, the regressor gives the exit
position, direction and throughput in the reduced frame, and the reduction is undone.

.. tabs::

    .. code-tab:: xml

        <sensor type="neural_lens">
            <string name="model" value="wide-22mm"/>
            <float name="focus_distance" value="2.5"/>
            <transform name="to_world">
                <lookat origin="0, 1, 5" target="0, 1, 0" up="0, 1, 0"/>
            </transform>
            <sampler type="ldsampler"><integer name="sample_count" value="64"/></sampler>
            <film type="hdrfilm"><integer name="width" value="640"/><integer name="height" value="480"/></film>
        </sensor>

    .. code-tab:: python

        'type': 'neural_lens',
        'model': 'wide-22mm',
        'focus_distance': 2.5,
        'to_world': mi.ScalarTransform4f().look_at(origin=[0, 1, 5], target=[0, 1, 0], up=[0, 1, 0]),
        'sampler': {'type': 'ldsampler', 'sample_count': 64},
        'film': {'type': 'hdrfilm', 'width': 640, 'height': 480},
"""


def resolve_model_path(spec: str, plugin: str = PLUGIN) -> str:
    """A model file path from the ``model`` property (a path, or a bundled lens name)."""
    if not isinstance(spec, str) or not spec.strip():
        raise SensorPropertyError(plugin, "model", f"must be a model file or a bundled lens name, got {spec!r}")
    try:
        import mitsuba as mi
        r = str(mi.file_resolver().resolve(spec))
        if os.path.exists(r):
            return r
    except Exception:  # pragma: no cover
        pass
    if os.path.exists(spec):
        return spec
    p = resources.find_model(spec)
    if p is not None:
        return str(p)
    raise SensorPropertyError(plugin, "model", f"no model {spec!r}: not a file, and no model of a lens of that "
                              f"name (models: {', '.join(resources.model_names()) or 'none'}; searched "
                              f"{resources.search_path_text()}); train one with `mi-neurallens train LENS`")


class NeuralLens(LensSensorBase):
    __doc__ = DOC
    PLUGIN = PLUGIN
    model = untraversed()      # the neural model: Python data, kept out of Dr.Jit's traversal (see base)

    def _read_properties(self, rd):
        self.lens_prop = rd.string("lens", None)
        self.model_spec = rd.string("model", None)      # None: the lens's bundled model (_default_model)
        self.use_classifier = rd.bool("use_classifier", True)
        self.mlp = rd.string("mlp", "fused", choices=MLP_MODES)
        self.method = rd.string("method", "neural", choices=METHODS)

    def _default_model(self) -> str:
        """The ``model`` when none is given: the bundled model of ``lens`` (a bundled name, or a file whose
        lens has one), or ``wide-22mm`` without ``lens``."""
        if not self.lens_prop:
            return "wide-22mm"
        name = load_lens(self.lens_prop, PLUGIN).name
        if resources.find_model(name) is not None:
            return name
        raise SensorPropertyError(PLUGIN, "model", f"not given, and no bundled model for lens '{name}': give the "
                                  f"model file `mi-neurallens train {self.lens_prop}` writes")

    def _load_lens(self, rd):
        if self.model_spec is None:
            self.model_spec = self._default_model()
        self.model_path = resolve_model_path(self.model_spec)
        try:
            probe = load_model(self.model_path)  # header + tensors; lens check below
        except ModelError as e:
            raise SensorPropertyError(PLUGIN, "model", str(e)) from e
        lens = load_lens(self.lens_prop or probe.lens_name, PLUGIN)
        if lens.fingerprint() != probe.fingerprint:
            raise SensorPropertyError(
                PLUGIN, "lens" if self.lens_prop else "model",
                f"model {self.model_path} was trained for lens '{probe.lens_name}' (fingerprint "
                f"{probe.fingerprint}), but the lens is '{lens.name}' (fingerprint {lens.fingerprint()}); "
                f"use the matching lens or train a model for this one")
        if not probe.has("transmit", "backward"):
            raise SensorPropertyError(PLUGIN, "model", f"model {self.model_path} has no backward transmit "
                                      f"map (it has {sorted(probe.maps)})")
        self.model = probe
        return lens

    def _iris(self, tm):
        """The iris the learned map must test (None: the one it was trained with)."""
        st = self.setup
        trained, want = Iris.of_lens(st.base_lens), Iris.of_lens(st.lens)
        if want.same_as(trained):
            return None
        prop = "fstop" if want.blades == trained.blades else "blades"
        if tm.stop_head is None:
            raise SensorPropertyError(
                PLUGIN, prop, f"model {self.model_path} was trained wide open (f/{st.max_fnumber:.3g}, "
                f"{trained.describe()}) and has no stop head, so its aperture is fixed; add one with "
                f"`mi-neurallens train {st.base_lens.name} --paths backward-transmit --keep networks` or use "
                f"realistic_lens")
        if trained.blades:
            raise SensorPropertyError(
                PLUGIN, prop, f"model {self.model_path} was trained with a bladed iris ({trained.describe()}); "
                f"only a model trained with a circular stop can change its aperture")
        if not want.within(trained):
            hint = ""
            if want.blades:
                n_min = st.max_fnumber * want.outer_radius_mm / want.radius_mm
                hint = (f": the corners of {want.blades} blades reach {want.outer_radius_mm:.4g} mm from the axis, "
                        f"where the map learned rays as blocked; use fstop >= {n_min * (1 + 1e-6):.4g} with "
                        f"{want.blades} blades (blades=0 is round at any f-number), or realistic_lens")
            raise SensorPropertyError(
                PLUGIN, prop, f"the requested iris ({want.describe()}) is not inside the one model "
                f"{self.model_path} was trained with ({trained.describe()}){hint}")
        return want

    def _make_map(self, geometry):
        st = self.setup
        try:
            self.model.check_sensor_distance(st.sensor_distance_mm)
        except ModelError as e:
            which = "sensor_distance" if not (st.focus_distance_mm > 0) else "focus_distance"
            raise SensorPropertyError(PLUGIN, which, str(e)) from e
        tm = self.model.map("transmit", "backward")
        if self.method == "neural":
            return dataclasses.replace(tm, use_classifier=self.use_classifier, mlp=self.mlp, iris=self._iris(tm))
        # a baseline between the same planes (docs/baselines.md); the map starts on its input
        # plane: the pupil sample only gives the direction
        from ..transport import make_map
        return make_map(st.lens, self.method, "transmit", "backward", z_in=tm.z_in, z_out=tm.z_out,
                        **({"fresnel": st.fresnel} if self.method == "exact" else {}))

    def _describe(self):
        iris = getattr(self.tmap, "iris", None)
        return (f"model='{self.model_spec}' ({os.path.basename(self.model_path)}), lens={self.setup.lens.name}, "
                f"iris={'as trained' if iris is None else iris.describe()}, "
                f"use_classifier={self.use_classifier}, mlp={self.mlp}, method={self.method}")
