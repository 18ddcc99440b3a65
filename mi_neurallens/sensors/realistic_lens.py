"""The ``realistic_lens`` sensor: exact ray tracing through a real lens prescription.

The class derives from the ``mi.Sensor`` of the variant that was set when this module was
(re-)imported; :func:`mi_neurallens.sensors.register` re-imports it per variant and registers it.
"""
from __future__ import annotations

from .base import LensSensorBase
from .common import load_lens
from .live import rim_band_factor
from ..transport.exact import ExactMap

PLUGIN = "realistic_lens"

DOC = r"""
.. _sensor-realistic_lens:

Realistic lens camera (:monosp:`realistic_lens`)
------------------------------------------------

.. pluginparameters::

 * - lens
   - |string|
   - Lens prescription: a file (project JSON, pbrt ``.dat``, Open Optical Designer ``.json``, Zemax
     ``.zmx``, CODE V ``.seq``; relative paths are resolved like other scene files) or the name of a lens in a
     lens library: a bundled lens, or one of ``$MI_NEURALLENS_LENSES`` (``mi-neurallens lens list`` names them).
     (Default: ``wide-22mm``)

 * - focus_distance
   - |float|
   - Distance in scene units from the SENSOR PLANE (the camera origin, like the distance scale of a
     real lens) to the plane in paraxial focus at 587.6 nm.  The whole lens moves (unit focusing), or, for a
     lens whose file gives moving groups (docs/lens-format.md, "Moving groups"), its focusing groups move as the
     prescription says, the sensor stays, and the plane is the real rays' best focus (on axis, whole pupil).  ``inf`` focuses at infinity.  Exclusive with ``sensor_distance``.
     (Default: infinity)

 * - sensor_distance
   - |float|
   - Manual focusing: distance in mm from the last lens vertex to the sensor plane.  Exclusive with
     ``focus_distance``; refused for a lens with moving groups (it focuses by them).  (Default: unset)

 * - focal_length
   - |float|
   - A zoom lens's focal length in mm (its EFL at infinity focus, 587.6 nm): the zoom groups move to it, the
     focusing groups keep ``focus_distance`` on the sensor, and the f-number, pupils and field of view follow.
     Within the range the prescription lists (a clear error outside it); refused for a lens that does not zoom.
     A parameter in ``mi.traverse`` like ``focus_distance``: after a first ``params.update()``, zooming and
     refocusing compile no kernel.  (Default: the prescription's first listed position)

 * - fstop
   - |float|
   - Stop down to this f-number (paraxial, object at infinity: EFL / entrance-pupil diameter).  A value
     smaller than the lens's own f-number is an error that names the widest; one within 0.5 % of it (the
     printed ``2.68`` for f/2.6837) means wide open.  (Default: the lens's widest aperture)

 * - blades
   - |int|
   - Number of straight iris blades: the stop becomes the regular polygon whose inscribed circle is
     the stop's (the f-number is that circle's; the corners, 1/cos(π/n) farther out, must stay in the
     stop's air gap, else an error names the f-number from which they do; 0: circular).  What makes bokeh
     polygonal.  (Default: the lens file's, usually 0)

 * - blade_rotation
   - |float|
   - Rotation of the blades in degrees (normal of the first blade from +x, counter-clockwise seen from
     the sensor).  (Default: the lens file's, usually 0)

 * - sensor_width
   - |float|
   - Sensor width in mm; the height follows from the film's aspect ratio.  (Default: 36)

 * - scene_unit_mm
   - |float|
   - Millimetres per scene unit.  (Default: 1000, i.e. the scene is in metres)

 * - fresnel
   - |bool|
   - Include the Fresnel (and coating) transmittance of every surface.  No bundled lens is coated,
     so with it their images are darker (the 22 mm lens's about half as bright).  (Default: |true|)

 * - pupil_sampling
   - |string|
   - ``exit_pupil``: aim rays at precomputed exit-pupil bounds (continuous in film radius, rotated to
     the film point's azimuth); ``rear_element``: aim them at the whole rear element (slow, for
     reference).  (Default: ``exit_pupil``)

 * - ray_kernel
   - |string|
   - ``inline``: the camera rays are computed inside the integrator's kernel (one kernel a render);
     ``separate``: in a kernel of their own before it (the rays stored, 44 bytes a sample in RGB, 64 in
     spectral variants), so the integrator's kernel does not carry the transport's registers through its
     path loop — the same image; ``auto``: separate on CUDA while a render pass's rays fit 4 GiB, inline
     otherwise and on the CPU.  Set it only to compare the two (render times: docs/performance.md).
     (Default: ``auto``)

 * - to_world
   - |transform|
   - Camera-to-world transform.  The camera origin is the centre of the sensor plane; it looks along
     +z like ``perspective``.  Not differentiable.  (Default: identity)

 * - film, sampler, shutter_open, shutter_close
   - |film|, |sampler|, |float|
   - As for every Mitsuba sensor.  Use a stratified sampler (``ldsampler``, ``multijitter``): each ray
     carries one wavelength.  In RGB variants without a shutter interval the sensor uses a unit shutter
     internally to get a stratified wavelength sample (see below).  ``srf`` is honoured only for a
     lens whose transport does not depend on λ, in spectral variants.

Each camera ray starts at a point of the sensor rectangle, is aimed at a point sampled on the
exit-pupil bound (or the rear element), traced backward through the lens (transmission only) at ONE
wavelength importance-sampled from the CIE curves, and leaves the front of the lens into the scene.

**Radiometry.**  The pixel value is the sensor-plane irradiance divided by π NA'², where
NA' = 1/(2N) and N is the paraxial working f-number of the configured stop at the focus distance:
``I(x) = (1/(π NA'²)) ∫ L(ray(x, ω)) T(x, ω) cosθ dω``.  A uniform environment of radiance 1
therefore renders to relative illumination × Fresnel transmittance: ≈ 1 at the centre for a lens
at f/8 with ``fresnel=false``, darker toward the corners (natural cos⁴ and optical vignetting).
NA' uses the paraxial *working* f-number at the focus distance, so exposure follows neither the
f-stop nor the focus distance (like Mitsuba's ``thinlens``, whose brightness does not change either).

**Spectral.**  Spectral variants put the ray's wavelength on all lanes with weight 1/pdf; RGB variants
weight it by ``xyz_to_srgb(cie1931_xyz(λ))·D65(λ)/pdf(λ)`` so white stays white.  For a lens whose
transport does not depend on λ (constant indices, no coatings) RGB uses weight 1 and spectral uses
Mitsuba's 4 hero wavelengths.

``ptracer`` and other adjoint/projective integrators are not supported (no ``sample_direction``).

**Parameters.**  ``mi.traverse`` exposes, besides ``to_world``, ``focus_distance``, ``sensor_distance`` and the
prescription: ``surface_{i}_curvature`` (1/mm), ``surface_{i}_thickness`` (the gap after surface ``i``, mm; the last
gap is ``sensor_distance``), ``surface_{i}_conic`` and ``surface_{i}_asphere`` (A4, A6, …), ``i`` numbered as in
``mi-neurallens lens info``.  ``params.update()`` re-derives the lens (focus, pupil bounds, normalisation); a
changed parameter becomes a kernel input, differentiable with the ``lens_ad`` integrator
(docs/differentiable.md); an invalid lens is an error that names ``mi_neurallens.project_valid``.

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




class RealisticLens(LensSensorBase):
    __doc__ = DOC
    PLUGIN = PLUGIN

    def _load_lens(self, rd):
        self.lens_spec = rd.string("lens", "wide-22mm")
        return load_lens(self.lens_spec, PLUGIN)

    LENS_PARAMETERS = True

    def _make_map(self, geometry):
        # from the film plane (where the pupil sample starts the ray) to the front of the lens
        if geometry is None:
            return ExactMap(self.setup.lens, "transmit", "backward", self.pupil.z_img, self.z_out,
                            fresnel=self.setup.fresnel)
        from ..trace.tracer import LensTracer
        return ExactMap(self.setup.lens, "transmit", "backward", self.pupil.z_img, self.z_out,
                        tracer=LensTracer(self.setup.lens, self.setup.fresnel, geometry=geometry),
                        numbers=self.live_planes)

    def _transport(self, o, d, lam, active):
        """As the base class's; for a lens being differentiated (a parameter ``params.update()`` changed has
        gradients enabled), traced
        with the aperture margin ``m`` (the smallest of every clear aperture, housing and the stop), and the
        throughput multiplied by :func:`.live.rim_band_factor` of it: the value unchanged, and the derivative of the
        rays within :data:`.live.RIM_BAND` of a rim adds the rims' boundary term (how the set of rays that pass
        changes), ``∫ f δ(m) ∂m/∂θ``, estimated one-sided over the band (bias O(band))."""
        if self.live_planes is None or not self.lens_parameters.differentiating():
            return super()._transport(o, d, lam, active)
        import drjit as dr
        tm = self.tmap
        res = tm.tracer.trace(o, d, lam, tm.spec, tm.direction, z_out=self.live_planes["z_out"], margin=True,
                              active=active)
        T = res.throughput if self.setup.fresnel else dr.zeros(type(res.throughput), dr.width(res.throughput)) + 1.0
        return res.position, res.direction, T * rim_band_factor(res.margin), res.valid

    def _describe(self):
        return f"lens='{self.lens_spec}' ({self.setup.lens.name})"
