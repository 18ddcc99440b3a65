"""A learned ghost map's flare error, verified against the tracer on the same samples.

The held-out metrics of a map (exit position in µm, misclassification) do not say how wrong its *flare*
is: a ghost's image also depends on where its classifier's edge sits and on how its errors add up over
the film.  This module measures that directly:

* a point light in front of the lens (the bundled scene ``night_point``: 100 W/sr at ``light`` m, the camera at
  the origin looking down +z), a small film;
* the ghost rendered alone, once by the tracer and once by its learned map, **with the same samples**
  (``pilot_with = "exact"``, same seed: common random numbers), so Monte Carlo noise cancels and what is
  left is the map's own error;
* the paired MAPE: the mean relative luminance error over the pixels where the exact ghost is brighter
  than 1 % of its peak; a ghost focused to a spot of fewer than 16 such pixels compared after both images are
  blurred by a Gaussian of 1 pixel, so that its error is its flux and placement at the pixel's scale, not how a
  sub-µm shift splits it between two pixels (:func:`mi_neurallens.metrics.paired_flare_error_map`);
* converged where it decides (:func:`refine_paired`): the noise that pairing leaves (a learned ray landing a
  few µm from its traced twin changes pixel near a pixel border) only adds to the error, so a ghost within
  the gate (``auto_max_flare_error``) at 2^24 samples is within it converged; one above it is rendered again
  with 4× the samples until it falls within the gate, stops falling (the protocol's "converged": less than
  :data:`CONVERGED_DROP` lower with 4× the samples) or reaches ``max_log2``.

:func:`verify_model` measures every forward ghost map of a model at a few light positions and keeps the
largest error; ``mi-neurallens evaluate MODEL --flare --write`` records it in the model file
(``metrics["flare"]`` of each map, or with ``--flare-boundary-band B`` ``metrics["flare_bands"]["B"]``:
:func:`store_flare_record`), where the flare's mode ``auto`` reads it (``auto_max_flare_error``) and, ghost by
ghost, uses the learned map with the narrowest band whose record passes, or the tracer.
"""
from __future__ import annotations

import math
import time
import typing

import numpy as np

#: light positions (m; x, y at z = 5 m in front of the lens): the night scene's (10° / 5° off axis) and one
#: near the axis, where the ghosts overlap most and the maps' errors showed most
LIGHTS = ((0.9, 0.45), (0.15, 0.1))
#: the verification lights lie within this fraction of the tangent of the field a model's ghost maps learned: a long
#: lens's narrow field gets :data:`LIGHTS` scaled toward the axis (:func:`verification_lights`); every bundled model's
#: field holds them as they are (the narrowest, ood-59mm's 21.9°, up to 0.241 m off axis at 5 m against 0.201)
LIGHT_FIELD_FRACTION = 0.6
#: the film of the verification renders (pixels; 36 mm wide on a full-frame sensor: 150 µm pixels)
FILM = (240, 160)
#: default samples of each render (all on one ghost; 2^24 ≈ 440 per film pixel, more on the ghost's mask: the
#: paired error converges only with many samples per pixel, where a learned ray landing one pixel over no longer
#: shows)
SAMPLES_LOG2 = 24
#: the most samples (log2) a ghost above the gate is refined to by default: 4× the start (≈ 12 s a render pair
#: of a dgauss-50mm ghost on a 2-core CPU, ≈ 3 s at 2^24); 28 is the benchmarks' converged budget (≈ 45 s a pair)
MAX_SAMPLES_LOG2 = 26
#: converged: 4× the samples lowered the paired error by less than this fraction (pure noise would halve it)
CONVERGED_DROP = 0.1
#: the boundary bands a ghost is verified at, each only for the ghosts the bands before leave above the gate
#: (:func:`record_flare_errors`, ``mi-neurallens train``'s ``verify_flare_bands``): the learned edges, then their
#: samples within ±1 logit traced, then within ±2 (a fold's edge, whose wrong rays lie further out: dgauss-50mm's
#: 33024 measured 0.77, 0.070 and 0.0092 at bands 0, 1 and 2), then within ±4 (a small ghost whose classifier is
#: unsure across much of it: the EF 24-70's ghost 48 at 68.1 mm, 0.0155, 0.0103 and 0.0073 at bands 2, 3 and 4,
#: tracing 14, 20 and 30 % of its samples)
BANDS = (0.0, 1.0, 2.0, 4.0)
#: a record whose band left more than this share of the ghost's samples to the tracer (``traced_share``, at any of its
#: light positions) lets no learned map in: at that band the map is mostly the tracer, and what it would save is
#: less than its networks cost (canon-rf-24mm-f1.4l-vcm's ghost 1280, whose classifier is sure of little beyond
#: ±3 logits: 2 %, 72 % and 99 % traced at bands 2, 3 and 4)
MAX_TRACED_SHARE = 0.5


