"""The sensor class both lens sensors derive from: everything but the lens transport itself.

:class:`LensSensorBase` is a ``mi.Sensor`` subclass of the Mitsuba variant that was set when this
module was (re-)imported (:func:`mi_neurallens.sensors.register` re-imports it per variant, as
Mitsuba's own Python plugins are); it reads the shared properties (``lens``, ``focus_distance`` XOR
``sensor_distance``, ``fstop``, ``blades``, ``blade_rotation``, ``sensor_width``, ``scene_unit_mm``, ``fresnel``,
``pupil_sampling``, ``ray_kernel``), focuses and stops down the lens (:func:`.common.configure_lens`), samples a film
point, a point on the exit-pupil bound (:class:`.pupil.PupilBounds`) and one wavelength
(:mod:`.wavelengths`), and turns the lens-space ray that leaves the front of the lens into a world
ray with the radiometric weight ``cos⁴θ · A / Δz² · T / (π NA'²)`` (see the ``realistic_lens`` docs).

A subclass provides the transport (sensor → object space) by overriding:

* ``_load_lens(rd)`` → the prescription as loaded (before stop/focus),
* ``_make_map(geometry)`` → the backward transmit :class:`~mi_neurallens.transport.base.TransportMap` of the
  configured lens (``self.setup``, ``self.pupil``); camera rays start on the film plane and leave on the map's
  output plane, which becomes ``self.z_out``.  ``geometry`` is None when the scene loads, and a
  :class:`~mi_neurallens.trace.parameters.LiveGeometry` after ``params.update()`` changed a parameter (the
  planes ``self.live_planes`` then give are Dr.Jit arrays),
* ``_describe()`` → extra text for ``to_string``.

``mi.traverse`` exposes ``to_world``, the focus distance, the sensor distance, a zoom lens's focal length and,
for a sensor with ``LENS_PARAMETERS`` (``realistic_lens``), the prescription (:mod:`.live`); ``params.update()``
re-derives the configured lens.  A subclass may add parameters of its own (``_traverse_more``, ``_changed_more``:
the learned map's regressor weights of ``neural_lens``).
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from ..constants import FULL_FRAME_MM
from ..jit import untraversed
from .common import PropertyReader, SensorPropertyError, configure_lens, film_to_sensor, lens_to_camera
from .live import SensorParameters
from .pupil import EXIT_PUPIL, MODES, PupilBounds
from .wavelengths import prepare_shutter, sample_wavelength

#: where the camera rays are computed: inside the integrator's kernel, or in a kernel of their own
AUTO, INLINE, SEPARATE = "auto", "inline", "separate"
RAY_KERNELS = (AUTO, INLINE, SEPARATE)
#: a lens being differentiated (a live parameter with gradients enabled) keeps its pupil bounds (in exit-pupil
#: space, :meth:`LensSensorBase._film_rays`) while its paraxial exit pupil's radius and distance from the film and
#: the stop's radius stay within this fraction of those the bounds were traced for, so that small steps (and
#: finite differences) see the same samples; the bounds are traced with :data:`LIVE_PUPIL_MARGIN` more room than
#: a loaded lens's, for what the steps move
LIVE_PUPIL_TOLERANCE = 0.02
LIVE_PUPIL_MARGIN = 1.05

#: ``auto``'s cap on the stored rays of one render pass (bytes): above it the rays stay inline, whose
#: wavefront stores nothing (a 1280×960, 64 spp RGB pass stores 78.6 M × 44 B = 3.5 GB)
SEPARATE_MAX_BYTES = 4 << 30


def ray_kernel_for(mode: str, cuda: bool, samples: int, floats_per_sample: int) -> str:
    """``inline`` or ``separate`` for a render pass of ``samples`` camera rays, each stored (if separate) as
    ``floats_per_sample`` 32-bit numbers.  ``auto``: separate on CUDA while the stored rays fit
    :data:`SEPARATE_MAX_BYTES`, inline otherwise and on the CPU: on a GPU the path tracer's kernel then does not
    carry the lens transport's registers through its loop, and on a CPU the two render alike while inline stores
    nothing (render times with both: docs/performance.md, "On a GPU")."""
    if mode != AUTO:
        return mode
    return SEPARATE if cuda and samples * floats_per_sample * 4 <= SEPARATE_MAX_BYTES else INLINE


class LensSensorBase(mi.Sensor):
    PLUGIN = "lens_sensor"
    # the lens, its set-up and its transport map are Python data, not kernel inputs: kept out of Dr.Jit's
    # traversal of the scene (mi_neurallens.jit.untraversed)
    setup = untraversed()
    pupil = untraversed()
    tmap = untraversed()
    lens_parameters = untraversed()
    #: whether ``mi.traverse`` exposes the prescription (differentiable) besides the focus and sensor distance
    LENS_PARAMETERS = False

    def __init__(self, props):
        plugin = self.PLUGIN
        rd = PropertyReader(props, plugin)
        self._read_properties(rd)
        focus = rd.float("focus_distance", None, allow_inf=True)
        sdist = rd.float("sensor_distance", None)
        focal = rd.float("focal_length", None, positive=True)
        fstop = rd.float("fstop", None)
        blades = rd.int("blades", None)
        rotation = rd.float("blade_rotation", None)
        width = rd.float("sensor_width", FULL_FRAME_MM[0], positive=True)
        unit = rd.float("scene_unit_mm", 1000.0, positive=True)
        fresnel = rd.bool("fresnel", True)
        mode = rd.string("pupil_sampling", EXIT_PUPIL, choices=MODES)
        #: ``separate``: the camera rays are evaluated (``dr.eval``) before the integrator's kernel is recorded;
        #: ``auto``: per render pass, :func:`ray_kernel_for`
        self.ray_kernel = rd.string("ray_kernel", AUTO, choices=RAY_KERNELS)
        if focus is not None and sdist is not None:
            raise SensorPropertyError(plugin, "focus_distance",
                                      "give either 'focus_distance' (scene units from the sensor plane) "
                                      "or 'sensor_distance' (mm behind the last vertex), not both")
        if focus is not None and not focus > 0:
            raise SensorPropertyError(plugin, "focus_distance",
                                      f"must be > 0 scene units (or inf), got {focus:g}")
        if sdist is not None and not sdist > 0:
            raise SensorPropertyError(plugin, "sensor_distance",
                                      f"must be > 0 mm behind the last vertex, got {sdist:g}")
        if fstop is not None and not fstop > 0:
            raise SensorPropertyError(plugin, "fstop", f"must be > 0, got {fstop:g}")
        base = self._load_lens(rd)
        # the wavelength mode must be known before the base class reads the shutter
        probe = configure_lens(base, fstop=fstop, blades=blades, blade_rotation_deg=rotation, fresnel=fresnel,
                               plugin=plugin, focal_length_mm=focal,
                               sensor_distance_mm=base.surfaces[-1].thickness if base.moving is None else None)
        lambda_mode = prepare_shutter(mi, props, self._lambda_dependent(probe))
        super().__init__(props)
        self.lambda_mode = lambda_mode
        size = self.film().size()

        def configure(lens, focus_mm, sensor_distance_mm, focal_length_mm=focal):
            return configure_lens(
                lens, fstop=fstop, blades=blades, blade_rotation_deg=rotation, sensor_distance_mm=sensor_distance_mm,
                focus_distance_mm=focus_mm, sensor_width_mm=width, film_size=(int(size[0]), int(size[1])),
                scene_unit_mm=unit, fresnel=fresnel, plugin=plugin, focal_length_mm=focal_length_mm)
        self.setup = configure(base, None if focus is None else focus * unit, sdist)
        self.pupil = PupilBounds(self.setup, mode)
        self.lens_parameters = SensorParameters(mi, base, self.setup, configure, lens_params=self.LENS_PARAMETERS,
                                                focus_driven=sdist is None, plugin=plugin)
        self._pupil_ref = None
        self._live = None
        self._set_planes(None)
        self.tmap = self._make_map(None)
        self.z_out = self.tmap.z_out
        self.m_needs_sample_3 = True

    def _front_plane(self) -> float:
        """The lens-space plane where rays leave the lens: in front of the whole first surface (mm)."""
        first = self.setup.lens.surfaces[0]
        sag = float(first.sag(first.semi_diameter)) if not first.is_stop else 0.0
        return min(0.0, sag if math.isfinite(sag) else 0.0)

    def _set_planes(self, live):
        """The numbers the camera rays are made of: the sensor plane ``z_img`` (lens space, mm; the rays' origin),
        the pupil table's plane distance ``dz`` (mm), the normalisation 1/(π NA'²), the front plane ``z_out``, and
        (``_aim``) where pupil samples are aimed.  ``live`` None: Python floats (literals), the rays aimed at the
        table's points; else ``(geometry, derived)`` (:meth:`.live.SensorParameters.derive`): the sensor plane and
        normalisation attached (Dr.Jit), and the samples carried to the paraxial exit pupil (:meth:`_film_rays`)."""
        self.z_out = self._front_plane()
        if live is None:
            self.live_planes = None
            self._z_img, self._dz, self._norm = self.pupil.z_img, self.pupil.dz, self.setup.normalisation
            self._aim, self._live = None, None
            return
        geometry, derived = live
        F = mi.Float
        z_xp, r_xp = derived["exit_pupil_z"], derived["exit_pupil_radius"]
        z_xp0, r_xp0 = float(dr.detach(z_xp).numpy()[0]), float(dr.detach(r_xp).numpy()[0])
        ref = self._pupil_ref
        gap = self.setup.image_z - z_xp0
        differentiating = self.lens_parameters.differentiating()
        if not differentiating or ref is None or not all(abs(a - b) <= LIVE_PUPIL_TOLERANCE * abs(c) for a, b, c in (
                (r_xp0, ref[1], ref[1]), (gap, ref[2], ref[2]), (self.setup.lens.stop.semi_diameter, ref[3], ref[3]))):
            # new bounds, traced with opaque numbers (no new kernel): on every primal update (the image is then the
            # one of loading the changed lens), and while differentiating when the exit pupil moved
            self.pupil = PupilBounds(self.setup, self.pupil.mode, opaque=True,
                                     margin=LIVE_PUPIL_MARGIN if differentiating else 1.01)
            self._pupil_ref = (z_xp0, r_xp0, gap, self.setup.lens.stop.semi_diameter)
        _, r_ref, gap_ref, _ = self._pupil_ref
        self._z_img, self._dz, self._norm = geometry.image_z, dr.opaque(F, self.pupil.dz), derived["normalisation"]
        #: the live geometry: the attached numbers are read per ray through it (:meth:`_ray_numbers`)
        self._live = geometry
        geometry.extra.update({"normalisation": self._norm, "exit_pupil_z": z_xp,
                               "exit_pupil_scale": r_xp * dr.opaque(F, 1.0 / r_ref)})
        if math.isfinite(gap_ref) and abs(gap_ref) > 1e-3 and math.isfinite(r_ref) and r_ref > 0:
            #: (k0, scale, gap): the table's point P carried along the ray from its film point to the exit pupil's
            #: plane as the table was built (k0, opaque), scaled with the exit pupil since then (attached), and the
            #: film to exit-pupil distance (attached)
            self._aim = (dr.opaque(F, gap_ref / self.pupil.dz), geometry.extra["exit_pupil_scale"],
                         self._z_img - z_xp)
        else:
            self._aim = None            # an exit pupil at infinity (or on the film): aim at the table's points
        #: the planes of the map as kernel inputs: the film (attached) and the front plane
        self.live_planes = {"z_in": self._z_img, "z_out": dr.opaque(F, self.z_out)}

    # ------------------------------------------------------------------ hooks
    def _read_properties(self, rd):
        """Read the plugin's own properties (before the shared ones)."""

    def _load_lens(self, rd):
        raise NotImplementedError

    def _lambda_dependent(self, setup) -> bool:
        return setup.lambda_dependent

    def _make_map(self, geometry):
        raise NotImplementedError

    def _ray_numbers(self, n: int):
        """``(z_img, normalisation, aim)`` for ``n`` camera rays (see :meth:`_set_planes`): the literals of a loaded
        lens, or a live lens's attached numbers read per ray from its packed array
        (:class:`~mi_neurallens.trace.parameters.Packed`), which keeps the reverse pass one kernel."""
        g = self._live
        if g is None:
            return self._z_img, self._norm, self._aim
        z_img = g.wide("image_z", n)
        aim = None if self._aim is None else (self._aim[0], g.wide("exit_pupil_scale", n),
                                              z_img - g.wide("exit_pupil_z", n))
        return z_img, g.wide("normalisation", n), aim

    def _transport(self, o, d, lam, active):
        """Camera rays on the film plane → (position, direction, throughput, valid) of the ray
        leaving the lens (lens space, position on ``self.z_out``); ``fresnel = false``: T = 1."""
        res = self.tmap.eval_dr(o, d, lam, active)
        T = res.throughput if self.setup.fresnel else dr.zeros(type(res.throughput), dr.width(res.throughput)) + 1.0
        return res.position, res.direction, T, res.valid

    def _describe(self) -> str:
        return f"lens={self.setup.lens.name}"

    # ------------------------------------------------------------------ rays
    def _film_rays(self, fx, fy, sample3, numbers=None):
        """Rays from the film points ``(fx, fy)`` (lens space, mm, on the sensor plane) toward the exit pupil
        points ``sample3`` picks (:attr:`pupil`): ``(o, d, area, cos_t)`` — origins and unit directions (lens
        space), the pupil sample's area weight, and the cosine of the ray to the axis.  ``numbers``:
        :meth:`_ray_numbers` of these rays (computed if None)."""
        X, Y, area = self.pupil.sample(mi, dr, fx, fy, sample3)
        z_img, _, aim = numbers if numbers is not None else self._ray_numbers(dr.width(fx))
        dzp = self._dz
        if aim is not None:
            # a lens being differentiated: the sample P (on the table's plane, detached) becomes the point Q where
            # the ray from the film point crosses the paraxial exit pupil's plane, scaled with that pupil; the ray
            # is aimed at Q from the (attached) film point.  As the lens changes, Q stays on the image of the same
            # stop point (paraxially), so the rays that pass the stop keep passing it: the stop's rim adds no
            # boundary term (up to the pupil's aberrations).  The measure: dω = cos³θ dA_Q / gap², A_Q = k0² s² A.
            k0, scale, dzp = aim
            X, Y = dr.fma(X - fx, k0, fx) * scale, dr.fma(Y - fy, k0, fy) * scale
            area = area * (k0 * k0) * (scale * scale)
        ex, ey = X - fx, Y - fy
        inv_len = dr.rsqrt(dr.fma(ex, ex, dr.fma(ey, ey, dzp * dzp)))
        d = (ex * inv_len, ey * inv_len, -dzp * inv_len)
        zf = dr.zeros(mi.Float, dr.width(fx)) + z_img
        return (fx, fy, zf), d, area, dzp * inv_len

    def _trace(self, time, sample1, sample2, sample3, active=True):
        st = self.setup
        lam, wav, wspec, time = sample_wavelength(mi, dr, self, self.lambda_mode, time, sample1,
                                                  sample2, sample3, active)
        fx, fy = film_to_sensor(mi, self, st, sample2)
        numbers = self._ray_numbers(dr.width(fx))
        z_img, norm, aim = numbers
        o, d, area, cos_t = self._film_rays(fx, fy, sample3, numbers)
        dzp = self._dz if aim is None else aim[2]
        pos, dirn, T, valid = self._transport(o, d, lam, active)
        c2 = cos_t * cos_t
        # cos^4θ · A / Δz² · T / (π NA'²)
        w = c2 * c2 * area * (norm / (dzp * dzp)) * T
        w = dr.select(valid, w, 0.0)
        (ox, oy, oz), (dx, dy, dz) = lens_to_camera(st, pos, dirn, z_img)
        o = mi.Point3f(dr.select(valid, ox, 0.0), dr.select(valid, oy, 0.0), dr.select(valid, oz, 0.0))
        dcam = mi.Vector3f(dr.select(valid, dx, 0.0), dr.select(valid, dy, 0.0), dr.select(valid, dz, 1.0))
        ray = mi.Ray3f(self.m_to_world @ o, dr.normalize(self.m_to_world @ dcam), time,
                       wav if wav is not None else [])
        # invalid rays: weight 0 and a zero-length segment so integrators stop at once
        ray.maxt = dr.select(valid, ray.maxt, 0.0)
        weight = wspec * w if not isinstance(wspec, float) else mi.Spectrum(w)
        if dr.is_jit_v(mi.Float) and not dr.flag(dr.JitFlag.SymbolicScope) and ray_kernel_for(
                self.ray_kernel, dr.backend_v(mi.Float) == dr.JitBackend.CUDA, dr.width(fx),
                8 + dr.size_v(mi.Spectrum) + dr.size_v(type(ray.wavelengths))) == SEPARATE:
            # the rays in a kernel of their own, stored; the integrator's kernel reads them instead of
            # carrying the transport's registers through its whole path loop.  Inside a symbolic scope (a
            # caller's loop or call) nothing may be evaluated: the rays stay inline there
            dr.eval(ray, weight)
        return ray, weight

    def sample_ray(self, time, sample1, sample2, sample3, active=True):
        return self._trace(time, sample1, sample2, sample3, active)

    def sample_ray_differential(self, time, sample1, sample2, sample3, active=True):
        ray, w = self._trace(time, sample1, sample2, sample3, active)
        rdiff = mi.RayDifferential3f(ray)
        rdiff.has_differentials = False
        return rdiff, w

    # ------------------------------------------------------------------ unsupported
    def _unsupported(self, what):
        raise NotImplementedError(
            f"{self.PLUGIN}: {what} is not supported: this sensor only generates camera rays (backward "
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
        self.lens_parameters.put(cb)
        self._traverse_more(cb)

    def _traverse_more(self, cb):
        """Parameters of the subclass's own, put into the traversal ``cb`` after the lens's."""

    def _changed_more(self, keys) -> bool:
        """After ``params.update()``: apply changes to the subclass's own parameters (``keys``: the names after
        the last dot); True when the transport map must be rebuilt."""
        return False

    def parameters_changed(self, keys=[]):
        """After ``params.update()``: a changed focus, sensor distance, focal length or prescription parameter
        re-derives the configured lens, its pupil bounds and normalisation, and makes the changed parameters kernel
        inputs (:mod:`.live`); an invalid parameter set is a :class:`~mi_neurallens.errors.NeuralLensError`."""
        from ..trace.parameters import LiveGeometry
        sp = self.lens_parameters
        own = self._changed_more(keys)
        if not sp.changed(keys):
            if own:
                self.tmap = self._make_map(self._live)
            return
        setup, live, derived = sp.derive()
        self.setup = setup
        geometry = LiveGeometry(setup.lens, live, mi.Float, stop_radius=derived["stop_radius"])
        self._set_planes((geometry, derived))
        self.tmap = self._make_map(geometry)

    def to_string(self):
        st = self.setup
        fd = st.focus_distance_mm / st.scene_unit_mm
        zoom = (f"focal_length={st.focal_length_mm:.4g} mm (EFL {st.lens.efl():.4g} mm at this focus), "
                if st.focal_length_mm is not None else "")
        return (f"{type(self).__name__}[{self._describe()}, {zoom}f/{st.fnumber:.3g} "
                f"(widest f/{st.max_fnumber:.3g}), focus_distance={fd:g} (sensor_distance="
                f"{st.sensor_distance_mm:.4f} mm), sensor {st.sensor_width_mm:g}x{st.sensor_height_mm:.4g} mm, "
                f"scene_unit_mm={st.scene_unit_mm:g}, fresnel={st.fresnel}, "
                f"pupil_sampling={self.pupil.mode}, ray_kernel={self.ray_kernel}, film={self.film().size()}]")
