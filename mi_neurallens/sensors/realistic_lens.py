"""The ``realistic_lens`` sensor: exact ray tracing through a real lens prescription.

The class is defined by :func:`make_realistic_lens` for the Mitsuba variant that is set when it is
called (a class defined under one variant has the wrong ``mi.Sensor`` base in another), and
registered by :func:`mi_neurallens.sensors.register`.
"""
from __future__ import annotations

import math

PLUGIN = "realistic_lens"

DOC = r"""
.. _sensor-realistic_lens:

Realistic lens camera (:monosp:`realistic_lens`)
------------------------------------------------

.. pluginparameters::

 * - lens
   - |string|
   - Lens prescription: a file (project JSON, pbrt ``.dat``, Open Optical Designer ``.json``; relative
     paths are resolved like other scene files) or the name of a bundled lens (``wide-22mm``,
     ``ood-59mm``, ``canon-ef-24mm-f1.4l``, ``dgauss-50mm``, ``fisheye-10mm``, ``telephoto-250mm``).
     (Default: ``wide-22mm``)

 * - focus_distance
   - |float|
   - Distance in scene units from the SENSOR PLANE (the camera origin, like the distance scale of a
     real lens) to the plane in paraxial focus at 587.6 nm.  The whole lens moves (unit focusing).
     ``inf`` focuses at infinity.  Exclusive with ``sensor_distance``.  (Default: infinity)

 * - sensor_distance
   - |float|
   - Manual focusing: distance in mm from the last lens vertex to the sensor plane.  Exclusive with
     ``focus_distance``.  (Default: unset)

 * - fstop
   - |float|
   - Stop down to this f-number (paraxial, object at infinity: EFL / entrance-pupil diameter).  It
     must not be smaller than the lens's own f-number.  (Default: the lens's widest aperture)

 * - sensor_width
   - |float|
   - Sensor width in mm; the height follows from the film's aspect ratio.  (Default: 36)

 * - scene_unit_mm
   - |float|
   - Millimetres per scene unit.  (Default: 1000, i.e. the scene is in metres)

 * - fresnel
   - |bool|
   - Include the Fresnel (and coating) transmittance of every surface.  (Default: |true|)

 * - pupil_sampling
   - |string|
   - ``exit_pupil``: aim rays at precomputed exit-pupil bounds (continuous in film radius, rotated to
     the film point's azimuth); ``rear_element``: aim them at the whole rear element (slow, for
     reference).  (Default: ``exit_pupil``)

 * - to_world
   - |transform|
   - Camera-to-world transform.  The camera origin is the centre of the sensor plane; it looks along
     +z like ``perspective``.  (Default: identity)

 * - film, sampler, shutter_open, shutter_close
   - |film|, |sampler|, |float|
   - As for every Mitsuba sensor.  Use a stratified sampler (``ldsampler``, ``multijitter``): each ray
     carries one wavelength.  In RGB variants without a shutter interval the sensor uses a unit shutter
     internally to get a stratified wavelength sample (see below).

Each camera ray starts at a point of the sensor rectangle, is aimed at a point sampled on the
exit-pupil bound (or the rear element), traced backward through the lens (transmission only) at ONE
wavelength importance-sampled from the CIE curves, and leaves the front of the lens into the scene.

**Radiometry.**  The pixel value is the sensor-plane irradiance divided by π NA'², where
NA' = 1/(2N) and N is the paraxial f-number (object at infinity) of the configured stop:
``I(x) = (1/(π NA'²)) ∫ L(ray(x, ω)) T(x, ω) cosθ dω``.  A uniform environment of radiance 1
therefore renders to relative illumination × Fresnel transmittance: ≈ 1 at the centre for a lens
at f/8 with ``fresnel=false``, darker toward the corners (natural cos⁴ and optical vignetting).
The normalisation follows the f-stop (exposure is compensated like aperture priority) but not the
focus distance (close focus is darker by the bellows factor, as on a real camera).

**Spectral.**  Spectral variants put the ray's wavelength on all lanes with weight 1/pdf; RGB variants
weight it by ``xyz_to_srgb(cie1931_xyz(λ))·D65(λ)/pdf(λ)`` so white stays white.  For a lens whose
transport does not depend on λ (constant indices, no coatings) RGB uses weight 1 and spectral uses
Mitsuba's 4 hero wavelengths.

``ptracer`` and other adjoint/projective integrators are not supported (no ``sample_direction``).

.. tabs::

    .. code-tab:: xml

        <sensor type="realistic_lens">
            <string name="lens" value="wide-22mm"/>
            <float name="focus_distance" value="2.5"/>
            <float name="fstop" value="4"/>
            <transform name="to_world">
                <lookat origin="0, 1, 5" target="0, 1, 0" up="0, 1, 0"/>
            </transform>
            <sampler type="ldsampler"><integer name="sample_count" value="64"/></sampler>
            <film type="hdrfilm"><integer name="width" value="640"/><integer name="height" value="480"/></film>
        </sensor>

    .. code-tab:: python

        'type': 'realistic_lens',
        'lens': 'wide-22mm',
        'focus_distance': 2.5,
        'fstop': 4.0,
        'to_world': mi.ScalarTransform4f().look_at(origin=[0, 1, 5], target=[0, 1, 0], up=[0, 1, 0]),
        'sampler': {'type': 'ldsampler', 'sample_count': 64},
        'film': {'type': 'hdrfilm', 'width': 640, 'height': 480},
"""


