"""What every lens sensor shares: property handling, lens setup (f-stop, focus), film mapping and frames.

Used by ``realistic_lens`` (and, later, ``neural_lens``).  Nothing here defines a Mitsuba class, so
the module imports without a variant; the Dr.Jit helpers take ``mi`` arrays of the current variant.

Frames (the single place they are written down for the sensors)
---------------------------------------------------------------
* **Lens space** (see :mod:`mi_neurallens.optics.prescription`): mm, +z from the object toward the
  sensor, first vertex at z = 0, image (sensor) plane at ``z_img = lens.image_z``.
* **Camera space** (Mitsuba's, before ``to_world``): scene units, the camera looks along +z, +x is
  image-left and +y image-up, exactly like ``perspective``.  Its **origin is the centre of the sensor
  plane**; the lens lies in front of it (+z).  A lens-space point maps to
  ``((x, y, z_img − z) / scene_unit_mm)`` and a direction to ``(dx, dy, −dz)``.  (This is a mirror
  of lens space; a rotationally symmetric lens is its own mirror image, so the only visible effect
  is that the blades of a polygonal stop appear mirrored.)
* **Film → sensor**: the normalised full-film position (u, v) ∈ [0, 1]² (u to the right, v down)
  maps to the lens-space sensor point ``((2u − 1)·w/2, (2v − 1)·h/2, z_img)``.  A real lens forms an
  inverted image, so a film point on the right (+x lens) sees an object on the left (+x camera):
  the rendered picture is upright and unmirrored, with the same orientation as ``perspective``.
"""
from __future__ import annotations

from dataclasses import dataclass
import dataclasses
import math
import os

from ..constants import FULL_FRAME_MM, LAMBDA_D
from ..errors import LensError, NeuralLensError

#: an fstop this much (relative) below the lens's widest f-number (e.g. the rounded value 2.68 for
#: f/2.6837) means "wide open" instead of an error
FSTOP_TOLERANCE = 0.005

#: wavelength (nm) at which paraxial focus, f-number and normalisation are computed (He d-line)
PARAXIAL_WAVELENGTH_NM = LAMBDA_D


class SensorPropertyError(NeuralLensError, ValueError):
    """An invalid or contradictory sensor property; the message names the plugin and property."""

    def __init__(self, plugin: str, prop: str | None, what: str):
        self.plugin, self.prop, self.what = plugin, prop, what
        where = f"{plugin}: property '{prop}': " if prop else f"{plugin}: "
        super().__init__(where + what)


# ----------------------------------------------------------------------------- property reading
class PropertyReader:
    """Reads (and so marks as used) the properties of a Mitsuba plugin, with typed validation."""

    def __init__(self, props, plugin: str):
        self.props, self.plugin = props, plugin

    def has(self, name: str) -> bool:
        return name in self.props

    def error(self, name, what):
        return SensorPropertyError(self.plugin, name, what)

    def float(self, name: str, default=None, *, positive=False, allow_inf=False):
        if name not in self.props:
            return default
        v = self.props.get(name)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            try:
                v = float(v)
            except (TypeError, ValueError):
                raise self.error(name, f"must be a number, got {v!r}") from None
        v = float(v)
        if math.isnan(v) or (math.isinf(v) and not (allow_inf and v > 0)):
            raise self.error(name, f"must be a finite number{' or inf' if allow_inf else ''}, got {v}")
        if positive and not v > 0:
            raise self.error(name, f"must be > 0, got {v:g}")
        return v

    def int(self, name: str, default=None):
        if name not in self.props:
            return default
        v = self.props.get(name)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or int(v) != v:
            raise self.error(name, f"must be an integer, got {v!r}")
        return int(v)

    def refuse_unknown(self, known, skip=()):
        """Raise for the first property that is neither in ``known`` nor in ``skip``."""
        for k in self.props.keys():
            if k not in known and k not in skip:
                raise self.error(k, f"unknown property; known: {', '.join(known)}")

    def bool(self, name: str, default: bool):
        if name not in self.props:
            return default
        v = self.props.get(name)
        if isinstance(v, bool):
            return v
        if isinstance(v, str) and v.lower() in ("true", "false"):
            return v.lower() == "true"
        raise self.error(name, f"must be a boolean (true/false), got {v!r}")

    def string(self, name: str, default=None, choices=None):
        if name not in self.props:
            return default
        v = self.props.get(name)
        if not isinstance(v, str):
            raise self.error(name, f"must be a string, got {v!r}")
        if choices is not None and v not in choices:
            raise self.error(name, f"must be one of {', '.join(repr(c) for c in choices)}, got {v!r}")
        return v


