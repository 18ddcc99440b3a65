"""``mi-neurallens train LENS``: train the neural lens transport maps of a lens.

Reads the lens's recipe ``recipes/<lens>.toml`` of its lens library when there is one (or ``--config``), plans the planes,
ranks the ghosts, trains every selected map (classifier, regressor and stop head, PyTorch on CPU or CUDA;
the maps of one direction together, each network stopping at its goals) with checkpoints in
``<out>.work/`` (rerun the same command to resume after an interruption) and writes one model file
``<out>/<lens>.model.safetensors`` (atomically, after each direction's maps) with the held-out metrics.
Last, each ghost map trained is rendered against the tracer and its verified flare error kept in the file
(the learned edges', and with the edges traced for the ghosts those miss 0.01), then timed against tracing the
ghost, which the flare's mode ``auto`` reads to learn or trace each ghost (``--no-verify``: later, with
``mi-neurallens evaluate --flare --write`` and ``--flare-cost --write``).
``--ray [ADDRESS]`` runs the maps of one or more lenses as jobs on Ray (training/distributed.py).
"""
from __future__ import annotations

import json
import os
import sys

from ..training.keep import FINISH_ONLY, KEEP, OLD_KEEP


def add_parser(subparsers):
    p = subparsers.add_parser("train", help="train the neural transport maps of a lens",
                              description=__doc__.split("\n\n", 1)[1] if __doc__ else None)
    p.add_argument("lens", nargs="+", help="bundled lens name(s) or lens file(s)")
    p.add_argument("--paths", help="comma list: transmit, ghosts, backward, forward, backward-transmit, "
                                   "forward-transmit or forward path ids (default: what the config lists)")
    p.add_argument("--config", help="TOML training recipe (default: the lens library's recipes/<lens>.toml when there is one)")
    p.add_argument("--out", default=None, help="output folder (default: the current folder; for a lens of a library "
                                               "in $MI_NEURALLENS_LENSES, that library's models/ folder, where "
                                               "neural_lens finds it by the lens's name)")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value, e.g. --set seed=3 --set regressor.max_steps=2000, --set flare_resolution=1024 "
                        "(looser flare-map goals), --set 'forward_regressor.sizes=[\"3x16\",\"5x32\"]' (the smallest "
                        "network that meets them) (JSON values)")
    p.add_argument("--keep", choices=KEEP + tuple(OLD_KEEP), metavar="{" + ",".join(KEEP) + "}",
                   help="keep this of each selected map from --base and train the rest: its regressor or its "
                        "classifier (the other network trains anew), or its networks (both: only the stop heads "
                        "train, a render-time aperture for an existing model; 'both' is the old spelling)")
    p.add_argument("--finish-only", choices=FINISH_ONLY,
                   help="train nothing anew: start from --base's networks and run only their Levenberg-Marquardt "
                        "finish (lm_minutes), each widened first where the config's width is larger; 'maps': the "
                        "regressors and classifiers (stop heads kept), 'stop-heads': the stop heads alone "
                        "(networks kept). `--keep refine` and `--keep refine-stop` are the old spellings")
    p.add_argument("--base", help="model file the --keep or --finish-only networks come from (default: the bundled "
                                  "model of the lens; an existing output file other than it must be named, and a "
                                  "rerun that resumes takes the base of the run before)")
    p.add_argument("--ray", nargs="?", const="local", metavar="ADDRESS",
                   help="run the maps as jobs on Ray (the 'cluster' extra): a local instance, or the cluster at "
                        "ADDRESS (e.g. auto, ray://head:10001); one GPU per job when the cluster has GPUs")
    p.add_argument("--jobs", type=int, default=4, help="with --ray: forward-map jobs per lens (default 4)")
    p.add_argument("--no-verify", action="store_true",
                   help="skip the flare verification that ends a run (each ghost map trained rendered against the "
                        "tracer, its record kept in the model file for the flare's mode auto, then timed against "
                        "tracing it; the verify_flare settings); `mi-neurallens evaluate MODEL --flare --write` and "
                        "`--flare-cost --write` do it later")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--quiet", action="store_true", help="no per-evaluation log lines")
    p.set_defaults(func=run)
    return p


def _overrides(sets):
    out: dict = {}
    for s in sets:
        if "=" not in s:
            from ..errors import NeuralLensError
            raise NeuralLensError(f"--set {s!r}: expected KEY=VALUE")
        k, v = s.split("=", 1)
        try:
            val = json.loads(v)
        except json.JSONDecodeError:
            val = v
        d = out
        parts = k.split(".")
        for p in parts[:-1]:
            d = d.setdefault(p, {})
        d[parts[-1]] = val
    return out


