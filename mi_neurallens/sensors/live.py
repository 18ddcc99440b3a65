"""A lens sensor's parameters in ``mi.traverse``, and what a change to them re-derives (``params.update()``).

:class:`SensorParameters` holds the Dr.Jit arrays (width 1) the sensor puts into Mitsuba's traversal —
``focus_distance`` (scene units from the sensor plane), ``sensor_distance`` (mm behind the last vertex),
``focal_length`` (mm, a zoom lens's: its groups move to it, :mod:`mi_neurallens.optics.moving`) and,
for ``realistic_lens``, the prescription (:mod:`mi_neurallens.trace.parameters`: ``surface_{i}_curvature``,
``_thickness``, ``_conic``, ``_asphere``) — and turns a change into a new configured lens.

A parameter becomes *live* the first time it changes: from then on it is a kernel input (the render's kernel
no longer changes with its value; the first update compiles once more, later ones reuse that kernel) and,
where its array has gradients enabled, the render is differentiable in it.  Untouched parameters stay
literals, so a primal render of an untouched sensor is the one of a freshly loaded scene.

What a change re-derives, in float64 from the detached values: the configured lens (the sensor distance that
focuses ``focus_distance`` paraxially, the stop for ``fstop``), the vertex positions, the pupil bounds and the
radiometric normalisation 1/(π NA'²).  Two of those enter the render with derivatives: the sensor plane (the
vertex positions are attached to the thicknesses and the sensor distance) and the normalisation; where they
are functions of other parameters (the sensor distance solved for ``focus_distance``, the normalisation of the
working f-number), their derivatives are central differences of those float64 functions, attached as
``value + Σ_p ∂f/∂p · (p − detach(p))`` (:func:`attach`).

Camera rays keep their direction when the sensor distance changes (the film point moves along z, the pupil
sample with it), so the rays that pass the stop still pass it: the stop's rim contributes no boundary term for
``sensor_distance`` and ``focus_distance``.  Parameters of the surfaces behind the stop move the stop's image,
and every surface's clear aperture vignettes some rays: those rims are discontinuities the gradient does not
see (docs/differentiable.md measures what they add).
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import LensError, NeuralLensError
from ..optics.prescription import surfaces_cross
from ..trace import parameters as lp

FOCUS, SENSOR, FOCAL = "focus_distance", "sensor_distance", "focal_length"
#: a lens being differentiated: the width, in aperture margin (1 − r²/R², :attr:`TraceResult.margin`), of the band
#: inside the rims whose rays carry the rims' boundary term (``realistic_lens``: the tracer's margin; ``neural_lens``: the classifier's logit over its margin scale).  0.003 (0.15 % of a
#: rim's radius): on dgauss-50mm's front curvature the band estimate was −1.77 ± 0.35 against central differences'
#: −1.76 ± 0.58; a band of 0.01 gave −1.46, 0.03 gave −1.55 (the one-sided band's bias grows with its width)
RIM_BAND = 0.003


def rim_band_factor(margin, per_unit: float = 1.0):
    """``1 + s − detach(s)``, ``s = clip(margin / (per_unit · RIM_BAND), 0, 1)``: a throughput times it keeps its
    value, and its derivative gains the rims' boundary term ``∫ f δ(m) ∂m/∂θ`` from the rays within :data:`RIM_BAND`
    of a rim (one-sided, bias O(band)).  ``margin``: a Dr.Jit array that is 0 on the rims and grows inward, in units
    of ``per_unit`` aperture margins (the tracer's margin: 1; a margin-trained classifier's logit: its margin
    scale)."""
    import drjit as dr
    s = dr.clip(margin * (1.0 / (per_unit * RIM_BAND)), 0.0, 1.0)
    return 1.0 + (s - dr.detach(s))


#: the numbers a configured lens derives from its parameters that enter the render with derivatives
DERIVED = (SENSOR, "normalisation", "exit_pupil_z", "exit_pupil_radius", "stop_radius", "efl")


def _derived_numbers(setup) -> tuple:
    """:data:`DERIVED` of a configured lens (mm; 1/(π NA'²); lens-space z, mm; mm; the stop's radius for the
    sensor's ``fstop``, mm; the paraxial effective focal length at 587.6 nm, mm)."""
    from .common import PARAXIAL_WAVELENGTH_NM
    px = setup.lens.paraxial(PARAXIAL_WAVELENGTH_NM)
    return (setup.sensor_distance_mm, setup.normalisation, float(px.exit_pupil_z), float(px.exit_pupil_radius),
            float(setup.lens.stop.semi_diameter), float(px.efl))


def _fd_step(lens, key: str, value: float) -> float:
    """Central-difference step of one parameter: a change of about 1e-6 mm at the surface's rim (curvature,
    conic and aspheric coefficients), 1e-5 mm for gaps and the sensor distance, 1e-6 relative for the focus."""
    if key == FOCUS:
        return 1e-6 * max(abs(value), 1.0)
    if key == SENSOR:
        return 1e-5
    i, kind = lp.parse(key)
    sd = float(lens.surfaces[i].semi_diameter)
    if kind == lp.CURVATURE:
        return 2e-6 / (sd * sd)
    if kind == lp.CONIC:
        return 1e-4
    return 1e-5


def attach(value: float, grads: dict, live: dict, float_type):
    """``value`` (a float64 number) as an opaque ``float_type`` array, plus ``Σ g · (p − detach(p))`` over the
    ``grads`` (name → ∂value/∂p, a float or per-coefficient array) of the ``live`` parameters with gradients
    enabled: the value unchanged, the derivative attached."""
    import drjit as dr
    out = dr.opaque(float_type, float(value))
    for key, g in grads.items():
        p = live[key]
        if np.ndim(g) == 0:
            # the derivative an opaque number too: a literal would change the kernel at every step
            out = out + dr.opaque(float_type, float(g)) * (p - dr.detach(p))
        else:
            out = out + dr.sum(float_type(np.asarray(g, np.float64)) * (p - dr.detach(p)))
    return out


class SensorParameters:
    """The parameters of one lens sensor (see the module docstring).

    ``base``: the lens as loaded; ``configure``: ``f(lens, focus_mm or None, sensor_distance_mm or None,
    focal_length_mm=the loaded one) → LensSetup`` (the sensor's :func:`~mi_neurallens.sensors.common.configure_lens`
    with its other properties bound); ``setup``: the configured lens of the loaded scene; ``lens_params``: whether
    the prescription is exposed (``realistic_lens``) or only the focus and a zoom lens's focal length
    (``neural_lens``); ``focus_driven``: whether the scene gave ``focus_distance`` (the sensor distance follows it)
    rather than ``sensor_distance``."""

    def __init__(self, mi, base, setup, configure, *, lens_params: bool, focus_driven: bool, plugin: str):
        self.mi, self.base, self.configure, self.plugin = mi, base, configure, plugin
        self.focus_driven = focus_driven
        self.unit = setup.scene_unit_mm
        F = mi.Float
        self.values = {FOCUS: F(setup.focus_distance_mm / self.unit), SENSOR: F(setup.sensor_distance_mm)}
        self.keys = [FOCUS, SENSOR]
        moving = getattr(base, "moving", None)
        if moving is not None and moving.is_zoom:        # a zoom lens: zooming is a parameter change too
            self.values[FOCAL] = F(setup.focal_length_mm)
            self.keys.append(FOCAL)
        if lens_params:
            for key in lp.parameter_names(base):
                v = lp.value_of(base, key)
                self.values[key] = F(v) if not isinstance(v, tuple) else F(list(v))
                self.keys.append(key)
        #: the parameters that have changed since the scene loaded: kernel inputs from then on
        self.live: set = set()
        self.derived: dict = {}

    # ------------------------------------------------------------------ traversal
    def put(self, cb):
        """Hand every parameter to Mitsuba's traversal ``cb`` (differentiable)."""
        for key in self.keys:
            cb.put(key, self.values[key], self.mi.ParamFlags.Differentiable)

    # ------------------------------------------------------------------ update
    def _numbers(self, key):
        import drjit as dr
        a = np.asarray(dr.detach(self.values[key]).numpy(), np.float64)
        return tuple(float(x) for x in a) if lp.parse(key) and lp.parse(key)[1] == lp.ASPHERE else float(a[0])

    def _setup_of(self, numbers: dict, focus_driven: bool):
        """The configured lens of parameter ``numbers`` (name → float or tuple); a parameter set that is not a lens
        is a :class:`NeuralLensError` that says how to get back into the valid region."""
        # the changed parameters only: the others keep the lens file's float64 values (``values`` holds float32)
        lens_values = {k: v for k, v in numbers.items() if lp.parse(k) and k in self.live}
        try:
            lens = lp.lens_with(self.base, lens_values) if lens_values else self.base
        except LensError as e:
            raise NeuralLensError(
                f"{self.plugin}: the updated parameters do not describe a lens: {e}.  "
                "mi_neurallens.project_valid(params, 'sensor') moves them back into the valid region") from e
        # the focal length as loaded (float64, where float32 could round it out of the lens's range) until it changes
        kw = {"focal_length_mm": numbers[FOCAL]} if FOCAL in self.live else {}
        if focus_driven:
            return self.configure(lens, numbers[FOCUS] * self.unit, None, **kw)
        return self.configure(lens, None, numbers[SENSOR], **kw)

    def changed(self, keys) -> bool:
        """Note which of ``keys`` (the names ``parameters_changed`` got) are ours; True when any is."""
        ours = [k for k in keys if k in self.values]
        if not ours:
            return False
        if FOCUS in ours and SENSOR in ours:
            raise NeuralLensError(f"{self.plugin}: 'focus_distance' and 'sensor_distance' were both changed: the "
                                  "one decides the other (unit focusing); change one of them")
        if FOCUS in ours:
            self.focus_driven = True
        elif SENSOR in ours:
            self.focus_driven = False
        self.live.update(ours)
        return True

    def derive(self):
        """The configured lens of the current values and its attached numbers: ``(setup, live, derived)`` —
        ``live`` the kernel-input arrays by name (``sensor_distance`` the attached one), ``derived`` a dict of
        Dr.Jit arrays: ``sensor_distance`` (mm), ``normalisation`` (1/(π NA'²)), ``exit_pupil_z`` (lens space,
        mm) and ``exit_pupil_radius`` (mm), the paraxial exit pupil at 587.6 nm, ``stop_radius`` (mm: with
        ``fstop``, the stop follows the lens's f-number) and ``efl`` (mm).  Kept as :attr:`derived`: a loss may
        use them (a lens design holds its focal length with ``derived["efl"]``)."""
        import drjit as dr
        F = self.mi.Float
        numbers = {k: self._numbers(k) for k in self.keys}
        setup = self._setup_of(numbers, self.focus_driven)
        live = {k: self.values[k] for k in self.live if k not in (FOCUS, SENSOR, FOCAL)}
        diff = [k for k in self.live if dr.grad_enabled(self.values[k])]
        if diff and getattr(self.base, "moving", None) is not None:
            raise NeuralLensError(
                f"{self.plugin}: lens '{self.base.name}' zooms or focuses by moving groups, whose motion (solved for "
                f"the focus and the focal length) is not differentiated: gradients with respect to {', '.join(diff)} "
                "would miss it.  Change the parameters without gradients, or differentiate a fixed configuration "
                "(`mi-neurallens lens convert LENS OUT.json --focal-length F --focus-distance D`)")
        driver = FOCUS if self.focus_driven else SENSOR
        # the derived numbers' derivatives: central differences of the float64 set-up
        grads = {n: {} for n in DERIVED}
        for key in diff:
            if key == (SENSOR if self.focus_driven else FOCUS):
                continue                        # the driven one: its value is derived, not an input
            v = numbers[key]
            arr = np.atleast_1d(np.asarray(v, np.float64))
            for j in range(arr.size):
                h = _fd_step(self.base, key, arr[j]) if lp.parse(key) is None or lp.parse(key)[1] != lp.ASPHERE \
                    else 1e-6 / float(self.base.surfaces[lp.parse(key)[0]].semi_diameter) ** (4 + 2 * j)
                res = []
                for sgn in (1.0, -1.0):
                    a = arr.copy()
                    a[j] += sgn * h
                    trial = dict(numbers)
                    trial[key] = tuple(a) if isinstance(v, tuple) else float(a[0])
                    res.append(_derived_numbers(self._setup_of(trial, self.focus_driven)))
                for name_, r in zip(DERIVED, np.array(res).T):
                    grads[name_].setdefault(key, np.zeros(arr.size))[j] = (r[0] - r[1]) / (2 * h)
        for name_ in DERIVED:
            grads[name_] = {k: (g if isinstance(numbers[k], tuple) else g[0]) for k, g in grads[name_].items()}
        if driver == SENSOR:
            grads[SENSOR] = {SENSOR: 1.0} if SENSOR in diff else {}
        values = dict(zip(DERIVED, _derived_numbers(setup)))
        derived = {n: attach(values[n], grads[n], self.values, F) for n in DERIVED}
        live[SENSOR] = derived[SENSOR]
        #: the configured lens's derived numbers as attached Dr.Jit arrays (see :meth:`derive`), after an update
        self.derived = derived
        return setup, live, derived

    def differentiating(self) -> bool:
        """Whether a live parameter has gradients enabled."""
        import drjit as dr
        return any(dr.grad_enabled(self.values[k]) for k in self.live)

    def numbers(self) -> dict:
        """The current values as Python numbers (name → float, or a tuple for ``asphere``)."""
        return {k: self._numbers(k) for k in self.keys}


#: how far inside the valid region :func:`project_values` puts a value it moves: a rim at most this fraction
#: of the sphere's largest semi-diameter, and surfaces at least this far apart (mm)
RIM_FRACTION = 0.995
MIN_GAP_MM = 1e-3


def project_values(lens, values: dict) -> dict:
    """The nearest valid parameter set to ``values`` (name → value) on ``lens``, by simple moves: a curvature
    whose sphere is smaller than the surface's clear semi-diameter is reduced until the rim lies at
    :data:`RIM_FRACTION` of the largest semi-diameter; a gap that is not positive becomes :data:`MIN_GAP_MM`;
    surfaces that cross within their semi-diameters are moved apart (the gap before the later one grows by the
    depth of the crossing plus :data:`MIN_GAP_MM`).  Returns the corrected values (the same keys); a parameter
    set that is already valid comes back unchanged."""
    out = dict(values)
    for key, v in values.items():
        i, kind = lp.parse(key)
        if kind == lp.THICKNESS and not float(v) > 0.0:
            out[key] = MIN_GAP_MM
    # the rim: |c| · sd · sqrt(1 + K) ≤ RIM_FRACTION
    trial = lp.replaced_surfaces(lens, out)
    for key in list(out):
        i, kind = lp.parse(key)
        if kind in (lp.CURVATURE, lp.CONIC):
            s = trial[i]
            c, k = float(s.curvature), float(s.conic)
            if c != 0.0 and 1.0 + k > 0.0:
                cmax = RIM_FRACTION / (s.semi_diameter * math.sqrt(1.0 + k))
                if abs(c) > cmax:
                    out.setdefault(lp.name(i, lp.CURVATURE), c)
                    out[lp.name(i, lp.CURVATURE)] = math.copysign(cmax, c)
                    trial = lp.replaced_surfaces(lens, out)
    # crossings: grow the gap before the later surface
    for _ in range(len(lens.surfaces)):
        trial = lp.replaced_surfaces(lens, out)
        z = np.concatenate([[0.0], np.cumsum([s.thickness for s in trial[:-1]])])
        moved = False
        for i in range(len(trial) - 1):
            hit = surfaces_cross(trial[i], z[i], trial[i + 1], z[i + 1])
            if hit is not None:
                key = lp.name(i, lp.THICKNESS)
                out[key] = float(trial[i].thickness) + hit[1] + MIN_GAP_MM
                moved = True
                break
        if not moved:
            break
    lp.lens_with(lens, out)           # raises if a move could not repair it
    return out


def project_valid(params, sensor: str = "sensor", opt=None) -> dict:
    """Move the prescription parameters of the ``realistic_lens`` under key ``sensor`` in ``params`` (a
    ``mi.SceneParameters``) back into the valid region (:func:`project_values`):
    curvatures whose sphere is smaller than the clear aperture, gaps that are not positive, surfaces that cross.
    Writes the corrected values into ``params`` (without ``update()``) and, for the keys an optimiser ``opt``
    (``mi.ad.Optimizer``) holds, into ``opt`` too (its state for them restarts); returns the names it changed."""
    import drjit as dr
    prefix = sensor + "."
    node = None
    for k in params.keys():
        if k.startswith(prefix) and lp.parse(k) is not None:
            node = params.properties[k][2]
            break
    if node is None:
        raise NeuralLensError(f"no prescription parameters under '{sensor}.' (a realistic_lens loaded with key "
                              f"'{sensor}'?)")
    sp = node.lens_parameters
    numbers = {k: v for k, v in sp.numbers().items() if lp.parse(k)}
    fixed = project_values(sp.base, numbers)
    changed = {}
    for k, v in fixed.items():
        if v != numbers[k]:
            arr = params[prefix + k]
            new = type(arr)(list(v) if isinstance(v, tuple) else v)
            if dr.grad_enabled(arr):
                dr.enable_grad(new)
            params[prefix + k] = new
            if opt is not None and prefix + k in opt.keys():
                opt[prefix + k] = type(arr)(list(v) if isinstance(v, tuple) else v)
            changed[k] = v
    return changed



def regressor_names(n_layers: int) -> list:
    """The ``mi.traverse`` names of a learned camera map's regressor (``neural_lens``), layer ``i`` as in the model
    file (``backward.0.regressor.{i}.weight``/``.bias``): ``regressor_{i}_weight`` (a tensor (out, in)) and
    ``regressor_{i}_bias`` (out)."""
    return [f"regressor_{i}_{part}" for i in range(n_layers) for part in ("weight", "bias")]


class NetworkParameters:
    """The regressor of ``neural_lens``'s camera map in ``mi.traverse``: its layers ``(W, b)`` (the model file's,
    before the output transform ``shift + scale·y``) as ``TensorXf`` (out, in) and ``Float`` (out), float32.

    Like the lens parameters, the weights become kernel inputs the first time one changes (:attr:`live`): the
    regressor is then evaluated as a :class:`~mi_neurallens.neural.coopvec.LiveNetwork` packed from these arrays at
    each ``params.update()``, differentiable in them where they have gradients enabled (the classifier's decision
    does not depend on them, so there is no boundary term)."""

    def __init__(self, mi, layers):
        from ..jit import from_numpy
        self.mi = mi
        self.n_layers = len(layers)
        self.values = {}
        for (W, b), (kw, kb) in zip(layers, zip(*[iter(regressor_names(len(layers)))] * 2)):
            W = np.asarray(W, np.float32)
            self.values[kw] = mi.TensorXf(from_numpy(mi.Float, W), W.shape)
            self.values[kb] = from_numpy(mi.Float, np.asarray(b, np.float32))
        #: whether a weight has changed since the scene loaded (the regressor then reads :attr:`values`)
        self.live = False

    def put(self, cb):
        for key, v in self.values.items():
            cb.put(key, v, self.mi.ParamFlags.Differentiable)

    def changed(self, keys) -> bool:
        """Note a change among ``keys`` (the names ``parameters_changed`` got); True when one is ours."""
        if any(k in self.values for k in keys):
            self.live = True
            return True
        return False

    def layers(self) -> list:
        """``[(W, b), ...]``: the current Dr.Jit arrays (attached where gradients are enabled)."""
        names = regressor_names(self.n_layers)
        return [(self.values[names[2 * i]], self.values[names[2 * i + 1]]) for i in range(self.n_layers)]

    def numpy_layers(self) -> list:
        """The current layers as float64 numpy arrays ``[(W (out, in), b (out,)), ...]``."""
        import drjit as dr
        out = []
        for W, b in self.layers():
            out.append((np.asarray(dr.detach(W).numpy(), np.float64).reshape(W.shape),
                        np.asarray(dr.detach(b).numpy(), np.float64)))
        return out
