"""The report commands end to end (small sizes): `evaluate` and `accuracy` write their JSON and
markdown files with the numbers the docs quote."""
from __future__ import annotations

import json
import os

import pytest

from mi_neurallens.cli import main


def test_evaluate_command_writes_reports(tmp_path, capsys):
    # a model file with one map, the RF 24 mm's camera map (every bundled model holds 29-34 maps since their
    # ghost sets are complete: a kernel each)
    from mi_neurallens.neural.model import bundled_model_path, load_model
    model = load_model(bundled_model_path("canon-rf-24mm-f1.4l-vcm"))
    for key in [k for k in model.maps if k != "backward.0"]:
        del model.maps[key]
    one = tmp_path / "camera.model.safetensors"
    model.save(str(one))
    jp, mp = tmp_path / "e.json", tmp_path / "e.md"
    assert main(["evaluate", str(one), "-n", "3000", "--json", str(jp), "--markdown", str(mp)]) == 0
    doc = json.loads(jp.read_text())
    r = doc["maps"]["backward.0"]["regressor"]
    assert r["n"] == 3000 and 0 < r["position_um_median"] < 100
    assert 0 <= doc["maps"]["backward.0"]["classifier"]["misclassification"] < 0.05
    assert "backward.0" in mp.read_text()
    assert "pos" in capsys.readouterr().out



def test_evaluate_recorded_reports_the_files_own_metrics(tmp_path):
    """``--recorded`` writes the metrics stored at training (no tracing), and says so in the markdown."""
    from mi_neurallens.neural.model import bundled_model_path, load_model
    jp, mp = tmp_path / "e.json", tmp_path / "e.md"
    assert main(["evaluate", "dgauss-50mm", "--recorded", "--json", str(jp), "--markdown", str(mp)]) == 0
    doc = json.loads(jp.read_text())
    stored = load_model(bundled_model_path("dgauss-50mm")).maps["backward.0"].metrics
    assert doc["recorded_at_training"] and doc["maps"]["backward.0"]["regressor"] == stored["regressor"]
    assert "recorded in the file at training" in mp.read_text()


def test_evaluate_recorded_shows_the_verified_flare_errors(tmp_path):
    """The paper lenses' ghost maps carry their verified flare error (``evaluate --flare --write``); the
    report shows it in a column; ``--write`` without ``--flare`` is refused before any work."""
    jp, mp = tmp_path / "e.json", tmp_path / "e.md"
    assert main(["evaluate", "canon-ef-24mm-f1.4l", "--recorded", "--json", str(jp), "--markdown", str(mp)]) == 0
    f = json.loads(jp.read_text())["maps"]["forward.12"]["flare"]
    assert 0 < f["paired_mape"] < 1 and f["log2_samples"] in (24, 26) and len(f["per_light"]) == 2
    assert f["paired_mape"] == max(f["per_light"])
    assert "flare, paired MAPE" in mp.read_text()
    assert main(["evaluate", "canon-ef-24mm-f1.4l", "--recorded", "--write", "--json", str(jp)]) == 1


