"""The report commands end to end (small sizes): `evaluate` and `accuracy` write their JSON and
markdown files with the numbers the docs quote."""
from __future__ import annotations

import json

import pytest

from mi_neurallens.cli import main


def test_evaluate_command_writes_reports(tmp_path, capsys):
    jp, mp = tmp_path / "e.json", tmp_path / "e.md"
    assert main(["evaluate", "canon-ef-24mm-f1.4l", "-n", "3000", "--json", str(jp), "--markdown", str(mp)]) == 0
    doc = json.loads(jp.read_text())
    r = doc["maps"]["backward.0"]["regressor"]
    assert r["n"] == 3000 and 0 < r["position_um_median"] < 100
    assert 0 <= doc["maps"]["backward.0"]["classifier"]["misclassification"] < 0.05
    assert "backward.0" in mp.read_text()
    assert "pos" in capsys.readouterr().out


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
