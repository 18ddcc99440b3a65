"""The ``lens_ad`` integrator: path tracing differentiable in the camera's rays (a lens being optimised).

The class derives from Mitsuba's ``ADIntegrator`` of the variant that was set when this module was
(re-)imported (AD variants only); :func:`mi_neurallens.integrators.register` re-imports and registers it.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
from mitsuba.ad.integrators.common import ADIntegrator

PLUGIN = "lens_ad"

DOC = r"""
.. _integrator-lens_ad:

Lens-differentiable path tracer (:monosp:`lens_ad`)
---------------------------------------------------

.. pluginparameters::

 * - max_depth
   - |int|
   - Longest path, as for ``path`` (-1: unbounded).  (Default: 8)

 * - rr_depth
   - |int|
   - Depth from which Russian roulette starts, as for ``path``.  (Default: 5)

Renders exactly what ``path`` renders (the primal image is a nested ``path`` integrator's), and in
``mi.render``'s forward and reverse modes differentiates it with respect to the camera: the parameters of a
``realistic_lens`` (focus, sensor distance, curvatures, gaps, conics, aspheric coefficients) or a ``neural_lens``
(focus, sensor distance, the regressor's weights), through the parameters' effect on where the camera rays go
and on the camera's weight (Fresnel, normalisation, the aperture rims' band, docs/differentiable.md).

Mitsuba's own differentiable integrators (``prb``, ``direct_projective``, …) start from a *detached* camera ray:
they differentiate the scene, never where the camera's rays go, and with a lens parameter they give a zero
gradient or refuse.  ``lens_ad`` keeps the camera ray attached: it intersects it with the scene
differentiably and estimates the radiance it carries as the emission at the first hit plus the BSDF-sampled
continuation, whose incoming radiance is a detached ``path`` estimate.  The derivative passes differentiate
that estimate — the interior term: how the image changes as rays move over textures, shading and emitters —
and use its value where the camera weight's derivative needs the radiance.  Discontinuities the rays cross (object silhouettes,
texture edges, the rims of the lens's apertures) contribute boundary terms it does not see; a smooth
(bilinearly filtered) texture and a scene without silhouettes where the image changes are where it is exact.
The scene's own parameters are differentiated through the first hit only; use ``prb`` for those.

Forward and reverse mode record the first hit's computation (a few hundred bytes a sample) for the AD graph;
keep the image and spp moderate (a 256 × 256 × 16 spp reverse pass uses about 1 GB).

.. tabs::

    .. code-tab:: python

        'integrator': {'type': 'lens_ad', 'max_depth': 4}
"""


class LensAD(ADIntegrator):
    __doc__ = DOC

    def __init__(self, props):
        max_depth = props.get("max_depth", 8)
        rr_depth = props.get("rr_depth", 5)
        super().__init__(props)
        self.max_depth = int(max_depth)
        path = lambda depth: mi.load_dict({"type": "path", "max_depth": depth, "rr_depth": int(rr_depth)})
        #: the primal image's integrator, and the continuation's (one bounce shorter: the first is ours)
        self.nested = path(self.max_depth)
        self.continuation = path(self.max_depth - 1 if self.max_depth > 1 else -1)

    def sample(self, mode, scene, sampler, ray, active, **kwargs):
        """The radiance of the camera rays ``ray``: a detached ``path`` estimate, plus (forward and reverse
        modes) the derivative of the attached first-hit estimate."""
        if mode == dr.ADMode.Primal:
            with dr.suspend_grad():
                L, valid, _ = self.nested.sample(scene, sampler, dr.detach(ray), None, active)
            return L, valid, [], None
        # the derivative passes: the first-hit estimate alone (its value, an estimate of the same radiance, is
        # what multiplies the camera weight's derivative; a second path estimate would only double the cost)
        with dr.resume_grad():
            L1 = self._first_hit(scene, sampler, ray, active)
        return L1, active, [], None

    def _first_hit(self, scene, sampler, ray, active):
        """The attached estimate: emission where the camera ray lands (or the environment where it escapes)
        plus the BSDF-sampled continuation times a detached ``path`` estimate of its incoming radiance."""
        si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=True, active=active)
        hit = active & si.is_valid()
        L = mi.Spectrum(si.emitter(scene).eval(si, hit))
        env = scene.environment()
        if env is not None:
            L = dr.select(hit, L, env.eval(si, active & ~hit))
        if self.max_depth == 1:
            return L
        ctx = mi.BSDFContext()
        bsdf = si.bsdf(ray)
        bs, w = bsdf.sample(ctx, si, sampler.next_1d(hit), sampler.next_2d(hit), hit)
        cont = hit & (bs.pdf > 0.0)
        with dr.suspend_grad():
            Li, _, _ = self.continuation.sample(scene, sampler, dr.detach(si.spawn_ray(si.to_world(bs.wo))), None, cont)
            if not dr.flag(dr.JitFlag.SymbolicScope):
                # stored by the pass's forward kernel: the derivative kernel reads it instead of tracing the
                # continuation again (that recomputation was a third path tracing per step)
                dr.schedule(Li)
        return L + dr.select(cont, w * Li, 0.0)

    def aov_names(self):
        return []

    def traverse(self, cb):
        pass

    def to_string(self):
        return f"LensAD[max_depth={self.max_depth}]"
