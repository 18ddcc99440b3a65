"""``mi-neurallens evaluate MODEL``: held-out accuracy of every map of a model file.

Traces fresh held-out rays (float64, a seed different from training) and prints, per map, the
classifier's misclassification / false-valid / false-blocked rates and the distance of wrong answers
from the true boundary, and the regressor's exit-position (µm), direction (arcsec) and relative
throughput errors, checked against the goals of docs/training.md.  Writes JSON and markdown
(``--json``, ``--markdown``; default next to the model, ``<model>.eval.json`` / ``.md``, or in the current folder for
a bundled model).

``--flare`` also renders every forward ghost map's flare against the tracer's on the same samples
(:mod:`mi_neurallens.flare.verify`: paired MAPE, the largest over two light positions; a ghost above the
0.01 gate is rendered again with 4× the samples, up to ``--flare-max-samples``, until it converges); ``--write``
records it in the model file, where the flare's mode ``auto`` uses it (``auto_max_flare_error``); with
``--flare-boundary-band B`` the record of that band is kept beside the learned edges' one, and ``auto`` renders a
ghost whose learned edges miss the gate with its edges traced where that record passes.  ``--flare-cost`` times each
ghost map ``auto`` may learn against tracing the ghost (this variant's backend); with ``--write`` the costs are kept,
and ``auto`` learns a ghost only where that is faster (``auto_max_cost``).
"""
from __future__ import annotations

import json
import os
from pathlib import Path


def add_parser(subparsers):
    p = subparsers.add_parser("evaluate", help="held-out accuracy of a neural lens model",
                              description=__doc__.split("\n\n", 1)[1] if __doc__ else None)
    p.add_argument("model", help="model file (.model.safetensors) or bundled lens name")
    p.add_argument("--lens", help="lens (default: the bundled lens named in the model)")
    p.add_argument("-n", type=int, default=200_000, help="held-out rays per map (default 200000)")
    p.add_argument("--seed", type=int, default=4242)
    p.add_argument("--json", help="output JSON (default <model>.eval.json beside the model; for a bundled model, "
                                  "in the current folder)")
    p.add_argument("--markdown", help="output markdown (default <model>.eval.md, placed as --json)")
    p.add_argument("--recorded", action="store_true",
                   help="report the held-out metrics recorded in the model file at training instead of tracing "
                        "fresh rays (seconds instead of ~30 s per map)")
    p.add_argument("--flare", action="store_true",
                   help="also verify each ghost map's flare against the tracer on the same samples (paired MAPE)")
    p.add_argument("--flare-samples", type=int, default=24, metavar="LOG2",
                   help="log2 samples of each verification render (default 24)")
    p.add_argument("--flare-max-samples", type=int, default=None, metavar="LOG2",
                   help="refine a ghost above the 0.01 gate with 4x the samples up to this (default 26; 28: the "
                        "benchmarks' converged budget, about 45 s a ghost and light on 2 cores; the --flare-samples "
                        "value: no refinement)")
    p.add_argument("--flare-boundary-band", type=float, default=0.0, metavar="LOGIT",
                   help="verify the learned renders with lens_flare's boundary_band (samples at the classifier's "
                        "edge traced exactly; default 0: off). --write keeps its record beside the other bands' "
                        "(metrics['flare_bands']): mode auto renders a ghost whose learned edges miss the gate "
                        "with the band whose record passes")
    p.add_argument("--flare-ghosts", metavar="IDS",
                   help="verify only these ghost maps (comma list of path ids; default: every ghost map), e.g. the "
                        "ones a run retrained, or with --flare-boundary-band those whose learned edges miss the gate")
    p.add_argument("--flare-cost", action="store_true",
                   help="measure what each ghost map auto may learn costs against tracing the ghost (µs per sample, on "
                        "this variant's backend; run it on a quiet machine); with --write keep it in the model file, "
                        "where mode auto learns a ghost only if it is cheaper than tracing it (auto_max_cost)")
    p.add_argument("--flare-cost-samples", type=int, default=22, metavar="LOG2",
                   help="log2 samples of each timed render of --flare-cost (default 22)")
    p.add_argument("--write", action="store_true",
                   help="with --flare / --flare-cost: record the verified flare errors / the costs in the model file "
                        "(mode auto reads them)")
    p.set_defaults(func=run)
    return p


