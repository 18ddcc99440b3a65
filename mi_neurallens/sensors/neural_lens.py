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

import drjit as dr
import mitsuba as mi

from .. import resources
from ..errors import ModelError
from ..jit import untraversed
from ..neural.model import MLP_MODES, load_model
from ..trace.iris import Iris
from .base import LensSensorBase
from .common import SensorPropertyError, load_lens
from .live import NetworkParameters, rim_band_factor

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
     kernel and tanh is within about 1e-6 of tanh (a minimax rational on the CPU, the GPU's exp2 and
     reciprocal on CUDA); the fastest evaluation once compiled, but every new weight set compiles a kernel
     of its own.  ``shared``: every number of the map is a kernel input (on the CPU the networks through
     packed cooperative-vector buffers, fp32 with Dr.Jit's tanh, equal to ``fused`` to a few 1e-5; on CUDA fp32 kernel parameters),
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

 * - focus_distance, sensor_distance, focal_length, fstop, blades, blade_rotation, sensor_width, scene_unit_mm,
     fresnel, pupil_sampling, ray_kernel, to_world, film, sampler, shutter_open, shutter_close
   - 
   - As for :ref:`realistic_lens <sensor-realistic_lens>`, so the two sensors are interchangeable in a
     scene.  Manual focusing (``sensor_distance`` / ``focus_distance``) moves the sensor with the same
     model, within the sensor-distance range the model was trained for (a clear error outside it).
     ``fstop`` (any value from the widest up) and ``blades``/``blade_rotation`` work without retraining
     when the model has a stop head: the map was learned wide open and also predicts where each ray
     crosses the stop plane, and that crossing is tested against the requested iris, exactly as the
     tracer tests it (a model without one is fixed at its trained aperture, with a clear error).
     ``fresnel=false`` replaces the learned throughput by 1.  A lens with moving groups (zoom, internal
     focusing) takes ``focal_length`` and ``focus_distance`` as ``realistic_lens`` does, and its model's one camera
     map takes the zoom and focus parameters as inputs beside the ray: any focal length and focus distance the map
     learned renders (a clear error outside them), and changed with ``params.update()`` compiles no kernel after
     the first update (docs/neural_lens.md, "Zoom and internal focusing").

The evaluation order per camera ray: film point and pupil sample (as ``realistic_lens``), then the
ray is moved to the model's input plane, reduced by the lens's rotational and mirror symmetry to
(r, ωx, ωy ≥ 0, λ), the classifier decides whether it is blocked, the regressor gives the exit
position, direction and throughput in the reduced frame, and the reduction is undone.

``mi.traverse`` exposes ``focus_distance`` (scene units), ``sensor_distance`` (mm) and the camera map's
regressor, ``regressor_{i}_weight`` (a tensor (out, in)) and ``regressor_{i}_bias`` per layer ``i``;
``params.update()`` re-derives the focus, and with the ``lens_ad`` integrator renders are differentiable in all of
them (docs/differentiable.md).  Changed regressor weights are read by the kernel through a cooperative-vector
buffer (no recompilation per step).

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
    network_parameters = untraversed()

    # ------------------------------------------------------------------ the regressor's weights (docs/differentiable.md)
    def _network_parameters(self) -> NetworkParameters | None:
        """The camera map's regressor in ``mi.traverse`` (created on first use); None for a baseline ``method``."""
        if self.method != "neural":
            return None
        if self.network_parameters is None:
            self.network_parameters = NetworkParameters(mi, self.model.map("transmit", "backward").regressor)
        return self.network_parameters

    def _traverse_more(self, cb):
        net = self._network_parameters()
        if net is not None:
            net.put(cb)

    def _changed_more(self, keys) -> bool:
        net = self._network_parameters()
        return net is not None and net.changed(keys)

    def fine_tuned_model(self, **record):
        """The model with the camera map's regressor replaced by the current (traversed) weights, recording in
        ``metadata()["fine_tuned"]`` that it no longer is the map of its prescription: the base model file, the
        changed map, ``matches_prescription: false`` and ``record`` (what it was tuned toward, the steps, the loss).
        The lens fingerprint stays, so the model still loads with its lens.  Save it with ``.save(path)``."""
        import copy
        net = self.network_parameters
        if net is None or not net.live:
            raise ModelError(f"{PLUGIN}: the regressor's weights were not changed (mi.traverse: "
                             f"sensor.regressor_<i>_weight/_bias, then params.update()); nothing to save")
        model = copy.copy(self.model)
        tm = model.map("transmit", "backward")
        tuned = dataclasses.replace(tm, regressor=net.numpy_layers(), live_regressor=None, params_pool=None,
                                    training={**tm.training, "fine_tuned": {"matches_prescription": False, **record}})
        model.maps = {**model.maps, tm.key: tuned}
        model.extra = {**model.extra, "fine_tuned": {"from": os.path.basename(self.model_path), "maps": [tm.key],
                                                     "matches_prescription": False, **record}}
        return model

    def _read_properties(self, rd):
        self.lens_prop = rd.string("lens", None)
        self.model_spec = rd.string("model", None)      # None: the lens's bundled model (_default_model)
        self.use_classifier = rd.bool("use_classifier", True)
        self.mlp = rd.string("mlp", "fused", choices=MLP_MODES)
        self.method = rd.string("method", "neural", choices=METHODS)
        self.network_parameters = None

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
        if lens.moving is not None and probe.map("transmit", "backward").domain.conditions is None:
            raise SensorPropertyError(PLUGIN, "model", f"lens '{lens.name}' zooms or focuses by moving groups, and "
                                      f"model {self.model_path}'s camera map does not take the zoom and focus as "
                                      "inputs: train one with `mi-neurallens train`")
        self.model = probe
        tuned = probe.extra.get("fine_tuned")
        if tuned:
            mi.Log(mi.LogLevel.Warn, f"{PLUGIN}: model {self.model_path} was fine-tuned ({', '.join(tuned.get('maps', []))}"
                   f" from {tuned.get('from', '?')}): its map no longer is the one of lens '{lens.name}'s prescription")
        return lens

    def _iris(self, tm):
        """The iris the learned map must test (None: the one it was trained with)."""
        st = self.setup
        trained, want = st.trained_iris, Iris.of_lens(st.lens)
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
        tm = self.model.map("transmit", "backward")
        if tm.domain.conditions is not None:
            tm = self._configured(tm)
        else:
            try:
                self.model.check_sensor_distance(st.sensor_distance_mm)
            except ModelError as e:
                which = "sensor_distance" if not (st.focus_distance_mm > 0) else "focus_distance"
                raise SensorPropertyError(PLUGIN, which, str(e)) from e
        if self.method == "neural":
            net = self.network_parameters
            live = None
            if net is not None and net.live:
                from ..neural.coopvec import LiveNetwork
                live = LiveNetwork(net.layers(), tm.out_scale, tm.out_shift, tm.regressor_activation, mi.Float)
            iris = self._iris(tm)
            if iris is not None and tm.domain.conditions is not None:
                # the stop's radius at this f-number moves with the zoom and focus: a kernel input, not a literal
                iris = dataclasses.replace(iris, radius_mm=dr.opaque(mi.Float, float(iris.radius_mm)))
            return dataclasses.replace(tm, use_classifier=self.use_classifier, mlp=self.mlp, iris=iris,
                                       live_regressor=live)
        # a baseline between the same planes (docs/baselines.md); the map starts on its input
        # plane: the pupil sample only gives the direction
        from ..transport import make_map
        return make_map(st.lens, self.method, "transmit", "backward", z_in=tm.z_in, z_out=tm.z_out,
                        **({"fresnel": st.fresnel} if self.method == "exact" else {}))

    def _configured(self, tm):
        """The camera map of a lens with moving groups at the sensor's configuration
        (:meth:`~mi_neurallens.sensors.common.LensSetup.configured_map`); a configuration outside the learned range
        is a clear error naming the property."""
        from ..errors import NeuralLensError
        try:
            return self.setup.configured_map(tm)
        except NeuralLensError as e:
            which = "focal_length" if str(e).startswith("zoom") else "focus_distance"
            raise SensorPropertyError(PLUGIN, which, f"model {self.model_path}: {e}") from e

    def _margin_scale(self) -> float | None:
        """Logit units per aperture margin of the map's classifier when it was trained on the tracer's margin
        (``target = "margin"``), else None (a label-trained logit is no distance to the rim)."""
        c = getattr(self.tmap, "training", {}).get("classifier", {})
        return float(c.get("margin_scale", 0.0)) or None if c.get("target") == "margin" else None

    def _transport(self, o, d, lam, active):
        """As the base class's; while a lens parameter with gradients enabled is live, the throughput carries the
        classifier's boundary term: :func:`.live.rim_band_factor` of the logit, which a margin-trained classifier
        learned as its margin scale times the tracer's aperture margin (the stop head's iris test, a hard decision
        too, gets none)."""
        if self.method != "neural" or self.live_planes is None or not self.lens_parameters.differentiating():
            return super()._transport(o, d, lam, active)
        scale = self._margin_scale()
        if scale is None or not self.use_classifier:
            return super()._transport(o, d, lam, active)
        res = self.tmap.eval_dr(o, d, lam, active)
        T = res.throughput if self.setup.fresnel else dr.zeros(type(res.throughput), dr.width(res.throughput)) + 1.0
        return res.position, res.direction, T * rim_band_factor(res.logit, scale), res.valid

    def _describe(self):
        iris = getattr(self.tmap, "iris", None)
        tuned = " (fine-tuned: not the prescription's map)" if self.model.extra.get("fine_tuned") else ""
        return (f"model='{self.model_spec}' ({os.path.basename(self.model_path)}){tuned}, lens={self.setup.lens.name}, "
                f"iris={'as trained' if iris is None else iris.describe()}, "
                f"use_classifier={self.use_classifier}, mlp={self.mlp}, method={self.method}")