def make_realistic_lens():
    """Define the ``realistic_lens`` class for the CURRENT Mitsuba variant (call after set_variant)."""
    import drjit as dr
    import mitsuba as mi

    from .common import PropertyReader, SensorPropertyError, configure_lens, film_to_sensor, \
        lens_to_camera, load_lens
    from .pupil import EXIT_PUPIL, MODES, PupilBounds
    from .wavelengths import prepare_shutter, sample_wavelength
    from ..trace.tracer import LensTracer

    class RealisticLens(mi.Sensor):
        __doc__ = DOC

        def __init__(self, props):
            rd = PropertyReader(props, PLUGIN)
            lens_spec = rd.string("lens", "wide-22mm")
            focus = rd.float("focus_distance", None, allow_inf=True)
            sdist = rd.float("sensor_distance", None)
            fstop = rd.float("fstop", None)
            width = rd.float("sensor_width", 36.0, positive=True)
            unit = rd.float("scene_unit_mm", 1000.0, positive=True)
            fresnel = rd.bool("fresnel", True)
            mode = rd.string("pupil_sampling", EXIT_PUPIL, choices=MODES)
            if focus is not None and sdist is not None:
                raise SensorPropertyError(PLUGIN, "focus_distance",
                                          "give either 'focus_distance' (scene units from the sensor plane) "
                                          "or 'sensor_distance' (mm behind the last vertex), not both")
            if focus is not None and not focus > 0:
                raise SensorPropertyError(PLUGIN, "focus_distance", f"must be > 0 scene units (or inf), got {focus:g}")
            if sdist is not None and not sdist > 0:
                raise SensorPropertyError(PLUGIN, "sensor_distance",
                                          f"must be > 0 mm behind the last vertex, got {sdist:g}")
            if fstop is not None and not fstop > 0:
                raise SensorPropertyError(PLUGIN, "fstop", f"must be > 0, got {fstop:g}")
            base = load_lens(lens_spec, PLUGIN)
            # wavelength mode needs to know whether λ matters before the base class reads the shutter
            probe = configure_lens(base, fstop=fstop, sensor_distance_mm=base.surfaces[-1].thickness,
                                   fresnel=fresnel)
            lambda_mode = prepare_shutter(mi, props, probe.lambda_dependent)
            super().__init__(props)
            self.lambda_mode = lambda_mode
            size = self.film().size()
            self.setup = configure_lens(
                base, fstop=fstop, sensor_distance_mm=sdist,
                focus_distance_mm=None if focus is None else focus * unit,
                sensor_width_mm=width, film_size=(int(size[0]), int(size[1])), scene_unit_mm=unit,
                fresnel=fresnel, plugin=PLUGIN)
            self.lens_spec = lens_spec
            self.pupil = PupilBounds(self.setup, mode)
            self.tracer = LensTracer(self.setup.lens, fresnel=fresnel)
            first = self.setup.lens.surfaces[0]
            sag = float(first.sag(first.semi_diameter)) if not first.is_stop else 0.0
            self.z_out = min(0.0, sag if math.isfinite(sag) else 0.0)
            self.m_needs_sample_3 = True

        # ------------------------------------------------------------------ rays
        def _trace(self, time, sample1, sample2, sample3, active=True):
            st = self.setup
            lam, wav, wspec, time = sample_wavelength(mi, dr, self, self.lambda_mode, time, sample1,
                                                      sample2, sample3, active)
            fx, fy = film_to_sensor(mi, self, st, sample2)
            X, Y, area = self.pupil.sample(mi, dr, fx, fy, sample3)
            z_img, dzp = self.pupil.z_img, self.pupil.dz
            ex, ey = X - fx, Y - fy
            inv_len = dr.rsqrt(dr.fma(ex, ex, dr.fma(ey, ey, dzp * dzp)))
            d = (ex * inv_len, ey * inv_len, -dzp * inv_len)
            zf = dr.zeros(mi.Float, dr.width(fx)) + z_img
            res = self.tracer.trace((fx, fy, zf), d, lam, "transmit", "backward", z_out=self.z_out,
                                    active=active)
            cos_t = dzp * inv_len
            c2 = cos_t * cos_t
            # cos^4θ · A / Δz² · T / (π NA'²)
            w = c2 * c2 * area * (st.normalisation / (dzp * dzp)) * res.throughput
            valid = res.valid
            w = dr.select(valid, w, 0.0)
            (ox, oy, oz), (dx, dy, dz) = lens_to_camera(st, res.position, res.direction)
            o = mi.Point3f(dr.select(valid, ox, 0.0), dr.select(valid, oy, 0.0), dr.select(valid, oz, 0.0))
            dcam = mi.Vector3f(dr.select(valid, dx, 0.0), dr.select(valid, dy, 0.0), dr.select(valid, dz, 1.0))
            ray = mi.Ray3f(self.m_to_world @ o, dr.normalize(self.m_to_world @ dcam), time,
                           wav if wav is not None else [])
            # invalid rays: weight 0 and a zero-length segment so integrators stop at once
            ray.maxt = dr.select(valid, ray.maxt, 0.0)
            weight = wspec * w if not isinstance(wspec, float) else mi.Spectrum(w)
            return ray, weight

        def sample_ray(self, time, sample1, sample2, sample3, active=True):
            return self._trace(time, sample1, sample2, sample3, active)

        def sample_ray_differential(self, time, sample1, sample2, sample3, active=True):
            ray, w = self._trace(time, sample1, sample2, sample3, active)
            rd = mi.RayDifferential3f(ray)
            rd.has_differentials = False
            return rd, w

        # ------------------------------------------------------------------ unsupported
        def _unsupported(self, what):
            raise NotImplementedError(
                f"{PLUGIN}: {what} is not supported: this sensor only generates camera rays (backward "
                "tracing), so integrators that connect to the camera from the scene (ptracer, "
                "prb_projective, direct_projective) cannot use it; use path, volpath, direct, aov, prb")

        def sample_direction(self, it, sample, active=True):
            self._unsupported("sample_direction")

        def pdf_direction(self, it, ds, active=True):
            self._unsupported("pdf_direction")

        def eval_direction(self, it, ds, active=True):
            self._unsupported("eval_direction")

        def sample_position(self, time, sample, active=True):
            self._unsupported("sample_position")

        def pdf_position(self, ps, active=True):
            self._unsupported("pdf_position")

        def eval(self, si, active=True):
            self._unsupported("eval")

        # ------------------------------------------------------------------ misc
        def bbox(self):
            """World-space box around the sensor and the lens body."""
            L = self.setup.lens
            k = 1.0 / self.setup.scene_unit_mm
            rmax = max(max(s.semi_diameter for s in L.surfaces), 0.5 * math.hypot(
                self.setup.sensor_width_mm, self.setup.sensor_height_mm)) * k
            zmax = (self.setup.image_z - self.z_out) * k
            m = self.m_to_world.matrix.numpy()
            M = mi.ScalarTransform4f(m[..., 0] if m.ndim == 3 else m)
            box = mi.ScalarBoundingBox3f()
            for x in (-rmax, rmax):
                for y in (-rmax, rmax):
                    for z in (0.0, zmax):
                        box.expand(M @ mi.ScalarPoint3f(x, y, z))
            return box

        def traverse(self, cb):
            cb.put("to_world", self.m_to_world, mi.ParamFlags.NonDifferentiable)

        def parameters_changed(self, keys=[]):
            pass

        def to_string(self):
            st = self.setup
            fd = st.focus_distance_mm / st.scene_unit_mm
            return (f"RealisticLens[lens='{self.lens_spec}' ({st.lens.name}), f/{st.fnumber:.3g} "
                    f"(widest f/{st.max_fnumber:.3g}), focus_distance={fd:g} (sensor_distance="
                    f"{st.sensor_distance_mm:.4f} mm), sensor {st.sensor_width_mm:g}x{st.sensor_height_mm:.4g} mm, "
                    f"scene_unit_mm={st.scene_unit_mm:g}, fresnel={st.fresnel}, "
                    f"pupil_sampling={self.pupil.mode}, film={self.film().size()}]")

    RealisticLens.__name__ = "RealisticLens"
    return RealisticLens