def test_evaluate_flare_write_records_the_verified_error(tmp_path):
    """``evaluate --flare --write`` on a model with one ghost map: the paired flare error goes into the
    report and into the model file, where the flare's ``auto`` reads it."""
    from mi_neurallens.neural.model import bundled_model_path, load_model
    m = load_model(bundled_model_path("wide-22mm"))
    m.maps = {k: v for k, v in m.maps.items() if k in ("backward.0", "forward.2560")}
    m.maps["forward.2560"].metrics.pop("flare", None)
    m.maps["forward.2560"].metrics.pop("flare_cost", None)
    f = tmp_path / "one-ghost.model.safetensors"
    m.save(f)
    jp, mp = tmp_path / "e.json", tmp_path / "e.md"
    assert main(["evaluate", str(f), "--recorded", "--flare", "--flare-samples", "14", "--flare-max-samples", "16",
                 "--write", "--json", str(jp), "--markdown", str(mp)]) == 0
    rec = load_model(f).map(2560, "forward").metrics["flare"]
    assert len(rec["per_light"]) == 2 and 0 < rec["paired_mape"] < 1
    # a light above the 0.01 gate at 2^14 samples is rendered again at 2^16, no further
    assert set(rec["per_light_log2_samples"]) <= {14, 16} and rec["log2_samples"] == max(rec["per_light_log2_samples"])
    assert all(v <= 0.01 for l2, v in zip(rec["per_light_log2_samples"], rec["per_light"]) if l2 == 14)
    assert json.loads(jp.read_text())["maps"]["forward.2560"]["flare"]["paired_mape"] == rec["paired_mape"]
    assert "flare, paired MAPE" in mp.read_text()
    # with a band, the record goes beside the learned edges' one (mode auto picks per ghost), for the ghosts named
    assert main(["evaluate", str(f), "--recorded", "--flare", "--flare-samples", "14", "--flare-max-samples", "14",
                 "--flare-boundary-band", "1", "--flare-ghosts", "2560", "--write", "--json", str(jp),
                 "--markdown", str(mp)]) == 0
    met = load_model(f).map(2560, "forward").metrics
    assert met["flare"] == rec and met["flare_bands"]["1"]["boundary_band"] == 1.0
    assert "flare, band 1" in mp.read_text()
    assert main(["evaluate", str(f), "--recorded", "--flare", "--flare-ghosts", "999"]) == 1
    # --flare-cost times the ghost against the tracer where a record lets auto learn it: kept with --write only
    before = f.read_bytes()
    assert main(["evaluate", str(f), "--recorded", "--flare-cost", "--flare-cost-samples", "14", "--json", str(jp),
                 "--markdown", str(mp)]) == 0
    assert f.read_bytes() == before
    assert main(["evaluate", str(f), "--recorded", "--flare-cost", "--flare-cost-samples", "14", "--write",
                 "--json", str(jp), "--markdown", str(mp)]) == 0
    met = load_model(f).map(2560, "forward").metrics
    passes = any(r["paired_mape"] <= 0.01 for r in (met["flare"], met["flare_bands"]["1"]))
    assert ("flare_cost" in met) == passes and met["flare"] == rec
    if passes:
        c = next(iter(met["flare_cost"].values()))
        assert len(met["flare_cost"]) == 1 and c["samples_log2"] == 14 and c["exact_us"] > 0


def test_accuracy_command_writes_reports(tmp_path):
    pytest.importorskip("mitsuba")
    assert main(["accuracy", "wide-22mm", "--paths", "2560", "--methods", "abcd,neural", "--n", "2000",
                 "--time-rays", "4096", "--flare-n", "4000", "--out", str(tmp_path)]) == 0
    doc = json.loads((tmp_path / "accuracy_wide-22mm.json").read_text())
    row = doc["paths"]["forward.2560"]["methods"]
    # the learned ghost map is far closer to the tracer than the paraxial matrix
    assert row["neural"]["position_um_median"] < 0.2 * row["abcd"]["position_um_median"]
    fl = doc["flare"]
    assert fl["all"]["neural"] < fl["all"]["abcd"]
    assert (tmp_path / "accuracy_wide-22mm.md").exists()


