"""``mi-neurallens flare``: render the lens flare of a scene's bright lights alone (no backward render).

The scene's first sensor must be ``realistic_lens`` or ``neural_lens``.  Options of the scene's
``lens_flare`` integrator (if any) are not read; give them here.  ``--spp N`` sets the forward
samples per light to N × film pixels (``--samples`` gives the count directly).

``--compare`` renders exact and neural (same samples) and writes them side by side with the
error map, for all ghosts combined and per ghost, and prints the MAPE:

    MAPE(a, b) = mean over p in M of |Y_a(p) − Y_b(p)| / (|Y_b(p)| + ε)

with Y the Rec.709 luminance, b the exact reference, M = {p : Y_b(p) > 0.01 · max Y_b} and
ε = 1e-3 · max Y_b.
"""
from __future__ import annotations

import json
import os
import sys
import time

import numpy as np

from ..flare.options import COATINGS
from ..metrics import mape_masked as mape  # the flare MAPE (definition in mi_neurallens.metrics)
from ..render_utils import add_variant_argument


def add_parser(subparsers):
    p = subparsers.add_parser("flare", help="render the lens flare of a scene's lights (exact or neural)",
                              description=__doc__.split("\n\n", 1)[1] if __doc__ else None)
    p.add_argument("scene", help="Mitsuba XML scene (its first sensor: realistic_lens or neural_lens)")
    p.add_argument("-o", "--output", help="output PNG (default: <scene>_flare.png); an EXR is written next to it")
    p.add_argument("--lens", help="lens of the sensor (bundled name or file)")
    p.add_argument("--mode", choices=("auto", "exact", "neural", "abcd", "taylor3", "taylor5", "fitted"),
                   default="auto", help="ghost evaluator: exact tracer, learned maps, or a baseline")
    p.add_argument("--model", help="neural model: a file or a bundled lens name, e.g. wide-22mm (default: the sensor's model, else "
                   "the bundled model of the sensor's lens when it has one)")
    p.add_argument("--auto-max-error", type=float, default=0.1, metavar="PX",
                   help="mode auto: use a learned ghost map only where its held-out median exit-position error "
                        "is at most PX film pixels, else trace the ghost (default 0.1)")
    p.add_argument("--auto-max-flare-error", type=float, default=0.01, metavar="MAPE",
                   help="mode auto: where the model records a verified flare error for a map (mi-neurallens evaluate "
                        "--flare --write), use the map only if it is at most MAPE (default 0.01)")
    p.add_argument("--boundary-band", type=float, default=0.0, metavar="LOGIT",
                   help="learned ghosts: trace the samples whose classifier logit is within +-LOGIT of its decision "
                        "(their edges; 1.0 traces about 5%% of a ghost's samples; default 0: off). Mode auto "
                        "also traces a ghost's edges where only its record with a band passes the gate")
    p.add_argument("--iris-band", type=float, default=None, metavar="B",
                   help="learned ghosts through another iris than the trained one (stopped down, --blades): trace the "
                        "samples whose predicted stop-plane crossing lies within B x 3 x the stop head's p99 error of "
                        "the iris's edge (default: --boundary-band, at least 1 in mode auto; 0: off)")
    p.add_argument("--auto-max-cost", type=float, default=1.0, metavar="RATIO",
                   help="mode auto: where the model records what a learned ghost costs against tracing it on this "
                        "backend (evaluate --flare-cost --write; train measures it), learn it only if that is at "
                        "most RATIO (default 1: only where it is faster; inf: accuracy alone decides)")
    p.add_argument("--mlp", choices=("auto", "fused", "shared", "coopvec"), default="auto",
                   help="how learned ghost maps enter their kernels: fused (weights as literals, a kernel per map), "
                        "shared (every number a kernel input, weights in packed buffers on a CPU: one kernel per "
                        "architecture), coopvec; auto: shared "
                        "when several ghosts are learned (default)")
    p.add_argument("--no-freeze", dest="freeze", action="store_false",
                   help="trace every kernel in Python at every render instead of replaying frozen ones (dr.freeze)")
    p.add_argument("--ghost", dest="ghosts", action="append", default=[], metavar="ID",
                   help="render only this ghost (path id or a:b surface pair; repeatable)")
    p.add_argument("--exclude", dest="exclude", action="append", default=[], metavar="ID")
    p.add_argument("--max-ghosts", type=int, default=32)
    p.add_argument("--spp", type=int, help="forward samples per light per film pixel")
    p.add_argument("--samples", type=int, help="forward samples per light (default 2^22)")
    p.add_argument("--coating", choices=COATINGS, default="lens")
    p.add_argument("--no-diffraction", dest="diffraction", action="store_false",
                   help="leave out the aperture's diffraction starburst (the lights' own images convolved with the "
                        "exit pupil's Fraunhofer pattern): the ghosts alone")
    p.add_argument("--blades", type=int)
    p.add_argument("--resolution", help="film size WxH")
    add_variant_argument(p)
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                   help="set a property of the scene's lens sensor (repeatable), e.g. --set fstop=10.74")
    p.add_argument("-D", dest="params", action="append", default=[], metavar="NAME=VALUE")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--exposure", type=float, default=0.0, help="PNG exposure in stops")
    p.add_argument("--compare", action="store_true", help="exact vs neural side by side with error maps and MAPE")
    p.add_argument("--per-ghost", action="store_true", help="also write one PNG per ghost")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--json", help="write the statistics (pass fractions, timings, MAPE) to this JSON file")
    p.set_defaults(func=run)
    return p