def record_band(rec) -> float:
    """The ``boundary_band`` a verified flare record was measured with (0: the learned edges)."""
    return float(rec.get("boundary_band", 0.0))


def flare_records(metrics) -> list:
    """A map's verified flare records (:func:`verify_model`), ascending by the ``boundary_band`` they were
    measured with: ``metrics["flare"]``, the learned edges' record (band 0; in files written before bands were
    kept apart, the one record of whatever band), and ``metrics["flare_bands"]``, the records measured with a
    band > 0, keyed by the band (``"1"``)."""
    recs = [] if metrics.get("flare") is None else [metrics["flare"]]
    recs += list((metrics.get("flare_bands") or {}).values())
    return sorted(recs, key=record_band)


def passing_band(records, band: float, gate: float):
    """The ``boundary_band`` mode ``auto`` renders a ghost with, from its verified ``records`` (:func:`flare_records`)
    and the render's own ``band``: ``band`` where a record measured within it passes ``gate`` (its paired MAPE at
    most the gate), else the narrowest wider band whose record passes, else None (no record passes: traced).  A
    record whose band traced more than :data:`MAX_TRACED_SHARE` of the ghost's samples does not pass."""
    def passes(r):
        return (r.get("paired_mape") is not None and r["paired_mape"] <= gate
                and not traced_share(r) > MAX_TRACED_SHARE)
    if any(passes(r) for r in records if record_band(r) <= band):
        return band
    wider = [record_band(r) for r in records if record_band(r) > band and passes(r)]
    return min(wider) if wider else None


def traced_share(rec) -> float:
    """The largest share of a ghost's samples a verified flare record's band left to the tracer over its light
    positions (0 for a record of the learned edges, or one written before the share was kept)."""
    return float(rec.get("traced_share") or 0.0)


def verification_done(metrics, bands, gate: float) -> bool:
    """Whether a map's flare verification (:func:`record_flare_errors` over ``bands``) is complete: a record passes
    ``gate``, or every band has its record (none passes: ``auto`` traces the ghost)."""
    recs = flare_records(metrics)
    if passing_band(recs, max(float(b) for b in bands), gate) is not None:
        return True
    return {float(b) for b in bands} <= {record_band(r) for r in recs}


def store_flare_record(metrics, rec):
    """Keep ``rec`` in a map's ``metrics`` beside its records of other bands (:func:`flare_records`): band 0
    replaces ``metrics["flare"]``, a band > 0 the record of that band in ``metrics["flare_bands"]``, so one map
    can say both how its learned edges do and how it does with its edges traced, and mode ``auto`` picks per
    ghost (:meth:`~mi_neurallens.flare.render.FlareRenderer.auto_choice`)."""
    band = record_band(rec)
    if band == 0.0:
        metrics["flare"] = rec
        return
    bands = dict(metrics.get("flare_bands") or {})
    old = metrics.get("flare")
    if old is not None and record_band(old) > 0.0:     # an older file's only record, measured with a band
        bands[f"{record_band(old):g}"] = metrics.pop("flare")
    bands[f"{band:g}"] = rec
    metrics["flare_bands"] = dict(sorted(bands.items(), key=lambda kv: float(kv[0])))


#: samples (log2) of a cost measurement's render (:func:`measure_flare_cost`), all on the one ghost
COST_SAMPLES_LOG2 = 22
#: timed renders of each evaluator in a cost measurement (the fastest is kept), after two small renders: the first
#: traces and compiles its kernels, the second records them (``dr.freeze``), so the timed ones replay them
COST_RENDERS = 2


