"""Where the maps of a lens live: their planes, the sensor distances they serve and their input domains.

Render time needs these as much as training does (a baseline map built with no model file takes the planes and
domains a neural map would have), so they live here, beside the reduced :class:`~.planning.Domain`, and import
neither torch nor ``mi_neurallens.training``.

Planes (lens space, mm, +z toward the sensor; stored in every model file):

* ``z_front`` = (the front-most point of any surface within its clear aperture, at most 0) − 1 mm.
  Forward maps start here; backward maps end here.
* ``z_rear`` lies between the rear-most point of any surface (rim sag included) and the *nearest*
  sensor plane the model supports, ``z_last_vertex + sensor_distance_min``: the midpoint, but at most
  1 mm behind the rear-most surface point.  Backward maps start here; forward maps end here.
  Because rays travel straight through the air between ``z_rear`` and the sensor, one map serves
  every sensor distance in ``[sensor_distance_min, sensor_distance_max]`` (manual focusing).

The defaults a lens's training recipe (``recipes/<lens>.toml`` of its lens library) may override and that
decide these — the close focus and the field margin — are written here once (:data:`DEFAULT_CLOSE_FOCUS_MM`,
:data:`DEFAULT_FIELD_MARGIN`); ``training/config.py``'s ``TrainConfig`` takes its defaults from them, and
:func:`recipe_close_focus` reads a recipe's close focus without the training configuration.
"""
from __future__ import annotations

import math

import numpy as np

from ..constants import FULL_FRAME_HALF_DIAGONAL_MM, LAMBDA_D
from ..errors import NeuralLensError
from .planning import Domain, Reach

#: ``TrainConfig.close_focus_mm``'s default: the nearest object distance the maps support, chosen per lens
#: (:func:`close_focus_mm`)
DEFAULT_CLOSE_FOCUS_MM = "auto"
#: ``TrainConfig.field_margin``'s default: the forward maps' field reaches 10 % beyond the film's corner
DEFAULT_FIELD_MARGIN = 1.1

#: ``close_focus_mm = "auto"``: never nearer than this (mm in front of the first vertex; every model trained before
#: the setting had a default of its own used it)
AUTO_CLOSE_FOCUS_MM = 300.0
#: ``close_focus_mm = "auto"``: nor nearer than where the paraxial magnification reaches this (1:4, about the
#: closest a non-macro lens focuses): what keeps a long lens's default valid (a 300 mm lens cannot focus 300 mm away)
AUTO_CLOSE_FOCUS_MAGNIFICATION = 0.25


# ----------------------------------------------------------------------------- the recipe's settings
def recipe_path(lens_name: str) -> str | None:
    """The lens's training recipe, ``recipes/<lens>.toml`` of the first lens library that has one
    (:func:`mi_neurallens.resources.find_recipe`), or ``None``: the defaults."""
    from .. import resources
    p = resources.find_recipe(lens_name)
    return str(p) if p is not None else None


def recipe_close_focus(lens_name: str):
    """The ``close_focus_mm`` of the lens's training recipe (:func:`recipe_path`), or :data:`DEFAULT_CLOSE_FOCUS_MM`
    where there is no recipe or it does not set one: what a model of the lens trained with its recipe supports."""
    path = recipe_path(lens_name)
    if not path:
        return DEFAULT_CLOSE_FOCUS_MM
    try:
        import tomllib
    except ImportError:                     # Python 3.10
        import tomli as tomllib
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except tomllib.TOMLDecodeError as e:
        raise NeuralLensError(f"training config {path}: {e}") from None
    return data.get("close_focus_mm", DEFAULT_CLOSE_FOCUS_MM)


# ----------------------------------------------------------------------------- planes and sensor distances
def surface_extent(lens):
    """(front-most z, rear-most z) of every optical surface within its clear aperture (mm)."""
    zs = lens.vertex_z
    lo, hi = math.inf, -math.inf
    for i, s in enumerate(lens.surfaces):
        if s.is_stop:
            continue
        r = np.linspace(0.0, s.semi_diameter, 129)
        z = zs[i] + s.sag(r)
        lo, hi = min(lo, float(np.nanmin(z))), max(hi, float(np.nanmax(z)))
    return lo, hi


