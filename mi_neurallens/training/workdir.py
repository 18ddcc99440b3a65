"""A training run's work folder (``<model>.work``): its checkpoints belong to one run.

A rerun into the same output resumes from the checkpoints there (Adam's stacks, each network's
Levenberg–Marquardt finish, the maps' domains), which is right only when it is the same run: the same
configuration (:meth:`~mi_neurallens.training.config.TrainConfig.digest`), the same mode (``--keep``,
``--finish-only``) and the same base model, byte for byte.  :func:`claim` records that identity in
``run.json`` and, when a new run's differs, moves the earlier run's files into ``superseded-<its digest>/``
(saying so) before anything trains: a finish into a reused folder with another width or base no longer
comes back as the earlier run's networks.  A folder from before the record is adopted as it is.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys

from ..fileio import atomic_write_json

#: the identity record; ``keep_base.json`` is the CLI's record of the base a resumed run takes (kept in place)
RECORD = "run.json"
KEPT = (RECORD, "keep_base.json")


def file_digest(path: str) -> str:
    """sha256 of a file's bytes, 16 hex digits."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:16]


def run_identity(cfg, keep: str | None = None, finish_only: str | None = None, base_path: str | None = None,
                 out_path: str | None = None) -> dict:
    """What makes two runs the same run: the configuration's digest, the mode and the base model's bytes (its path
    alone where the run writes its output over its base, whose bytes the run itself changes)."""
    base = None
    if base_path:
        base = {"path": os.path.abspath(base_path)}
        if not (out_path and os.path.exists(out_path) and os.path.samefile(base_path, out_path)):
            base["sha256"] = file_digest(base_path)
    return {"config_digest": cfg.digest(), "keep": keep, "finish_only": finish_only, "base": base}


def claim(workdir: str, identity: dict, log=sys.stderr) -> str | None:
    """Make ``workdir`` this run's: create it, and where it holds another run's files (its ``run.json`` differs
    from ``identity``), move them into ``superseded-<that run's digest>`` (replacing an older folder of that name)
    and say so on ``log``.  Returns the folder they went to, or None."""
    os.makedirs(workdir, exist_ok=True)
    rec_path = os.path.join(workdir, RECORD)
    moved_to = None
    if os.path.exists(rec_path):
        try:
            with open(rec_path) as f:
                before = json.load(f)
        except (OSError, ValueError):
            before = {}
        if before != identity:
            moved_to = os.path.join(workdir, f"superseded-{before.get('config_digest', 'unknown')}")
            shutil.rmtree(moved_to, ignore_errors=True)
            names = [n for n in os.listdir(workdir) if n not in KEPT and not n.startswith("superseded-")]
            os.makedirs(moved_to)
            for n in names:
                os.replace(os.path.join(workdir, n), os.path.join(moved_to, n))
            os.replace(rec_path, os.path.join(moved_to, RECORD))
            what = [k for k in ("config_digest", "keep", "finish_only", "base") if before.get(k) != identity.get(k)]
            print(f"{workdir}: its checkpoints are another run's (its {', '.join(what) or 'record'} differs), so "
                  f"this run starts afresh; they were moved to {moved_to}", file=log, flush=True)
    atomic_write_json(rec_path, identity)
    return moved_to
