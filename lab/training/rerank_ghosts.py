"""Rewrite the ghost ranking a model file stores with the render-time one.

    python training/rerank_ghosts.py MODEL.safetensors [MODEL ...]

A flare render with learned maps selects its ghosts (``mode = auto``, no ``ghosts`` list) from the
ranking stored in the model file, so that it need not trace every ghost first; the exact flare ranks
them with :func:`~mi_neurallens.flare.energy.ghost_energy_ranking`.  Models trained before the two
were one stored another measure (uniform over the training domain), and a neural flare then picked
other ghosts than the exact one.  This replaces ``ghost_ranking`` and ``ghosts_selected`` with the
render-time ranking of the model's lens (its own sensor distance, full-frame film); the maps, and
which ghosts have one (``ghosts_trained``), are unchanged.  The file is rewritten atomically.
"""
from __future__ import annotations

import argparse
import sys

from mi_neurallens.flare.energy import ghost_energy_ranking, select_ghosts
from mi_neurallens.neural.model import load_model
from mi_neurallens.optics.prescription import Lens


def rerank(path: str) -> list[int]:
    """Rewrite ``path``'s stored ranking; returns the ghosts the default selection now picks."""
    model = load_model(path)
    lens = Lens.load(model.lens_name)
    if lens.fingerprint() != model.fingerprint:
        raise SystemExit(f"{path}: the lens file '{model.lens_name}' has changed since this model was trained")
    cfg = model.extra.get("training_config") or {}
    ranking = ghost_energy_ranking(lens, fresnel=bool(cfg.get("fresnel", True)))
    selected = select_ghosts(ranking, float(cfg.get("ghost_energy_fraction", 0.99)), int(cfg.get("max_ghosts", 32)))
    model.extra["ghost_ranking"] = ranking
    model.extra["ghosts_selected"] = selected
    model.save(path)
    return selected


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("models", nargs="+")
    for path in ap.parse_args(argv).models:
        sel = rerank(path)
        print(f"{path}: {len(sel)} ghosts selected by default: {sel}")


if __name__ == "__main__":
    sys.exit(main())