def _norm_png(path, img, ref_max=None, exposure=0.0):
    from ..render_utils import write_png
    img = np.asarray(img, np.float32)[..., :3]
    m = ref_max if ref_max is not None else float(np.percentile(img[img > 0], 99.5)) if (img > 0).any() else 1.0
    write_png(path, img / max(m, 1e-30), exposure)


def run(args) -> int:
    from .render import _resolution, load_scene
    res = _resolution(args.resolution) if args.resolution else None
    scene = load_scene(args.scene, variant=args.variant, lens=args.lens, resolution=res, params=args.params,
                       sets=args.sets)
    sensor = scene.sensors()[0]
    W, H = (int(v) for v in sensor.film().crop_size())
    n = args.samples or (args.spp * W * H if args.spp else 1 << 22)
    kw = _options(args, int(n), _model(args, sensor))
    out = args.output or os.path.splitext(os.path.basename(args.scene))[0] + "_flare.png"
    base = os.path.splitext(out)[0]
    report = {"scene": args.scene, "samples_per_light": int(n), "film": [W, H]}
    modes = ("exact", "neural") if args.compare else (args.mode,)
    results = {}
    for mode in modes:
        results[mode], report[mode] = _render(args, scene, sensor, mode, kw)
    if not args.compare:
        _write(args, results[args.mode], out, base)
    else:
        _write_comparison(args, results["exact"], results["neural"], out, base, report)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(report, f, indent=1)
    return 0


def _model(args, sensor):
    """The neural model of the learned ghosts: ``--model``, else — for ``--compare`` or mode neural on a
    ``realistic_lens`` scene — the bundled model of the sensor's very lens (same fingerprint) where there is one,
    else None (the sensor's own, if any)."""
    model = args.model
    if model is None and (args.compare or args.mode == "neural") and getattr(sensor, "model", None) is None:
        # a realistic_lens scene: the learned ghosts of its lens's bundled model, when there is one for
        # this very lens (same fingerprint)
        from ..errors import ModelError
        from ..neural.model import bundled_model_path, load_model
        lens = sensor.setup.base_lens
        path = bundled_model_path(lens.name)
        if os.path.exists(path):
            try:
                model = load_model(path, lens)
                print(f"neural ghosts: {path}", file=sys.stderr)
            except ModelError:
                pass
    return model