def run(args):
    from ..neural.model import bundled_model_path, load_model
    from ..optics.prescription import Lens
    from ..trace.paths import ghost_surfaces, resolve_path
    from ..training.evaluate import GOALS, evaluate_map, markdown_table, meets_goals
    from ..fileio import atomic_write_text
    if args.write and not (args.flare or args.flare_cost):
        from ..errors import NeuralLensError
        raise NeuralLensError("evaluate: --write records the verified flare errors or the ghosts' costs; add --flare "
                              "or --flare-cost")
    path = args.model if os.path.exists(args.model) else bundled_model_path(args.model)
    probe = load_model(path)
    made = provenance_text(probe)
    print(made, flush=True)
    lens = Lens.load(args.lens or probe.lens_name)
    model = load_model(path, lens)
    rows, out = [], {"model": os.path.basename(path), "lens": lens.name, "fingerprint": lens.fingerprint(),
                     "goals": GOALS, "recorded_at_training": bool(args.recorded), "maps": {}}
    for i, (key, tm) in enumerate(model.maps.items()):
        if args.recorded:
            if not tm.metrics.get("regressor") or not tm.metrics.get("classifier"):
                from ..errors import ModelError
                raise ModelError(f"{path}: map {key} has no recorded held-out metrics; evaluate without --recorded")
            m = {k: dict(v) for k, v in tm.metrics.items()}
        else:
            m = evaluate_map(lens, tm, n=args.n, seed=args.seed + 17 * i)
        m["describe"] = "transmit" if tm.path_id == 0 else "ghost a={}, b={}".format(*ghost_surfaces(tm.path_id))
        m["steps"] = resolve_path(lens, tm.path_id, tm.direction).describe()
        m["meets_goals"] = meets_goals(m)
        out["maps"][key] = m
        rows.append((key, m))
        r, c = m["regressor"], m["classifier"]
        print(f"{key:>16}: pos {r['position_um_median']:.3g}/{r['position_um_p99']:.3g} µm (median/p99), "
              f"dir {r['direction_arcsec_median']:.3g}/{r['direction_arcsec_p99']:.3g}\", "
              f"T {100 * r['throughput_rel_median']:.3g}%, misclass {100 * c['misclassification']:.3g}% "
              f"(false-valid {100 * c['false_valid']:.3g}%, false-blocked {100 * c['false_blocked']:.3g}%)", flush=True)
    if args.flare:
        _verify_flare(args, path, model, out)
    how = (f"`mi-neurallens evaluate {args.model} --recorded`: the held-out metrics recorded in the file at training "
           f"(each map's own held-out rays and seed)" if args.recorded else
           f"`mi-neurallens evaluate {args.model} -n {args.n} --seed {args.seed}`")
    md = (f"# Held-out accuracy of `{os.path.basename(path)}` ({lens.name})\n\n{made}\n\n{how}\n\n"
          + markdown_table(model, rows))
    jp = args.json or _beside(path) + ".eval.json"
    mp = args.markdown or _beside(path) + ".eval.md"
    atomic_write_text(jp, json.dumps(out, indent=1))
    atomic_write_text(mp, md)
    print(md)
    print(f"wrote {jp} and {mp}")
    if args.flare and args.write:
        _record_flare(path, model)
    if args.flare_cost:
        _flare_cost(args, path, model)
    return 0


def provenance_text(model) -> str:
    """How the model file was made, from its own metadata: each training run's command, recipe, package version,
    date, machine and time (``extra["runs"]``, written by ``mi-neurallens train``; the run that wrote the file
    took ``extra["training_time"]``, a merged one what its own file recorded);
    a file written before runs were recorded says so, with the number of distinct configurations its maps were
    trained with (each map's ``training["config_digest"]``)."""
    from ..training.whole_lens import own_run
    extra = model.extra or {}
    lines = ["How this model was made:"]
    runs = [r for r in extra.get("runs", []) if isinstance(r, dict)]
    seconds = (extra.get("training_time") or {}).get("seconds")
    own = own_run(runs)
    for i, r in enumerate(runs, 1):
        recipe = (r.get("recipe") or {}).get("file") or "the defaults (no recipe)"
        took = r.get("seconds") or (seconds if i - 1 == own else None)
        lines.append(f"* run {i}: `{r.get('command', '?')}` — {r.get('started', '?')}{' (resumed)' if r.get('resumed') else ''}"
                     + (f", {took / 60:.1f} min" if took else "") + "; "
                     f"recipe {recipe}, configuration {r.get('config_digest', '?')}; mi-neurallens "
                     f"{r.get('mi_neurallens', '?')}; {r.get('machine', '?')}"
                     + (f"; merged into this file: {', '.join(r['merged_maps'])}" if r.get("merged_maps") else ""))
    if not runs:
        digests = {m.training.get("config_digest") for m in model.maps.values() if m.training}
        lines.append(f"* the runs are not recorded (the file was written before `mi-neurallens train` recorded its "
                     f"command); its {len(model.maps)} maps were trained with {len(digests)} configuration(s) "
                     f"(each map's `training` record holds its settings, seed and times)")
    if seconds and own is None:
        lines.append(f"* the run that wrote this file took {seconds / 60:.1f} min")
    return "\n".join(lines)


