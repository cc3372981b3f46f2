"""dm2 bench end to end on the twin: the smoke suite (control, feed step, bump) is scored
against the fault truth; bad suite input exits 2. The full regression suite is slow."""

import json

import pytest
from typer.testing import CliRunner

from dm2.cli.main import app

runner = CliRunner()


def test_smoke_suite_detects_with_sign_onset_and_no_false_positive(tmp_path):
    res = runner.invoke(app, ["bench", "--suite", "smoke", "--out", str(tmp_path / "b")])
    assert res.exit_code == 0, res.output
    doc = json.loads((tmp_path / "b" / "bench.json").read_text())
    runs = doc["runs"]
    assert set(runs) == {"control", "feed_step", "bump"}
    # the fault-free control: no faults, no over/underbuild track at all
    assert runs["control"]["faults"] == [] and runs["control"]["false_positive_tracks"] == []
    (step,) = runs["feed_step"]["faults"]
    assert step["detected"] and step["sign_ok"] and step["sign"] == 1
    assert step["onset_layer"] == 1 and step["onset_delay_layers"] == 0  # +60 % feed: 0.5 mm
    assert step["iou"] > 0.5
    (bump,) = runs["bump"]["faults"]
    assert bump["detected"] and bump["sign_ok"] and bump["sign"] == 1
    # the blob appears as layer 1 starts: that layer's scans see it
    assert bump["onset_layer"] == 1 and bump["onset_delay_layers"] == 0
    assert abs(bump["height_error_mm"]) < 0.3
    for r in runs.values():
        assert r["expect_passed"] and r["false_positive_tracks"] == []
        assert 0.02 < r["reconstruction_rms_mm"] < 0.3  # against the true layer surfaces
    s = doc["summary"]
    assert s["f1"] == 1.0 and s["qualifying_defects"] == 2 and s["passed"]
    assert (tmp_path / "b" / "bump" / "truth" / "faults.json").exists()


def test_bad_suite_and_override_exit_2(tmp_path):
    res = runner.invoke(app, ["bench", "--suite", "nope", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "neither a known suite" in res.output
    res = runner.invoke(app, ["bench", "--suite", "smoke", "--set", "toolpath.bogus=1",
                              "--out", str(tmp_path)])
    assert res.exit_code == 2 and "toolpath.bogus" in res.output
    res = runner.invoke(app, ["sweep", "pad", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "no faults[0]" in res.output


@pytest.mark.slow
def test_regression_suite_meets_its_targets(tmp_path):
    res = runner.invoke(app, ["bench", "--suite", "regression", "--out", str(tmp_path / "r")])
    assert res.exit_code == 0, res.output
    s = json.loads((tmp_path / "r" / "bench.json").read_text())["summary"]
    assert s["f1"] >= 0.95 and s["max_onset_delay_layers"] <= 1
    assert s["false_positive_tracks"] == 0