def _options(args, n: int, model) -> dict:
    """The :class:`~mi_neurallens.flare.options.FlareOptions` fields of the command line but ``mode``, for ``n``
    samples per light."""
    from ..flare.options import parse_id_list
    return dict(samples=n, ghosts=parse_id_list(args.ghosts) or None, exclude_ghosts=parse_id_list(args.exclude),
                max_ghosts=args.max_ghosts, coating=args.coating, blades=args.blades, model=model,
                auto_max_error_px=args.auto_max_error, auto_max_flare_error=args.auto_max_flare_error, mlp=args.mlp,
                freeze=args.freeze, boundary_band=args.boundary_band, iris_band=args.iris_band,
                auto_max_cost=args.auto_max_cost, diffraction=args.diffraction)


def _render(args, scene, sensor, mode: str, kw: dict):
    """The flare in ``mode``, its statistics printed per (light, ghost): ``(FlareResult, report entry)``."""
    from ..errors import NeuralLensError
    from ..flare.options import FlareOptions
    from ..flare.render import FlareRenderer
    fr = FlareRenderer(scene, sensor, FlareOptions(mode=mode, **kw))
    if not fr.lights:
        raise NeuralLensError(f"{args.scene}: no point, spot or directional emitter to flare")
    t0 = time.perf_counter()
    r = fr.render(seed=args.seed, per_ghost=args.per_ghost or args.compare, progress=not args.no_progress)
    secs = time.perf_counter() - t0
    print(f"{mode}: {len(set(s.path_id for s in r.stats))} path(s) x {len(fr.lights)} light(s) in {secs:.2f} s",
          file=sys.stderr)
    for s in r.stats:
        why = s.why_traced or (fr.auto_reason(s.path_id) if mode == "auto" and s.evaluator == "exact"
                               and s.path_id else None)
        print(f"  ghost {s.path_id:>8} {str(tuple(s.surfaces)):>9} {s.evaluator:6} {s.light:16} "
              f"samples {s.samples:>9}  reach sensor: before {s.fraction_before:6.3f}  after "
              f"{s.fraction_after:6.3f}" + (f"  (traced: {why})" if why else "")
              + (f"  (edges traced" + (f", band {s.band:g}" if s.band > 0 else ", the iris's")
                 + f": {s.traced / max(s.samples, 1):.1%} of its samples)" if s.band > 0 or s.traced else ""),
              file=sys.stderr)
    return r, {"seconds": secs, "ghosts": [s.as_dict() for s in r.stats]}


def _write(args, r, out, base):
    """One mode's flare: ``base``.exr, the PNG ``out`` and with ``--per-ghost`` one PNG per ghost."""
    from ..render_utils import write_exr
    write_exr(base + ".exr", r.total)
    _norm_png(out, r.total, exposure=args.exposure)
    if args.per_ghost:
        for pid, img in r.ghosts.items():
            _norm_png(f"{base}_ghost{pid}.png", img, exposure=args.exposure)
    print(f"wrote {out} and {base}.exr")


def _write_comparison(args, ex, ne, out, base, report):
    """``--compare``: exact | neural | 10× |error| side by side in ``out`` (and per ghost with ``--per-ghost``),
    the MAPE of all ghosts and of each printed and kept in ``report``."""
    m_all = mape(ne.total, ex.total)
    report["mape_all"] = m_all
    report["mape_per_ghost"] = {}
    ref_max = float(np.percentile(ex.total[ex.total > 0], 99.5)) if (ex.total > 0).any() else 1.0
    err = np.abs(ne.total - ex.total)
    _norm_png(out, np.concatenate([ex.total, ne.total, err * 10.0], 1), ref_max, args.exposure)
    print(f"MAPE all ghosts (neural vs exact): {m_all:.4f}")
    for pid in ex.ghosts:
        if pid in ne.ghosts:
            mg = mape(ne.ghosts[pid], ex.ghosts[pid])
            report["mape_per_ghost"][str(pid)] = mg
            print(f"  ghost {pid:>8}: MAPE {mg:.4f}")
            if args.per_ghost:
                a, b = ex.ghosts[pid], ne.ghosts[pid]
                _norm_png(f"{base}_ghost{pid}.png", np.concatenate([a, b, np.abs(b - a) * 10], 1),
                          None, args.exposure)
    print(f"wrote {out} (exact | neural | 10x |error|)")
