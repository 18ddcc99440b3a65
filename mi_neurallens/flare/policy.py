"""Which evaluator a ghost gets: mode ``auto``'s choice between its learned map (and with which ``boundary_band``
and iris band) and the tracer, how the learned maps enter their kernels, and the field they learned.

:class:`FlarePolicy` decides per ghost from what the model file records about its map — the held-out exit-position
error against the film's pixel, the verified flare errors at each band (:mod:`mi_neurallens.flare.verify`), what
the map costs against tracing its ghost — and from whether the map can apply this render's iris and coatings.
:func:`light_sine` and :func:`beyond_field` decide per (light, ghost): a light steeper than the field a map
learned is left to the tracer.  The renderer (:mod:`mi_neurallens.flare.render`) asks; nothing here runs a
kernel, save :func:`light_sine`'s few rays toward the light.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from .options import BASELINE_MODES, FlareError

#: ``mlp = "auto"``: from this many learned ghost maps in one render on, their networks are evaluated as
#: kernel inputs (``"shared"``: one compilation per architecture, ≈ 1 s on a CPU with packed weights) instead
#: of literals (one compilation per map, 1–8 s each): the first render on an empty kernel cache is then the
#: shorter one from two maps on; warm, the literals are 2 ms (3×16 maps) to 60 ms (5×32) per map and render
#: faster, which repays their compilation after 100–500 renders
SHARED_FROM = 2


class FlarePolicy:
    """How one renderer evaluates each ghost, and the learned maps as it evaluates them (built once, kept across
    its renders).

    ``opts``: the :class:`~mi_neurallens.flare.options.FlareOptions`; ``model``: the neural model (None: none);
    ``lens_modified``: the flare's coatings differ from the trained lens's; ``iris``: the iris the learned maps must
    test (None: the one they were trained with), ``trained_iris`` that one, ``iris_ok``: whether a stop head can
    reproduce ``iris`` (the trained iris round and ``iris`` within it); ``sensor_width_mm`` and ``film_width_px``:
    the film's pixel pitch; ``ghost_ids``: a callable returning the render's paths (:meth:`learned_mlp`)."""

    def __init__(self, opts, model, *, lens_modified: bool, iris, trained_iris, iris_ok: bool,
                 sensor_width_mm: float, film_width_px: int, ghost_ids):
        self.opts, self.model = opts, model
        self.lens_modified, self.iris, self.trained_iris, self.iris_ok = lens_modified, iris, trained_iris, iris_ok
        self.sensor_width_mm, self.film_width_px = sensor_width_mm, film_width_px
        self.ghost_ids = ghost_ids
        self._learned_maps = {}     # (map key, mlp) -> the learned map as the renderer evaluates it

    def iris_band(self, band: float) -> float:
        """The iris band of this render's learned ghosts (:class:`~mi_neurallens.flare.evaluator.GhostEvaluator`),
        given their ``band``: ``opts.iris_band``, else ``band`` in mode neural and at least 1 in mode auto (whose
        records were measured at the trained iris, so the edge of any other is traced).  Matters only where an iris
        is tested at render time."""
        if self.opts.iris_band is not None:
            return float(self.opts.iris_band)
        return max(band, 1.0) if self.opts.mode == "auto" else band

    def auto_learns(self, pid) -> bool:
        """Whether mode ``auto`` evaluates ghost ``pid`` with its learned map (:meth:`auto_choice`)."""
        return self.opts.mode == "auto" and self.auto_choice(pid)[0] is not None

    def auto_choice(self, pid) -> tuple:
        """How mode ``auto`` evaluates ghost ``pid``: ``(band, None)`` with its learned map and that
        ``boundary_band``, or ``(None, why)`` with the tracer — no model or no map for it, coatings other than
        the trained lens's, a map that fails :meth:`map_band`'s gates for this film, or an iris it cannot apply."""
        m = self.model
        if pid == 0:
            return None, "the direct image is traced"
        if m is None:
            return None, "no neural model"
        if self.lens_modified:
            return None, "the coatings differ from the trained lens"
        if not m.has(pid, "forward"):
            return None, "the model has no map for it"
        tm = m.map(pid, "forward")
        band, why = self.map_band(tm)
        if why is None and self.iris is not None and not (tm.stop_head is not None and self.iris_ok):
            return None, ("its map has no stop head for the iris" if tm.stop_head is None else
                          "the iris reaches beyond the one its map was trained with")
        return band, why

    def map_band(self, tm) -> tuple:
        """Whether mode ``auto`` may use the learned map ``tm``, and with which ``boundary_band``: ``(band,
        None)`` where it may, ``(None, why)`` where not.  Its held-out median exit-position error (the model
        file's ``metrics``; none recorded: no) must be at most ``auto_max_error_px`` pixels of this film.  Where
        the map records verified flare errors (:func:`~mi_neurallens.flare.verify.flare_records`: its learned
        edges', and with the edges traced at a band), one of them must be at most ``auto_max_flare_error``: a
        record measured with at most this render's ``boundary_band`` lets the map in at that band; else the
        narrowest wider band whose record passes is the one this ghost is rendered with (its edges traced,
        what the record measured), so a ghost whose learned edges miss the gate is still learned where the
        tracer at its edges brings it within.  No record: this render's band.  Where the map records what it
        costs against tracing its ghost on this backend, that must be at most ``auto_max_cost``.  A record whose band
        left more than :data:`~mi_neurallens.flare.verify.MAX_TRACED_SHARE` of the ghost's samples to the tracer
        lets nothing in (the map would be mostly the tracer, and cost more)."""
        from .verify import (MAX_TRACED_SHARE, flare_records, learned_cost_ratio, passing_band, record_band,
                             traced_share, variant_backend)
        err_um = (tm.metrics.get("regressor") or {}).get("position_um_median")
        lim_um = self.opts.auto_max_error_px * 1000.0 * self.sensor_width_mm / self.film_width_px
        if err_um is None:
            return None, "no recorded held-out accuracy"
        if err_um > lim_um:
            return None, f"position error {err_um:.3g} µm > {self.opts.auto_max_error_px:g} px = {lim_um:.3g} µm"
        recs = flare_records(tm.metrics)
        own = self.opts.boundary_band
        if not recs:
            return own, None
        lim = self.opts.auto_max_flare_error
        band = passing_band(recs, own, lim)
        if band is not None:
            ratio = learned_cost_ratio(tm.metrics, band)
            if ratio is not None and ratio > self.opts.auto_max_cost:
                return None, (f"learned, it costs {ratio:.2f}× tracing it"
                              + (f" (boundary_band {band:g})" if band else "") + f", above auto_max_cost "
                              f"{self.opts.auto_max_cost:g} (measured on {variant_backend()})")
            return band, None
        r = recs[-1]                           # the widest band measured: the best the map can do
        at = f" (boundary_band {record_band(r):g})" if record_band(r) > 0 else ""
        if r.get("paired_mape") is None:
            return None, f"verified flare error: none (the ghost reached no pixel){at}"
        if r["paired_mape"] <= lim:
            return None, (f"within the flare gate only with {traced_share(r):.0%} of its samples traced{at}, "
                          f"above {MAX_TRACED_SHARE:.0%}")
        return None, f"verified flare error {r['paired_mape']:.3g} > {lim:g}{at}"

    def learned_mlp(self, ids=None) -> str:
        """How this render's learned maps enter their kernels (:class:`~mi_neurallens.neural.model.NeuralMap`'s
        ``mlp``): ``opts.mlp``, or for ``auto`` ``shared`` (one kernel per architecture) when the render uses at
        least :data:`SHARED_FROM` learned ghost maps, ``fused`` (one kernel, the fastest once compiled) below
        that.  ``ids``: the render's paths (default: ``ghost_ids()``)."""
        if self.opts.mlp != "auto":
            return self.opts.mlp
        m = self.model
        if m is None or self.opts.mode == "exact" or self.opts.mode in BASELINE_MODES:
            return "fused"
        ids = self.ghost_ids() if ids is None else ids
        n = sum(1 for pid in ids if pid and (m.has(pid, "forward") if self.opts.mode == "neural" else self.auto_learns(pid)))
        return "shared" if n >= SHARED_FROM else "fused"

    def learned(self, tm, mlp: str, strict: bool):
        """The learned map ``tm`` evaluated with ``mlp`` (:meth:`learned_mlp`), with this flare's iris (None, or an
        error when ``strict``, if it cannot apply it: no stop head, or an iris outside the trained one)."""
        key = (tm.key, mlp, tm.condition_values, tm.z_in)
        if key in self._learned_maps:      # the same object at every render: its packed networks and kernel
            return self._learned_maps[key]  # inputs are built once
        if tm.mlp != mlp:
            tm = dataclasses.replace(tm, mlp=mlp)
        if self.iris is None:
            self._learned_maps[key] = tm
            return tm
        if tm.stop_head is not None and self.iris_ok:
            self._learned_maps[key] = dataclasses.replace(tm, iris=self.iris)
            return self._learned_maps[key]
        if strict:
            why = ("has no stop head" if tm.stop_head is None else
                   "was trained with a bladed iris" if self.trained_iris.blades else
                   "cannot reproduce an iris reaching beyond the trained one (polygon corners near wide open)")
            raise FlareError(f"lens_flare: mode='neural': the learned map of ghost {tm.path_id} {why}, so it "
                             f"cannot render the iris {self.iris.describe()}; use mode='auto' (exact where "
                             f"a map cannot) or add stop heads (`mi-neurallens train LENS --keep networks`)")
        return None


# ------------------------------------------------------------------------------------ the field the maps learned
def light_sine(emitter, radius: float, interaction, to_cam) -> float:
    """The largest sine of the angle to the lens axis (|ω_xy| of the unit direction, the quantity a forward
    map's domain bounds: ``s_max``) among ``emitter``'s rays toward the flare's input disk of ``radius`` (mm): sampled
    from the disk's centre and 8 points of its rim, each toward 9 points of the emitter (an area light's extent),
    plus a margin for the rays between them.  ``interaction(qx, qy)``: the scene-space interaction at lens-space
    points of the input plane (:meth:`~mi_neurallens.flare.kernels.FlareKernels.interaction`); ``to_cam``: the
    sensor's world → camera transform."""
    import mitsuba as mi
    R = radius
    ang = np.linspace(0.0, 2.0 * np.pi, 8, endpoint=False)
    qx = np.concatenate([[0.0], R * np.cos(ang)])
    qy = np.concatenate([[0.0], R * np.sin(ang)])
    u = np.array([0.05, 0.5, 0.95])
    k, U0, U1 = (a.ravel() for a in np.meshgrid(np.arange(len(qx)), u, u, indexing="ij"))
    it = interaction(mi.Float(qx[k]), mi.Float(qy[k]))
    ds, _ = emitter.sample_direction(it, mi.Point2f(mi.Float(U0), mi.Float(U1)), False)
    dl = to_cam @ (-ds.d)
    dx, dy, dz = (np.asarray(v, np.float64) for v in (dl.x, dl.y, dl.z))
    n = np.sqrt(dx * dx + dy * dy + dz * dz)
    sine = np.sqrt(dx * dx + dy * dy) / np.where(n > 0.0, n, 1.0)
    # over the rim the sine is s0 + a·cos(φ − φ0) to first order (a: half its spread), so between two rim points
    # 45° apart it rises above both by at most a·(1 − cos(π/8)): twice that is added (0 for a directional light)
    return float(sine.max() + np.ptp(sine) * (1.0 - math.cos(math.pi / 8)))


def learned_field(ev) -> float | None:
    """The sine of the steepest light the map of the learned (or baseline) evaluator ``ev`` was trained on (its
    domain's ``s_max``: the film's field × the training's ``field_margin``); None for the tracer and for a map
    without a domain."""
    dom = getattr(ev.map, "domain", None) if ev.kind != "exact" else None
    if dom is None:
        return None
    from ..transport.planning import Domain
    return Domain.from_dict(dom).s_max


def beyond_field(sine: float, s_max: float) -> str | None:
    """Why a map that learned the field up to sine ``s_max`` cannot render a light whose rays reach sine ``sine``
    (:func:`light_sine`): beyond its field a map answers only "blocked" — so a light just outside the frame, whose
    ghosts may well cross the film, would lose them.  None where the map covers the light."""
    if sine <= s_max:
        return None
    return (f"the light lies up to {math.degrees(math.asin(min(sine, 1.0))):.1f}° off axis, beyond the "
            f"{math.degrees(math.asin(s_max)):.1f}° field its map learned")
