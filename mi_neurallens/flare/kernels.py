"""The flare's two sampling kernels — the pilot pass's and the main pass's (splat) — and their frozen recordings.

One lane is one forward sample (the measurement is derived in :mod:`mi_neurallens.flare.render`): a point q on
the input plane z = z_in (lens space, mm), the light sampled from q (``emitter.sample_direction``: the direction
toward the light and E⊥), the ray continued through a :class:`~mi_neurallens.flare.evaluator.GhostEvaluator` to
the sensor plane, and its film value ``E⊥ · w_λ · T · |cos θ_q| · K / A_pix`` (the caller scales by A_q / N).
The pilot draws q from PCG32 streams in given cells; the main pass from a rank-1 lattice (an R_6 additive
recurrence in 32-bit fixed point) in the kept cells or the whole disk.

Dr.Jit traces these functions into one kernel each per evaluator: the renderer's constants (film, the sensor's
size) are literals, everything that changes between calls (the light, the scene, the camera's pose, the
film factor K / A_pix, sample counts) is an input, and so are the numbers a zoom or focus changes (the input and
sensor planes here, the tracer's vertex positions and stop radius), so that another configuration of the lens
reuses the kernels compiled for the first (Dr.Jit's kernel cache).  :meth:`FlareKernels.run` replays a kernel
recorded with ``dr.freeze`` instead of tracing it again (docs/flares.md, "Frozen kernels").
"""
from __future__ import annotations

import gc
import math

from ..constants import LUMINANCE_WEIGHTS

# golden-ratio style additive recurrence (R_d sequence, d = 6) in 32-bit fixed point
_PHI6 = 1.0
for _ in range(64):
    _PHI6 = (1.0 + _PHI6) ** (1.0 / 7.0)
_ALPHA = [int((1.0 / _PHI6 ** (k + 1)) % 1.0 * 2 ** 32) & 0xFFFFFFFF for k in range(6)]


#: PCG32's default initial state (its constructor's ``initstate``)
_PCG32_STATE = 0x853C49E6748FEA9B


def _u32_to_unit(mi, dr, x):
    return mi.Float(x >> 8) * (1.0 / 16777216.0)


def ev_hash(ev):
    """Random-stream id of an evaluator: its path only (not exact/neural), so that modes can share
    samples (see ``FlareOptions.pilot_with``)."""
    return (int(ev.pid) * 2654435761) & 0xFFFFFFFF


def rgb(hit, val, lam):
    """The film value of :meth:`FlareKernels.contrib`'s samples: ``([r, g, b], luminance)``, 0 where not ``hit``
    (pixel units; ``lam``: the samples' wavelengths (nm), whose colour is applied here, or None)."""
    import mitsuba as mi
    import drjit as dr
    if lam is not None:
        from ..sensors.wavelengths import rgb_weight
        val = val * rgb_weight(mi, lam)
    rgb = [dr.select(hit, val[i], 0.0) for i in range(3)]
    lum = LUMINANCE_WEIGHTS[0] * rgb[0] + LUMINANCE_WEIGHTS[1] * rgb[1] + LUMINANCE_WEIGHTS[2] * rgb[2]
    return rgb, lum


