"""Training on Ray (training/distributed.py) on a local Ray instance: a lens's maps run as jobs, a job
whose worker dies is run again and resumes from its own model file instead of retraining, and the
jobs' maps are merged into one model file."""
from __future__ import annotations

import math
import os

import numpy as np
import pytest

ray = pytest.importorskip("ray")
pytest.importorskip("torch")

from mi_neurallens.optics.glass import AIR, constant  # noqa: E402
from mi_neurallens.optics.prescription import Lens, Surface  # noqa: E402
from mi_neurallens.training.config import load_config  # noqa: E402
from mi_neurallens.training.distributed import KILL_ONCE_ENV, plan_jobs, train_on_ray  # noqa: E402


def _lens():
    return Lens((Surface(math.inf, 3.0, AIR, 7.0, is_stop=True),
                 Surface(50.0, 6.0, constant(1.6), 12.0),
                 Surface(-50.0, 40.0, AIR, 12.0)), name="thick")


def _cfg():
    small = dict(hidden=2, width=16, batch=1024, pool=20000, refresh_every=200, eval_every=100, max_minutes=1.0,
                 warmup_steps=20, patience=100, max_steps=200, lr=1e-2, lm_minutes=0.0)     # Adam alone
    return load_config(overrides={"regressor": small, "classifier": dict(small, target="label"),
                                  "stop": dict(small, max_steps=100),
                                  "forward_regressor": {"max_steps": 200, "lm_minutes": 0.0},
                                  "forward_classifier": {"max_steps": 200, "lm_minutes": 0.0}, "backward": ["transmit"],
                                  "forward": ["transmit"], "heldout": 5000, "threads": 1,
                                  "close_focus_mm": 500.0})


def test_jobs_are_planned_per_direction_and_chunk():
    cfg = _cfg()
    jobs, ranking, _ = plan_jobs(_lens(), cfg, None, jobs=3)
    assert jobs == ["backward-transmit", "forward-transmit"] and ranking is None


def test_ray_jobs_survive_a_dead_worker_and_merge(tmp_path, monkeypatch):
    monkeypatch.setenv(KILL_ONCE_ENV, str(tmp_path))
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False,
             runtime_env={"env_vars": {KILL_ONCE_ENV: str(tmp_path), "MI_NEURALLENS_TORCH_COMPILE": "0"}})
    try:
        got = train_on_ray([_lens()], [_cfg()], str(tmp_path / "out"), jobs=1, log=lambda m: None)
        killed = sorted(os.listdir(tmp_path))
        # a later run of some maps merges into the model already there: the others stay (its job finds its
        # worker's kill marker from the run before, so it runs once)
        again = train_on_ray([_lens()], [_cfg()], str(tmp_path / "out"), jobs=1, paths="backward-transmit",
                             work_dir=str(tmp_path / "work2"), log=lambda m: None)
    finally:
        ray.shutdown()
    # every job's worker died once after training, and Ray ran it again
    assert killed == ["out", "thick.job0.model.safetensors.killed", "thick.job1.model.safetensors.killed"]
    from mi_neurallens.neural.model import load_model
    model = load_model(got["models"]["thick"])
    assert sorted(model.maps) == ["backward.0", "forward.0"]
    for job in got["jobs"]:
        # the second attempt found its maps in its model file: it did not train them again
        trained = [m for m in model.maps.values() if m.direction == ("backward" if job["job"] == 0 else "forward")]
        assert job["seconds"] < 0.5 * trained[0].training["wall_seconds_this_run"]
    for m in model.maps.values():
        assert m.metrics["regressor"]["position_um_median"] < 1000.0 and m.stop_head is not None
    x = np.array([[1.0, 0.01, 0.02, 550.0]])
    assert np.isfinite(model.maps["backward.0"].eval_reduced_np(x)[1]).all()
    assert sorted(load_model(again["models"]["thick"]).maps) == ["backward.0", "forward.0"]
