"""Numpy-facing exact tracing: ``Lens.trace`` (numpy in, numpy out).

Runs the Dr.Jit tracer on the LLVM backend (CUDA if LLVM is unavailable), independent of any
Mitsuba variant that may be set.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..errors import NeuralLensError
from ..jit import from_numpy


@dataclass
class RayBundle:
    """Result of :func:`trace`, numpy arrays in lens space (mm).

    ``position`` (N,3): where the ray crosses the output plane (forward: the image plane;
    backward: the first-vertex plane z = 0); ``direction`` (N,3) unit; ``throughput`` (N,):
    product of Fresnel factors; ``valid`` (N,) bool.  Invalid rays have NaN position/direction
    and zero throughput.  ``points`` (N, M, 3), with ``record=True``: the input point, each
    surface/stop hit in path order, and the output point (NaN where the ray is invalid).  Float64, or
    float32 when :func:`trace` was given float32 rays at float32 precision.
    """

    position: np.ndarray
    direction: np.ndarray
    throughput: np.ndarray
    valid: np.ndarray
    points: np.ndarray | None = None


def float_type(precision: str = "float32"):
    """The Dr.Jit float array type used by the numpy API (``float32`` or ``float64``)."""
    import drjit as dr
    if precision not in ("float32", "float64"):
        raise NeuralLensError(f"precision must be 'float32' or 'float64', got {precision!r}")
    if dr.has_backend(dr.JitBackend.LLVM):
        from ..jit import check_llvm
        check_llvm()
        import drjit.llvm as be
    elif dr.has_backend(dr.JitBackend.CUDA):  # pragma: no cover - no GPU here
        import drjit.cuda as be
    else:  # pragma: no cover
        raise NeuralLensError("Dr.Jit has neither an LLVM nor a CUDA backend; install libLLVM >= 16")
    return be.Float if precision == "float32" else be.Float64


@lru_cache(maxsize=32)
def tracer_for(lens, fresnel: bool = True):
    """A cached :class:`~mi_neurallens.trace.tracer.LensTracer` for ``lens``."""
    from .tracer import LensTracer
    return LensTracer(lens, fresnel=fresnel)


def trace(lens, origins, directions, wavelength_nm, direction: str = "forward", path="transmit", *,
          fresnel: bool = True, precision: str = "float32", z_out: float | None = None,
          record: bool = False, opaque: bool = False) -> RayBundle:
    """Trace rays exactly through ``lens`` along one path type.

    Parameters
    ----------
    origins, directions: (N, 3) arrays in lens space (mm); directions are normalised here.
        Forward rays start in object space (z < first surface) heading +z; backward rays start on
        the sensor side heading −z.  A ray is a line in its first medium, so the origin may lie
        anywhere on it in front of the first surface it meets.
    wavelength_nm: scalar or (N,) wavelengths in nm.
    direction: ``"forward"`` (object → sensor) or ``"backward"`` (sensor → object).
    path: ``"transmit"``, an integer path id or a ghost ``(a, b)``; see :mod:`.paths`.
    fresnel: include Fresnel factors in the throughput.
    precision: ``"float32"`` (rendering) or ``"float64"`` (reference data).  With ``float32`` and
        float32 ``origins`` and ``directions``, everything stays float32, the results included (the fast
        path); otherwise the inputs are read as float64 and the results are float64.
    z_out: output plane z in lens space (default: image plane forward, z = 0 backward).
    record: also return every hit point (``RayBundle.points``).
    opaque: the surfaces' curvatures, conics, aspheric coefficients and vertex positions enter the kernel as
        inputs, not literals (:meth:`~mi_neurallens.trace.parameters.LiveGeometry.opaque`), so that lenses that
        differ only in those numbers share one kernel (a lens being optimised: its pupil bounds each step).
    """
    import drjit as dr
    F = float_type(precision)
    dt = np.float32 if precision == "float32" else np.float64
    # float32 in, float32 precision: float32 end to end (no float64 copies in or out)
    f32 = dt == np.float32 and all(getattr(a, "dtype", None) == np.float32 for a in (origins, directions))
    wd = np.float32 if f32 else np.float64
    o = np.asarray(origins, dtype=wd)
    d = np.asarray(directions, dtype=wd)
    if o.ndim != 2 or o.shape[1] != 3 or d.shape != o.shape:
        raise NeuralLensError(f"origins and directions must both be (N, 3) arrays, got {o.shape} and {d.shape}")
    n = o.shape[0]
    lam = np.broadcast_to(np.asarray(wavelength_nm, dtype=wd), (n,))
    if not np.all(np.isfinite(lam)) or np.any(lam <= 0):
        raise NeuralLensError("wavelength_nm must be positive and finite (nanometres)")
    cols = lambda a: tuple(from_numpy(F, a[:, i]) for i in range(3))
    if opaque:
        from .parameters import LiveGeometry
        from .tracer import LensTracer
        tr = LensTracer(lens, bool(fresnel), geometry=LiveGeometry.opaque(lens, F))
    else:
        tr = tracer_for(lens, bool(fresnel))
    dx, dy, dz = cols(d)
    inv = 1.0 / dr.sqrt(dx * dx + dy * dy + dz * dz)          # normalised in the kernel
    res = tr.trace(cols(o), (dx * inv, dy * inv, dz * inv), from_numpy(F, lam), path,
                   direction, z_out=z_out, record=record)
    # invalid rays: NaN position and direction, zero throughput (selected in the kernel as well)
    position = [dr.select(res.valid, c, dr.nan) for c in res.position]
    direction_ = [dr.select(res.valid, c, dr.nan) for c in res.direction]
    throughput = dr.select(res.valid, res.throughput, 0.0)
    arrays = [*position, *direction_, throughput]
    if record:
        for p in res.points:
            arrays += list(p)
        arrays += list(res.alive)
    dr.eval(arrays, res.valid)
    valid = res.valid.numpy().astype(bool)

    def rows(vec):
        """(N, 3) from three Dr.Jit columns: one contiguous copy per column into a (3, N) block."""
        out = np.empty((3, n), wd)
        for i, c in enumerate(vec):
            out[i] = c.numpy()
        return out.T

    pos, dirn = rows(position), rows(direction_)
    thr = throughput.numpy().astype(wd, copy=False)
    pts = None
    if record:
        pts = np.stack([np.stack([c.numpy() for c in p], 1) for p in res.points], 1).astype(wd, copy=False)
        alive = np.stack([np.broadcast_to(a.numpy().astype(bool), (n,)) for a in res.alive], 1)
        # keep the hit where a ray is blocked: alive[k] is recorded when the ray reaches point k, before
        # that step's aperture, stop and TIR tests, so a ray blocked at point k still shows it and
        # nothing after it
        pts[~alive] = np.nan
    return RayBundle(pos, dirn, thr, valid, pts)