def variant_backend() -> str:
    """``"cuda"`` or ``"llvm"``: the Dr.Jit backend of the current Mitsuba variant (none set: the one
    :func:`~mi_neurallens.render_utils.default_variant` would set), which a cost is measured on."""
    import mitsuba as mi
    from ..render_utils import default_variant
    return "cuda" if "cuda" in (mi.variant() or default_variant()) else "llvm"


def flare_costs(metrics) -> dict:
    """A map's measured costs (:func:`measure_flare_cost`), one record per backend: ``metrics["flare_cost"]`` is
    ``{"llvm": record, "cuda": record}`` (the ratio differs between CPU and GPU, so neither replaces the other)."""
    return dict(metrics.get("flare_cost") or {})


def cost_bands(metrics, gate: float) -> list:
    """The bands a map's cost is measured at (:func:`record_flare_costs`): those of its verified records that pass
    ``gate``, the bands ``auto`` may render it with; ``[0.0]`` without records; ``[]`` where none passes (``auto``
    traces the ghost, so its cost does not matter)."""
    recs = flare_records(metrics)
    if not recs:
        return [0.0]
    return sorted({record_band(r) for r in recs if r.get("paired_mape") is not None and r["paired_mape"] <= gate})


def learned_cost_ratio(metrics, band: float):
    """A learned ghost's measured cost per sample at ``band``, divided by the tracer's on the same ghost, on the
    current variant's backend (:func:`flare_costs`), or None: not measured there, or not at that band."""
    c = flare_costs(metrics).get(variant_backend()) or {}
    lu = (c.get("learned_us") or {}).get(f"{float(band):g}")
    if lu is None or not c.get("exact_us"):
        return None
    return float(lu) / float(c["exact_us"])


def measure_flare_cost(scene, pid, bands=(0.0,), samples_log2=COST_SAMPLES_LOG2, model=None) -> dict:
    """What ghost ``pid`` of ``scene`` (:func:`verification_scene`) costs per sample, traced and with its learned map
    at each of ``bands`` (``boundary_band``, the samples it leaves to the tracer included): µs per sample of the main
    pass, the fastest of :data:`COST_RENDERS` renders of 2^``samples_log2`` samples that replay their recorded
    kernels (``dr.freeze``; what a renderer's later renders do) — the cost per sample without a render's fixed
    cost of tracing its kernels in Python (docs/flares.md, "Frozen kernels").  The pilot is excluded (its cost per
    sample is alike); learned maps as a full flare render evaluates them (``mlp = "shared"``).  Returns the
    record ``metrics["flare_cost"][backend]`` keeps (:func:`flare_costs`): ``exact_us``, ``learned_us`` {band: µs},
    ``backend``, ``samples_log2``."""
    from .options import FlareOptions
    from .render import FlareRenderer

    def us_per_sample(**kw):
        r = FlareRenderer(scene, 0, FlareOptions(ghosts=[pid], pilot_with="exact", diffraction=False, model=model,
                                                 **kw))
        for k in range(2):                # traces and compiles, then records: the kernels a later render replays
            r.render(seed=k, samples=1 << 16)
        best = float("inf")
        for k in range(COST_RENDERS):
            st = [s for s in r.render(seed=k + 2, samples=1 << samples_log2).stats if s.path_id == pid and s.samples]
            if st:
                best = min(best, 1e6 * sum(s.splat_seconds for s in st) / sum(s.samples for s in st))
        return None if best == float("inf") else best

    return {"exact_us": us_per_sample(mode="exact"),
            "learned_us": {f"{float(b):g}": us_per_sample(mode="neural", mlp="shared", boundary_band=float(b))
                           for b in bands},
            "backend": variant_backend(), "samples_log2": int(samples_log2),
            "protocol": f"µs per sample of the main pass, the fastest of {COST_RENDERS} renders of 2^{samples_log2} samples "
                        "replaying their frozen kernels, the ghost alone, at the verification scene's first light"}