# ----------------------------------------------------------------------------- lens loading
def bundled_lens_names() -> list[str]:
    """Names of the lenses on the search path (:func:`mi_neurallens.resources.lens_names`)."""
    from .. import resources
    return resources.lens_names()


def load_lens(spec: str, plugin: str = "realistic_lens", prop: str = "lens"):
    """Load the lens named by a sensor's ``lens`` property: a file (resolved with Mitsuba's file
    resolver, so paths relative to the scene XML work) or a bundled lens name."""
    from ..optics.prescription import Lens
    if not isinstance(spec, str) or not spec.strip():
        raise SensorPropertyError(plugin, prop, f"must be a lens file or bundled lens name, got {spec!r}")
    path = spec
    try:
        import mitsuba as mi
        fr = mi.file_resolver() if hasattr(mi, 'file_resolver') else mi.Thread.thread().file_resolver()
        r = str(fr.resolve(spec))
        if os.path.exists(r):
            path = r
    except Exception:  # pragma: no cover - no variant / resolver
        pass
    names = bundled_lens_names()
    looks_like_file = os.path.exists(path) or os.sep in spec or "." in os.path.basename(spec)
    if not os.path.exists(path) and spec not in names and looks_like_file:
        raise SensorPropertyError(plugin, prop, f"lens file {spec!r} not found; give a path to a lens "
                                  f"file (project JSON, pbrt .dat, OOD .json, Zemax .zmx) or one of the bundled "
                                  f"lenses: {', '.join(names) or '(none installed)'}")
    try:
        return Lens.load(path)
    except LensError as e:
        raise SensorPropertyError(plugin, prop, f"cannot use lens {spec!r}: {e}") from e
    except (FileNotFoundError, ImportError, OSError, KeyError) as e:
        raise SensorPropertyError(plugin, prop, f"unknown lens {spec!r}: not a readable file and not a "
                                  f"bundled lens (bundled: {', '.join(names) or '(none installed)'}); "
                                  f"{type(e).__name__}: {e}") from e


# ----------------------------------------------------------------------------- focus / stop
def solve_sensor_distance(lens, focus_from_sensor_mm: float, wavelength_nm: float = PARAXIAL_WAVELENGTH_NM,
                          plugin: str = "realistic_lens", prop: str = "focus_distance") -> float:
    """Sensor distance (mm behind the last vertex) that puts an object ``focus_from_sensor_mm`` in
    front of the SENSOR PLANE in paraxial focus (unit focusing: the whole lens moves).

    The object-to-sensor distance h(s) = focus_distance_for(s) + track + s falls from ∞ at s = BFL to
    a minimum (≈ 4f for a thin lens) and rises again; the far-focus branch between is solved by
    bisection.  Raises :class:`SensorPropertyError` when the distance is closer than that minimum.
    """
    F = float(focus_from_sensor_mm)
    px = lens.paraxial(wavelength_nm)
    if math.isinf(F):
        if not px.bfl > 0:
            raise SensorPropertyError(plugin, prop, f"the lens cannot focus at infinity (BFL {px.bfl:.4g} mm)")
        return px.bfl
    T = lens.total_track
    f = abs(px.efl)

    def h(s):
        try:
            return px.focus_distance_for(s) + T + s
        except LensError:
            return math.nan

    lo = px.bfl
    ts = [1e-9 * (1.6 ** k) for k in range(64)]       # up to ~ 1e4 · f
    vals = [(lo + f * t, h(lo + f * t)) for t in ts]
    vals = [(s, v) for s, v in vals if math.isfinite(v)]
    if not vals:
        raise SensorPropertyError(plugin, prop, "cannot compute the lens's focusing range")
    i_min = min(range(len(vals)), key=lambda i: vals[i][1])
    s_min, h_min = vals[i_min]
    if F < h_min:
        raise SensorPropertyError(plugin, prop, f"focus distance {F:g} mm (from the sensor plane) is closer "
                                  f"than this lens can focus: the minimum is about {h_min:.6g} mm "
                                  f"(object-to-sensor distance); use a larger value or inf")
    a = lo
    b = s_min
    for _ in range(200):
        m = 0.5 * (a + b)
        hm = h(m)
        if not math.isfinite(hm) or hm > F:
            a = m
        else:
            b = m
        if b - a < 1e-12 * max(1.0, b):
            break
    return 0.5 * (a + b)