def _beside(path: str) -> str:
    """Where a report on the model file ``path`` goes by default: beside it, except for a model inside the
    installed package (its shipped evaluation record stays as it is), whose report goes into the current
    folder."""
    from .. import resources
    bundled = resources.bundled_library().path.resolve()
    if bundled in Path(path).resolve().parents:
        return os.path.basename(path)
    return path


def _flare_cost(args, path, model):
    """``--flare-cost``: what each ghost map that mode ``auto`` may learn costs against tracing the ghost
    (:func:`~mi_neurallens.flare.verify.record_flare_costs`), printed, and kept in the model file with ``--write``
    (after the verified errors, which ``--flare --write`` saved first)."""
    import shutil
    import tempfile
    from ..flare.options import parse_id_list
    from ..flare.verify import record_flare_costs
    ghosts = parse_id_list(args.flare_ghosts) if args.flare_ghosts else None
    if args.write:
        record_flare_costs(path, args.lens or model.lens_name, ghosts=ghosts, samples_log2=args.flare_cost_samples)
        print(f"recorded the ghosts' costs in {path}")
        return
    with tempfile.TemporaryDirectory() as tmp:          # measure on a copy: the model file stays as it is
        copy = os.path.join(tmp, os.path.basename(path))
        shutil.copy(path, copy)
        record_flare_costs(copy, args.lens or model.lens_name, ghosts=ghosts, samples_log2=args.flare_cost_samples)
    print("(not recorded: add --write to keep the costs in the model file)")


def _verify_flare(args, path, model, out):
    """``--flare``: the paired flare error of every forward ghost map, into the report and into the maps'
    metrics (``metrics["flare"]``, or ``metrics["flare_bands"]`` with a band: :func:`store_flare_record`;
    saved by :func:`_record_flare` with ``--write``)."""
    import mitsuba as mi
    from ..flare.verify import MAX_SAMPLES_LOG2, store_flare_record, verify_model
    from ..render_utils import default_variant
    if not mi.variant():
        mi.set_variant(default_variant())
    # the lens as given (a file of the user's own lens, or a bundled name), for the neural_lens sensor
    top = max(MAX_SAMPLES_LOG2 if args.flare_max_samples is None else args.flare_max_samples, args.flare_samples)
    from ..flare.options import parse_id_list
    ghosts = parse_id_list(args.flare_ghosts) if args.flare_ghosts else None
    res = verify_model(path, args.lens or model.lens_name, ghosts=ghosts, samples_log2=args.flare_samples,
                       max_log2=top, boundary_band=args.flare_boundary_band)
    for pid, rec in res.items():
        tm = model.map(pid, "forward")
        key = next(k for k, m in model.maps.items() if m is tm)
        store_flare_record(out["maps"][key], rec)
        store_flare_record(tm.metrics, rec)
        err = rec["paired_mape"]
        samples = "/".join(f"2^{l2}" for l2 in rec["per_light_log2_samples"])
        falling = top > args.flare_samples and not all(
            c for c, v in zip(rec["converged"], rec["per_light"]) if v is not None)
        print(f"{key:>16}: flare, paired MAPE {'no pixel' if err is None else f'{err:.4f}'} "
              f"(max over {len(rec['lights_m'])} light positions, {samples} samples"
              f"{', still falling' if falling else ''}{_spots(rec)})", flush=True)


def _spots(rec) -> str:
    """How many of a flare record's light positions saw the ghost as a spot, compared blurred
    (:func:`~mi_neurallens.metrics.paired_flare_error_map`)."""
    n = sum(1 for c in rec.get("compact", ()) if c)
    return f"; a spot at {n}, compared blurred" if n else ""


def _record_flare(path, model):
    """``--write``: save the model with its maps' verified flare errors (after the reports are written, so a
    file that cannot be written loses nothing)."""
    from ..errors import NeuralLensError
    n = sum(1 for m in model.maps.values() if "flare" in m.metrics or "flare_bands" in m.metrics)
    if not n:
        print(f"{path}: no ghost maps, nothing to record")
        return
    try:
        model.save(path)
    except OSError as e:
        raise NeuralLensError(f"evaluate --write: cannot write {path} ({e}); the reports above hold the "
                              f"verified flare errors") from e
    print(f"recorded the verified flare errors of {n} ghost maps in {path}")