def record_flare_costs(model_path, lens=None, *, ghosts=None, samples_log2=COST_SAMPLES_LOG2, gate=None,
                       log=print) -> dict:
    """Measure what each ghost map ``ghosts`` (default: all) of the model file ``model_path`` costs against tracing
    the ghost (:func:`measure_flare_cost`) and keep it in the model file (``metrics["flare_cost"]``, beside the
    records of other backends: :func:`flare_costs`), where mode
    ``auto`` reads it (``auto_max_cost``: a ghost whose learned map costs more than tracing it is traced).  Measured at
    the bands ``auto`` may render the ghost with: those of its verified records that pass ``gate`` (default: the
    flare's ``auto_max_flare_error``; none recorded: band 0); a ghost no record passes is traced by ``auto`` anyway
    and is skipped.  On the current variant's backend; run it on a quiet machine (it times renders).  What
    ``mi-neurallens evaluate MODEL --flare-cost --write`` does; ``mi-neurallens train`` ends with it.
    Returns {path_id: record}."""
    import mitsuba as mi
    from .options import FlareOptions
    from ..neural.model import load_model
    from ..render_utils import default_variant
    if not mi.variant():
        mi.set_variant(default_variant())
    gate = FlareOptions.auto_max_flare_error if gate is None else float(gate)
    model = load_model(model_path)
    ids = model.ghost_ids if ghosts is None else [int(g) for g in ghosts]
    missing = [pid for pid in ids if not model.has(pid, "forward")]
    if missing:
        from ..errors import ModelError
        raise ModelError(f"{model_path} has no forward map for {missing} to measure; its ghost maps are "
                         f"{model.ghost_ids}")
    plan = {pid: cost_bands(model.map(pid, "forward").metrics, gate) for pid in ids}
    plan = {pid: bands for pid, bands in plan.items() if bands}
    if log:
        log(f"measuring the cost of {len(plan)} ghost map(s) against tracing them ({variant_backend()}, 2^{samples_log2} "
            f"samples a render, {COST_RENDERS} renders each)" + (f"; {len(ids) - len(plan)} skipped (traced by auto: "
                                                                  "no record within the gate)" if len(plan) < len(ids) else ""))
    configs = verification_configurations(model, lens)
    camera = configs[len(configs) // 2]          # a zoom lens: the middle of its zoom
    scene = verification_scene(lens or model.lens_name, model_path, verification_lights(model)[0], FILM, camera)
    out, t0 = {}, time.perf_counter()
    for k, (pid, bands) in enumerate(plan.items()):
        out[pid] = c = measure_flare_cost(scene, pid, bands, samples_log2, model=model_path)
        if log:
            ratios = ", ".join(f"band {b}: {v / c['exact_us']:.2f}×" for b, v in c["learned_us"].items()
                               if v is not None and c["exact_us"])
            left = (time.perf_counter() - t0) * (len(plan) - k - 1) / (k + 1)
            log(f"ghost {pid} ({k + 1}/{len(plan)}): traced {c['exact_us'] or float('nan'):.3g} µs a sample; "
                f"learned / traced {ratios or 'n/a'}" + (f"; about {_duration(left)} left" if k + 1 < len(plan) else ""))
    model = load_model(model_path)
    for pid, c in out.items():
        met = model.map(pid, "forward").metrics
        met["flare_cost"] = {**flare_costs(met), c["backend"]: c}
    model.save(model_path)
    return out


def refine_paired(error_at, log2_from: int, log2_max: int, above: float, drop: float = CONVERGED_DROP) -> dict:
    """The paired error of one ghost at one light, refined where it decides: ``error_at(log2)`` → a
    :func:`paired_flare_error` record at 2^log2 samples; starting at ``log2_from``, 4× the samples (log2 + 2) while
    the error is above ``above`` and ``log2`` < ``log2_max``, until it falls by less than ``drop`` (its relative
    fall).  Returns the last record with ``log2_samples``, ``sequence`` ([[log2, paired_mape], …]) and ``converged``
    (True: within ``above``, or no longer falling; False: stopped at ``log2_max`` still falling, or no pixel)."""
    log2 = int(log2_from)
    r = dict(error_at(log2))
    seq = [[log2, r["paired_mape"]]]
    converged = r["paired_mape"] is not None and r["paired_mape"] <= above
    while r["paired_mape"] is not None and not converged and log2 + 2 <= log2_max:
        prev = r["paired_mape"]
        log2 += 2
        r = dict(error_at(log2))
        seq.append([log2, r["paired_mape"]])
        if r["paired_mape"] is None:
            break
        converged = r["paired_mape"] <= above or r["paired_mape"] >= (1.0 - drop) * prev
    r.update(log2_samples=log2, sequence=seq, converged=bool(converged))
    return r


def lights_within_field(lights, s_max: float, fraction: float = LIGHT_FIELD_FRACTION, z_m: float = 5.0) -> tuple:
    """Light positions ``lights`` ((x, y) m at ``z_m`` in front of the lens) as they are where the farthest lies
    within ``fraction`` of the tangent of the field whose sine is ``s_max`` (a forward map's domain), else all
    scaled toward the axis by one factor until it does (their pattern kept)."""
    t_field = s_max / math.sqrt(max(1.0 - s_max * s_max, 1e-12))
    t_far = max(math.hypot(float(x), float(y)) for x, y in lights) / z_m
    k = min(1.0, fraction * t_field / t_far) if t_far > 0 else 1.0
    return tuple((float(x) * k, float(y) * k) for x, y in lights)


def learned_field_sine(model) -> float | None:
    """The sine of the narrowest field a model's forward ghost maps learned (their domains' ``s_max``), None
    without ghost maps: beyond it a map answers only "blocked" (``FlareRenderer.beyond_field``)."""
    from ..transport.planning import Domain
    sines = [Domain.from_dict(model.map(pid, "forward").domain).s_max for pid in model.ghost_ids]
    return min(sines) if sines else None


def verification_lights(model, lights=LIGHTS) -> tuple:
    """The light positions a model's ghost maps are verified at: :data:`LIGHTS`, scaled toward the axis for a
    model whose maps learned a narrower field (:func:`lights_within_field` of :func:`learned_field_sine`).  A
    light outside that field would be traced (``FlareRenderer.beyond_field``), so a record measured there would
    say nothing of the map."""
    s_max = learned_field_sine(model)
    return tuple(lights) if s_max is None else lights_within_field(lights, s_max)


def verification_configurations(model, lens=None) -> list:
    """The camera settings a model's ghost maps are verified at: ``[{}]`` (the lens as loaded) for a lens of one
    configuration; for a zoom lens whose maps take the zoom as an input, :data:`VERIFY_ZOOMS` focal lengths (its
    ends and the zoom parameter's middle) at infinity focus, each ``{"focal_length": mm}``; for a lens that only
    focuses by moving groups, infinity and the prescription's close focus (``{"focus_distance": m}``, from the
    sensor).  ``lens``: the lens object, a bundled name or file (default: the model's)."""
    from ..transport.planning import Domain
    conds = [Domain.from_dict(model.map(pid, "forward").domain).conditions for pid in model.ghost_ids]
    cond = next((c for c in conds if c is not None), None)
    if cond is None:
        return [{}]
    from ..optics import moving as mv
    from ..sensors.common import load_lens
    lens = load_lens(lens or model.lens_name) if not hasattr(lens, "moving") else lens
    if "zoom" in cond.names:
        t0, t1 = cond.zoom_range
        return [{"focal_length": round(mv.focal_length(lens, float(t)), 4)}
                for t in np.linspace(t0, t1, VERIFY_ZOOMS)]
    close = float(lens.moving.close_focus_mm)
    return [{}] + ([{"focus_distance": close / 1e3}] if math.isfinite(close) and close > 0 else [])


#: the zoom positions a zoom lens's ghost maps are verified at (:func:`verification_configurations`): the ends and
#: the middle of the zoom range
VERIFY_ZOOMS = 3


def verification_scene(lens, model, light=LIGHTS[0], film=FILM, camera=None):
    """The night_point scene as a dict: ``neural_lens`` with ``model`` (a file or bundled name) through
    ``lens``, one point light at ``(x, y, 5)`` m; ``camera``: more properties of the sensor (a zoom lens's
    ``focal_length``, :func:`verification_configurations`).  A model without a camera map (ghost maps trained on
    their own) gets ``realistic_lens`` instead: the flare does not use the camera map, and the renders here take
    the model as ``lens_flare``'s (``model`` of :func:`paired_renders`).  The current Mitsuba variant."""
    import mitsuba as mi
    import mi_neurallens
    from ..neural.model import NeuralLensModel
    from ..sensors.neural_lens import resolve_model_path
    mi_neurallens.register()
    m = model if isinstance(model, NeuralLensModel) else NeuralLensModel.load(resolve_model_path(str(model), "lens_flare"))
    sensor = {"type": "neural_lens", "model": str(model)} if m.has("transmit", "backward") else {"type": "realistic_lens"}
    return mi.load_dict({
        "type": "scene",
        "camera": {**sensor, "lens": lens,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[0, 0, 1], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": int(film[0]), "height": int(film[1]),
                            "pixel_format": "rgb"}, **(camera or {})},
        "light": {"type": "point", "position": [float(light[0]), float(light[1]), 5.0],
                  "intensity": {"type": "rgb", "value": 100.0}},
    })


