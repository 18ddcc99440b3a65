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

Where things live
-----------------
This module sets a render up (the sensor's lens with the flare's coatings and blades, the lights, the ghost
list), picks each ghost's evaluator and runs the pilot, the budget and the splats.  What it asks elsewhere:
:mod:`~mi_neurallens.flare.policy` (mode ``auto``'s choice per ghost, the learned maps' ``mlp``, the field the
maps learned), :mod:`~mi_neurallens.flare.evaluator` (a ghost's map continued to the film) and
:mod:`~mi_neurallens.flare.kernels` (the pilot and splat kernels, frozen with ``dr.freeze``).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
import math
import os
import time
import zlib

import numpy as np

from ..constants import FULL_FRAME_MM
from ..errors import ModelError
from ..jit import from_numpy
from ..trace.iris import Iris
from . import policy
from .energy import front_radius, ghost_energy_ranking, input_plane, select_ghosts, trivial_ghost
from .evaluator import GhostEvaluator
from .kernels import FlareKernels, ev_hash, rgb
from .lights import scene_lights
from .options import BASELINE_MODES, FlareError, FlareOptions
from .policy import FlarePolicy


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
    per-ghost images were requested; ``stats``: one :class:`GhostStats` per (light, ghost); ``diffraction``: the
    starburst's part of ``total`` (None without diffraction)."""
    total: np.ndarray
    ghosts: dict
    stats: list
    diffraction: np.ndarray | None = None


# ------------------------------------------------------------------------------------ set-up
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
    if isinstance(m, (str, os.PathLike)) and os.fspath(m):
        return NeuralLensModel.load(resolve_model_path(os.fspath(m), "lens_flare"), None)
    return None


def flare_lens(setup, opts: FlareOptions):
    """The sensor's configured lens with the flare options (coatings, blades) applied."""
    from ..optics.coatings import Coating, preset
    lens = setup.lens
    if opts.coating == "none":
        lens = lens.with_coating(None)
    elif opts.coating in ("quarter_wave", "broadband"):
        c = (Coating(index=float(opts.coating_index), design_wavelength_nm=float(opts.coating_wavelength))
             if opts.coating == "quarter_wave" else preset("broadband"))
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
        trained, iris = setup.trained_iris, Iris.of_lens(self.lens)
        self.iris = None if iris.same_as(trained) else iris
        self._iris_ok = not trained.blades and iris.within(trained)
        self.fresnel = bool(setup.fresnel)
        from ..sensors.wavelengths import LAMBDA_NONE, LAMBDA_SAMPLE1
        lam_dep = (any(not m.is_constant for m in [self.lens.object_medium] + [s.medium for s in self.lens.surfaces])
                   or (self.fresnel and any(s.coating is not None for s in self.lens.surfaces)))
        self.lambda_mode = LAMBDA_SAMPLE1 if lam_dep else LAMBDA_NONE
        from ..trace.parameters import LiveGeometry
        from ..trace.tracer import LensTracer
        #: the tracer with the configuration's numbers (vertex positions, sensor plane, stop radius) as kernel
        #: inputs: a zoom, focus or f-number change compiles no new kernel
        self.tracer = LensTracer(self.lens, fresnel=self.fresnel,
                                 geometry=LiveGeometry.configuration(self.lens, mi.Float))
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
        #: the pilot and splat kernels and their frozen recordings (:meth:`_kernel`)
        self.kernels = FlareKernels(setup, sensor, self.lambda_mode, self.z_in, self.size, self.crop_offset,
                                    self.crop_size)
        #: how each ghost is evaluated (mode auto's choice, the learned maps' mlp), and the learned maps
        self.policy = FlarePolicy(self.opts, self.model, lens_modified=self.lens_modified, iris=self.iris,
                                  trained_iris=trained, iris_ok=self._iris_ok, sensor_width_mm=setup.sensor_width_mm,
                                  film_width_px=self.size[0], ghost_ids=self.ghost_ids)
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

    # -------------------------------------------------------------- evaluators
    def exact_map(self, pid):
        """The tracer on path ``pid``, from the flare's input plane to the sensor plane."""
        from ..transport.exact import ExactMap
        return ExactMap(self.lens, pid, "forward", self.z_in, self.z_img, tracer=self.tracer,
                        numbers={"z_in": self.kernels.planes()[0], "z_out": self.tracer.image_z})

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
                                 f"--paths {pid} --out DIR`, then `mi-neurallens merge` its maps into this model: "
                                 f"docs/training.md)")
            tmap = self._learned(m.map(pid, "forward"), strict=True)
        else:                              # auto: the learned map where its gates let it in, at its band
            band, _ = self.auto_choice(pid)
            tmap = None if band is None else self._learned(m.map(pid, "forward"), strict=False)
            if tmap is None:                          # the tracer (which ignores the band)
                tmap = self.exact_map(pid)
        return GhostEvaluator(tmap, self.z_img, self.fresnel, band or 0.0, self.iris_band(band or 0.0),
                              z_var=self.tracer.image_z)

    def exact_evaluator(self, pid):
        """The tracer's :class:`GhostEvaluator` of path ``pid``, one per path and renderer (the pilot with
        ``pilot_with = "exact"``, ``boundary_band``'s second pass)."""
        ev = self._exact_evs.get(pid)
        if ev is None:
            ev = self._exact_evs[pid] = GhostEvaluator(self.exact_map(pid), self.z_img, self.fresnel,
                                                       z_var=self.tracer.image_z)
        return ev

    def _learned(self, tm, strict: bool):
        """The learned map ``tm`` as this render evaluates it (:meth:`FlarePolicy.learned
        <mi_neurallens.flare.policy.FlarePolicy.learned>`), with the render's :meth:`learned_mlp`; a map of a lens
        with moving groups at the sensor's zoom and focus (:meth:`~mi_neurallens.sensors.common.LensSetup.
        configured_map`), or, outside the configurations it learned, an error when ``strict``, else None (traced)."""
        from ..errors import NeuralLensError
        if self._mlp is None:
            self._mlp = self.learned_mlp()
        try:
            tm = self.setup.configured_map(tm)
        except NeuralLensError as e:
            if strict:
                raise FlareError(f"lens_flare: mode='neural': the learned map of ghost {tm.path_id}: {e}; use "
                                 "mode='auto' (exact where a map cannot)") from e
            return None
        return self.policy.learned(tm, self._mlp, strict)

    # -------------------------------------------------------------- mode auto's choice (flare/policy.py)
    def iris_band(self, band: float) -> float:
        """The iris band of this render's learned ghosts given their ``band`` (:meth:`FlarePolicy.iris_band
        <mi_neurallens.flare.policy.FlarePolicy.iris_band>`)."""
        return self.policy.iris_band(band)

    def auto_learns(self, pid) -> bool:
        """Whether mode ``auto`` evaluates ghost ``pid`` with its learned map (:meth:`auto_choice`)."""
        return self.policy.auto_learns(pid)

    def auto_reason(self, pid) -> str | None:
        """Why mode ``auto`` traces ghost ``pid`` (a short phrase for messages), or None where it learns it."""
        return self.policy.auto_choice(pid)[1]

    def auto_choice(self, pid) -> tuple:
        """How mode ``auto`` evaluates ghost ``pid``: ``(band, None)`` with its learned map and that
        ``boundary_band``, or ``(None, why)`` with the tracer (:meth:`FlarePolicy.auto_choice
        <mi_neurallens.flare.policy.FlarePolicy.auto_choice>`)."""
        return self.policy.auto_choice(pid)

    def learned_mlp(self, ids=None) -> str:
        """How this render's learned maps enter their kernels (:meth:`FlarePolicy.learned_mlp
        <mi_neurallens.flare.policy.FlarePolicy.learned_mlp>`); ``ids``: the render's paths (default:
        :meth:`ghost_ids`)."""
        return self.policy.learned_mlp(ids)

    # -------------------------------------------------------------- the field the maps learned
    def light_sine(self, light) -> float:
        """The largest sine of the angle to the lens axis among ``light``'s rays toward the flare's input disk
        (:func:`~mi_neurallens.flare.policy.light_sine`).  Cached per render."""
        got = self._light_sines.get(light.name)
        if got is not None:
            return got
        R = self._region_radius(light)
        got = self._light_sines[light.name] = policy.light_sine(
            light.emitter, R, lambda qx, qy: self.kernels.interaction(qx, qy, None, self._to_world), self._to_cam)
        return got

    def beyond_field(self, light, ev) -> str | None:
        """Why the learned (or baseline) evaluator ``ev`` cannot render ``light``: some of its rays arrive
        steeper than the field the map was trained on (:func:`~mi_neurallens.flare.policy.beyond_field`).  None
        where the map covers the light (and for the tracer)."""
        s_max = policy.learned_field(ev)
        if s_max is None:
            return None
        return policy.beyond_field(self.light_sine(light), s_max)

    # -------------------------------------------------------------- sampling
    def _region_radius(self, light):
        """Radius of the conservative input disk for ``light`` (lens space, mm)."""
        import mitsuba as mi
        # direction from the light toward the lens centre, via a sample from the axis point
        it = self.kernels.interaction(mi.Float(0.0), mi.Float(0.0), None, self._to_world)
        ds, _ = light.emitter.sample_direction(it, mi.Point2f(0.5, 0.5), True)
        dl = self._to_cam @ (-ds.d)
        dz = abs(float(dl.z[0]))
        tmax = math.sqrt(max(1.0 - dz * dz, 0.0)) / max(dz, 1e-3)
        # a finite light near the lens sees the rim at steeper angles: add the rim's angular size
        return front_radius(self.lens, min(tmax * 1.2 + 0.05, 20.0), self.z_in)

    def _kernel(self, kind, ev, light, d):
        """Run the ``kind`` (``"pilot"`` or ``"splat"``) kernel of evaluator ``ev`` for ``light`` on the inputs
        ``d``, frozen with ``opts.freeze`` (:meth:`FlareKernels.run <mi_neurallens.flare.kernels.FlareKernels.run>`:
        one recording per learned-map architecture, replayed), with the scene for the light's visibility test
        (``opts.visibility``), the camera's pose and the film factor K / A_pix."""
        scene = self.scene if self.opts.visibility else None
        return self.kernels.run(kind, ev, light.emitter, scene, self.xf(), d, freeze=self.opts.freeze)

    def xf(self):
        """What the kernels read of the sensor besides the lens, all kernel inputs: (camera → world, world →
        camera, the film factor K / A_pix, the input and sensor planes (:meth:`FlareKernels.planes
        <mi_neurallens.flare.kernels.FlareKernels.planes>`))."""
        return (self._to_world, self._to_cam, self._k_pix, self.kernels.planes())

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
        _, lum = rgb(hit, val, lam)
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
        rgb_, _ = rgb(hit, val, lam)
        block.put(mi.Point2f(px, py), rgb_, hit)
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
            rgb_, _ = rgb(hit, val, lam)
            block.put(mi.Point2f(px, py), rgb_, hit)
            hits = hits + dr.count(hit)
        return hits, n_near

    # -------------------------------------------------------------- a render
    def new_block(self):
        import mitsuba as mi
        return mi.ImageBlock(mi.ScalarVector2u(*self.crop_size), mi.ScalarPoint2i(*self.crop_offset), 3,
                             rfilter=self._box, border=False, normalize=True)

    def render(self, seed=0, per_ghost=False, samples=None, progress=False):
        """Render the flare; returns a :class:`FlareResult` (numpy images).  ``progress``: a progress bar on
        standard error (tqdm), one step per (light, path) pilot and one per main pass, for a long render."""
        N = int(samples or self.opts.samples)
        self._refresh()
        ids = self.ghost_ids()
        self._mlp = self.learned_mlp(ids)
        # with diffraction every light's own image (the transmit path) is traced too, into a block of its own kind
        diffract = bool(self.opts.diffraction)
        paths = [0] + ids if diffract and 0 not in ids else ids
        total = self.new_block()
        blocks, direct, offframe = {}, {}, []
        stats = []
        self._light_sines = {}
        bar = None
        if progress:
            from ..render_utils import progress_bar
            bar = progress_bar(2 * len(self.lights) * len(paths), f"flare ({self.opts.mode})")
        for li, light in enumerate(self.lights):
            plan = self._plan(light, paths, seed * 1000 + li, stats, bar)
            if bar is not None:
                bar.update(len(paths) - len(plan))      # paths whose pilot missed the film have no main pass
            if diffract and light.kind != "area" and not any(p[0] == 0 for p in plan):
                offframe.append(light)                  # its own image misses the film; its spikes may not
            for (pid, ev, pl, st), n in zip(plan, self._budget(plan, N)):
                blk = total
                if diffract and pid == 0:
                    blk = direct.setdefault("seen" if light.kind == "area" else "unseen", self.new_block())
                elif per_ghost:
                    blk = blocks.setdefault(pid, self.new_block())
                self._splat_ghost(light, ev, pl, st, n, blk, seed * 7919 + li)
                if bar is not None:
                    bar.update(1)
        if bar is not None:
            bar.close()
        img, ghosts = self._images(total, blocks, per_ghost)
        star = None
        if diffract:
            from .starburst import starburst_image
            star = starburst_image(self, direct, offframe, seed * 7919 + 17)
            if star is not None:
                img = img + star
        return FlareResult(img, ghosts, stats, star)

    def diffraction_kernel(self):
        """The starburst's :class:`~mi_neurallens.flare.diffraction.FilmKernel` of this render's lens and film
        (:func:`~mi_neurallens.flare.starburst.film_kernel_of`: kept while the iris, focus and film stay)."""
        from .starburst import film_kernel_of
        return film_kernel_of(self)

    def _plan(self, light, ids, seed, stats, bar=None):
        """Each path of ``ids`` for ``light``: its evaluator (the tracer where the light lies beyond the field its
        map learned) and its pilot (seed ``seed``), its :class:`GhostStats` appended to ``stats`` (and a step of
        the progress ``bar``, if any).  Returns the ``(path id, evaluator, pilot, stats)`` of the paths whose pilot
        reached the film."""
        from ..trace.paths import ghost_surfaces
        plan = []
        for pid in ids:
            t0 = time.perf_counter()
            ev = self.evaluator(pid)
            why = self.beyond_field(light, ev)
            if why is not None:                   # the map learned nothing there: the tracer renders it
                ev = self.exact_evaluator(pid)
            ev_plan = ev if self.opts.pilot_with == "self" or ev.kind == "exact" else self.exact_evaluator(pid)
            pl = self.pilot(light, ev_plan, seed)
            st = GhostStats(pid, ghost_surfaces(pid) if pid else (), light.name, ev.kind,
                            pilot_samples=pl.samples, pilot_hits=pl.hits, cells=len(pl.cells),
                            cells_total=int(round(math.pi * pl.radius ** 2 / pl.cell_size ** 2)),
                            energy=pl.energy, seconds=time.perf_counter() - t0, band=ev.band, why_traced=why)
            stats.append(st)
            if bar is not None:
                bar.update(1)
            if pl.hits > 0:
                plan.append((pid, ev, pl, st))
        return plan

    def _budget(self, plan, N):
        """The main pass's samples of each entry of ``plan`` (:meth:`_plan`), of ``N`` for the light.  Ghosts share
        the budget in proportion to their energy; the transmit path (include_transmit: the light's own, sharp
        image, ~100x brighter than all ghosts together but only a few pixels wide) gets one equal share instead,
        or it would take nearly every sample.  At least ``min_samples``, rounded up to a multiple of 256."""
        ghosts_in_plan = [p for p in plan if p[0] != 0]
        etot = sum(max(st.energy, 0.0) for _, _, _, st in ghosts_in_plan)
        n_ghost_budget = N * len(ghosts_in_plan) // len(plan) if ghosts_in_plan else 0
        out = []
        for pid, _, _, st in plan:
            if pid == 0:
                n = N // len(plan)
            else:
                share = max(st.energy, 0.0) / etot if etot > 0 else 1.0 / len(ghosts_in_plan)
                n = int(n_ghost_budget * share)
            n = max(n, self.opts.min_samples)
            out.append((n + 255) // 256 * 256)
        return out

    def _splat_ghost(self, light, ev, pl, st, n, block, seed):
        """The main pass of one (light, path): ``n`` samples of evaluator ``ev`` in its pilot ``pl``'s cells (the
        whole disk with ``bounds = "none"``) into ``block``, evaluated; its counts and time into ``st``."""
        import drjit as dr
        t0 = time.perf_counter()
        nh, st.traced = self.splat(light, ev, n, block, None if self.opts.bounds == "none" else pl.cells,
                                   pl.cell_size, pl.radius, seed=seed)
        dr.eval(block.tensor())
        st.samples, st.hits = n, int(nh[0] if hasattr(nh, "__len__") else nh)
        st.splat_seconds = time.perf_counter() - t0
        st.seconds += st.splat_seconds

    def _images(self, total, blocks, per_ghost):
        """``(total, {path id: image})`` as numpy (H, W, 3) arrays: the whole flare from ``total``, or with
        ``per_ghost`` each path's image from ``blocks`` and their sum."""
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
        return np.asarray(tot), ghosts


def render_flare(scene, sensor=0, *, seed=0, per_ghost=False, **options):
    """Python API: render the flare image of ``scene`` (loaded with a lens sensor) alone.
    ``options`` are :class:`FlareOptions` fields.  Returns a :class:`FlareResult`."""
    opts = FlareOptions(**options)
    return FlareRenderer(scene, sensor, opts).render(seed=seed, per_ghost=per_ghost)