def test_train_command_keeps_the_bundled_regressor(tmp_path, capsys):
    """`train --keep regressor`: only the classifier of the selected ghost trains; the regressor comes
    bit for bit from the bundled model (the way the GPU-trained ghost classifiers were made)."""
    pytest.importorskip("torch")
    import numpy as np
    from mi_neurallens.neural.model import bundled_model_path, load_model
    old_288_flare = load_model(bundled_model_path("wide-22mm")).maps["forward.288"].metrics["flare"]
    assert main(["train", "wide-22mm", "--base", "x.safetensors"]) == 1          # --base needs --keep
    assert "--keep" in capsys.readouterr().err
    small = ["--set", "heldout=5000", "--set", "forward_classifier.max_steps=60",
             "--set", "forward_classifier.pool=60000", "--set", "forward_classifier.batch=2048",
             "--set", "forward_classifier.eval_every=30", "--set", "forward_classifier.lm_iterations=20",
             "--set", "verify_flare_samples=20", "--set", "verify_flare_max_samples=20",
             "--set", "verify_flare_cost_samples=16"]
    assert main(["train", "wide-22mm", "--paths", "192", "--keep", "regressor", "--out", str(tmp_path),
                 "--no-progress", "--quiet"] + small) == 0
    model = load_model(str(tmp_path / "wide-22mm.model.safetensors"))
    new = model.maps["forward.192"]
    old = load_model(bundled_model_path("wide-22mm")).maps["forward.192"]
    for (W, b), (W0, b0) in zip(new.regressor, old.regressor):
        np.testing.assert_array_equal(W, W0)
        np.testing.assert_array_equal(b, b0)
    assert new.training["kept"]["network"] == "regressor" and new.training["classifier_steps"] == 60
    assert new.metrics["regressor"]["position_um_median"] < 3.0
    # the run ended by verifying the flare of the ghost it trained (a classifier of 60 steps: its learned edges
    # miss the gate, so its record with the edges traced was measured too, and band 2's where band 1 misses it
    # as well); the maps it carried over keep theirs
    from mi_neurallens.flare.verify import flare_records
    recs = flare_records(new.metrics)
    bands = [r["boundary_band"] for r in recs]
    assert bands == ([0.0, 1.0] if recs[1]["paired_mape"] <= 0.01 else [0.0, 1.0, 2.0]), bands
    assert recs[0]["paired_mape"] > 0.01
    assert all(r["log2_samples"] == 20 and r["film"] == [240, 160] for r in recs)
    assert recs[1]["paired_mape"] < recs[0]["paired_mape"]
    # then timed against tracing it, where a record lets auto learn it (the cost auto_max_cost reads)
    passes = any(r["paired_mape"] is not None and r["paired_mape"] <= 0.01 for r in recs)
    assert ("flare_cost" in new.metrics) == passes
    if passes:
        c = next(iter(new.metrics["flare_cost"].values()))
        assert c["exact_us"] > 0 and c["samples_log2"] == 16
    assert model.maps["forward.288"].metrics["flare"] == old_288_flare
    assert model.extra["training_time"]["flare_verification_seconds"] > 0
    # the file says how it was made: the command as typed, the recipe it read (and its text), the package, the
    # machine; evaluate prints it
    (run,) = model.extra["runs"]
    assert run["command"].startswith("mi-neurallens train wide-22mm --paths 192 --keep regressor --out ")
    assert run["recipe"]["file"] == "wide-22mm.toml" and "[regressor]" in run["recipe"]["text"]
    assert run["config_digest"] == new.training["config_digest"] and run["mi_neurallens"]
    from mi_neurallens.commands.evaluate import provenance_text
    made = provenance_text(model)
    assert "run 1: `mi-neurallens train wide-22mm --paths 192" in made and "recipe wide-22mm.toml" in made
    assert "not recorded" in provenance_text(load_model(bundled_model_path("dgauss-50mm")))
    # the output file now exists: another --keep run into it must say which model it builds on (an earlier
    # run's file is never taken silently), while a rerun of the same command resumes from the same base
    assert main(["train", "wide-22mm", "--paths", "288", "--keep", "regressor", "--out", str(tmp_path),
                 "--no-progress", "--quiet"] + small) == 1
    err = capsys.readouterr().err
    assert "already exists" in err and "--base" in err
    import argparse
    from mi_neurallens.commands.train import _keep_base
    from mi_neurallens.optics.prescription import Lens
    out = str(tmp_path / "wide-22mm.model.safetensors")
    again = argparse.Namespace(keep="regressor", paths="192", base=None)
    assert _keep_base(again, Lens.load("wide-22mm"), out) == os.path.abspath(bundled_model_path("wide-22mm"))
    assert _keep_base(argparse.Namespace(keep="both", paths="288", base=out), Lens.load("wide-22mm"), out) == out
    # a base model without the selected map: a clear error naming what it has
    assert main(["train", "wide-22mm", "--paths", "999", "--keep", "regressor", "--base",
                 str(tmp_path / "wide-22mm.model.safetensors"), "--out", str(tmp_path / "b"), "--no-progress",
                 "--quiet"] + small) == 1
    assert "no map 'forward.999'" in capsys.readouterr().err


