"""First-order (paraxial) optics of a :class:`~mi_neurallens.optics.prescription.Lens`.

:class:`ParaxialSystem` runs a y–nu trace (equivalently, multiplies 2×2 ray-transfer matrices) at one
wavelength, with every medium's index ``medium.index(λ)`` and the object medium ``lens.object_medium``.
Conics and even aspheres enter with their vertex curvature ``1/R`` only (the polynomial terms start
at r⁴ and have no paraxial effect).  The aperture stop is a flat surface in a gap: it only transfers.

Conventions (lens space, see :mod:`mi_neurallens.optics.prescription`):

* lengths in mm; ``*_z`` attributes are lens-space z coordinates (first vertex at z = 0, +z toward
  the sensor); ``inf`` means "at infinity".
* *Distances* are measured from the natural vertex and are positive in the natural direction:
  ``bfl`` is from the LAST vertex to the rear focal point, positive behind it (+z); ``ffl`` is from
  the FIRST vertex to the front focal point, positive IN FRONT of it (−z).  Object distances are
  measured in front of the first vertex (positive toward the object); sensor/image distances are
  measured behind the last vertex.
* Reduced angle ω = n·u, with u = dy/dz the paraxial slope in a medium of index n.
  Refraction at a surface of vertex curvature c from n to n′: ω′ = ω − y·φ, φ = (n′ − n)·c.
  Transfer over a thickness t in the medium n′ after a surface: y′ = y + t·ω′/n′.
* Power Φ = −C of the system matrix (:meth:`ParaxialSystem.abcd`).
  ``efl`` is the REAR (image-space) focal length n′/Φ: the distance from the rear principal plane to
  the rear focal point, which is also what optiland's ``f2()`` and rayoptics' ``fod.efl`` report.
  The front focal length is ``front_focal_length`` = n/Φ (positive for a converging lens; the front
  focal point lies that far in front of the front principal plane).  In air both equal 1/Φ.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import NamedTuple

import numpy as np

from ..constants import LAMBDA_D
from ..errors import LensError

#: |Φ| · (track length + 1 mm) below this is treated as afocal (no finite focal length).
AFOCAL_TOL = 1e-9


class FieldOfView(NamedTuple):
    """Full field of view in degrees of a rectangular sensor (see :meth:`ParaxialSystem.fov_deg`)."""

    horizontal: float
    vertical: float
    diagonal: float


class DepthOfField(NamedTuple):
    """Depth of field; every distance is in mm IN FRONT OF THE FIRST VERTEX (``inf`` = infinity)."""

    near_mm: float
    far_mm: float
    total_mm: float
    hyperfocal_mm: float


def _mat_refract(phi: float) -> np.ndarray:
    return np.array([[1.0, 0.0], [-phi, 1.0]])


def _mat_transfer(t: float, n: float) -> np.ndarray:
    return np.array([[1.0, t / n], [0.0, 1.0]])


def _json_num(x):
    """float, with ±inf/NaN written as None (JSON has no infinity); None means "at infinity"."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


@dataclass(frozen=True)
class _Matrices:
    system: np.ndarray       # first vertex (object side) -> last vertex (image side)
    front: np.ndarray        # first vertex (object side) -> stop plane
    rear: np.ndarray         # stop plane -> last vertex (image side)