def _focus_text(lens, setting) -> str:
    """The focus range a training supports, for its header (and the check that the lens can focus it, before any
    work: :func:`~mi_neurallens.transport.planes.sensor_distance_range` raises otherwise)."""
    from ..transport import planes as plan
    mg = getattr(lens, "moving", None)
    if mg is not None:                  # the groups focus (and zoom); the sensor stays
        zoom = (f"{mg.zoom_efl_mm[0]:g}–{mg.zoom_efl_mm[-1]:g} mm, " if mg.is_zoom and mg.zoom_efl_mm else "")
        close = setting if isinstance(setting, (int, float)) and setting > 0 else mg.close_focus_mm
        focus = f"infinity to {close / 1000:.3g} m from the sensor" if mg.focuses and close else "infinity"
        return f"{zoom}{focus} by the lens's moving groups, zoom and focus as inputs of every map"
    s0, s1 = plan.sensor_distance_range(lens, setting)
    d = plan.close_focus_mm(lens, setting)
    if not d:
        return "infinity only"
    return (f"infinity to {d / 1000:.3g} m in front of the first vertex (close_focus_mm = {setting!r}; sensor "
            f"{s0:.4g}–{s1:.4g} mm behind the last vertex)")


#: how to get PyTorch for training, in one place (README.md says the same)
TORCH_HINT = ("training needs PyTorch, which mi-neurallens installs only with its 'train' extra: for the CPU build, "
              "`pip install torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu` first, then "
              "`pip install 'mi-neurallens[train]'` (with a CUDA GPU: `pip install 'mi-neurallens[train]'` alone); "
              "rendering, evaluating and the flare work without it")


def require_torch() -> None:
    """A clear error, not an ImportError deep in the trainer, when PyTorch is not installed."""
    import importlib.util
    if importlib.util.find_spec("torch") is None:
        from ..errors import NeuralLensError
        raise NeuralLensError(TORCH_HINT)


def default_out_dir(spec: str, name: str) -> str:
    """Where ``train`` writes a model without ``--out``: the ``models/`` folder of the user's lens library
    (``$MI_NEURALLENS_LENSES``) the lens was loaded from by name, else the current folder (never into the
    installed package: retraining a bundled model in a source checkout names ``--out
    mi_neurallens/data/lenses/models``)."""
    from .. import resources
    lib = resources.lens_origin(name) if spec == name else None
    if lib is not None and lib.origin != resources.BUNDLED:
        return str(lib.path / "models")
    return "."


def _mode(args) -> tuple:
    """(keep, finish_only) of the command line in today's spelling; ``--keep refine`` and ``--keep refine-stop``
    say, in one line, that they are now ``--finish-only maps`` and ``--finish-only stop-heads``."""
    from ..training.keep import run_mode
    keep, finish_only = getattr(args, "keep", None), getattr(args, "finish_only", None)
    if keep in OLD_KEEP and OLD_KEEP[keep][1] is not None:
        print(f"note: --keep {keep} is now --finish-only {OLD_KEEP[keep][1]}; the old spelling will go",
              file=sys.stderr)
    return run_mode(keep, finish_only)


def _mode_flag(keep, finish_only) -> str:
    """The command-line words of a run's mode: ``--keep regressor`` or ``--finish-only maps``."""
    return f"--finish-only {finish_only}" if finish_only is not None else f"--keep {keep}"


def run(args):
    require_torch()
    from ..optics.prescription import Lens
    from ..training.config import default_config_path, load_config
    args.keep, args.finish_only = _mode(args)
    lenses = [Lens.load(name) for name in args.lens]
    cfgs, outs, cfg_paths = [], [], []
    for spec, lens in zip(args.lens, lenses):
        cfg_path = args.config or default_config_path(lens.name)
        cfg = load_config(cfg_path, lens=lens.name, overrides=_overrides(args.sets))
        cfg_paths.append(cfg_path)
        if args.no_verify:
            cfg.verify_flare = False
        out_dir = args.out or default_out_dir(spec, lens.name)
        outs.append(os.path.join(out_dir, f"{lens.name}.model.safetensors"))
        cfgs.append(cfg)
        print(f"training {lens.name} (fingerprint {lens.fingerprint()}), config {cfg_path or 'defaults'} "
              f"[{cfg.digest()}] -> {outs[-1]}", file=sys.stderr)
        print(f"  focus: {_focus_text(lens, cfg.close_focus_mm)}", file=sys.stderr)
    if args.ray:
        if args.keep or args.finish_only:
            from ..errors import NeuralLensError
            raise NeuralLensError(f"{_mode_flag(args.keep, args.finish_only)} trains on this machine only; drop --ray")
        from ..training.distributed import train_on_ray
        out_dir = args.out or os.path.dirname(outs[0])
        got = train_on_ray(lenses, cfgs, out_dir, address=None if args.ray == "local" else args.ray,
                           jobs=args.jobs, paths=args.paths, log=lambda m: print(m, file=sys.stderr, flush=True))
        for name, path in got["models"].items():
            _report(path)
        return 0
    for lens, cfg, out, cfg_path in zip(lenses, cfgs, outs, cfg_paths):
        _train_one(args, lens, cfg, out, provenance(getattr(args, "argv", sys.argv[1:]), cfg_path, cfg))
    return 0


