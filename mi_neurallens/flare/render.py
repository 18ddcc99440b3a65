"""Forward light tracing of lens ghosts (the flare image), exact or neural, for the current variant.

Measurement (what a splat deposits)
-----------------------------------
The lens sensors report ``I(x) = K ∫ L T cosθ dω`` with ``K = 1/(π NA'²)``: K times the
sensor-plane irradiance E(x).  A pixel of area A_pix (mm² on the sensor) therefore reads
``K · Φ_pix / A_pix``, Φ_pix the flux landing on it (the cosθ of the measurement equation is the
projected-area factor that turns radiance into irradiance; a flux splat already carries it).

A forward sample starts at a point q on the input plane z = z_in (in front of the first surface),
sampled uniformly over a region of area A_q (mm²); the emitter is sampled from q with
``emitter.sample_direction`` which returns the direction toward the light and
``E⊥ = L/pdf_ω`` (for a point/spot light: I/r², r in scene units; directional: its irradiance).
The flux through dA_q from that direction is ``E⊥ · |cos θ_q| · dA_q`` (θ_q: angle to the lens
axis), so with N samples each sample that reaches the sensor along a path with Fresnel
throughput T deposits into its pixel

    v = E⊥ · w_λ · T · |cos θ_q| · (A_q / N) · K / A_pix          (A_q, A_pix both in mm²)

w_λ is the sensor's own wavelength weight (:func:`~mi_neurallens.sensors.wavelengths.sample_wavelength`,
the same λ sampling and RGB weights as the backward render).  Lens-space frames, film mapping and
K come from the sensor (``sensor.setup``); nothing is duplicated here.  Radiometry is checked in
``tests/test_flare.py`` against a backward ``realistic_lens`` + ``path`` render of a tiny sphere of
equal power (transmit path splatted forward).

Sampling region
---------------
A pilot pass traces ``pilot_grid²`` cells × ``pilot_spp`` jittered samples over the conservative
disk that can hit the front element (per light and ghost), keeps the cells where a sample reached
the film, dilates them by one cell and the main pass samples uniformly inside the kept cells (a
cell is picked uniformly, then a point in it).  The pilot also estimates each ghost's flux, which
sets the per-ghost sample budget (∝ energy, with a floor ``min_samples``).  With ``include_transmit``
the light's own image gets one equal share of the budget (1 / number of paths) and the ghosts split
the rest by energy: the direct image is far brighter but only a few pixels wide.  With ``bounds='none'`` the main pass
samples the whole disk (the "before" pass fraction).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
import gc
import math
import time
import zlib

import numpy as np

from ..constants import FULL_FRAME_MM, LUMINANCE_WEIGHTS
from ..errors import ModelError
from ..jit import from_numpy
from ..trace.iris import Iris
from .energy import front_radius, ghost_energy_ranking, input_plane, select_ghosts, trivial_ghost
from .lights import scene_lights
from .options import BASELINE_MODES, FlareError, FlareOptions

#: ``mlp = "auto"``: from this many learned ghost maps in one render on, their networks are evaluated as
#: kernel inputs (``"shared"``: one compilation per architecture, ≈ 1 s on a CPU with packed weights) instead
#: of literals (one compilation per map, 1–8 s each): the first render on an empty kernel cache is then the
#: shorter one from two maps on; warm, the literals are 2 ms (3×16 maps) to 60 ms (5×32) per map and render
#: faster, which repays their compilation after 100–500 renders (docs/results.md, "One compilation")
SHARED_FROM = 2

# golden-ratio style additive recurrence (R_d sequence, d = 6) in 32-bit fixed point
_PHI6 = 1.0
for _ in range(64):
    _PHI6 = (1.0 + _PHI6) ** (1.0 / 7.0)
_ALPHA = [int((1.0 / _PHI6 ** (k + 1)) % 1.0 * 2 ** 32) & 0xFFFFFFFF for k in range(6)]


#: PCG32's default initial state (its constructor's ``initstate``)
_PCG32_STATE = 0x853C49E6748FEA9B


@dataclass
class GhostStats:
    path_id: int
    surfaces: tuple
    light: str
    evaluator: str                    # exact | neural
    samples: int = 0
    pilot_samples: int = 0
    pilot_hits: int = 0
    hits: int = 0
    cells: int = 0
    cells_total: int = 0
    energy: float = 0.0               #: pilot estimate of the luminance flux on the film (pixel units · pixels)
    seconds: float = 0.0               #: pilot and main pass, wall clock
    splat_seconds: float = 0.0         #: the main pass alone (the tracer's second pass included), wall clock
    traced: int = 0                   #: of ``samples``, traced exactly near a learned map's edges (boundary_band)
    band: float = 0.0                 #: the learned map's boundary_band in this render (0: its edges learned)
    #: why a ghost the render would have learned is traced for this light (its map cannot answer there), else None
    why_traced: str | None = None

    @property
    def fraction_before(self):
        return self.pilot_hits / self.pilot_samples if self.pilot_samples else 0.0

    @property
    def fraction_after(self):
        return self.hits / self.samples if self.samples else 0.0

    def as_dict(self):
        return {"path_id": self.path_id, "surfaces": list(self.surfaces), "light": self.light,
                "evaluator": self.evaluator, "samples": self.samples, "hits": self.hits,
                "fraction_before": self.fraction_before, "fraction_after": self.fraction_after,
                "cells": self.cells, "cells_total": self.cells_total, "energy": self.energy,
                "seconds": self.seconds, "splat_seconds": self.splat_seconds, "traced": self.traced,
                "band": self.band, "why_traced": self.why_traced}


@dataclass
class Pilot:
    """What the pilot pass found for one (light, path): the kept cells of the input disk (lower-left
    corners, (n, 2), lens space mm), their size and the disk's radius (mm), the pilot's in-disk
    samples and hits, and the estimated luminance flux on the film (pixel units · pixels)."""
    cells: np.ndarray
    cell_size: float
    radius: float
    samples: int
    hits: int
    energy: float


@dataclass
class FlareResult:
    """``total``: (H, W, 3) numpy flare image (crop window); ``ghosts``: {path_id: (H, W, 3)} when
    per-ghost images were requested; ``stats``: one :class:`GhostStats` per (light, ghost)."""
    total: np.ndarray
    ghosts: dict
    stats: list


# ------------------------------------------------------------------------------------ evaluators
#: a learned ghost rendered through an iris other than the one it was trained with tests its predicted stop-plane
#: crossings against that iris (:mod:`mi_neurallens.trace.iris`); with an iris band b > 0, a sample whose predicted
#: crossing lies within b × this × the stop head's held-out p99 crossing error (``metrics["stop"]``) of the iris's
#: edge is traced instead, as the classifier's undecided samples are (docs/flares.md, "Exact edges")
IRIS_BAND_P99 = 3.0
#: the p99 crossing error assumed (µm) for a stop head without recorded metrics: the aperture issue's goal
IRIS_BAND_DEFAULT_P99_UM = 20.0


def iris_band_mm(tmap, band: float) -> float:
    """Half-width (mm, stop plane) of the band around the iris's edge whose samples a learned map with iris band
    ``band`` leaves to the tracer: 0 without a band or without an iris tested at render time
    (:data:`IRIS_BAND_P99`)."""
    if not band > 0.0 or getattr(tmap, "iris", None) is None:
        return 0.0
    p99 = ((getattr(tmap, "metrics", None) or {}).get("stop") or {}).get("stop_um_p99")
    return float(band) * IRIS_BAND_P99 * float(p99 if p99 is not None else IRIS_BAND_DEFAULT_P99_UM) * 1e-3


class GhostEvaluator:
    """One path's transport map (exact, learned or a baseline), from the flare's input plane, continued
    straight to the sensor plane ``z_sensor``: ``(o, d, lam, active)`` → ``(valid, x, y, T, near)`` on the
    sensor (lens space, mm).  ``fresnel = False``: T = 1.  ``band`` > 0 (a learned map with a classifier):
    ``near`` marks the samples whose classifier logit is within ±``band`` of its decision; ``iris_band`` > 0
    (default: ``band``; a learned map with an iris tested at render time): also those whose predicted stop-plane
    crossing lies within :func:`iris_band_mm` of the iris's edge.  The map leaves ``near`` out (``valid`` is
    false there) for the tracer to take (:meth:`FlareRenderer.splat`); without a band ``near`` is None."""

    def __init__(self, tmap, z_sensor, fresnel=True, band=0.0, iris_band=None):
        self.map, self.z, self.fresnel = tmap, float(z_sensor), fresnel
        #: ``exact`` for the tracer, ``neural`` for every other map (the learned ones and the baselines)
        self.kind = "exact" if tmap.method == "exact" else "neural"
        self.band = float(band) if self.kind == "neural" and getattr(tmap, "use_classifier", False) else 0.0
        ib = band if iris_band is None else iris_band
        #: the iris band's half-width (mm; 0: the iris's edge is learned)
        self.iris_mm = iris_band_mm(tmap, ib) if self.kind == "neural" else 0.0
        self._iris_vars = {}

    @property
    def pid(self) -> int:
        return self.map.path_id

    @property
    def shared_numbers(self) -> bool:
        """Whether the map's numbers are kernel inputs (``mlp`` shared or coopvec): then so is the iris band."""
        tm = self.map
        return hasattr(tm, "kernel_signature") and tm.kernel_signature() is not None

    def _iris_width(self, float_t):
        """The iris band's half-width as the kernel reads it: an opaque variable (a kernel input, one per float
        type, created before any recording) where the map's numbers are inputs, else a literal."""
        if not self.shared_numbers:
            return self.iris_mm
        import drjit as dr
        v = self._iris_vars.get(float_t)
        if v is None:
            v = self._iris_vars[float_t] = dr.opaque(float_t, self.iris_mm)
        return v

    def freeze_key(self, float_t):
        """``(signature, inputs)`` for the renderer's frozen kernels: a learned map whose numbers are kernel
        inputs (``mlp`` shared or coopvec) shares its signature with every map of its architecture and hands
        its numbers and packed networks (``inputs``, Dr.Jit variables); any other map (the tracer, literals, a
        baseline) has a signature of its own and no inputs."""
        tm = self.map
        sig = tm.kernel_signature() if hasattr(tm, "kernel_signature") else None
        if sig is None:
            return ("map", tm.method, tm.key, self.z, self.fresnel, self.band, self.iris_mm), []
        extra = [self._iris_width(float_t)] if self.iris_mm > 0.0 else []
        return (sig, self.z, self.fresnel, self.band, self.iris_mm > 0.0), tm.kernel_inputs(float_t) + extra

    def __call__(self, o, d, lam, active):
        import drjit as dr
        res = self.map.eval_dr(o, d, lam, active)
        (px, py, pz), (dx, dy, dz) = res.position, res.direction
        t = (self.z - pz) / dz
        x, y = dr.fma(t, dx, px), dr.fma(t, dy, py)
        T = res.throughput if self.fresnel else res.throughput * 0.0 + 1.0
        valid = res.valid & (dz > 0.0)
        near = None
        if self.band > 0.0 and res.logit is not None:
            near = active & (dr.abs(res.logit) < self.band)
        if self.iris_mm > 0.0 and res.stop:
            # the iris decides only where the classifier lets the ray through (or has not decided)
            cand = active if res.logit is None else active & (res.logit > -self.band)
            w = self._iris_width(type(x))
            for sx, sy in res.stop:
                at = cand & (dr.abs(self.map.iris.edge_distance_dr(sx, sy)) < w)
                near = at if near is None else near | at
        if near is not None:
            valid &= ~near
        return valid, x, y, T, near