class PairedRenders(typing.NamedTuple):
    """Two flare renders of the same ghosts on the same samples (:func:`paired_renders`): H×W×3 numpy images."""

    exact: object
    learned: object
    #: of the learned render's samples, the share its bands (or a ghost its map cannot answer) left to the tracer
    traced_share: float


def paired_renders(scene, ghosts, samples, seed=1, sensor=0, boundary_band=0.0, iris_band=None,
                   model=None) -> PairedRenders:
    """The exact and the learned flare images of ``ghosts`` alone (no diffraction) on the same samples, and the
    share of the learned render's samples left to the tracer; ``boundary_band``, ``iris_band``, ``model``: the
    learned render's (:class:`~mi_neurallens.flare.options.FlareOptions`; ``model`` None: the sensor's)."""
    from .render import render_flare
    ex = render_flare(scene, sensor, seed=seed, ghosts=list(ghosts), samples=samples, mode="exact",
                      diffraction=False).total
    ne = render_flare(scene, sensor, seed=seed, ghosts=list(ghosts), samples=samples, mode="neural",
                      pilot_with="exact", boundary_band=boundary_band, iris_band=iris_band, diffraction=False,
                      model=model)
    n = sum(s.samples for s in ne.stats)
    left = sum(s.samples if s.why_traced else s.traced for s in ne.stats)    # a ghost its map cannot answer: all
    return PairedRenders(ex, ne.total, left / n if n else 0.0)