@dataclass
class LensSetup:
    """A lens prepared for rendering: stopped down and focused, plus the numbers a sensor needs."""

    lens: object                  #: the configured prescription (stop radius, last thickness = sensor distance)
    base_lens: object             #: as loaded
    fnumber: float                #: paraxial f-number (object at infinity) of the configured stop
    max_fnumber: float            #: the lens's widest f-number (as loaded)
    sensor_distance_mm: float     #: last vertex to sensor plane
    focus_distance_mm: float      #: in-focus object distance from the SENSOR PLANE (inf allowed)
    sensor_width_mm: float
    sensor_height_mm: float
    scene_unit_mm: float
    fresnel: bool

    @property
    def image_z(self) -> float:
        return float(self.lens.image_z)

    #: paraxial working f-number at the focus distance (= fnumber when focused at infinity)
    working_fnumber: float = math.nan
    #: a lens with moving groups: its focal length (mm: the EFL at infinity focus, d line, of this zoom; the
    #: configured lens's own EFL breathes with the focus) and the zoom and focus parameters
    #: (:mod:`mi_neurallens.optics.moving`); None for a lens without
    focal_length_mm: float | None = None
    zoom: float | None = None
    focus_parameter: float | None = None

    @property
    def trained_iris(self):
        """The iris a learned map of :attr:`base_lens` was trained with, at this configuration
        (:class:`~mi_neurallens.trace.iris.Iris`): the lens file's stop, for a zoom lens at the stop diameter its
        moving groups give at :attr:`zoom`."""
        from ..trace.iris import Iris
        trained = Iris.of_lens(self.base_lens)
        moving = getattr(self.base_lens, "moving", None)
        if moving is not None and moving.stop_at(self.zoom) is not None:
            trained = dataclasses.replace(trained, radius_mm=moving.stop_at(self.zoom))
        return trained

    def configured_map(self, tm):
        """The learned map ``tm`` of a lens with moving groups (its domain's ``conditions``) at this configuration:
        its zoom and focus parameters as its condition inputs, its planes moved from the configurations' frame (the
        sensor fixed) into the configured lens's space; a configuration outside the learned range is a
        :class:`~mi_neurallens.errors.NeuralLensError` (its message starts with "zoom" or "focus").  A map without
        conditions is returned as is."""
        cond = getattr(tm.domain, "conditions", None)
        if cond is None:
            return tm
        return cond.configure_map(tm, self.lens.image_z, self.zoom, self.focus_parameter)

    @property
    def na_image(self) -> float:
        """Paraxial image-space numerical aperture of the on-axis image at the focus distance:
        NA' = 1 / (2 N_w), N_w the working f-number (N at infinity focus)."""
        n = self.working_fnumber if math.isfinite(self.working_fnumber) else self.fnumber
        return 1.0 / (2.0 * n)

    @property
    def normalisation(self) -> float:
        """1 / (π NA'²): divides the sensor-plane irradiance integral ∫ L cosθ dω."""
        return 1.0 / (math.pi * self.na_image ** 2)

    @property
    def film_half_diagonal_mm(self) -> float:
        return 0.5 * math.hypot(self.sensor_width_mm, self.sensor_height_mm)

    @property
    def lambda_dependent(self) -> bool:
        """True when the lens's transport depends on the wavelength (dispersive media or coatings)."""
        L = self.lens
        media = [L.object_medium] + [s.medium for s in L.surfaces]
        return (any(not m.is_constant for m in media)
                or (self.fresnel and any(s.coating is not None for s in L.surfaces)))


def _check_polygon_fits(lens, r_widest: float, n_max: float, plugin: str):
    """A bladed stop's corners (its circumscribed circle, :attr:`Iris.outer_radius_mm`) must lie in the
    air gap like the stop itself; near wide open they can reach past a neighbouring surface's sag (into
    glass: no physical iris does that), which is an error naming the f-number from which the polygon
    fits.  ``r_widest``: the stop radius (mm) at the widest aperture ``n_max``."""
    from ..trace.iris import Iris
    stop = lens.stop
    if not stop.blades:
        return
    grow = Iris.of_surface(stop).outer_radius_mm / stop.semi_diameter

    def fits(r):
        try:
            lens.with_surface(lens.stop_index, blades=0, semi_diameter=r * grow)
            return True
        except LensError:
            return False
    if fits(stop.semi_diameter):
        return
    lo, hi = 0.0, stop.semi_diameter          # fits(lo), not fits(hi)
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if fits(mid) else (lo, mid)
    n_min = n_max * r_widest / lo
    raise SensorPropertyError(plugin, "blades",
                              f"{stop.blades} blades at this f-number put the iris corners "
                              f"{stop.semi_diameter * grow:.4g} mm from the axis, past where a neighbouring "
                              f"surface of lens '{lens.name}' crosses the stop plane ({lo * grow:.4g} mm); "
                              f"use fstop >= {n_min * (1 + 1e-6):.4g} with {stop.blades} blades, or blades=0")


