"""Network size per error budget: the architecture ladder (``NetConfig.sizes``, ``maps.train_sized``)
and the flare goals stated at a film resolution (``TrainConfig.flare_resolution``)."""
from __future__ import annotations

import math

import pytest

from mi_neurallens.errors import NeuralLensError
from mi_neurallens.training.config import flare_goals, load_config, parse_size
from mi_neurallens.training.maps import train_sized


def _fake_train(meets, calls):
    """A stand-in for train_regressors: the map whose key is in meets[(hidden, width)] meets its goals
    there; records which maps trained at which size."""
    def train(problems, nc, *, ckpt, desc, **kw):
        calls.append(((nc.hidden, nc.width), [p["key"] for p in problems], ckpt, desc))
        out = []
        for p in problems:
            ok = p["key"] in meets.get((nc.hidden, nc.width), ())
            out.append({"layers": f"{p['key']}@{nc.hidden}x{nc.width}",
                        "state": {"stop_reason": "goals" if ok else "max_minutes", "seconds": 1.0, "step": 10,
                                  "best_val": 0.5 if ok else math.inf}})
        return out
    return train


def test_each_map_keeps_the_smallest_size_that_meets_its_goals():
    cfg = load_config(None, "x", {"forward_regressor": {"sizes": ["2x8", "3x16", "5x32"]}})
    nc = cfg.net("regressor", "forward")
    problems = [{"key": k} for k in ("forward.12", "forward.96", "forward.320")]
    calls = []
    meets = {(2, 8): {"forward.96"}, (3, 16): {"forward.12"}}
    out = train_sized(_fake_train(meets, calls), problems, nc, lambda name, keys: f"{name}:{','.join(keys)}",
                      "regressor")
    # every map starts small; only the ones that missed move up, and the last size keeps what it got
    assert [c[0] for c in calls] == [(2, 8), (3, 16), (5, 32)]
    assert calls[0][1] == ["forward.12", "forward.96", "forward.320"]
    assert calls[1][1] == ["forward.12", "forward.320"]
    assert calls[2][1] == ["forward.320"]
    # one checkpoint per size and set of maps, so a resume finds each stack
    assert len({c[2] for c in calls}) == 3 and calls[0][2].startswith("regressor-2x8:")
    assert [r["layers"] for r in out] == ["forward.12@3x16", "forward.96@2x8", "forward.320@5x32"]
    assert [(r["config"]["hidden"], r["config"]["width"]) for r in out] == [(3, 16), (2, 8), (5, 32)]
    assert [t["size"] for t in out[0]["sizes_tried"]] == ["2x8", "3x16"]
    assert [t["stop"] for t in out[2]["sizes_tried"]] == ["max_minutes"] * 3
    assert out[2]["sizes_tried"][0]["best_val"] is None and out[1]["sizes_tried"][0]["best_val"] == 0.5


def test_without_sizes_one_training_at_hidden_times_width():
    nc = load_config(None, "x").net("classifier", "forward")
    calls = []
    out = train_sized(_fake_train({}, calls), [{"key": "forward.12"}], nc, lambda name, keys: name, "classifier")
    assert calls == [((nc.hidden, nc.width), ["forward.12"], "classifier", "forward.12 classifier")]
    assert out[0]["config"]["hidden"] == nc.hidden and len(out[0]["sizes_tried"]) == 1


def test_flare_goals_scale_with_the_pixel():
    cfg = load_config(None, "x")
    fwd, bwd = cfg.net("regressor", "forward"), cfg.net("regressor", "backward")
    assert fwd.goal_position_um == (3.0, 30.0) and fwd.goal_direction_arcsec == (30.0, 200.0)
    assert bwd.goal_position_um == (2.0, 20.0)          # camera rays: not flare goals
    half = load_config(None, "x", {"flare_resolution": 1024}).net("regressor", "forward")
    assert half.goal_position_um == (6.0, 60.0) and half.goal_direction_arcsec == (60.0, 400.0)
    assert flare_goals(4096)["goal_position_um"] == (1.5, 15.0)
    # a recipe's explicit goals win over the resolution's
    own = load_config(None, "x", {"flare_resolution": 1024,
                                  "forward_regressor": {"goal_position_um": [4.0, 40.0]}}).net("regressor", "forward")
    assert tuple(own.goal_position_um) == (4.0, 40.0) and own.goal_direction_arcsec == (60.0, 400.0)
    with pytest.raises(NeuralLensError, match="flare_resolution"):
        flare_goals(0)


def test_a_camera_classifier_trains_to_its_patience_and_a_ghosts_stops_at_its_goals():
    """The camera map's classifier runs past its goals by default (fewer rays misclassified for seconds more); the
    forward maps' classifiers (up to 32 ghosts) stop at theirs, also where a recipe runs the camera's on."""
    cfg = load_config(None, "x")
    assert not cfg.net("classifier", "backward").stop_at_goals and cfg.net("classifier", "forward").stop_at_goals
    assert cfg.net("regressor", "backward").stop_at_goals and cfg.net("stop", "backward").stop_at_goals
    recipe = load_config(None, "x", {"classifier": {"stop_at_goals": False, "max_minutes": 3.0}})
    assert recipe.net("classifier", "forward").stop_at_goals
    assert not load_config(None, "x", {"forward_classifier": {"stop_at_goals": False}}).net(
        "classifier", "forward").stop_at_goals


def test_sizes_are_checked_when_read():
    assert parse_size("3x16") == (3, 16) and parse_size("5X32") == (5, 32)
    for bad in ("3", "3x", "0x16", "ax16"):
        with pytest.raises(NeuralLensError, match="hidden layers x width"):
            parse_size(bad)
    with pytest.raises(NeuralLensError, match="size"):
        load_config(None, "x", {"regressor": {"sizes": ["3x16", "wide"]}})