def test_train_keep_says_what_is_kept_and_finish_only_what_runs(capsys):
    """`train --keep` says what each map keeps of --base (regressor, classifier or networks; `both` the old spelling
    of networks), `--finish-only maps|stop-heads` that only the finish runs; `--keep refine` and `--keep refine-stop`
    still work, with a one-line note naming the new flag, and the two flags together are refused."""
    from mi_neurallens.cli import build_parser
    from mi_neurallens.commands.train import _mode
    from mi_neurallens.training.keep import run_mode
    parser = build_parser()

    def mode(*argv):
        return _mode(parser.parse_args(["train", "wide-22mm", *argv]))

    assert mode() == (None, None)
    assert mode("--keep", "networks") == mode("--keep", "both") == ("networks", None)
    assert mode("--keep", "regressor") == ("regressor", None)
    assert mode("--finish-only", "maps") == (None, "maps") and mode("--finish-only", "stop-heads") == (None, "stop-heads")
    assert capsys.readouterr().err == ""
    assert mode("--keep", "refine") == (None, "maps")
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "--finish-only maps" in err
    assert mode("--keep", "refine-stop") == (None, "stop-heads")
    assert "--finish-only stop-heads" in capsys.readouterr().err
    assert run_mode("refine") == (None, "maps") and run_mode("both") == ("networks", None)      # the Python API too
    assert main(["train", "wide-22mm", "--keep", "networks", "--finish-only", "maps"]) == 1
    assert "give one of them" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        parser.parse_args(["train", "--help"])
    out = capsys.readouterr().out
    assert "{regressor,classifier,networks}" in out and "--finish-only {maps,stop-heads}" in out


def test_a_ghost_that_misses_the_gate_at_every_band_is_finished_again_after_its_verification(tmp_path):
    """``verify_flare_refine_minutes``: after the verification, a ghost whose records all miss the gate gets its
    regressor's finish again past its goals (a ``finish_only = "maps"`` run of that ghost, verified as any run), the
    better map is kept, and the map is marked so that a rerun does not finish it again."""
    pytest.importorskip("torch")
    import time
    from mi_neurallens import Lens
    from mi_neurallens.neural.model import bundled_model_path, load_model
    from mi_neurallens.training.config import load_config
    from mi_neurallens.training.whole_lens import FINISH_MISSED_KEY, _finish_missed
    lens = Lens.load("wide-22mm")
    m = load_model(bundled_model_path("wide-22mm"))
    m.maps = {k: v for k, v in m.maps.items() if k in ("backward.0", "forward.2560")}
    met = m.maps["forward.2560"].metrics
    met["flare"] = {"paired_mape": 0.5, "boundary_band": 0.0}            # as if it missed at every band
    met["flare_bands"] = {"1": {"paired_mape": 0.5, "boundary_band": 1.0},
                          "2": {"paired_mape": 0.5, "boundary_band": 2.0}}
    out = str(tmp_path / "wide-22mm.model.safetensors")
    m.save(out)
    from mi_neurallens.resources import find_recipe
    cfg = load_config(find_recipe("wide-22mm"), overrides={
        "heldout": 5000, "verify_flare_samples": 14, "verify_flare_max_samples": 14, "verify_flare_cost": False,
        "verify_flare_refine_minutes": 0.02, "forward_classifier": {"lm_minutes": 0.01}})
    said = []
    got = _finish_missed(lens, cfg, out, [2560], str(tmp_path / "work"), False, None, said.append, time.perf_counter())
    mark = got.map(2560, "forward").training[FINISH_MISSED_KEY]
    assert mark["best_before"] == 0.5 and mark["best_refined"] is not None and mark["best_refined"] < 0.5
    assert mark["kept"] == "refined" and got.map(2560, "forward").training["config_digest"] == cfg.digest()
    back = load_model(out)
    assert back.map(2560, "forward").training[FINISH_MISSED_KEY]["kept"] == "refined"
    assert back.map(2560, "forward").stop_head is not None                       # its render-time aperture stays
    assert any("finished past their goals" in s for s in said)
    # a rerun finds nothing to finish again: the map is marked
    said.clear()
    _finish_missed(lens, cfg, out, [2560], str(tmp_path / "work"), False, None, said.append, time.perf_counter())
    assert not said