def paired_flare_error(scene, pid, samples=1 << SAMPLES_LOG2, seed=1, boundary_band=0.0, model=None) -> dict:
    """The learned map of ghost ``pid`` against the tracer on the same samples: ``paired_mape`` (None when
    the exact ghost leaves no pixel above the mask threshold: nothing to compare), ``pixels`` in the
    mask it was measured on (the blurred images' for a spot), ``compact`` (a spot of a few pixels, compared
    blurred: :func:`~mi_neurallens.metrics.paired_flare_error_map`), ``flux_ratio`` (learned / exact
    luminance), ``traced_share`` (of the learned render's samples, those ``boundary_band`` left to the tracer)."""
    import numpy as np
    from ..metrics import LUMINANCE, paired_flare_error_map
    ex, ne, share = paired_renders(scene, [pid], samples, seed, boundary_band=boundary_band, model=model)
    rel, mask, compact = paired_flare_error_map(ne, ex)
    ye, yn = float(np.sum(ex[..., :3] @ LUMINANCE)), float(np.sum(ne[..., :3] @ LUMINANCE))
    return {"paired_mape": float(rel[mask].mean()) if mask.any() else None, "pixels": int(mask.sum()),
            "compact": compact, "flux_ratio": yn / ye if ye > 0 else None, "traced_share": float(share)}


