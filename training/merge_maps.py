"""Copy trained maps from one model file into another of the same lens (e.g. a map retrained with a
longer budget into the bundled model).

    python training/merge_maps.py SRC.model.safetensors DST.model.safetensors [--keys backward.0,forward.4608]

Without ``--keys`` every map of SRC replaces (or joins) DST's.  Both files must belong to the same lens
(fingerprint) and planes; DST keeps its ghost ranking, and its ``ghosts_trained`` list is updated to the
ghost maps it now holds, in ranking order.  A map of SRC without a stop head keeps the one of the DST map it
replaces (same path, planes and domain: ``mi_neurallens.training.merge.keep_stop_head``), so maps retrained
with ``--set forward_stop.max_minutes=0`` keep their render-time aperture.  DST is rewritten atomically.
"""
from __future__ import annotations

import argparse
import sys

from mi_neurallens.neural.model import load_model
from mi_neurallens.training.merge import merge_models


def merge(src_path: str, dst_path: str, keys=None) -> list[str]:
    dst = load_model(dst_path)
    done = merge_models(load_model(src_path), dst, keys)
    dst.save(dst_path)
    return done


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("src")
    ap.add_argument("dst")
    ap.add_argument("--keys", default="", help="comma list of map keys (default: all of SRC's)")
    a = ap.parse_args(argv)
    keys = [k.strip() for k in a.keys.split(",") if k.strip()]
    done = merge(a.src, a.dst, keys)
    print(f"merged {', '.join(done)} into {a.dst}")
    out = load_model(a.dst)
    kept = [k for k in done if "stop_head_kept_from" in out.maps[k].training]
    none = [k for k in done if out.maps[k].stop_head is None]
    if kept:
        print(f"kept the destination's stop heads of {', '.join(kept)}")
    if none:
        print(f"without a stop head (the aperture is fixed for them): {', '.join(none)}")


if __name__ == "__main__":
    sys.exit(main())