# ------------------------------------------------------------------------------------ helpers
def sensor_model(sensor, opts: FlareOptions):
    """The neural model to use: ``opts.model`` (object, file or bundled lens name, as the ``neural_lens``
    sensor's ``model``) else the sensor's, else None."""
    from ..neural.model import NeuralLensModel
    from ..sensors.neural_lens import resolve_model_path
    m = opts.model
    if m is None:
        m = getattr(sensor, "model", None)
    if m is None or isinstance(m, NeuralLensModel):
        return m
    if isinstance(m, str) and m:
        return NeuralLensModel.load(resolve_model_path(m, "lens_flare"), None)
    return None


def flare_lens(setup, opts: FlareOptions):
    """The sensor's configured lens with the flare options (coatings, blades) applied."""
    from ..optics.prescription import Coating
    lens = setup.lens
    if opts.coating == "none":
        lens = lens.with_coating(None)
    elif opts.coating == "quarter_wave":
        c = Coating(index=float(opts.coating_index), design_wavelength_nm=float(opts.coating_wavelength))
        opt = lens.optical_indices
        if opts.coating_surfaces is None:
            sel = set(range(len(opt)))
        else:
            sel = set(int(k) for k in opts.coating_surfaces)
            bad = [k for k in sel if not 0 <= k < len(opt)]
            if bad:
                raise FlareError(f"lens_flare: 'coating_surfaces': {bad} out of range; lens '{lens.name}' has "
                                 f"{len(opt)} optical surfaces (0..{len(opt) - 1})")
        surfs = list(lens.surfaces)
        for k in sel:
            i = opt[k]
            if lens.medium_before(i) != surfs[i].medium:
                surfs[i] = dataclasses.replace(surfs[i], coating=c)
        lens = lens.replace(surfaces=tuple(surfs))
    kw = {}
    if opts.blades is not None:
        kw["blades"] = int(opts.blades)
    if opts.blade_rotation is not None:
        kw["blade_rotation_deg"] = float(opts.blade_rotation)
    if kw:
        lens = lens.with_surface(lens.stop_index, **kw)
    return lens