def focus_for_sensor_distance(lens, sensor_distance_mm: float) -> float:
    """Object distance in focus (paraxial, d line) in mm from the *sensor plane* when the sensor is
    ``sensor_distance_mm`` behind the last vertex: the convention of ``focus_distance``.  Raises
    :class:`LensError` for a sensor closer than the rear focal point (focus "beyond infinity")."""
    s = float(sensor_distance_mm)
    return lens.paraxial(PARAXIAL_WAVELENGTH_NM).focus_distance_for(s) + lens.total_track + s


def configure_lens(base_lens, *, fstop=None, focus_distance_mm=None, sensor_distance_mm=None,
                   blades=None, blade_rotation_deg=None, sensor_width_mm=FULL_FRAME_MM[0], film_size=(1, 1),
                   scene_unit_mm=1000.0, fresnel=True, plugin="realistic_lens", focal_length_mm=None) -> LensSetup:
    """Stop down (``fstop``), shape the iris (``blades`` straight blades, 0 = circular, rotated by
    ``blade_rotation_deg``; None keeps the lens file's) and focus (``focus_distance_mm`` from the
    sensor plane XOR ``sensor_distance_mm`` behind the last vertex; default: infinity) a loaded lens.

    A lens with moving groups (:mod:`mi_neurallens.optics.moving`) is first set to ``focal_length_mm`` (a zoom
    lens's; None: its first listed position) and focused by its groups on ``focus_distance_mm`` (the sensor stays:
    ``sensor_distance_mm`` is refused); the f-number, pupils and field follow that configuration."""
    if focus_distance_mm is not None and sensor_distance_mm is not None:
        raise SensorPropertyError(plugin, "focus_distance",
                                  "give either 'focus_distance' (scene units from the sensor plane) or "
                                  "'sensor_distance' (mm behind the last vertex), not both")
    moving = getattr(base_lens, "moving", None)
    if focal_length_mm is not None and (moving is None or not moving.is_zoom):
        raise SensorPropertyError(plugin, "focal_length", f"lens '{base_lens.name}' is not a zoom lens (its focal "
                                  f"length is {base_lens.efl(PARAXIAL_WAVELENGTH_NM):.4g} mm): leave focal_length out")
    if moving is not None:
        return _configure_moving(base_lens, fstop=fstop, focus_distance_mm=focus_distance_mm,
                                 sensor_distance_mm=sensor_distance_mm, blades=blades,
                                 blade_rotation_deg=blade_rotation_deg, sensor_width_mm=sensor_width_mm,
                                 film_size=film_size, scene_unit_mm=scene_unit_mm, fresnel=fresnel, plugin=plugin,
                                 focal_length_mm=focal_length_mm)
    px0 = base_lens.paraxial(PARAXIAL_WAVELENGTH_NM)
    n_max = float(px0.fnumber)
    lens = base_lens
    if fstop is not None:
        if not fstop > 0:
            raise SensorPropertyError(plugin, "fstop", f"must be > 0, got {fstop:g}")
        if fstop < n_max * (1.0 - FSTOP_TOLERANCE):
            raise SensorPropertyError(plugin, "fstop", f"f/{fstop:g} is wider than lens "
                                      f"'{base_lens.name}' allows: its widest aperture is f/{n_max:.3g} "
                                      f"(paraxial entrance pupil radius {px0.entrance_pupil_radius:.4g} mm, "
                                      f"EFL {px0.efl:.4g} mm); use fstop >= {n_max:.3g}")
        if fstop > n_max:   # within FSTOP_TOLERANCE of the widest aperture: wide open
            lens = lens.with_stop_radius(lens.stop.semi_diameter * n_max / fstop)
    if blades is not None and blades != 0 and blades < 3:
        raise SensorPropertyError(plugin, "blades", f"must be 0 (circular) or >= 3, got {blades}")
    iris = {k: v for k, v in (("blades", blades), ("blade_rotation_deg", blade_rotation_deg)) if v is not None}
    if iris:
        lens = lens.with_surface(lens.stop_index, **{k: (int(v) if k == "blades" else float(v))
                                                     for k, v in iris.items()})
    _check_polygon_fits(lens, base_lens.stop.semi_diameter, n_max, plugin)
    if sensor_distance_mm is not None:
        if not (sensor_distance_mm > 0 and math.isfinite(sensor_distance_mm)):
            raise SensorPropertyError(plugin, "sensor_distance",
                                      f"must be a finite distance > 0 mm behind the last vertex, got "
                                      f"{sensor_distance_mm:g}")
        s = float(sensor_distance_mm)
        try:
            focus = focus_for_sensor_distance(lens, s)
        except LensError:
            focus = math.nan          # sensor closer than the rear focal point: "beyond infinity"
    else:
        focus = math.inf if focus_distance_mm is None else float(focus_distance_mm)
        if not focus > 0:
            raise SensorPropertyError(plugin, "focus_distance", f"must be > 0 (or inf), got {focus:g}")
        s = solve_sensor_distance(lens, focus, plugin=plugin)
    lens = lens.with_sensor_distance(s)
    px = lens.paraxial(PARAXIAL_WAVELENGTH_NM)
    w = float(sensor_width_mm)
    h = w * float(film_size[1]) / float(film_size[0])
    nw = float(px.fnumber)
    if math.isfinite(focus):
        try:
            nw = float(px.working_fnumber(focus - lens.total_track - s))
        except LensError:
            pass
    return LensSetup(lens=lens, base_lens=base_lens, fnumber=float(px.fnumber), max_fnumber=n_max,
                     working_fnumber=nw,
                     sensor_distance_mm=s, focus_distance_mm=focus, sensor_width_mm=w, sensor_height_mm=h,
                     scene_unit_mm=float(scene_unit_mm), fresnel=bool(fresnel))


