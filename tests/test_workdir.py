"""A training run's work folder: a rerun of the same run resumes from its checkpoints, another run does not."""
from __future__ import annotations

import io
import json
import os

from mi_neurallens.training.config import TrainConfig
from mi_neurallens.training.workdir import claim, run_identity


def test_checkpoints_of_another_run_are_moved_aside_and_the_same_run_resumes(tmp_path):
    work = str(tmp_path / "lens.model.safetensors.work")
    base = tmp_path / "base.model.safetensors"
    base.write_bytes(b"base networks")
    cfg = TrainConfig()
    first = run_identity(cfg, finish_only="maps", base_path=str(base))
    assert claim(work, first) is None
    ckpt = os.path.join(work, "backward.0.regressor-refine.ckpt.lm.backward.0.json")
    with open(ckpt, "w") as f:
        f.write("{}")
    with open(os.path.join(work, "keep_base.json"), "w") as f:
        f.write("{}")
    # the same run again (an interrupted one resumed): everything stays
    log = io.StringIO()
    assert claim(work, run_identity(cfg, finish_only="maps", base_path=str(base)), log=log) is None
    assert os.path.exists(ckpt) and log.getvalue() == ""
    # a wider regressor: another configuration, so the 4x23 finish's checkpoint is not this run's
    cfg.regressor.width = 25
    wider = run_identity(cfg, finish_only="maps", base_path=str(base))
    assert wider["config_digest"] != first["config_digest"]
    moved = claim(work, wider, log=log)
    assert moved == os.path.join(work, f"superseded-{first['config_digest']}")
    assert not os.path.exists(ckpt) and os.path.exists(os.path.join(moved, os.path.basename(ckpt)))
    assert os.path.exists(os.path.join(work, "keep_base.json"))        # the CLI's record of the base stays
    assert "config_digest differs" in log.getvalue() and moved in log.getvalue()
    assert json.load(open(os.path.join(work, "run.json"))) == wider
    # the same configuration on a base whose bytes changed (a merge into it since) is another run too
    base.write_bytes(b"other networks")
    log = io.StringIO()
    assert claim(work, run_identity(cfg, finish_only="maps", base_path=str(base)), log=log) is not None
    assert "base differs" in log.getvalue()
    # a run writing over its own base is identified by the base's path, not by bytes it changes itself
    own = run_identity(cfg, finish_only="maps", base_path=str(base), out_path=str(base))
    assert own["base"] == {"path": str(base)}
