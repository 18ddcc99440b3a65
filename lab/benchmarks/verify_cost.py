"""What the flare verification that ends ``mi-neurallens train`` costs, and what ``auto`` makes of its records.

    python benchmarks/verify_cost.py [--lens canon-rf-24mm-f1.4l-vcm] [--samples 24] [--max-samples 26]
                                     [--json OUT]

A copy of the bundled model with its verified flare records removed (a model as training leaves it) goes
through :func:`mi_neurallens.flare.verify.record_flare_errors` with the training defaults (every ghost at band 0
with 2^samples, the ghosts above 0.01 at band 1, refined up to 2^max-samples at that last band), timed.  Then,
per ghost, the band mode ``auto`` would render it with from those records against the band it gets from the
bundled model's records (``mi-neurallens evaluate --flare``'s converged protocol, both bands refined to 2^26):
how many ghosts each learns, and where they differ.  Run it on an idle machine: the seconds are the number.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def auto_band(metrics, gate=0.01):
    """The band ``auto`` renders the ghost with at ``boundary_band = 0`` from these records, or None: traced."""
    from mi_neurallens.flare.verify import flare_records, passing_band
    return passing_band(flare_records(metrics), 0.0, gate)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lens", default="canon-rf-24mm-f1.4l-vcm")
    ap.add_argument("--samples", type=int, default=24)
    ap.add_argument("--max-samples", type=int, default=26)
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    from mi_neurallens.flare.verify import record_flare_errors
    from mi_neurallens.neural.model import bundled_model_path, load_model
    src = bundled_model_path(a.lens)
    bundled = load_model(src)
    stripped = load_model(src)
    for tm in stripped.maps.values():
        tm.metrics.pop("flare", None)
        tm.metrics.pop("flare_bands", None)
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, os.path.basename(src))
        stripped.save(path)
        t0 = time.perf_counter()
        record_flare_errors(path, a.lens, samples_log2=a.samples, max_log2=a.max_samples,
                            log=lambda s: print(f"[{time.perf_counter() - t0:7.1f}s] {s}", flush=True))
        seconds = time.perf_counter() - t0
        fresh = load_model(path)
    rows = {pid: {"train_defaults": auto_band(fresh.map(pid, "forward").metrics),
                  "converged": auto_band(bundled.map(pid, "forward").metrics)} for pid in bundled.ghost_ids}

    def count(key, band=None):
        return sum(1 for r in rows.values() if r[key] is not None and (band is None or r[key] == band))

    out = {"lens": a.lens, "command": "python benchmarks/verify_cost.py " + " ".join(argv or sys.argv[1:]),
           "samples_log2": a.samples, "max_samples_log2": a.max_samples, "seconds": seconds,
           "ghosts": len(rows),
           "learned": {"train_defaults": count("train_defaults"), "converged": count("converged")},
           "learned_edges": {"train_defaults": count("train_defaults", 0.0), "converged": count("converged", 0.0)},
           "differ": {str(k): v for k, v in rows.items() if v["train_defaults"] != v["converged"]}}
    print(json.dumps(out, indent=1))
    if a.json:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