class ParaxialSystem:
    """Paraxial (first-order) model of ``lens`` at ``wavelength_nm``.

    Build with ``lens.paraxial(λ)``.  Every number is a plain float in mm (or degrees where named);
    positions are lens-space z (see the module docstring for signs).  Raises
    :class:`~mi_neurallens.errors.LensError` for an afocal system (Φ = 0): a camera lens must focus.
    """

    def __init__(self, lens, wavelength_nm: float = LAMBDA_D):
        wl = float(wavelength_nm)
        if not (math.isfinite(wl) and wl > 0):
            raise LensError(f"wavelength must be a positive number of nm, got {wavelength_nm!r}",
                            file=lens.path)
        self.lens = lens
        self.wavelength_nm = wl
        surfs = lens.surfaces
        n_before = float(lens.object_medium.index(wl))
        self.object_index = n_before
        #: index of the medium after each surface at this wavelength
        self.indices = []
        for i, s in enumerate(surfs):
            n_after = float(s.medium.index(wl))
            if not (math.isfinite(n_after) and n_after > 0):
                raise LensError(f"refractive index of '{s.medium.name}' at {wl:g} nm is {n_after}; "
                                "it must be a positive number", file=lens.path, surface=i,
                                label=s.label or None, field="medium")
            self.indices.append(n_after)
        self.image_index = self.indices[-1]
        self.vertex_z = np.asarray(lens.vertex_z, dtype=np.float64)
        self.stop_index = lens.stop_index
        self.stop_z = float(self.vertex_z[self.stop_index])
        self.stop_radius = float(lens.stop.semi_diameter)
        self.last_vertex_z = float(self.vertex_z[-1])
        self.image_z = float(lens.image_z)
        #: the current sensor distance: last vertex to image plane (the last thickness)
        self.sensor_distance = float(surfs[-1].thickness)
        self._m = self._build()

        A, B, C, D = self._m.system.ravel()
        self.power = -float(C)
        track = abs(self.last_vertex_z) + 1.0
        if not abs(self.power) * track > AFOCAL_TOL:
            raise LensError(f"the system is afocal at {wl:g} nm (power {self.power:.3g} 1/mm): it has no "
                            "focal length, focal points or image of an object at infinity",
                            file=lens.path)
        n, n2, P = self.object_index, self.image_index, self.power
        self.efl = n2 / P
        self.front_focal_length = n / P
        self.bfl = float(A) * n2 / P
        self.ffl = float(D) * n / P
        self.rear_focal_z = self.last_vertex_z + self.bfl
        self.front_focal_z = -self.ffl
        self.rear_principal_z = self.rear_focal_z - self.efl
        self.front_principal_z = self.front_focal_z + self.front_focal_length
        # nodal points: displaced from the principal points by (n' - n)/Φ toward +z
        self.front_nodal_z = self.front_principal_z + (n2 - n) / P
        self.rear_nodal_z = self.rear_principal_z + (n2 - n) / P

        # Entrance pupil: the stop seen through the surfaces in front of it.
        a, b, _, _ = self._m.front.ravel()
        if abs(a) < 1e-15:
            self.entrance_pupil_z = math.inf
            self.entrance_pupil_radius = math.inf
        else:
            self.entrance_pupil_z = float(b) * n / float(a)
            self.entrance_pupil_radius = self.stop_radius / abs(float(a))
        # Exit pupil: the stop seen through the surfaces behind it.
        _, b2, _, d2 = self._m.rear.ravel()
        if abs(d2) < 1e-15:
            self.exit_pupil_z = math.inf
            self.exit_pupil_radius = math.inf
        else:
            self.exit_pupil_z = self.last_vertex_z - float(b2) * n2 / float(d2)
            self.exit_pupil_radius = self.stop_radius / abs(float(d2))
        self.entrance_pupil_diameter = 2.0 * self.entrance_pupil_radius
        #: EFL / entrance-pupil diameter (object at infinity)
        self.fnumber = abs(self.efl) / self.entrance_pupil_diameter
        #: exit-pupil radius / entrance-pupil radius
        self.pupil_magnification = (self.exit_pupil_radius / self.entrance_pupil_radius
                                    if math.isfinite(self.entrance_pupil_radius) else math.nan)

    # ------------------------------------------------------------------ matrices
    def _build(self) -> _Matrices:
        surfs = self.lens.surfaces
        n_prev = self.object_index
        M = np.eye(2)
        front = None
        for i, s in enumerate(surfs):
            n_next = self.indices[i]
            if i == self.stop_index:
                front = M.copy()           # at the stop plane (stop is flat, no power)
                M = np.eye(2)
            else:
                M = _mat_refract((n_next - n_prev) * s.curvature) @ M
            if i < len(surfs) - 1:
                M = _mat_transfer(s.thickness, n_next) @ M
            n_prev = n_next
        rear = M
        return _Matrices(system=rear @ front, front=front, rear=rear)

    def abcd(self) -> np.ndarray:
        """The 2×2 system matrix ``[[A, B], [C, D]]`` (a copy), reduced-angle convention.

        It maps ``(y, n·u)`` at the FIRST vertex plane, in the object medium just before the first
        surface, to ``(y, n′·u′)`` at the LAST vertex plane, in the image medium just after the last
        surface; u = dy/dz.  det = 1 and C = −Φ (power, 1/mm).
        """
        return self._m.system.copy()

    # ------------------------------------------------------------------ conjugates
    def _object_matrix(self, object_distance_mm: float) -> np.ndarray:
        d = float(object_distance_mm)
        return self._m.system @ _mat_transfer(d, self.object_index)

    def _check_object_distance(self, d):
        d = float(d)
        if math.isnan(d) or d <= 0:
            raise LensError(f"object distance must be > 0 mm in front of the first vertex (or inf), "
                            f"got {d}", file=self.lens.path)
        return d

    def image_distance(self, object_distance_mm: float) -> float:
        """Signed paraxial image distance behind the LAST vertex (mm) of an object at
        ``object_distance_mm`` in front of the FIRST vertex (``inf`` → :attr:`bfl`).

        A negative value is a virtual image (the object lies inside the front focal length of a
        converging lens).  Raises :class:`LensError` when the object sits in the front focal plane
        (image at infinity).  :meth:`sensor_distance_for` additionally rejects virtual images.
        """
        d = self._check_object_distance(object_distance_mm)
        if math.isinf(d):
            return self.bfl
        (a, b), (c, dd) = self._object_matrix(d)
        if abs(dd) < 1e-14 * (abs(a) + abs(b) + 1):
            raise LensError(f"an object {d:g} mm in front of the first vertex lies in the front focal "
                            f"plane (front focal distance {self.ffl:.6g} mm): its image is at infinity",
                            file=self.lens.path)
        return float(-self.image_index * b / dd)

    def sensor_distance_for(self, object_distance_mm: float) -> float:
        """Distance behind the LAST vertex (mm) at which an object ``object_distance_mm`` in front of
        the FIRST vertex is in paraxial focus (``inf`` → :attr:`bfl`).

        Raises :class:`LensError` when no sensor can focus it: the object at or inside the front focal
        point (virtual image or image at infinity), or a real image that would lie in front of the
        last vertex.
        """
        d = self._check_object_distance(object_distance_mm)
        if math.isinf(d):
            if self.bfl <= 0:
                raise LensError(f"the rear focal point lies {-self.bfl:.6g} mm in front of the last vertex "
                                "(inside the lens): no sensor position focuses infinity",
                                file=self.lens.path)
            return self.bfl
        if self.power > 0 and d <= self.ffl:
            raise LensError(f"cannot focus an object {d:g} mm in front of the first vertex: it must lie "
                            f"beyond the front focal point, more than {self.ffl:.6g} mm in front of the "
                            "first vertex (closer objects form virtual images)", file=self.lens.path)
        s = self.image_distance(d)
        if not s > 0:
            raise LensError(f"an object {d:g} mm in front of the first vertex has its image "
                            f"{'at ' + format(s, '.6g') + ' mm from' if s <= 0 else 'behind'} the last vertex, "
                            "which no sensor behind the lens can reach", file=self.lens.path)
        return s

    def focus_distance_for(self, sensor_distance_mm: float) -> float:
        """Object distance in front of the FIRST vertex (mm) that is in paraxial focus on a sensor
        ``sensor_distance_mm`` behind the LAST vertex; ``inf`` when the sensor is at the rear focal
        point.  The inverse of :meth:`sensor_distance_for`.

        Raises :class:`LensError` when the sensor is closer to the lens than the rear focal point
        (it would focus "beyond infinity") or the required object is virtual.
        """
        s = float(sensor_distance_mm)
        if not (math.isfinite(s) and s > 0):
            raise LensError(f"sensor distance must be a finite number of mm > 0 behind the last vertex, "
                            f"got {sensor_distance_mm!r}", file=self.lens.path)
        (A, B), (C, D) = self._m.system
        n, n2 = self.object_index, self.image_index
        if abs(s - self.bfl) <= 1e-12 * max(1.0, abs(self.bfl)):
            return math.inf
        den = s * C + n2 * A
        d = -n * (n2 * B + s * D) / den
        if not d > 0 and not (self.power > 0 and s < self.bfl):
            raise LensError(f"a sensor {s:g} mm behind the last vertex is conjugate to a point {-d:.6g} mm "
                            "BEHIND the first vertex (a virtual object): no real object is in focus there",
                            file=self.lens.path)
        if not d > 0 or (self.power > 0 and s < self.bfl):
            raise LensError(f"a sensor {s:g} mm behind the last vertex is closer than the rear focal point "
                            f"(BFL {self.bfl:.6g} mm): nothing in front of the lens is in focus there "
                            "(it would focus beyond infinity)", file=self.lens.path)
        return float(d)

    def magnification(self, object_distance_mm: float) -> float:
        """Paraxial lateral magnification y′/y of an object ``object_distance_mm`` in front of the
        first vertex, imaged at its paraxial image (negative: inverted; 0 for an object at infinity)."""
        d = self._check_object_distance(object_distance_mm)
        if math.isinf(d):
            return 0.0
        (_, _), (_, dd) = self._object_matrix(d)
        if dd == 0:
            return math.inf
        return float(1.0 / dd)

    def working_fnumber(self, object_distance_mm: float = math.inf) -> float:
        """Working (effective) f-number 1/(2 n′ |u′|) of the paraxial marginal ray from the on-axis
        object point at ``object_distance_mm`` in front of the first vertex, filling the entrance
        pupil; ≈ N (1 − m/m_p) and equal to :attr:`fnumber` · n′⁻¹ for an object at infinity."""
        d = self._check_object_distance(object_distance_mm)
        r = self.entrance_pupil_radius
        if math.isinf(d):
            omega = self._m.system[1, 0] * r
        else:
            dist = d + self.entrance_pupil_z          # object to entrance pupil, along +z
            if not math.isfinite(dist) or dist <= 0:
                raise LensError(f"an object {d:g} mm in front of the first vertex is not in front of the "
                                f"entrance pupil (z = {self.entrance_pupil_z:.6g} mm)", file=self.lens.path)
            u = r / dist
            omega = (self._object_matrix(d) @ np.array([0.0, self.object_index * u]))[1]
        if omega == 0:
            return math.inf
        return float(1.0 / (2.0 * abs(omega)))

    # ------------------------------------------------------------------ field of view
    def image_height_per_tan(self) -> float:
        """Paraxial chief-ray image height (mm) per unit tan(field angle) at the CURRENT image plane
        (last thickness), for an object at infinity.  It equals ``front_focal_length`` (= EFL in air)
        when the image plane is at the rear focal point."""
        a, b, _, _ = self._m.front.ravel()
        _, b2, _, d2 = self._m.rear.ravel()
        if abs(a) < 1e-15:
            raise LensError("the entrance pupil is at infinity (object-space telecentric): the chief ray "
                            "has no field angle", file=self.lens.path)
        # chief ray: ω = 1 at the stop centre; object space slope a/n, image plane height:
        h = float(b2) + self.sensor_distance * float(d2) / self.image_index
        return h * self.object_index / float(a)

    def fov_deg(self, sensor_width_mm: float, sensor_height_mm: float | None = None):
        """Full field of view (degrees) of a sensor centred on the axis at the current image plane,
        object at infinity.

        PARAXIAL, tan-based (gnomonic / distortion-free): a point at distance h from the axis sees the
        field angle atan(h / k), with k = :meth:`image_height_per_tan` (= EFL at infinity focus).
        Real lenses with distortion differ, fisheyes hugely (a fisheye's real field exceeds the
        < 180° this gives); trace real chief rays for those.

        With only ``sensor_width_mm``: the full angle across that extent (a float; pass the diagonal
        to get the diagonal FOV).  With both: :class:`FieldOfView` (horizontal, vertical, diagonal).
        """
        k = abs(self.image_height_per_tan())

        def full(w):
            w = float(w)
            if not (math.isfinite(w) and w > 0):
                raise LensError(f"sensor size must be > 0 mm, got {w!r}", file=self.lens.path)
            return 2.0 * math.degrees(math.atan(0.5 * w / k))

        if sensor_height_mm is None:
            return full(sensor_width_mm)
        return FieldOfView(full(sensor_width_mm), full(sensor_height_mm),
                           full(math.hypot(float(sensor_width_mm), float(sensor_height_mm))))

    # ------------------------------------------------------------------ depth of field
    def depth_of_field(self, object_distance_mm: float, fnumber: float | None = None,
                       coc_mm: float = 0.03) -> DepthOfField:
        """Paraxial depth of field around ``object_distance_mm`` (in front of the first vertex).

        Thick-lens model: distances are taken from the principal planes / focal points (Newton's
        form x·x′ = f·f′, f = n/Φ, f′ = n′/Φ), the sensor at the paraxial image of the focus
        distance, and the blur is the cone from an aperture of diameter D = EFL/N placed at the rear
        principal plane (pupil magnification 1; for air this is the classic
        near/far = s f² / (f² ± N c (s − f)) with s measured from the front principal plane).
        ``fnumber`` defaults to :attr:`fnumber`; ``coc_mm`` is the circle-of-confusion diameter.

        Returns :class:`DepthOfField` with near/far limits, total depth and the hyperfocal distance,
        all in mm IN FRONT OF THE FIRST VERTEX (``far_mm``/``total_mm`` = inf beyond hyperfocal).
        """
        N = self.fnumber if fnumber is None else float(fnumber)
        c = float(coc_mm)
        if not (N > 0 and math.isfinite(N)) or not (c > 0 and math.isfinite(c)):
            raise LensError(f"depth of field needs fnumber > 0 and coc_mm > 0, got {N}, {c}",
                            file=self.lens.path)
        if self.power <= 0:
            raise LensError("depth of field is defined for converging lenses only", file=self.lens.path)
        d = self._check_object_distance(object_distance_mm)
        f, f2 = self.front_focal_length, self.efl
        Dap = f2 / N
        hyper = f * Dap / c + self.ffl                     # x = f D / c, from F to the first vertex
        if math.isinf(d):
            x0p = 0.0
        else:
            self.sensor_distance_for(d)                    # raises for unfocusable objects
            x = d - self.ffl                               # object distance from the front focal point
            x0p = f * f2 / x                               # image distance from the rear focal point
        k = c / Dap
        xn = (x0p + k * f2) / (1.0 - k) if k < 1 else math.inf
        near = self.ffl + (f * f2 / xn if xn > 0 else math.inf)
        xf = (x0p - k * f2) / (1.0 + k)
        far = self.ffl + f * f2 / xf if xf > 0 else math.inf
        return DepthOfField(float(near), float(far), float(far - near), float(hyper))

    # ------------------------------------------------------------------ export
    def to_dict(self) -> dict:
        """Every number, JSON-ready, keyed by the attribute names.

        Units: mm (``power`` in 1/mm, ``wavelength_nm`` in nm, indices and ``fnumber`` unitless);
        ``*_z`` are lens-space z coordinates.  ``None`` stands for infinity (JSON has none).
        ``total_track`` = first to last vertex; ``sensor_distance`` = last vertex to image plane;
        ``focus_distance`` = object distance (in front of the first vertex) in focus on the current
        image plane; ``focus`` is ``"finite"``, ``"infinity"`` or ``"beyond_infinity"`` (sensor
        closer than the rear focal point; ``focus_distance`` is then ``None`` too).
        ``abcd`` is :meth:`abcd` as nested lists.
        """
        try:
            focus = self.focus_distance_for(self.sensor_distance)
            focus_state = "infinity" if math.isinf(focus) else "finite"
        except LensError:
            focus, focus_state = math.nan, "beyond_infinity"   # sensor in front of the rear focal point
        try:
            k = self.image_height_per_tan()
        except LensError:
            k = math.nan
        out = {
            "wavelength_nm": self.wavelength_nm,
            "object_index": self.object_index,
            "image_index": self.image_index,
            "power": self.power,
            "efl": self.efl,
            "front_focal_length": self.front_focal_length,
            "bfl": self.bfl,
            "ffl": self.ffl,
            "front_focal_z": self.front_focal_z,
            "rear_focal_z": self.rear_focal_z,
            "front_principal_z": self.front_principal_z,
            "rear_principal_z": self.rear_principal_z,
            "front_nodal_z": self.front_nodal_z,
            "rear_nodal_z": self.rear_nodal_z,
            "stop_z": self.stop_z,
            "stop_radius": self.stop_radius,
            "entrance_pupil_z": self.entrance_pupil_z,
            "entrance_pupil_radius": self.entrance_pupil_radius,
            "entrance_pupil_diameter": self.entrance_pupil_diameter,
            "exit_pupil_z": self.exit_pupil_z,
            "exit_pupil_radius": self.exit_pupil_radius,
            "pupil_magnification": self.pupil_magnification,
            "fnumber": self.fnumber,
            "total_track": self.last_vertex_z,
            "image_z": self.image_z,
            "sensor_distance": self.sensor_distance,
            "focus_distance": focus,
            "focus": focus_state,
            "image_height_per_tan": k,
            "abcd": [[float(v) for v in row] for row in self._m.system],
        }
        res = {}
        for key, v in out.items():
            if key in ("abcd", "focus"):
                res[key] = v
            else:
                res[key] = _json_num(v)
        return res

    def __repr__(self) -> str:
        return (f"ParaxialSystem({self.lens.name!r}, λ={self.wavelength_nm:g} nm, EFL={self.efl:.4f} mm, "
                f"BFL={self.bfl:.4f} mm, f/{self.fnumber:.3g})")