def verify_model(model_path, lens=None, *, ghosts=None, lights=None, samples_log2=SAMPLES_LOG2,
                 max_log2=MAX_SAMPLES_LOG2, refine_above=None, film=FILM, boundary_band=0.0, log=print) -> dict:
    """Every forward ghost map (or those of ``ghosts``, each of which it must have: else a ModelError) of the
    model at ``model_path`` against the tracer: {path_id: record}, the record ``metrics["flare"]`` keeps — ``paired_mape`` the largest over ``lights``
    (None if the ghost reached no pixel at any of them), the per-light values, flux ratios and sample counts
    (log2), whether each converged, and the protocol (film, lights; default :func:`verification_lights`).  Each light starts at 2^``samples_log2``
    samples and a ghost above ``refine_above`` (default: the flare's ``auto_max_flare_error``, 0.01) is refined
    up to 2^``max_log2`` (:func:`refine_paired`; ``max_log2 = samples_log2``: no refinement).  ``lens``: a
    bundled name or a lens file (default: the model's lens).  ``boundary_band``: the learned renders'
    (:class:`~mi_neurallens.flare.options.FlareOptions`; 0, the default, is what ``auto`` gates on)."""
    from ..metrics import FLARE_COMPACT_PIXELS, FLARE_COMPACT_SIGMA_PX
    from .options import FlareOptions
    if refine_above is None:
        refine_above = FlareOptions.auto_max_flare_error
    max_log2 = max(int(max_log2), int(samples_log2))
    from ..neural.model import load_model
    model = load_model(model_path)
    lens = lens or model.lens_name
    lights = verification_lights(model) if lights is None else lights
    ids = model.ghost_ids if ghosts is None else [int(g) for g in ghosts]
    missing = [pid for pid in ids if not model.has(pid, "forward")]
    if missing:
        from ..errors import ModelError
        raise ModelError(f"{model_path} has no forward map for {missing} to verify; its ghost maps are "
                         f"{model.ghost_ids}")
    per = {pid: [] for pid in ids}
    configs = verification_configurations(model, lens)
    runs = [(c, light) for c in configs for light in lights]
    t0, done, total = time.perf_counter(), 0, len(runs) * len(ids)
    for camera, light in runs:
        scene = verification_scene(lens, model_path, light, film, camera)
        where = "".join(f"{k} {v:g}, " for k, v in camera.items())
        for k, pid in enumerate(ids):
            r = refine_paired(lambda l2: paired_flare_error(scene, pid, 1 << l2, boundary_band=boundary_band,
                                                            model=model_path),
                              samples_log2, max_log2, refine_above)
            per[pid].append(r)
            done += 1
            if log:
                m = " → ".join("no pixel" if v is None else f"{v:.4f} (2^{l2})" for l2, v in r["sequence"])
                left = (time.perf_counter() - t0) * (total - done) / done
                log(f"{where}light {light}: ghost {pid} ({k + 1}/{len(ids)}) paired MAPE {m}"
                    + (", a spot: compared blurred" if r.get("compact") else "")
                    + (f", {r['traced_share']:.0%} of its samples traced" if boundary_band > 0 else "")
                    + ("" if r["converged"] or r["paired_mape"] is None else ", still falling")
                    + (f"; about {_duration(left)} left" if done < total else ""))
    out = {}
    for pid, rs in per.items():
        vals = [r["paired_mape"] for r in rs if r["paired_mape"] is not None]
        out[pid] = {"paired_mape": max(vals) if vals else None,
                    "per_light": [r["paired_mape"] for r in rs],
                    "flux_ratio": [r["flux_ratio"] for r in rs],
                    "pixels": [r["pixels"] for r in rs], "compact": [bool(r.get("compact")) for r in rs],
                    "traced_share": max(r["traced_share"] for r in rs),
                    "per_light_traced_share": [r["traced_share"] for r in rs],
                    "lights_m": [[float(x), float(y), 5.0] for _, (x, y) in runs],
                    **({"configurations": [c for c, _ in runs]} if configs != [{}] else {}),
                    "log2_samples": max(r["log2_samples"] for r in rs),
                    "per_light_log2_samples": [r["log2_samples"] for r in rs],
                    "converged": [r["converged"] for r in rs],
                    "refined_above": float(refine_above), "film": [int(film[0]), int(film[1])],
                    "boundary_band": float(boundary_band),
                    "protocol": "paired (same samples, pilot_with=exact), mask > 1 % of the exact ghost's peak "
                                f"(fewer than {FLARE_COMPACT_PIXELS} pixels: both blurred by a Gaussian of "
                                f"{FLARE_COMPACT_SIGMA_PX:g} px first); "
                                f"refined with 4x the samples above {refine_above:g} until it falls by less than "
                                f"{CONVERGED_DROP:g}"}
    return out


def _duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 90 else f"{seconds / 60:.1f} min"