class FlareKernels:
    """The pilot and splat kernels of one renderer, and their frozen recordings.

    Fixed for the renderer's life and read as literals: ``setup`` (the sensor's lens set-up: its scene unit and
    size in mm), ``sensor`` (its wavelength sampling), ``lambda_mode`` (one λ per sample or none), the film's
    ``size`` and its crop window ``crop_offset``, ``crop_size`` (pixels).  ``z_in`` (the input plane, lens space,
    mm) and the set-up's sensor plane are kernel inputs, handed to each call in ``xf`` (:meth:`planes`)."""

    def __init__(self, setup, sensor, lambda_mode, z_in: float, size: tuple, crop_offset: tuple, crop_size: tuple):
        self.setup, self.sensor, self.lambda_mode, self.z_in = setup, sensor, lambda_mode, z_in
        self.size, self.crop_offset, self.crop_size = size, crop_offset, crop_size
        self._bodies = {"pilot": self.pilot_kernel, "splat": self.splat_kernel}     # kind -> its body
        self.frozen = {}            # kind -> the frozen kernel (dr.freeze), see run
        self.unfrozen = {}          # (kind, signature) -> why it could not be frozen
        self._uses = {}             # (kind, signature) -> calls so far
        self._frozen_ev = None      # the evaluator of the call being recorded
        #: contrib's hits must land in the crop window (False: anywhere on the sensor plane, for
        #: FlareRenderer.offframe_image)
        self.crop_test = True

    def planes(self):
        """(z_in, the sensor plane) as width-1 ``mi.Float`` arrays (lens space, mm): kernel inputs, the last
        entry of the ``xf`` the kernels take."""
        import mitsuba as mi
        import drjit as dr
        if getattr(self, "_planes", None) is None:
            self._planes = (dr.opaque(mi.Float, float(self.z_in)), dr.opaque(mi.Float, float(self.setup.image_z)))
        return self._planes

    # -------------------------------------------------------------- one forward sample
    def interaction(self, qx, qy, wav, to_world, planes=None):
        """The scene-space interaction at the lens-space points (``qx``, ``qy``, z_in) (mm), for sampling a light
        from there; ``wav``: its wavelengths (None: none); ``to_world``: the sensor's camera → world transform;
        ``planes``: :meth:`planes` (the default)."""
        import mitsuba as mi
        import drjit as dr
        from ..sensors.common import lens_to_camera
        z_in, image_z = self.planes() if planes is None else planes
        zq = dr.zeros(mi.Float, dr.width(qx)) + z_in
        (cx, cy, cz), _ = lens_to_camera(self.setup, (qx, qy, zq), (qx, qy, zq), image_z=image_z)
        it = dr.zeros(mi.Interaction3f, dr.width(qx))
        it.p = to_world @ mi.Point3f(cx, cy, cz)
        it.t = mi.Float(0.0)
        if wav is not None:
            it.wavelengths = wav
        return it

    def contrib(self, ev, emitter, scene, xf, qx, qy, u_lam, u_em, active=True):
        """One forward sample per lane: ``(hit, px, py, value, lam, near)``, ``value`` its film value without the
        A_q/N area factor (the caller scales) and, where ``lam`` is not None (RGB variants, a sampled
        wavelength), without the wavelength's colour either (:func:`rgb` applies it: it reads Mitsuba's CIE
        tables, which a frozen kernel cannot), ``near`` the samples a learned evaluator leaves to the tracer
        (:class:`~mi_neurallens.flare.evaluator.GhostEvaluator`; None without).  ``px``, ``py``: film position
        (pixels of the full film).  ``scene``: for the light's visibility test (None: none); ``xf``: the sensor's
        (to_world, to_camera) transforms, the film factor K / A_pix (opaque) and :meth:`planes`."""
        import mitsuba as mi
        import drjit as dr
        from ..sensors.wavelengths import sample_wavelength
        to_world, to_cam, k_pix, planes = xf
        lam, wav, wspec, _ = sample_wavelength(mi, dr, self.sensor, self.lambda_mode, mi.Float(0.0), u_lam,
                                               None, None, active, deferred=True)
        it = self.interaction(qx, qy, wav, to_world, planes)
        ds, E = emitter.sample_direction(it, u_em, active)
        dcam = to_cam @ (-ds.d)
        dx, dy, dz = dcam.x, dcam.y, -dcam.z          # camera → lens direction
        ok = active & (dz > 1e-6) & (ds.pdf > 0.0)
        if scene is not None:
            ray = mi.Ray3f(it.p, ds.d, dr.select(dr.isfinite(ds.dist), ds.dist * (1.0 - 1e-4), dr.inf),
                           mi.Float(0.0), wav if wav is not None else [])
            ok &= ~scene.ray_test(ray, ok)
        zq = dr.zeros(mi.Float, dr.width(qx)) + planes[0]
        valid, x, y, T, near = ev((qx, qy, zq), (dx, dy, dz), lam, ok)
        W, H = self.size
        px = (x * (1.0 / self.setup.sensor_width_mm) + 0.5) * W
        py = (y * (1.0 / self.setup.sensor_height_mm) + 0.5) * H
        hit = (valid & self.in_crop(px, py)) if self.crop_test else valid
        val = E * (T * dz * k_pix)
        if not isinstance(wspec, float):
            val = val * wspec
        if mi.is_spectral:
            return hit, px, py, mi.spectrum_to_srgb(val, wav, hit), None, near
        return hit, px, py, val, (None if isinstance(lam, float) else lam), near

    def in_crop(self, px, py):
        """Whether film position (``px``, ``py``; pixels of the full film) lies in the film's crop window."""
        ox, oy = self.crop_offset
        cw, ch = self.crop_size
        return (px >= ox) & (px < ox + cw) & (py >= oy) & (py < oy + ch)

    # -------------------------------------------------------------- the two kernels
    def pilot_kernel(self, ev, emitter, scene, xf, d):
        """The pilot's samples in the cells ``d["cx"], d["cy"]`` (lower-left corners, one per sample; lens space,
        mm) of size ``d["c"]`` inside the disk of radius ``d["R"]``: (hit, value, λ, in-disk) per sample
        (:meth:`contrib`)."""
        import mitsuba as mi
        import drjit as dr
        idx = mi.UInt64(d["idx"])
        # as mi.PCG32(size=n, initseq=s), which seeds lane i with initstate + i and initseq s + i
        rng = mi.PCG32(1, mi.UInt64(_PCG32_STATE) + idx, idx + idx + d["seed"])
        qx = dr.fma(rng.next_float32(), d["c"], d["cx"])
        qy = dr.fma(rng.next_float32(), d["c"], d["cy"])
        indisk = dr.fma(qx, qx, qy * qy) <= d["R"] * d["R"]
        u_lam = rng.next_float32()
        u_em = mi.Point2f(rng.next_float32(), rng.next_float32())
        hit, px, py, val, lam, near = self.contrib(ev, emitter, scene, xf, qx, qy, u_lam, u_em, indisk)
        if near is not None:
            # the samples a learned evaluator leaves to the tracer (boundary_band, iris_band) may well be lit: the
            # main pass traces them, so their cells must be kept, and their learned value counts toward the ghost's
            # energy.  Counted as dark, a thin ghost (a fold's band) whose cells hold only such samples vanished
            hit = hit | (near & self.in_crop(px, py))
        return hit, val, lam, indisk

    def splat_kernel(self, ev, emitter, scene, xf, d):
        """The main pass's samples ``d["idx"]`` (0..n−1, a rank-1 lattice shifted by ``d["shift"]``) inside the
        kept cells ``d["cells_x"], d["cells_y"]`` of size ``d["c"]`` (or, without cells, the disk of radius
        ``d["R"]``; lens space, mm), each weighted by ``d["scale"]`` = sampled area / n: (px, py, value, λ, hit),
        and ``near`` where the evaluator leaves samples to the tracer (``boundary_band``)."""
        import mitsuba as mi
        import drjit as dr
        idx = d["idx"]
        u = [_u32_to_unit(mi, dr, idx * a + s) for a, s in zip(_ALPHA, d["shift"])]
        if "cells_x" not in d:
            r = d["R"] * dr.sqrt(u[1])
            s_, c_ = dr.sincos(2.0 * math.pi * u[2])
            qx, qy = r * c_, r * s_
        else:
            nc = d["ncells"]
            k = dr.minimum(mi.UInt32(u[0] * mi.Float(nc)), nc - 1)
            qx = dr.gather(mi.Float, d["cells_x"], k) + u[1] * d["c"]
            qy = dr.gather(mi.Float, d["cells_y"], k) + u[2] * d["c"]
        hit, px, py, val, lam, near = self.contrib(ev, emitter, scene, xf, qx, qy, u[3], mi.Point2f(u[4], u[5]),
                                                   True)
        if near is None:
            return px, py, val * d["scale"], lam, hit
        return px, py, val * d["scale"], lam, hit, near

    # -------------------------------------------------------------- traced, or replayed
    def run(self, kind, ev, emitter, scene, xf, d, freeze: bool = True):
        """Run the ``kind`` (``"pilot"`` or ``"splat"``) kernel of evaluator ``ev`` for ``emitter`` on the inputs
        ``d`` (a dict of Dr.Jit arrays and opaque scalars; widths change from call to call); ``scene`` and ``xf``
        as :meth:`contrib` takes them.

        With ``freeze`` the kernel is a frozen function (``dr.freeze``): the first call of a signature is
        traced as usual, the second records it (Python tracing and kernel assembly, with the recording's own
        overhead), later calls replay the recorded kernels with new inputs.  The signature
        (:meth:`~mi_neurallens.flare.evaluator.GhostEvaluator.freeze_key`) is the evaluator's own for the tracer
        and literal maps, and the architecture's for learned maps with kernel parameters, whose numbers and packed
        networks are then inputs: one recording serves every ghost map of one architecture, in this render and
        the next (a learned ghost traced again cost ≈ 20 ms per render).  Everything else a
        kernel reads is an input too (the light, the scene, the transforms); the constants of this object (lens,
        film, sensor) are fixed for its life.  A signature that cannot be frozen (Dr.Jit refuses a recording that
        reads a variable it was not given) is traced, the reason kept in :attr:`unfrozen`."""
        import mitsuba as mi
        import drjit as dr
        body = self._bodies[kind]
        if not freeze or mi.is_spectral or not hasattr(ev, "freeze_key"):
            return body(ev, emitter, scene, xf, d)      # (an evaluator of the caller's own: traced)
        sig, state = ev.freeze_key(mi.Float)
        uses = self._uses[(kind, sig)] = self._uses.get((kind, sig), 0) + 1
        if uses == 1 or (kind, sig) in self.unfrozen:   # record only what runs again: a recording costs
            return body(ev, emitter, scene, xf, d)      # more than tracing (docs/flares.md, "Frozen kernels")
        f = self.frozen.get(kind)
        if f is None:
            def frozen(kind, sig, state, emitter, scene, xf, d):
                return self._bodies[kind](self._frozen_ev, emitter, scene, xf, d)
            # every input opaque: with auto_opaque, an input that changed from one call to the next (a sample count,
            # a moved camera) was recorded once more before Dr.Jit made it an input
            f = self.frozen[kind] = dr.freeze(frozen, warn_after=1 << 30, auto_opaque=False)
        n0 = f.n_recordings
        pool = getattr(ev.map, "params_pool", None)
        n_pool = len(pool) if pool is not None else 0
        self._frozen_ev = ev
        gc_on = gc.isenabled()
        # no garbage collection inside a recording: an unrelated Dr.Jit variable freed there (a mapped numpy
        # buffer's release is a host callback) aborts the process ("cannot be recorded")
        gc.disable()
        try:
            out = f(kind, sig, state, emitter, scene, xf, d)
        except Exception as e:     # e.g. a kernel reading a variable it was not given: run it unfrozen
            self.unfrozen[(kind, sig)] = f"{type(e).__name__}: {e.__cause__ or e}"
            return body(ev, emitter, scene, xf, d)
        finally:
            self._frozen_ev = None
            if gc_on:
                gc.enable()
        if f.n_recordings != n0 and pool is not None and len(pool) != n_pool:
            # the recording created kernel parameters it was not handed: baked into it, wrong for other maps
            raise RuntimeError(f"lens_flare: the frozen {kind} kernel of path {ev.pid} read numbers it was not "
                               "given as inputs; render with freeze = False and report this")
        return out