def close_focus_mm(lens, setting) -> float:
    """The nearest object distance (mm in front of the first vertex; 0: infinity only) a training supports, from
    the config's ``close_focus_mm``: a number is taken as it is; ``"auto"`` is :data:`AUTO_CLOSE_FOCUS_MM`, or, for
    a lens that cannot focus that near or only with more than :data:`AUTO_CLOSE_FOCUS_MAGNIFICATION`, the
    distance of that magnification: Newton's ``x = f / m`` beyond the front focal point (d-line, paraxial).  For
    the lenses up to 60 mm here that is the 300 mm; the 250 mm telephoto gets 1.33 m, a 300 mm lens 1.71 m."""
    if isinstance(setting, str):
        if setting != "auto":
            raise NeuralLensError(f"training config: close_focus_mm = {setting!r}; give a distance in mm in front "
                                  "of the first vertex, 0 (infinity only) or \"auto\"")
        px = lens.paraxial(LAMBDA_D)
        if not px.power > 0:
            return AUTO_CLOSE_FOCUS_MM
        return max(AUTO_CLOSE_FOCUS_MM, float(px.ffl) + float(px.efl) / AUTO_CLOSE_FOCUS_MAGNIFICATION)
    if not (isinstance(setting, (int, float)) and setting >= 0):
        raise NeuralLensError(f"training config: close_focus_mm = {setting!r}; give a distance in mm in front of "
                              "the first vertex, 0 (infinity only) or \"auto\"")
    return float(setting)


def sensor_distance_range(lens, close_focus: float | str | None, margin: float = 0.02):
    """[s_min, s_max] (mm behind the last vertex): from just beyond infinity focus (``margin`` ·
    BFL closer, and never farther than the file's own sensor distance) to the paraxial sensor
    distance for an object ``close_focus`` in front of the first vertex (the config's ``close_focus_mm``:
    :func:`close_focus_mm`; 0 or None: infinity only).  A distance the lens cannot focus raises
    :class:`~mi_neurallens.errors.NeuralLensError` naming the setting."""
    from ..errors import LensError
    px = lens.paraxial(LAMBDA_D)
    s_inf = float(px.bfl)
    s_min = min(s_inf, float(lens.surfaces[-1].thickness)) * (1.0 - margin)
    d = close_focus_mm(lens, close_focus) if close_focus is not None else 0.0
    try:
        s_max = s_inf if not d else float(px.sensor_distance_for(d))
    except LensError as e:
        raise NeuralLensError(f"lens '{lens.name}': close_focus_mm = {d:g}: {e.what}; "
                              f"set close_focus_mm farther (or \"auto\", which would be "
                              f"{close_focus_mm(lens, 'auto'):.4g} mm for this lens)") from None
    return s_min, max(s_max, s_inf, float(lens.surfaces[-1].thickness))


def planes(lens, s_min: float):
    """(z_front, z_rear) (lens space, mm) of a model whose nearest sensor plane lies ``s_min`` mm behind the last
    vertex (see the module docstring)."""
    front, rear = surface_extent(lens)
    z_front = min(front, 0.0) - 1.0
    z_sensor_min = lens.total_track + s_min
    if not z_sensor_min > rear:
        raise NeuralLensError(f"lens '{lens.name}': the nearest supported sensor plane (z = {z_sensor_min:.4g} mm) "
                              f"lies inside the lens (rear-most surface point z = {rear:.4g} mm)")
    z_rear = min(0.5 * (rear + z_sensor_min), rear + 1.0)
    return z_front, z_rear


def moving_planes(configs):
    """(z_front, z_rear) (mm) of a map of a lens with moving groups, in its configurations' frame
    (:class:`~mi_neurallens.transport.configurations.Configurations`: the sensor fixed at ``z_sensor``): as
    :func:`planes`, with the front-most and rear-most surface points over every configuration the map learns, and
    the sensor plane the nearest one."""
    from ..optics import moving as mv
    lo, hi = math.inf, -math.inf
    for t, f in configs.corner_configurations():
        lens = mv.at(configs.lens, t, f, check=False)
        shift = configs.shift_of(lens.image_z)
        front, rear = surface_extent(lens)
        lo, hi = min(lo, front - shift), max(hi, rear - shift)
    if not configs.z_sensor > hi:
        raise NeuralLensError(f"lens '{configs.lens.name}': a configuration reaches the sensor plane (rear-most "
                              f"surface point z = {hi:.4g} mm, sensor {configs.z_sensor:.4g} mm)")
    return min(lo, 0.0) - 1.0, min(0.5 * (hi + configs.z_sensor), hi + 1.0)


# ----------------------------------------------------------------------------- input domains
def default_field_half_angle(lens, film_half_diagonal_mm: float = FULL_FRAME_HALF_DIAGONAL_MM,
                             margin: float = DEFAULT_FIELD_MARGIN) -> float:
    """The forward maps' field (degrees off the axis): the film corner's paraxial angle (d-line) times ``margin``,
    at most 80°."""
    px = lens.paraxial(LAMBDA_D)
    return min(math.degrees(math.atan(film_half_diagonal_mm / abs(px.efl))) * margin, 80.0)