def _configure_moving(base_lens, *, focus_distance_mm, sensor_distance_mm, focal_length_mm, plugin, **kw) -> LensSetup:
    """:func:`configure_lens` of a lens with moving groups: the configuration at the focal length and focus
    distance (:func:`mi_neurallens.optics.moving.configure`), then stopped down like any lens, its sensor at the
    configuration's image distance."""
    from ..optics import moving as mv
    if sensor_distance_mm is not None:
        raise SensorPropertyError(plugin, "sensor_distance",
                                  f"lens '{base_lens.name}' focuses by moving groups of its elements (its sensor "
                                  "stays where it is): give focus_distance instead (docs/lens-format.md, "
                                  "'Moving groups')")
    focus = math.inf if focus_distance_mm is None else float(focus_distance_mm)
    if not focus > 0:
        raise SensorPropertyError(plugin, "focus_distance", f"must be > 0 (or inf), got {focus:g}")
    try:
        lens, zoom, fpar = mv.configure(base_lens, focal_length_mm, focus)
    except LensError as e:
        which = "focal_length" if ("focal length" in str(e) or "zoom lens" in str(e)) else "focus_distance"
        raise SensorPropertyError(plugin, which, str(e)) from e
    setup = configure_lens(lens, sensor_distance_mm=lens.surfaces[-1].thickness, plugin=plugin, **kw)
    efl_inf = float(focal_length_mm) if focal_length_mm is not None else mv.focal_length(base_lens, zoom)
    return dataclasses.replace(setup, base_lens=base_lens, focus_distance_mm=focus, focal_length_mm=efl_inf, zoom=zoom,
                               focus_parameter=fpar)


# ----------------------------------------------------------------------------- Dr.Jit helpers
def film_to_sensor(mi, sensor, setup: LensSetup, sample2):
    """Lens-space sensor point (x, y) in mm of a film sample (``sample2`` in the crop window)."""
    film = sensor.film()
    size, csize, coff = film.size(), film.crop_size(), film.crop_offset()
    w, h = setup.sensor_width_mm, setup.sensor_height_mm
    sx = w * float(csize[0]) / float(size[0])
    sy = h * float(csize[1]) / float(size[1])
    ox = w * float(coff[0]) / float(size[0]) - 0.5 * w
    oy = h * float(coff[1]) / float(size[1]) - 0.5 * h
    import drjit as dr
    return dr.fma(sample2.x, sx, ox), dr.fma(sample2.y, sy, oy)


def lens_to_camera(setup: LensSetup, p, d, image_z=None):
    """Lens-space point/direction tuples (mm) → camera-space tuples (scene units).  ``image_z``: the sensor
    plane's z (lens space, mm) if not the set-up's (a Dr.Jit array where it is differentiated)."""
    k = 1.0 / setup.scene_unit_mm
    zi = setup.image_z if image_z is None else image_z
    x, y, z = p
    dx, dy, dz = d
    return (x * k, y * k, (zi - z) * k), (dx, dy, -dz)
