"""The validated model of a rotationally symmetric lens prescription.

Conventions (the single place they are written down in code; see docs/lens-format.md):

* Lens space is in **millimetres**.  The optical axis is +z, from object space toward the sensor.
* The FIRST surface's vertex is at z = 0; vertex i+1 lies ``thickness[i]`` behind vertex i.
* ``radius > 0``: the centre of curvature lies on the image side (+z).  ``math.inf`` = flat.
* Each surface lists the medium AFTER it (toward +z).  The object-space medium is
  :attr:`Lens.object_medium` (air by default).
* The last surface's thickness is the distance from the last vertex to the image (sensor) plane,
  so the image plane is at z = Σ thickness.
* Sag: ``z(r) = c r² / (1 + sqrt(1 − (1+K) c² r²)) + A4 r⁴ + A6 r⁶ + … + A16 r¹⁶``, c = 1/R.
* The aperture stop is its own surface (flat, in a gap; ``is_stop=True``) with the stop radius as
  its semi-diameter, optionally a polygon of ``blades`` straight blades whose *inscribed* circle
  is ``semi_diameter`` (so the f-number is that of the inscribed circle).
* ``housing_radius``: optional radius of a mechanical baffle (spacer/retaining ring) in the plane of
  the surface's rim, z = vertex + sag(semi_diameter); rays crossing that plane farther from the axis
  are absorbed.  ``None``: no baffle beyond the clear semi-diameter.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
import hashlib
import json
import math

import numpy as np

from ..constants import LAMBDA_D
from ..errors import LensError
from .coatings import Coating, CoatingStack
from .glass import AIR, Medium

MAX_ASPHERIC = 7  # A4 … A16


@dataclass(frozen=True)
class Surface:
    """One surface of a sequential lens.  Lengths in mm."""

    radius: float
    thickness: float
    medium: Medium
    semi_diameter: float
    conic: float = 0.0
    aspheric: tuple[float, ...] = ()
    housing_radius: float | None = None
    is_stop: bool = False
    blades: int = 0
    blade_rotation_deg: float = 0.0
    coating: Coating | CoatingStack | None = None
    label: str = ""

    @property
    def curvature(self) -> float:
        """c = 1/R in 1/mm (0 for a flat surface)."""
        return 0.0 if math.isinf(self.radius) else 1.0 / self.radius

    @property
    def is_flat(self) -> bool:
        return self.curvature == 0.0 and not any(self.aspheric)

    @property
    def is_aspheric(self) -> bool:
        return any(a != 0.0 for a in self.aspheric)

    def sag(self, r):
        """Sag z(r) − z_vertex in mm at radial distance ``r`` (mm, numpy or float)."""
        r = np.asarray(r, dtype=np.float64)
        c, k = self.curvature, self.conic
        s = r * r
        arg = 1.0 - (1.0 + k) * c * c * s
        with np.errstate(invalid="ignore"):
            z = c * s / (1.0 + np.sqrt(arg))
        p = s * s
        for a in self.aspheric:
            z = z + a * p
            p = p * s
        return z

    def sag_slope(self, r):
        """dz/dr (numpy)."""
        r = np.asarray(r, dtype=np.float64)
        c, k = self.curvature, self.conic
        s = r * r
        with np.errstate(invalid="ignore", divide="ignore"):
            dz_ds = c / (2.0 * np.sqrt(1.0 - (1.0 + k) * c * c * s))
        for i, a in enumerate(self.aspheric):
            dz_ds = dz_ds + (i + 2) * a * s ** (i + 1)
        return 2.0 * r * dz_ds

    def max_semi_diameter(self) -> float:
        """Largest radial extent at which the conic sag is defined (inf when unlimited)."""
        c, k = self.curvature, self.conic
        if c == 0.0 or 1.0 + k <= 0.0:
            return math.inf
        return 1.0 / (abs(c) * math.sqrt(1.0 + k))


@dataclass(frozen=True)
class Lens:
    """A validated, immutable lens prescription.  Build with :meth:`Lens.load` or the constructor.

    The constructor validates (see :func:`validate`); errors are :class:`~mi_neurallens.errors.LensError`
    naming the file, surface and field.
    """

    surfaces: tuple[Surface, ...]
    name: str = "lens"
    object_medium: Medium = AIR
    #: variable gaps for zoom and focusing (:class:`~mi_neurallens.optics.moving.MovingGroups`), or None: one
    #: configuration, focused by moving the whole lens (unit focusing).  Part of the fingerprint.
    moving: object = field(default=None, hash=False)
    #: provenance and free-form metadata (source file, patent, notes); not part of the fingerprint
    metadata: dict = field(default_factory=dict, compare=False, hash=False)
    #: file this lens was read from, used in error messages
    path: str | None = field(default=None, compare=False, hash=False)

    def __post_init__(self):
        object.__setattr__(self, "surfaces", tuple(self.surfaces))
        validate(self)

    # ------------------------------------------------------------------ geometry
    @property
    def num_surfaces(self) -> int:
        return len(self.surfaces)

    @property
    def vertex_z(self) -> np.ndarray:
        """z of each vertex in lens space (mm); the first is 0."""
        t = np.array([s.thickness for s in self.surfaces[:-1]], dtype=np.float64)
        return np.concatenate([[0.0], np.cumsum(t)])

    @property
    def image_z(self) -> float:
        """z of the image (sensor) plane in lens space (mm): Σ thickness."""
        return float(sum(s.thickness for s in self.surfaces))

    @property
    def total_track(self) -> float:
        """First vertex to last vertex (mm)."""
        return float(self.vertex_z[-1])

    @property
    def stop_index(self) -> int:
        return next(i for i, s in enumerate(self.surfaces) if s.is_stop)

    @property
    def stop(self) -> Surface:
        return self.surfaces[self.stop_index]

    @property
    def optical_indices(self) -> tuple[int, ...]:
        """Indices of the surfaces that refract/reflect (every surface but the stop), front to back.

        Path ids (see :mod:`mi_neurallens.trace.paths`) count interactions on these surfaces only.
        """
        return tuple(i for i, s in enumerate(self.surfaces) if not s.is_stop)

    def medium_before(self, i: int) -> Medium:
        return self.object_medium if i == 0 else self.surfaces[i - 1].medium

    # ------------------------------------------------------------------ variants
    def replace(self, **kw) -> "Lens":
        return dataclasses.replace(self, **kw)

    def unchecked(self, **kw) -> "Lens":
        """A copy with ``kw`` replaced and **no validation**: for numeric searches that only need the paraxial
        optics of many trial configurations (:mod:`.moving`); build the result with :meth:`replace`."""
        out = object.__new__(Lens)
        for f in dataclasses.fields(self):
            object.__setattr__(out, f.name, kw.get(f.name, getattr(self, f.name)))
        object.__setattr__(out, "surfaces", tuple(out.surfaces))
        return out

    def with_surface(self, i: int, **kw) -> "Lens":
        s = list(self.surfaces)
        s[i] = dataclasses.replace(s[i], **kw)
        return self.replace(surfaces=tuple(s))

    def with_sensor_distance(self, d_mm: float) -> "Lens":
        """The same lens with the image plane ``d_mm`` behind the last vertex."""
        return self.with_surface(len(self.surfaces) - 1, thickness=float(d_mm))

    def with_stop_radius(self, r_mm: float) -> "Lens":
        return self.with_surface(self.stop_index, semi_diameter=float(r_mm))

    def with_coating(self, coating: Coating | CoatingStack | None) -> "Lens":
        """Every optical surface but the stop gets ``coating`` (``None`` removes all); surfaces between
        identical media ignore it."""
        s = [dataclasses.replace(x, coating=None if x.is_stop else coating) for x in self.surfaces]
        return self.replace(surfaces=tuple(s))

    # ------------------------------------------------------------------ identity
    def to_dict(self) -> dict:
        from .formats.project_json import lens_to_dict
        return lens_to_dict(self)

    def fingerprint(self) -> str:
        """SHA-256 (hex, 16 chars) of the optical content: surfaces and media, not names/metadata."""
        payload = {
            "object_medium": _medium_key(self.object_medium),
            "surfaces": [
                [_num(s.radius), _num(s.thickness), _medium_key(s.medium), _num(s.semi_diameter),
                 _num(s.conic), [_num(a) for a in s.aspheric], _num(s.housing_radius), s.is_stop,
                 s.blades, _num(s.blade_rotation_deg),
                 _coating_key(s.coating)]
                for s in self.surfaces
            ],
        }
        if self.moving is not None:         # only then: a lens without moving groups keeps its fingerprint
            payload["moving"] = self.moving.key()
        blob = json.dumps(payload, sort_keys=True, separators=(",", ":")).encode()
        return hashlib.sha256(blob).hexdigest()[:16]

    # ------------------------------------------------------------------ I/O, optics (thin wrappers)
    @staticmethod
    def load(path, **kw) -> "Lens":
        """Read a prescription: project JSON, pbrt ``.dat``, Open Optical Designer or LensVisualizer JSON,
        Zemax ``.zmx`` (detected from the content), or the name of a bundled lens (see ``lenses/``)."""
        from .formats import load_lens
        return load_lens(path, **kw)

    def save(self, path) -> None:
        """Write the project JSON format (atomically)."""
        from .formats.project_json import save_lens
        save_lens(self, path)

    def paraxial(self, wavelength_nm: float = LAMBDA_D):
        from .paraxial import ParaxialSystem
        return ParaxialSystem(self, wavelength_nm)

    def efl(self, wavelength_nm: float = LAMBDA_D) -> float:
        """Effective focal length (mm), paraxial."""
        return self.paraxial(wavelength_nm).efl

    def bfl(self, wavelength_nm: float = LAMBDA_D) -> float:
        """Back focal length (mm): last vertex to the paraxial image of an object at infinity."""
        return self.paraxial(wavelength_nm).bfl

    def trace(self, origins, directions, wavelength_nm, direction: str = "forward",
              path="transmit", **kw):
        """Trace rays exactly (numpy in, numpy out); see :func:`mi_neurallens.trace.api.trace`."""
        from ..trace.api import trace
        return trace(self, origins, directions, wavelength_nm, direction=direction, path=path, **kw)

    def __repr__(self) -> str:
        return (f"Lens({self.name!r}, {len(self.surfaces)} surfaces, stop at {self.stop_index}, "
                f"track {self.total_track:.3f} mm, image plane z={self.image_z:.3f} mm)")


def _num(x):
    if x is None:
        return None
    x = float(x)
    return "inf" if math.isinf(x) else float(f"{x:.12g}")


def _medium_key(m: Medium):
    return [m.formula, [_num(c) for c in m.coefficients]]


def _coating_key(c):
    """A single layer as the first model files recorded it; a stack by its design wavelength and layers."""
    if c is None:
        return None
    if isinstance(c, Coating):
        return [_num(c.index), _num(c.design_wavelength_nm)]
    return ["stack", _num(c.design_wavelength_nm), [[_medium_key(l.medium), _num(l.thickness_nm)] for l in c.layers]]


# ---------------------------------------------------------------------- validation
def validate(lens: Lens) -> None:
    """Raise :class:`LensError` for an impossible prescription.

    Checks: finite numbers of the right type, at least one optical surface, exactly one stop (flat,
    no coating), positive semi-diameters no larger than the surface allows, thicknesses positive
    (zero allowed only for the last surface before focusing and the stop), aspheric terms ≤ A16,
    blades ≥ 3 or 0, housing ≥ 0, and no two consecutive surfaces whose sags cross inside their
    common clear aperture.
    """
    f = lens.path
    surfs = lens.surfaces
    if len(surfs) < 2:
        raise LensError(f"a lens needs at least one optical surface and a stop, got {len(surfs)} surface(s)",
                        file=f)
    stops = [i for i, s in enumerate(surfs) if s.is_stop]
    if not stops:
        raise LensError("no aperture stop: mark exactly one surface as the stop", file=f)
    if len(stops) > 1:
        raise LensError(f"more than one aperture stop (surfaces {stops}); exactly one is allowed", file=f)
    for i, s in enumerate(surfs):
        where = dict(file=f, surface=i, label=s.label or None)
        for name in ("radius", "thickness", "semi_diameter", "conic", "blade_rotation_deg"):
            v = getattr(s, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise LensError(f"must be a number, got {type(v).__name__} {v!r}", field=name, **where)
            if math.isnan(v) or (math.isinf(v) and name != "radius"):
                raise LensError(f"must be finite, got {v}", field=name, **where)
        if s.radius == 0.0:
            raise LensError("radius 0 is not a surface; write inf (or null) for a flat one", field="radius",
                            **where)
        if not isinstance(s.medium, Medium):
            raise LensError(f"medium must be a Medium, got {s.medium!r}", field="medium", **where)
        last = i == len(surfs) - 1
        if s.thickness < 0 or (s.thickness == 0 and not last and not s.is_stop
                               and not surfs[i + 1].is_stop):
            raise LensError(f"thickness must be > 0 (distance to the next vertex), got {s.thickness}",
                            field="thickness", **where)
        if not s.semi_diameter > 0:
            raise LensError(f"clear semi-diameter must be > 0 mm, got {s.semi_diameter}",
                            field="semi_diameter", **where)
        mx = s.max_semi_diameter()
        if s.semi_diameter > mx * (1 + 1e-9):
            raise LensError(f"semi-diameter {s.semi_diameter:g} mm is larger than the surface allows "
                            f"({mx:.6g} mm for R={s.radius:g}, K={s.conic:g})", field="semi_diameter", **where)
        if len(s.aspheric) > MAX_ASPHERIC or any(not math.isfinite(a) for a in s.aspheric):
            raise LensError(f"aspheric coefficients must be finite A4…A16 (≤ {MAX_ASPHERIC} values), "
                            f"got {list(s.aspheric)}", field="aspheric", **where)
        if s.housing_radius is not None and not (s.housing_radius > 0 and math.isfinite(s.housing_radius)):
            raise LensError(f"housing radius must be a positive number of mm, got {s.housing_radius}",
                            field="housing_radius", **where)
        if s.blades and (not s.is_stop or s.blades < 3):
            raise LensError(f"blades must be 0 (circular) or ≥ 3, and only on the stop; got {s.blades}",
                            field="blades", **where)
        if s.is_stop:
            if not math.isinf(s.radius) or s.conic or s.is_aspheric:
                raise LensError("the aperture stop must be flat (radius inf)", field="radius", **where)
            if s.medium != lens.medium_before(i):
                raise LensError("the aperture stop must sit in a gap: the medium after it must equal the "
                                f"medium before it ({lens.medium_before(i).name}), got {s.medium.name}",
                                field="medium", **where)
            if s.coating is not None:
                raise LensError("the aperture stop cannot carry a coating", field="coating", **where)
    _check_sags(lens)
    if lens.moving is not None:
        _check_moving(lens)


def surfaces_cross(a: Surface, za: float, b: Surface, zb: float):
    """Where surface ``b`` (vertex at ``zb``) lies in front of the surface ``a`` before it (vertex at
    ``za``) within their common semi-diameter: ``(r, depth)`` in mm of the first such radius (65 samples,
    1 nm tolerance), or None when they do not cross."""
    r = np.linspace(0.0, min(a.semi_diameter, b.semi_diameter), 65)
    gap = (zb + b.sag(r)) - (za + a.sag(r))
    bad = np.nonzero(~(gap >= -1e-6))[0]
    return (float(r[bad[0]]), float(-gap[bad[0]])) if bad.size else None


def _check_sags(lens: Lens) -> None:
    z = lens.vertex_z
    surfs = lens.surfaces
    for i in range(len(surfs) - 1):
        a = surfs[i]
        hit = surfaces_cross(a, z[i], surfs[i + 1], z[i + 1])
        if hit is not None:
            raise LensError(f"surfaces {i} and {i + 1} cross: at r = {hit[0]:.4g} mm surface {i + 1} lies "
                            f"{hit[1]:.4g} mm in front of surface {i} (increase thickness {i} or reduce "
                            f"the semi-diameters)", file=lens.path, surface=i, label=a.label or None,
                            field="thickness")


def _check_moving(lens: Lens) -> None:
    """Moving groups name existing surfaces and hold the surfaces' own gaps at their first position and infinity
    focus (the lens as written is that configuration).  The other configurations are checked when one is built
    (:func:`~mi_neurallens.optics.moving.at`): a catalogue's computed close-focus gaps can make groups collide at
    a position the lens is never asked for."""
    from .moving import MovingGroups
    mg, f = lens.moving, lens.path
    if not isinstance(mg, MovingGroups):
        raise LensError(f"moving groups must be a MovingGroups, got {type(mg).__name__}", file=f)
    n = len(lens.surfaces)
    for i, v in mg.gaps.items():
        if not 0 <= i < n:
            raise LensError(f"moving groups: variable gap after surface {i}, but the lens has surfaces 0-{n - 1}",
                            file=f, field="moving")
        if abs(v[0][0] - lens.surfaces[i].thickness) > 1e-9 * max(1.0, abs(v[0][0])):
            raise LensError(f"moving groups: the gap after surface {i} is {lens.surfaces[i].thickness:g} mm, but its "
                            f"first position at infinity focus lists {v[0][0]:g} mm (the lens as written must be that "
                            "configuration)", file=f, surface=i, field="thickness")
    if mg.stop_semi_diameters is not None and abs(mg.stop_semi_diameters[0] - lens.stop.semi_diameter) > 1e-9 * max(
            1.0, lens.stop.semi_diameter):
        raise LensError(f"moving groups: the stop's semi-diameter is {lens.stop.semi_diameter:g} mm, but its first "
                        f"position lists {mg.stop_semi_diameters[0]:g} mm", file=f, field="moving")
