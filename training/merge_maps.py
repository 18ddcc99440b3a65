"""Copy trained maps from one model file into another of the same lens (e.g. a map retrained with a
longer budget into the bundled model).

    python training/merge_maps.py SRC.model.safetensors DST.model.safetensors [--keys backward.0,forward.4608]

Without ``--keys`` every map of SRC replaces (or joins) DST's.  Both files must belong to the same lens
(fingerprint) and planes; DST keeps its ghost ranking, and its ``ghosts_trained`` list is updated to the
ghost maps it now holds, in ranking order.  DST is rewritten atomically.
"""
from __future__ import annotations

import argparse
import sys

from mi_neurallens.errors import ModelError
from mi_neurallens.neural.model import load_model


def merge(src_path: str, dst_path: str, keys=None) -> list[str]:
    src, dst = load_model(src_path), load_model(dst_path)
    if src.fingerprint != dst.fingerprint:
        raise ModelError(f"{src_path} is for lens {src.lens_name} ({src.fingerprint}), "
                         f"{dst_path} for {dst.lens_name} ({dst.fingerprint})")
    if abs(src.z_front - dst.z_front) > 1e-9 or abs(src.z_rear - dst.z_rear) > 1e-9:
        raise ModelError("the two models use different planes (different close_focus_mm?)")
    keys = list(src.maps) if not keys else keys
    for k in keys:
        if k not in src.maps:
            raise ModelError(f"{src_path} has no map {k!r}; it has {sorted(src.maps)}")
        dst.maps[k] = src.maps[k]
    order = [int(d["path_id"]) for d in dst.extra.get("ghost_ranking", [])]
    have = set(dst.ghost_ids)
    dst.extra["ghosts_trained"] = [p for p in order if p in have] + sorted(have - set(order))
    dst.save(dst_path)
    return keys


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("src")
    ap.add_argument("dst")
    ap.add_argument("--keys", default="", help="comma list of map keys (default: all of SRC's)")
    a = ap.parse_args(argv)
    keys = [k.strip() for k in a.keys.split(",") if k.strip()]
    done = merge(a.src, a.dst, keys)
    print(f"merged {', '.join(done)} into {a.dst}")


if __name__ == "__main__":
    sys.exit(main())