def _stop_fields(lens) -> dict:
    st = lens.stop
    return {"semi_diameter": st.semi_diameter, "blades": st.blades, "blade_rotation_deg": st.blade_rotation_deg}


def _u32_to_unit(mi, dr, x):
    return mi.Float(x >> 8) * (1.0 / 16777216.0)


# ------------------------------------------------------------------------------------ the renderer
class FlareRenderer:
    """Renders the flare of ``scene`` as seen by ``sensor`` (a ``realistic_lens``/``neural_lens``)."""

    def __init__(self, scene, sensor, opts: FlareOptions | None = None):
        import mitsuba as mi
        import drjit as dr
        self.opts = (opts or FlareOptions()).validate()
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        setup = getattr(sensor, "setup", None)
        if setup is None:
            raise FlareError("lens_flare: the sensor must be a lens sensor (realistic_lens or neural_lens); "
                             f"got {sensor.class_().name() if hasattr(sensor, 'class_') else type(sensor).__name__}")
        self.scene, self.sensor, self.setup = scene, sensor, setup
        self.lens = flare_lens(setup, self.opts)
        #: the flare changes the lens beyond its iris (coatings): the learned maps do not apply
        self.lens_modified = self.lens.with_surface(self.lens.stop_index, **_stop_fields(setup.lens)) != setup.lens
        #: the iris the learned ghost maps must test: None when it is the one they were trained with
        trained, iris = Iris.of_lens(setup.base_lens), Iris.of_lens(self.lens)
        self.iris = None if iris.same_as(trained) else iris
        self._iris_ok = not trained.blades and iris.within(trained)
        self.fresnel = bool(setup.fresnel)
        from ..sensors.wavelengths import LAMBDA_NONE, LAMBDA_SAMPLE1
        lam_dep = (any(not m.is_constant for m in [self.lens.object_medium] + [s.medium for s in self.lens.surfaces])
                   or (self.fresnel and any(s.coating is not None for s in self.lens.surfaces)))
        self.lambda_mode = LAMBDA_SAMPLE1 if lam_dep else LAMBDA_NONE
        from ..trace.tracer import LensTracer
        self.tracer = LensTracer(self.lens, fresnel=self.fresnel)
        self.model = sensor_model(sensor, self.opts)
        film = sensor.film()
        self.size = (int(film.size()[0]), int(film.size()[1]))
        self.crop_size = (int(film.crop_size()[0]), int(film.crop_size()[1]))
        self.crop_offset = (int(film.crop_offset()[0]), int(film.crop_offset()[1]))
        self.z_in = input_plane(self.lens)
        self.z_img = float(self.lens.image_z)
        w, h = setup.sensor_width_mm, setup.sensor_height_mm
        self.pix_area_mm2 = (w / self.size[0]) * (h / self.size[1])
        self.K = float(setup.normalisation)
        self._refresh()
        self._box = mi.load_dict({"type": "box"})
        #: the splat weight's film factor K / A_pix, a kernel input (one kernel for every film)
        self._k_pix = dr.opaque(mi.Float, self.K / self.pix_area_mm2)
        self._kernels = {"pilot": self._pilot_kernel, "splat": self._splat_kernel}     # kind -> its body
        self._frozen = {}           # kind -> the frozen kernel (dr.freeze), see _kernel
        self._unfrozen = {}         # (kind, signature) -> why it could not be frozen
        self._uses = {}             # (kind, signature) -> calls so far
        self._frozen_ev = None      # the evaluator of the call being recorded
        self._learned_maps = {}     # (map key, mlp) -> the learned map as this renderer evaluates it
        self._exact_evs = {}        # path id -> the tracer's evaluator (exact_evaluator)
        self._light_sines = {}      # light name -> light_sine(), for one render
        self._mlp = None            # learned_mlp(), resolved at the first learned map

    def _refresh(self):
        """Read what may change between renders of one renderer: the scene's lights and the camera's pose."""
        import drjit as dr
        self.lights = scene_lights(self.scene, self.opts)
        # opaque: a pose baked into a frozen kernel as literals would record it again when the camera moves
        self._to_world = self.sensor.m_to_world
        self._to_cam = self._to_world.inverse()
        dr.make_opaque(self._to_world, self._to_cam)

    # -------------------------------------------------------------- ghost selection
    def ranking(self):
        """Ghost energy ranking: the model's stored ranking when neural maps are used on the lens exactly
        as it was trained (same focus, iris and coatings) with a full-frame film, else
        :func:`~mi_neurallens.flare.energy.ghost_energy_ranking` of the configured lens and film, as
        the exact flare ranks it: stopping down or refocusing changes which ghosts matter, and a ghost
        near the selection cut-off may swap with its neighbour."""
        as_trained = (self.lens == self.setup.base_lens
                      and (self.setup.sensor_width_mm, self.setup.sensor_height_mm) == FULL_FRAME_MM)
        if self.model is not None and as_trained and self.opts.mode != "exact":
            rk = self.model.extra.get("ghost_ranking")
            if rk:
                return [dict(d) for d in rk]
        return ghost_energy_ranking(self.lens, sensor_width_mm=self.setup.sensor_width_mm,
                                    sensor_height_mm=self.setup.sensor_height_mm, fresnel=self.fresnel)

    def ghost_ids(self):
        from ..trace.paths import all_ghosts
        valid = {pid: (a, b) for pid, a, b in all_ghosts(self.lens)}
        if self.opts.transmit_only:
            return [0]
        for g in list(self.opts.ghosts or []) + list(self.opts.exclude_ghosts or []):
            if g not in valid:
                raise FlareError(
                    f"lens_flare: ghost id {g} is not a forward two-reflection path of lens '{self.lens.name}' "
                    f"({len(self.lens.optical_indices)} optical surfaces); valid ids are "
                    f"ghost_id(a, b) = (1<<a)|(1<<(2a-b)) for 0 <= b < a < {len(self.lens.optical_indices)}, "
                    f"e.g. {sorted(valid)[:6]} ...; pairs can be given as 'a:b'")
        if self.opts.ghosts:
            ids = [g for g in self.opts.ghosts if g not in set(self.opts.exclude_ghosts or [])]
        else:
            rk = [d for d in self.ranking() if int(d["path_id"]) not in set(self.opts.exclude_ghosts or [])]
            ids = select_ghosts(rk, self.opts.energy_fraction, self.opts.max_ghosts)
        ids = [g for g in ids if not trivial_ghost(self.lens, *valid[g])]
        if self.opts.include_transmit:
            ids = [0] + ids
        return ids

    def exact_map(self, pid):
        """The tracer on path ``pid``, from the flare's input plane to the sensor plane."""
        from ..transport.exact import ExactMap
        return ExactMap(self.lens, pid, "forward", self.z_in, self.z_img, tracer=self.tracer)

    def evaluator(self, pid):
        """The :class:`GhostEvaluator` of path ``pid`` according to ``mode``: the exact map, the learned
        map, or a baseline."""
        mode = self.opts.mode
        m = self.model
        band = self.opts.boundary_band
        if mode == "exact" or pid == 0 and mode == "auto":
            tmap = self.exact_map(pid)
        elif mode in BASELINE_MODES:
            from ..transport import make_map
            tmap = make_map(self.lens, mode, pid, "forward")
        elif mode == "neural":
            if m is None:
                raise ModelError("lens_flare: mode='neural' needs a neural model: use a neural_lens sensor "
                                 "or give the integrator a 'model' file")
            if self.lens_modified:
                raise FlareError("lens_flare: mode='neural' cannot change the lens's coatings: the learned "
                                 "maps were trained for the lens as it is; use mode='exact'")
            if not m.has(pid, "forward"):
                raise ModelError(f"lens_flare: the model {m.path or ''} has no forward map for path {pid}; "
                                 f"it has ghost maps {m.ghost_ids}; use mode='auto' (exact for missing ghosts), "
                                 f"restrict 'ghosts', or train it (`mi-neurallens train {self.lens.name} "
                                 f"--paths {pid} --out DIR`, then training/merge_maps.py: docs/training.md)")
            tmap = self._learned(m.map(pid, "forward"), strict=True)
        else:                              # auto: the learned map where its gates let it in, at its band
            band, _ = self.auto_choice(pid)
            tmap = None if band is None else self._learned(m.map(pid, "forward"), strict=False)
            if tmap is None:                          # the tracer (which ignores the band)
                tmap = self.exact_map(pid)
        return GhostEvaluator(tmap, self.z_img, self.fresnel, band or 0.0, self.iris_band(band or 0.0))

    def iris_band(self, band: float) -> float:
        """The iris band of this render's learned ghosts (:class:`GhostEvaluator`), given their ``band``:
        ``opts.iris_band``, else ``band`` in mode neural and at least 1 in mode auto (whose records were measured
        at the trained iris, so the edge of any other is traced).  Matters only where an iris is tested at render
        time."""
        if self.opts.iris_band is not None:
            return float(self.opts.iris_band)
        return max(band, 1.0) if self.opts.mode == "auto" else band

    def auto_learns(self, pid) -> bool:
        """Whether mode ``auto`` evaluates ghost ``pid`` with its learned map (:meth:`auto_choice`)."""
        return self.opts.mode == "auto" and self.auto_choice(pid)[0] is not None

    def auto_reason(self, pid) -> str | None:
        """Why mode ``auto`` traces ghost ``pid`` (a short phrase for messages), or None where it learns it."""
        return self.auto_choice(pid)[1]

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
        if why is None and self.iris is not None and not (tm.stop_head is not None and self._iris_ok):
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
        tracer at its edges brings it within.  No record: this render's band."""
        from .verify import flare_records, learned_cost_ratio, passing_band, record_band, variant_backend
        err_um = (tm.metrics.get("regressor") or {}).get("position_um_median")
        lim_um = self.opts.auto_max_error_px * 1000.0 * self.setup.sensor_width_mm / self.size[0]
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
        return None, f"verified flare error {r['paired_mape']:.3g} > {lim:g}{at}"

    def learned_mlp(self, ids=None) -> str:
        """How this render's learned maps enter their kernels (:class:`~mi_neurallens.neural.model.NeuralMap`'s
        ``mlp``): ``opts.mlp``, or for ``auto`` ``shared`` (one kernel per architecture) when the render uses at
        least :data:`SHARED_FROM` learned ghost maps, ``fused`` (one kernel, the fastest once compiled) below
        that.  ``ids``: the render's paths (default: :meth:`ghost_ids`)."""
        if self.opts.mlp != "auto":
            return self.opts.mlp
        m = self.model
        if m is None or self.opts.mode == "exact" or self.opts.mode in BASELINE_MODES:
            return "fused"
        ids = self.ghost_ids() if ids is None else ids
        n = sum(1 for pid in ids if pid and (m.has(pid, "forward") if self.opts.mode == "neural" else self.auto_learns(pid)))
        return "shared" if n >= SHARED_FROM else "fused"

    def _learned(self, tm, strict: bool):
        """The learned map ``tm`` evaluated as :meth:`learned_mlp` says, with this flare's iris (None, or an
        error when ``strict``, if it cannot apply it: no stop head, or an iris outside the trained one)."""
        if self._mlp is None:
            self._mlp = self.learned_mlp()
        key = (tm.key, self._mlp)
        if key in self._learned_maps:      # the same object at every render: its packed networks and kernel
            return self._learned_maps[key]  # inputs are built once
        if tm.mlp != self._mlp:
            tm = dataclasses.replace(tm, mlp=self._mlp)
        if self.iris is None:
            self._learned_maps[key] = tm
            return tm
        if tm.stop_head is not None and self._iris_ok:
            self._learned_maps[key] = dataclasses.replace(tm, iris=self.iris)
            return self._learned_maps[key]
        if strict:
            why = ("has no stop head" if tm.stop_head is None else
                   "was trained with a bladed iris" if Iris.of_lens(self.setup.base_lens).blades else
                   "cannot reproduce an iris reaching beyond the trained one (polygon corners near wide open)")
            raise FlareError(f"lens_flare: mode='neural': the learned map of ghost {tm.path_id} {why}, so it "
                             f"cannot render the iris {self.iris.describe()}; use mode='auto' (exact where "
                             f"a map cannot) or add stop heads (`mi-neurallens train LENS --keep both`)")
        return None

    # -------------------------------------------------------------- the field the maps learned
    def light_sine(self, light) -> float:
        """The largest sine of the angle to the lens axis (|ω_xy| of the unit direction, the quantity a forward
        map's domain bounds: ``s_max``) among ``light``'s rays toward the flare's input disk: sampled from the
        disk's centre and 8 points of its rim, each toward 9 points of the emitter (an area light's extent),
        plus a margin for the rays between them.  Cached per render."""
        import mitsuba as mi
        import drjit as dr
        got = self._light_sines.get(light.name)
        if got is not None:
            return got
        R = self._region_radius(light)
        ang = np.linspace(0.0, 2.0 * np.pi, 8, endpoint=False)
        qx = np.concatenate([[0.0], R * np.cos(ang)])
        qy = np.concatenate([[0.0], R * np.sin(ang)])
        u = np.array([0.05, 0.5, 0.95])
        k, U0, U1 = (a.ravel() for a in np.meshgrid(np.arange(len(qx)), u, u, indexing="ij"))
        it = self._interaction(mi.Float(qx[k]), mi.Float(qy[k]), None, self._to_world)
        ds, _ = light.emitter.sample_direction(it, mi.Point2f(mi.Float(U0), mi.Float(U1)), False)
        dl = self._to_cam @ (-ds.d)
        dx, dy, dz = (np.asarray(v, np.float64) for v in (dl.x, dl.y, dl.z))
        n = np.sqrt(dx * dx + dy * dy + dz * dz)
        sine = np.sqrt(dx * dx + dy * dy) / np.where(n > 0.0, n, 1.0)
        # over the rim the sine is s0 + a·cos(φ − φ0) to first order (a: half its spread), so between two rim points
        # 45° apart it rises above both by at most a·(1 − cos(π/8)): twice that is added (0 for a directional light)
        got = self._light_sines[light.name] = float(sine.max() + np.ptp(sine) * (1.0 - math.cos(math.pi / 8)))
        return got

    def beyond_field(self, light, ev) -> str | None:
        """Why the learned (or baseline) evaluator ``ev`` cannot render ``light``: some of its rays arrive
        steeper than the field the map was trained on (its domain's ``s_max``, the film's field × the training's
        ``field_margin``), where a map answers only "blocked" — so a light just outside the frame, whose ghosts
        may well cross the film, would lose them.  None where the map covers the light (and for the tracer)."""
        dom = getattr(ev.map, "domain", None) if ev.kind != "exact" else None
        if dom is None:
            return None
        from ..transport.planning import Domain
        s_max = Domain.from_dict(dom).s_max
        sine = self.light_sine(light)
        if sine <= s_max:
            return None
        return (f"the light lies up to {math.degrees(math.asin(min(sine, 1.0))):.1f}° off axis, beyond the "
                f"{math.degrees(math.asin(s_max)):.1f}° field its map learned")

    # -------------------------------------------------------------- sampling core
    def _region_radius(self, light):
        """Radius of the conservative input disk for ``light`` (lens space, mm)."""
        import mitsuba as mi
        # direction from the light toward the lens centre, via a sample from the axis point
        it = self._interaction(mi.Float(0.0), mi.Float(0.0), None, self._to_world)
        ds, _ = light.emitter.sample_direction(it, mi.Point2f(0.5, 0.5), True)
        dl = self._to_cam @ (-ds.d)
        dz = abs(float(dl.z[0]))
        tmax = math.sqrt(max(1.0 - dz * dz, 0.0)) / max(dz, 1e-3)
        # a finite light near the lens sees the rim at steeper angles: add the rim's angular size
        return front_radius(self.lens, min(tmax * 1.2 + 0.05, 20.0), self.z_in)

    def _interaction(self, qx, qy, wav, to_world):
        import mitsuba as mi
        import drjit as dr
        from ..sensors.common import lens_to_camera
        zq = dr.zeros(mi.Float, dr.width(qx)) + self.z_in
        (cx, cy, cz), _ = lens_to_camera(self.setup, (qx, qy, zq), (qx, qy, zq))
        it = dr.zeros(mi.Interaction3f, dr.width(qx))
        it.p = to_world @ mi.Point3f(cx, cy, cz)
        it.t = mi.Float(0.0)
        if wav is not None:
            it.wavelengths = wav
        return it

    def _contrib(self, ev, emitter, scene, xf, qx, qy, u_lam, u_em, active=True):
        """One forward sample per lane: ``(hit, px, py, value, lam, near)``, ``value`` its film value without the
        A_q/N area factor (the caller scales) and, where ``lam`` is not None (RGB variants, a sampled
        wavelength), without the wavelength's colour either (:meth:`_rgb` applies it: it reads Mitsuba's CIE
        tables, which a frozen kernel cannot), ``near`` the samples a learned evaluator leaves to the tracer
        (:class:`GhostEvaluator`; None without).  ``scene``: for the light's visibility test (None: none);
        ``xf``: the sensor's (to_world, to_camera) transforms and the film factor K / A_pix (opaque)."""
        import mitsuba as mi
        import drjit as dr
        from ..sensors.wavelengths import sample_wavelength
        to_world, to_cam, k_pix = xf
        lam, wav, wspec, _ = sample_wavelength(mi, dr, self.sensor, self.lambda_mode, mi.Float(0.0), u_lam,
                                               None, None, active, deferred=True)
        it = self._interaction(qx, qy, wav, to_world)
        ds, E = emitter.sample_direction(it, u_em, active)
        dcam = to_cam @ (-ds.d)
        dx, dy, dz = dcam.x, dcam.y, -dcam.z          # camera → lens direction
        ok = active & (dz > 1e-6) & (ds.pdf > 0.0)
        if scene is not None:
            ray = mi.Ray3f(it.p, ds.d, dr.select(dr.isfinite(ds.dist), ds.dist * (1.0 - 1e-4), dr.inf),
                           mi.Float(0.0), wav if wav is not None else [])
            ok &= ~scene.ray_test(ray, ok)
        zq = dr.zeros(mi.Float, dr.width(qx)) + self.z_in
        valid, x, y, T, near = ev((qx, qy, zq), (dx, dy, dz), lam, ok)
        W, H = self.size
        px = (x * (1.0 / self.setup.sensor_width_mm) + 0.5) * W
        py = (y * (1.0 / self.setup.sensor_height_mm) + 0.5) * H
        hit = valid & self._in_crop(px, py)
        val = E * (T * dz * k_pix)
        if not isinstance(wspec, float):
            val = val * wspec
        if mi.is_spectral:
            return hit, px, py, mi.spectrum_to_srgb(val, wav, hit), None, near
        return hit, px, py, val, (None if isinstance(lam, float) else lam), near

    def _in_crop(self, px, py):
        """Whether film position (``px``, ``py``; pixels of the full film) lies in the film's crop window."""
        ox, oy = self.crop_offset
        cw, ch = self.crop_size
        return (px >= ox) & (px < ox + cw) & (py >= oy) & (py < oy + ch)

    @staticmethod
    def _rgb(hit, val, lam):
        """The film value of :meth:`_contrib`'s samples: ``([r, g, b], luminance)``, 0 where not ``hit``."""
        import mitsuba as mi
        import drjit as dr
        if lam is not None:
            from ..sensors.wavelengths import rgb_weight
            val = val * rgb_weight(mi, lam)
        rgb = [dr.select(hit, val[i], 0.0) for i in range(3)]
        lum = LUMINANCE_WEIGHTS[0] * rgb[0] + LUMINANCE_WEIGHTS[1] * rgb[1] + LUMINANCE_WEIGHTS[2] * rgb[2]
        return rgb, lum

    # -------------------------------------------------------------- the two kernels, frozen
    def _pilot_kernel(self, ev, emitter, scene, xf, d):
        """The pilot's samples in the cells ``d["cx"], d["cy"]`` (lower-left corners, one per sample) of size
        ``d["c"]`` inside the disk of radius ``d["R"]``: (hit, value, λ, in-disk) per sample (:meth:`_contrib`)."""
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
        hit, px, py, val, lam, near = self._contrib(ev, emitter, scene, xf, qx, qy, u_lam, u_em, indisk)
        if near is not None:
            # the samples a learned evaluator leaves to the tracer (boundary_band, iris_band) may well be lit: the
            # main pass traces them, so their cells must be kept, and their learned value counts toward the ghost's
            # energy.  Counted as dark, a thin ghost (a fold's band) whose cells hold only such samples vanished
            hit = hit | (near & self._in_crop(px, py))
        return hit, val, lam, indisk

    def _splat_kernel(self, ev, emitter, scene, xf, d):
        """The main pass's samples ``d["idx"]`` (0..n−1, a rank-1 lattice shifted by ``d["shift"]``) inside the
        kept cells ``d["cells_x"], d["cells_y"]`` of size ``d["c"]`` (or, without cells, the disk of radius
        ``d["R"]``), each weighted by ``d["scale"]`` = sampled area / n: (px, py, value, λ, hit), and ``near`` where
        the evaluator leaves samples to the tracer (``boundary_band``)."""
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
        hit, px, py, val, lam, near = self._contrib(ev, emitter, scene, xf, qx, qy, u[3], mi.Point2f(u[4], u[5]),
                                                    True)
        if near is None:
            return px, py, val * d["scale"], lam, hit
        return px, py, val * d["scale"], lam, hit, near

    def _kernel(self, kind, ev, light, d):
        """Run the ``kind`` (``"pilot"`` or ``"splat"``) kernel of evaluator ``ev`` for ``light`` on the inputs
        ``d`` (a dict of Dr.Jit arrays and opaque scalars; widths change from call to call).

        With ``opts.freeze`` the kernel is a frozen function (``dr.freeze``): the first call of a signature is
        traced as usual, the second records it (Python tracing and kernel assembly, with the recording's own
        overhead), later calls replay the recorded kernels with new inputs.  The signature
        (:meth:`GhostEvaluator.freeze_key`) is the evaluator's own for the tracer and literal maps, and the
        architecture's for learned maps with kernel parameters, whose numbers and packed networks are then
        inputs: one recording serves every ghost map of one architecture, in this render and the next (a
        learned ghost traced again cost ≈ 20 ms per render, docs/results.md).  Everything else a kernel reads
        is an input too (the light, the scene, the transforms); the renderer's own constants (lens, film,
        sensor) are fixed for its life.  A signature that cannot be frozen (Dr.Jit refuses a recording that
        reads a variable it was not given) is traced."""
        import mitsuba as mi
        import drjit as dr
        body = self._kernels[kind]
        scene = self.scene if self.opts.visibility else None
        xf = (self._to_world, self._to_cam, self._k_pix)
        if not self.opts.freeze or mi.is_spectral or not hasattr(ev, "freeze_key"):
            return body(ev, light.emitter, scene, xf, d)      # (an evaluator of the caller's own: traced)
        sig, state = ev.freeze_key(mi.Float)
        uses = self._uses[(kind, sig)] = self._uses.get((kind, sig), 0) + 1
        if uses == 1 or (kind, sig) in self._unfrozen:      # record only what runs again: a recording costs
            return body(ev, light.emitter, scene, xf, d)    # more than tracing (docs/flares.md, "Frozen kernels")
        f = self._frozen.get(kind)
        if f is None:
            def frozen(kind, sig, state, emitter, scene, xf, d):
                return self._kernels[kind](self._frozen_ev, emitter, scene, xf, d)
            # every input opaque: with auto_opaque, an input that changed from one call to the next (a sample count,
            # a moved camera) was recorded once more before Dr.Jit made it an input
            f = self._frozen[kind] = dr.freeze(frozen, warn_after=1 << 30, auto_opaque=False)
        n0 = f.n_recordings
        pool = getattr(ev.map, "params_pool", None)
        n_pool = len(pool) if pool is not None else 0
        self._frozen_ev = ev
        gc_on = gc.isenabled()
        # no garbage collection inside a recording: an unrelated Dr.Jit variable freed there (a mapped numpy
        # buffer's release is a host callback) aborts the process ("cannot be recorded")
        gc.disable()
        try:
            out = f(kind, sig, state, light.emitter, scene, xf, d)
        except Exception as e:     # e.g. a kernel reading a variable it was not given: run it unfrozen
            self._unfrozen[(kind, sig)] = f"{type(e).__name__}: {e.__cause__ or e}"
            return body(ev, light.emitter, scene, xf, d)
        finally:
            self._frozen_ev = None
            if gc_on:
                gc.enable()
        if f.n_recordings != n0 and pool is not None and len(pool) != n_pool:
            # the recording created kernel parameters it was not handed: baked into it, wrong for other maps
            raise RuntimeError(f"lens_flare: the frozen {kind} kernel of path {ev.pid} read numbers it was not "
                               "given as inputs; render with freeze = False and report this")
        return out

    def pilot(self, light, ev, seed=0):
        """Occupied cells (dilated) of the input region for ``light`` and evaluator ``ev``: a :class:`Pilot`."""
        import mitsuba as mi
        import drjit as dr
        G, S = self.opts.pilot_grid, self.opts.pilot_spp
        R = self._region_radius(light)
        c = 2.0 * R / G
        gx, gy = np.meshgrid(np.arange(G), np.arange(G), indexing="xy")
        x0 = -R + gx.ravel() * c
        y0 = -R + gy.ravel() * c
        # cells that intersect the disk
        nx = np.clip(0.0, x0, x0 + c)
        ny = np.clip(0.0, y0, y0 + c)
        indisk = nx * nx + ny * ny <= R * R
        cells = np.nonzero(indisk)[0]
        n = len(cells) * S
        cid = np.repeat(cells, S).astype(np.uint32)
        d = {"idx": dr.arange(mi.UInt32, n), "cx": from_numpy(mi.Float, x0[cid]),
             "cy": from_numpy(mi.Float, y0[cid]), "c": dr.opaque(mi.Float, c), "R": dr.opaque(mi.Float, R),
             "seed": dr.opaque(mi.UInt64, (0x51ed * (seed + 1) + 7 * ev_hash(ev)) & 0xFFFFFFFF)}
        hit, val, lam, indisk_s = self._kernel("pilot", ev, light, d)
        _, lum = self._rgb(hit, val, lam)
        dr.eval(hit, lum, indisk_s)
        h = hit.numpy().astype(bool)
        ins = indisk_s.numpy().astype(bool)
        lum_np = lum.numpy().astype(np.float64)
        n_in = int(ins.sum())
        n_hit = int(h.sum())
        area = math.pi * R * R
        energy = float(lum_np.sum()) * area / max(n_in, 1)
        occ = np.zeros(G * G, bool)
        occ[cid[h]] = True
        occ = occ.reshape(G, G)
        if occ.any():
            d = occ.copy()
            d[1:, :] |= occ[:-1, :]; d[:-1, :] |= occ[1:, :]
            d2 = d.copy()
            d2[:, 1:] |= d[:, :-1]; d2[:, :-1] |= d[:, 1:]
            occ = d2
        keep = np.nonzero(occ.ravel())[0]
        return Pilot(np.stack([x0[keep], y0[keep]], 1), c, R, n_in, n_hit, energy)

    def splat(self, light, ev, n, block, cells, c, R, seed=0):
        """Splat ``n`` samples of one (light, path) into ``block``; cells None = whole disk.  Returns (film hits,
        samples traced exactly): a learned evaluator with ``boundary_band`` leaves the samples its classifier
        has not decided (``near``) to the tracer, which renders just those, at the same lattice points, in a
        second pass — the sample set and its weights are unchanged, only who evaluates each sample."""
        import mitsuba as mi
        import drjit as dr
        rng = np.random.default_rng([seed, ev_hash(ev), zlib.crc32(light.name.encode()) & 0xFFFF])
        d = {"idx": dr.arange(mi.UInt32, n),
             "shift": [dr.opaque(mi.UInt32, int(v)) for v in rng.integers(0, 2 ** 32, 6, dtype=np.uint64)]}
        if cells is None:
            d["R"] = dr.opaque(mi.Float, R)
            area = math.pi * R * R
        else:
            d.update(cells_x=from_numpy(mi.Float, cells[:, 0]), cells_y=from_numpy(mi.Float, cells[:, 1]),
                     ncells=dr.opaque(mi.UInt32, len(cells)), c=dr.opaque(mi.Float, c))
            area = len(cells) * c * c
        d["scale"] = dr.opaque(mi.Float, area / n)
        px, py, val, lam, hit, *near = self._kernel("splat", ev, light, d)
        rgb, _ = self._rgb(hit, val, lam)
        block.put(mi.Point2f(px, py), rgb, hit)
        if not near:
            return dr.count(hit), 0
        # the samples the learned map left to the tracer (its classifier undecided): the same lattice points
        # (their indices), traced in a second pass over just them
        dr.eval(block.tensor(), near[0])
        idx = dr.compress(near[0])
        n_near = dr.width(idx)
        hits = dr.count(hit)
        if n_near:
            d = {**d, "idx": idx}
            px, py, val, lam, hit = self._kernel("splat", self.exact_evaluator(ev.pid), light, d)[:5]
            rgb, _ = self._rgb(hit, val, lam)
            block.put(mi.Point2f(px, py), rgb, hit)
            hits = hits + dr.count(hit)
        return hits, n_near

    def exact_evaluator(self, pid):
        """The tracer's :class:`GhostEvaluator` of path ``pid``, one per path and renderer (the pilot with
        ``pilot_with = "exact"``, ``boundary_band``'s second pass)."""
        ev = self._exact_evs.get(pid)
        if ev is None:
            ev = self._exact_evs[pid] = GhostEvaluator(self.exact_map(pid), self.z_img, self.fresnel)
        return ev

    def new_block(self):
        import mitsuba as mi
        return mi.ImageBlock(mi.ScalarVector2u(*self.crop_size), mi.ScalarPoint2i(*self.crop_offset), 3,
                             rfilter=self._box, border=False, normalize=True)

    def render(self, seed=0, per_ghost=False, samples=None):
        """Render the flare; returns a :class:`FlareResult` (numpy images)."""
        import drjit as dr
        opts = self.opts
        N = int(samples or opts.samples)
        self._refresh()
        ids = self.ghost_ids()
        self._mlp = self.learned_mlp(ids)
        from ..trace.paths import ghost_surfaces
        total = self.new_block()
        blocks = {}
        stats = []
        self._light_sines = {}
        for li, light in enumerate(self.lights):
            plan = []          # (path id, evaluator, pilot, stats) of the paths that reach the film
            for pid in ids:
                t0 = time.perf_counter()
                ev = self.evaluator(pid)
                why = self.beyond_field(light, ev)
                if why is not None:                   # the map learned nothing there: the tracer renders it
                    ev = self.exact_evaluator(pid)
                ev_plan = ev if opts.pilot_with == "self" or ev.kind == "exact" else self.exact_evaluator(pid)
                pl = self.pilot(light, ev_plan, seed * 1000 + li)
                st = GhostStats(pid, ghost_surfaces(pid) if pid else (), light.name, ev.kind,
                                pilot_samples=pl.samples, pilot_hits=pl.hits, cells=len(pl.cells),
                                cells_total=int(round(math.pi * pl.radius ** 2 / pl.cell_size ** 2)),
                                energy=pl.energy, seconds=time.perf_counter() - t0, band=ev.band, why_traced=why)
                stats.append(st)
                if pl.hits > 0:
                    plan.append((pid, ev, pl, st))
            # ghosts share the budget in proportion to their energy; the transmit path (include_transmit:
            # the light's own, sharp image, ~100x brighter than all ghosts together but only a few pixels
            # wide) gets one equal share instead, or it would take nearly every sample
            ghosts_in_plan = [p for p in plan if p[0] != 0]
            etot = sum(max(st.energy, 0.0) for _, _, _, st in ghosts_in_plan)
            n_ghost_budget = N * len(ghosts_in_plan) // len(plan) if ghosts_in_plan else 0
            for pid, ev, pl, st in plan:
                t0 = time.perf_counter()
                if pid == 0:
                    n = N // len(plan)
                else:
                    share = max(st.energy, 0.0) / etot if etot > 0 else 1.0 / len(ghosts_in_plan)
                    n = int(n_ghost_budget * share)
                n = max(n, opts.min_samples)
                n = (n + 255) // 256 * 256
                blk = total
                if per_ghost:
                    blk = blocks.setdefault(pid, self.new_block())
                nh, st.traced = self.splat(light, ev, n, blk, None if opts.bounds == "none" else pl.cells,
                                           pl.cell_size, pl.radius, seed=seed * 7919 + li)
                dr.eval(blk.tensor())
                st.samples, st.hits = n, int(nh[0] if hasattr(nh, "__len__") else nh)
                st.splat_seconds = time.perf_counter() - t0
                st.seconds += st.splat_seconds
        ghosts = {}
        if per_ghost:
            acc = None
            for pid, b in blocks.items():
                img = b.tensor().numpy()
                ghosts[pid] = img
                acc = img.copy() if acc is None else acc + img
            tot = acc if acc is not None else np.zeros((self.crop_size[1], self.crop_size[0], 3), np.float32)
        else:
            tot = total.tensor().numpy()
        return FlareResult(np.asarray(tot), ghosts, stats)


def ev_hash(ev):
    """Random-stream id of an evaluator: its path only (not exact/neural), so that modes can share
    samples (see ``FlareOptions.pilot_with``)."""
    return (int(ev.pid) * 2654435761) & 0xFFFFFFFF


def render_flare(scene, sensor=0, *, seed=0, per_ghost=False, **options):
    """Python API: render the flare image of ``scene`` (loaded with a lens sensor) alone.
    ``options`` are :class:`FlareOptions` fields.  Returns a :class:`FlareResult`."""
    opts = FlareOptions(**options)
    return FlareRenderer(scene, sensor, opts).render(seed=seed, per_ghost=per_ghost)