def record_flare_errors(model_path, lens=None, *, ghosts=None, bands=BANDS, samples_log2=SAMPLES_LOG2,
                        max_log2=MAX_SAMPLES_LOG2, gate=None, keep_measured=False, log=print) -> dict:
    """Verify the ghost maps ``ghosts`` (default: all) of the model file ``model_path`` and keep the records in it,
    where mode ``auto`` reads them (:meth:`~mi_neurallens.flare.render.FlareRenderer.auto_choice`): every ghost
    at ``bands[0]``, then each further band only for the ghosts whose records so far all miss ``gate`` (default:
    the flare's ``auto_max_flare_error``) — so a ghost ends with the record of the narrowest band it passes at,
    or with every band's when none passes (``auto`` then traces it).  What ``mi-neurallens evaluate MODEL --flare
    --write`` (and ``--flare-boundary-band 1``) do, in one call; ``mi-neurallens train`` ends with it.

    Every band renders 2^``samples_log2`` samples; every band but the first (and the first too when it is the only
    one) refines a ghost above the gate, up to 2^``max_log2`` (:func:`verify_model`).  The first is not refined
    because a ghost it leaves above the gate is measured at the next band anyway, and noise only ever raises the
    paired error: so a ghost is learned at a wider band, or traced, where a converged record of the learned edges
    would let it in narrower — never the other way.  A later band is refined, so that a ghost goes on to a still
    wider band only when the narrower one, converged, misses the gate.  The file is rewritten (atomically)
    after each band, so an interruption keeps the bands done; ``keep_measured``: a ghost's record of a band that the
    file already holds is kept, not measured again (how a resumed ``train`` goes on).  Returns
    {band: {path_id: record}}."""
    import mitsuba as mi
    from .options import FlareOptions
    from ..neural.model import load_model
    from ..render_utils import default_variant
    if not mi.variant():
        mi.set_variant(default_variant())
    gate = FlareOptions.auto_max_flare_error if gate is None else float(gate)
    todo = list(load_model(model_path).ghost_ids if ghosts is None else (int(g) for g in ghosts))
    lights = verification_lights(load_model(model_path))
    out = {}
    for band in bands:
        if not todo:
            break
        refine = band == bands[-1] or band != bands[0]
        have = {}
        if keep_measured:
            model = load_model(model_path)
            for pid in todo:
                rec = [r for r in flare_records(model.map(pid, "forward").metrics) if record_band(r) == float(band)]
                if rec:
                    have[pid] = rec[0]
        run = [pid for pid in todo if pid not in have]
        if log and have:
            log(f"{len(have)} ghost map(s) already verified at boundary_band {band:g}: kept")
        if not run:
            out[float(band)] = have
            todo = [pid for pid in todo if have[pid].get("paired_mape") is not None and have[pid]["paired_mape"] > gate]
            continue
        if log:
            log(f"verifying the flare of {len(run)} ghost map(s) against the tracer"
                + (f" with their edges traced (boundary_band {band:g})" if band else " (their learned edges)")
                + f": 2^{samples_log2} samples a render"
                + (f" (up to 2^{max_log2} for a ghost above {gate:g})" if refine and max_log2 > samples_log2 else "")
                + f", {len(lights)} light positions"
                + ("" if lights == LIGHTS else " (" + ", ".join(f"({x:.3g}, {y:.3g}, 5) m" for x, y in lights)
                   + ": within the maps' field)"))
        res = verify_model(model_path, lens, ghosts=run, lights=lights, samples_log2=samples_log2,
                           max_log2=max_log2 if refine else samples_log2, refine_above=gate, boundary_band=band, log=log)
        model = load_model(model_path)
        for pid, rec in res.items():
            store_flare_record(model.map(pid, "forward").metrics, rec)
        model.save(model_path)
        res = {**have, **res}
        out[float(band)] = res
        todo = [pid for pid in todo if res[pid]["paired_mape"] is not None and res[pid]["paired_mape"] > gate]
        if log:
            passed = sum(1 for r in res.values() if r["paired_mape"] is not None and r["paired_mape"] <= gate)
            log(f"{passed} of {len(res)} within {gate:g}" + (f"; {len(todo)} above it" if todo else ""))
    return out
