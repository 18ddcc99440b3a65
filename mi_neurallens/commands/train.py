"""``mi-neurallens train LENS``: train the neural lens transport maps of a lens.

Reads the per-lens recipe ``training/<lens>.toml`` when it exists (or ``--config``), plans the planes,
ranks the ghosts, trains every selected map (classifier + regressor, PyTorch on CPU or CUDA) with
checkpoints in ``<out>.work/`` (rerun the same command to resume after an interruption) and writes one
model file ``<out>/<lens>.model.safetensors`` (atomically, after each map) with the held-out metrics.
"""
from __future__ import annotations

import json
import os
import sys


def add_parser(subparsers):
    p = subparsers.add_parser("train", help="train the neural transport maps of a lens",
                              description=__doc__.split("\n\n", 1)[1] if __doc__ else None)
    p.add_argument("lens", help="bundled lens name or lens file")
    p.add_argument("--paths", help="comma list: transmit, ghosts, backward, forward, backward-transmit, "
                                   "forward-transmit or forward path ids (default: what the config lists)")
    p.add_argument("--config", help="TOML training config (default: training/<lens>.toml when present)")
    p.add_argument("--out", default=None, help="output folder (default: lenses/models)")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value, e.g. --set seed=3 --set regressor.max_steps=2000 (JSON values)")
    p.add_argument("--keep", choices=("regressor", "classifier", "both"),
                   help="keep this network of each selected map from --base and train the rest; 'both': train "
                        "only the stop heads (a render-time aperture for an existing model)")
    p.add_argument("--base", help="model file the --keep networks come from (default: the output model file "
                                  "when it exists, else the bundled model of the lens)")
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


def run(args):
    from ..optics.prescription import Lens
    from ..training.config import default_config_path, load_config
    from ..training.trainer import train_lens
    from ..neural.model import bundled_model_path
    lens = Lens.load(args.lens)
    cfg_path = args.config or default_config_path(lens.name)
    cfg = load_config(cfg_path, lens=lens.name, overrides=_overrides(args.sets))
    out_dir = args.out or os.path.dirname(bundled_model_path(lens.name))
    out = os.path.join(out_dir, f"{lens.name}.model.safetensors")
    print(f"training {lens.name} (fingerprint {lens.fingerprint()}), config {cfg_path or 'defaults'} "
          f"[{cfg.digest()}] -> {out}", file=sys.stderr)

    def log(desc, rec):
        if not args.quiet:
            print(desc + " " + " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                        for k, v in rec.items()), file=sys.stderr, flush=True)

    base = None
    if args.keep:
        base = args.base or (out if os.path.exists(out) else bundled_model_path(lens.name))
        what = "classifiers and regressors (training stop heads only)" if args.keep == "both" else f"{args.keep}s"
        print(f"keeping the {what} of {base}", file=sys.stderr)
    elif args.base:
        from ..errors import NeuralLensError
        raise NeuralLensError("--base names where --keep takes its networks from; give --keep too")
    model = train_lens(lens, cfg, out, paths=args.paths, progress=not args.no_progress, log=log,
                       keep=args.keep, base_path=base)
    from ..training.evaluate import markdown_table
    print(markdown_table(model, [(k, m.metrics) for k, m in model.maps.items() if m.metrics]))
    print(f"wrote {out}")
    return 0