def _report(path):
    from ..neural.model import load_model
    from ..training.evaluate import markdown_table
    model = load_model(path)
    print(markdown_table(model, [(k, m.metrics) for k, m in model.maps.items() if m.metrics]))
    print(f"wrote {path}")


def _keep_base(args, lens, out) -> str:
    """The model file ``--keep`` or ``--finish-only`` takes its networks from: ``--base``; on a rerun of the same mode
    and ``--paths`` into the same output (resuming an interrupted run), the base that run took (recorded in
    ``<out>.work/keep_base.json``; a record in the old spellings counts as its mode); else the bundled model of the
    lens.  An existing output file that is not the bundled model is never taken silently — it may be an earlier
    run's — so then ``--base`` must say which."""
    from ..errors import NeuralLensError
    from ..fileio import atomic_write_text
    from ..neural.model import bundled_model_path
    from ..training.keep import run_mode
    rec_path = os.path.join(out + ".work", "keep_base.json")
    mode = run_mode(getattr(args, "keep", None), getattr(args, "finish_only", None))
    flag = _mode_flag(*mode)
    base = args.base
    if base is None and os.path.exists(rec_path):
        with open(rec_path) as f:
            rec = json.load(f)
        try:
            same = run_mode(rec.get("keep"), rec.get("finish_only")) == mode and rec.get("paths") == args.paths
        except NeuralLensError:         # a record this version cannot read: not the same run
            same = False
        if same and os.path.exists(rec.get("base", "")):
            base = rec["base"]
            print(f"resuming {out}: {flag} takes its networks from {base}, as the run before", file=sys.stderr)
    if base is None:
        bundled = bundled_model_path(lens.name)
        if os.path.exists(out) and not (os.path.exists(bundled) and os.path.samefile(out, bundled)):
            import datetime
            when = datetime.datetime.fromtimestamp(os.path.getmtime(out)).strftime("%Y-%m-%d %H:%M")
            raise NeuralLensError(
                f"{flag}: {out} already exists (written {when}) and is not the bundled model; say "
                f"which model the kept networks come from: --base {out} to build on it, --base {bundled} for "
                f"the bundled one, or a new --out")
        base = bundled
    os.makedirs(out + ".work", exist_ok=True)
    atomic_write_text(rec_path, json.dumps({"keep": mode[0], "finish_only": mode[1], "paths": args.paths,
                                            "base": os.path.abspath(base)}))
    return base


def provenance(argv, cfg_path: str | None, cfg) -> dict:
    """What a model file records of the run that trained it (``extra["runs"]``, printed by ``evaluate``): the
    command line, the recipe (its file name and text, or the defaults) and the configuration's digest, the
    package's version, the date (UTC) and the machine."""
    import datetime
    import platform
    import shlex
    from .. import __version__
    recipe = None
    if cfg_path:
        with open(cfg_path, encoding="utf-8") as f:
            recipe = {"file": os.path.basename(cfg_path), "text": f.read()}
    return {"command": "mi-neurallens " + " ".join(shlex.quote(str(a)) for a in argv),
            "recipe": recipe, "config_digest": cfg.digest(), "mi_neurallens": __version__,
            "started": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
            "machine": f"{platform.system()} {platform.machine()}, {os.cpu_count()} CPUs, "
                       f"{platform.processor() or 'unknown processor'}, Python {platform.python_version()}"}


def _train_one(args, lens, cfg, out, prov=None):
    from ..training.whole_lens import train_lens

    def log(desc, rec):
        if not args.quiet:
            print(desc + " " + " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                        for k, v in rec.items()), file=sys.stderr, flush=True)

    base = None
    if args.keep or args.finish_only:
        base = _keep_base(args, lens, out)
        what = {"networks": "classifiers and regressors (training stop heads only)",
                "stop-heads": "classifiers and regressors, and their stop heads as the start of the finish",
                "maps": "classifiers and regressors as the start of their Levenberg-Marquardt finish"}.get(
            args.finish_only or args.keep, f"{args.keep}s")
        print(f"keeping the {what} of {base}", file=sys.stderr)
    elif args.base:
        from ..errors import NeuralLensError
        raise NeuralLensError("--base names where --keep or --finish-only take their networks from; give one of "
                              "them too")
    train_lens(lens, cfg, out, paths=args.paths, progress=not args.no_progress, log=log,
               keep=args.keep, finish_only=args.finish_only, base_path=base, provenance=prov)
    _report(out)
