"""``mi-neurallens merge SRC DST``: copy trained maps from one model file into another of the same lens.

For instance a map retrained with a longer budget, or ghost maps trained on a GPU, into the bundled model.
Without ``--keys`` every map of SRC replaces (or joins) DST's.  Both files must belong to the same lens
(fingerprint) and planes; DST keeps its ghost ranking, and its ``ghosts_trained`` list is updated to the ghost
maps it now holds, in ranking order.  A map of SRC without a stop head keeps the one of the DST map it replaces
(same path, planes and domain), so maps retrained with ``--set forward_stop.max_minutes=0`` keep their
render-time aperture.  DST is rewritten atomically.
"""
from __future__ import annotations


def add_parser(subparsers):
    p = subparsers.add_parser("merge", help="copy trained maps from one model file into another of the same lens",
                              description=__doc__.split("\n\n", 1)[1])
    p.add_argument("src", help="model file the maps come from")
    p.add_argument("dst", help="model file they go into (rewritten)")
    p.add_argument("--keys", default="", help="comma list of map keys, e.g. backward.0,forward.4608 "
                                              "(default: all of SRC's)")
    p.set_defaults(func=run)
    return p


def merge(src_path: str, dst_path: str, keys=None) -> list[str]:
    """Merge the maps ``keys`` (default: all) of the model file ``src_path`` into ``dst_path``; returns the keys
    merged."""
    from ..neural.model import load_model
    from ..training.merge import merge_models
    dst = load_model(dst_path)
    done = merge_models(load_model(src_path), dst, keys)
    dst.save(dst_path)
    return done


def run(args) -> int:
    from ..neural.model import load_model
    keys = [k.strip() for k in args.keys.split(",") if k.strip()]
    done = merge(args.src, args.dst, keys)
    print(f"merged {', '.join(done)} into {args.dst}")
    out = load_model(args.dst)
    kept = [k for k in done if "stop_head_kept_from" in out.maps[k].training]
    none = [k for k in done if out.maps[k].stop_head is None]
    if kept:
        print(f"kept the destination's stop heads of {', '.join(kept)}")
    if none:
        print(f"without a stop head (the aperture is fixed for them): {', '.join(none)}")
    return 0