def forward_domain(lens, z_front: float, field_half_angle_deg: float, margin: float = 1.02,
                   reach: Reach | None = None) -> Domain:
    """Rays entering the front within the field: r covers every ray that can still hit the front
    surface's clear aperture at that angle.  ``reach``: the film reach of the maps (:func:`film_reach`)."""
    s = lens.surfaces[lens.optical_indices[0]]
    rim = float(s.sag(s.semi_diameter)) if not s.is_stop else 0.0
    t = math.tan(math.radians(field_half_angle_deg))
    r = (s.semi_diameter + max(rim - z_front, 0.0) * t) * margin
    return Domain(r_max=r, s_max=min(math.sin(math.radians(field_half_angle_deg)), 0.999), reach=reach)


def moving_forward_domain(configs, z_front: float, film_half_diagonal_mm: float, field_margin: float,
                          reach_radius_mm: float | None, margin: float = 1.02) -> Domain:
    """The forward maps' domain of a lens with moving groups (:class:`~mi_neurallens.transport.configurations.
    Configurations`; ``z_front`` in their frame, the sensor fixed at ``z_sensor``): the field of its widest
    configuration (:func:`default_field_half_angle` at the shortest focal length), r covering every configuration's
    front element from ``z_front`` (:func:`forward_domain` of each, its plane moved into that lens's space), the
    film reach on the one sensor plane (``reach_radius_mm``; None: every ray that passes), the configurations as
    inputs."""
    from ..optics import moving as mv
    lenses = [mv.at(configs.lens, t, f, check=False) for t, f in configs.corner_configurations(per_interval=1)]
    field = max(default_field_half_angle(ln, film_half_diagonal_mm, field_margin) for ln in lenses)
    r = max(forward_domain(ln, z_front + configs.shift_of(ln.image_z), field, margin).r_max for ln in lenses)
    reach = (Reach(float(configs.z_sensor), float(configs.z_sensor), float(reach_radius_mm))
             if reach_radius_mm else None)
    return Domain(r_max=r, s_max=min(math.sin(math.radians(field)), 0.999), reach=reach, conditions=configs)


def film_reach(lens, s_range, radius_mm: float) -> Reach:
    """The film reach of forward maps (:class:`~mi_neurallens.transport.planning.Reach`): the sensor planes
    at both ends of the supported sensor distances ``s_range`` (mm behind the last vertex) and ``radius_mm``
    (the film half diagonal times ``TrainConfig.film_reach``)."""
    s0, s1 = s_range
    return Reach(float(lens.total_track + s0), float(lens.total_track + s1), float(radius_mm))


def backward_domain(lens, path_id: int, z_rear: float, z_front: float, rng, n: int = 1 << 22,
                    margin: float = 1.04, conditions=None) -> Domain:
    """Pilot-traced extent of the valid backward region (largest r and |ω_xy| of a valid ray), plus
    ``margin``: ``n`` unit-cube points from ``rng`` traced in float32 over a domain wider than the lens.
    ``conditions``: a lens with moving groups, its configuration inputs
    (:class:`~mi_neurallens.transport.configurations.Configurations`; the planes in their frame): the extent over
    every configuration, and the domain takes them."""
    import drjit as dr
    from ..jit import from_numpy
    from ..trace.api import float_type
    from .exact import ExactMap
    big = max(s.semi_diameter for s in lens.surfaces) * 2.0
    pilot = Domain(big, 0.995, conditions=conditions)
    em = ExactMap(lens, path_id, "backward", z_rear, z_front, fresnel=True, domain=pilot)
    u = rng.random((n, pilot.dims))
    F = float_type("float32")
    valid, outs = em.core_reduced_finite_dr(pilot.u_to_x_dr([from_numpy(F, u[:, i]) for i in range(pilot.dims)]), 5)
    dr.eval(outs, valid)                # the kernel the training sampler's trace_u runs
    xv = pilot.u_to_x(u[valid.numpy().astype(bool)])
    if len(xv) == 0:
        raise NeuralLensError(f"lens '{lens.name}': no backward ray passes the lens")
    r = float(xv[:, 0].max()) * margin
    s = min(float(np.hypot(xv[:, 1], xv[:, 2]).max()) * margin, 0.999)
    return Domain(r_max=r, s_max=s, conditions=conditions)
