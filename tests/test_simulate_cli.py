"""``dm2 simulate``: bad input exits 2 with nothing written; a run writes a replayable recording
and ground truth that holds the injected fault with its size and sign."""

from __future__ import annotations

import json

import numpy as np
from typer.testing import CliRunner

from dm2.cli.main import app
from dm2.core.messages import LayerMark, Profile
from dm2.io.recording import read_recording

runner = CliRunner()

PAD_BUMP = """schema = 1
name = "pad_bump"
seed = 1
[part]
generator = "pad"
[toolpath]
max_layers = 2
[[faults]]
kind = "bump"
layers = [0, 0]
center_O_mm = [60.0, 60.0]
height_mm = 0.5
width_mm = 4.0
"""


def test_bad_scenario_exits_2_and_writes_nothing(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(PAD_BUMP.replace("seed = 1", "seed = 1\nspeed = 3"))
    out = tmp_path / "run.mcap"
    res = runner.invoke(app, ["simulate", str(bad), "--out", str(out)])
    assert res.exit_code == 2
    assert "speed" in res.output and "unknown key" in res.output
    assert list(tmp_path.iterdir()) == [bad]
    res = runner.invoke(app, ["simulate", "no_such_scenario", "--out", str(out)])
    assert res.exit_code == 2 and "no_such_scenario" in res.output


def test_gui_without_display_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    sc = tmp_path / "pad.toml"
    sc.write_text(PAD_BUMP)
    res = runner.invoke(app, ["simulate", str(sc), "--out", str(tmp_path / "r.mcap"), "--gui"])
    assert res.exit_code == 2 and "display" in res.output
    assert not any(p.suffix in (".mcap", ".part") for p in tmp_path.iterdir())


def test_run_writes_recording_and_fault_truth(tmp_path):
    sc = tmp_path / "pad.toml"
    sc.write_text(PAD_BUMP)
    from dm2.report.outdir import write_manifest

    out, truth = tmp_path / "run.mcap", tmp_path / "truth"
    truth.mkdir()  # an earlier, longer run's truth (its manifest): its layers must not survive
    for k in range(5):
        (truth / f"layer_{k:03d}.ply").write_text("stale")
    write_manifest(truth, [f"layer_{k:03d}.ply" for k in range(5)], command="dm2 simulate")
    (truth / "notes.txt").write_text("mine")  # a user's file: refused, kept with --force
    args = ["simulate", str(sc), "--out", str(out), "--truth", str(truth)]
    res = runner.invoke(app, args)
    assert res.exit_code == 2 and "notes.txt" in res.output
    res = runner.invoke(app, [*args, "--force"])
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in truth.iterdir()) == [
        ".dm2-manifest.json", "deviation_000.npz", "deviation_001.npz", "faults.json",
        "layer_000.ply", "layer_001.ply", "notes.txt", "validity.json"]
    assert (truth / "notes.txt").read_text() == "mine"
    rec = read_recording(out)
    msgs = list(rec.messages())
    assert [m.layer for m in msgs if isinstance(m, LayerMark)] == [0, 1]
    assert sum(isinstance(m, Profile) for m in msgs) > 100
    assert "pad_bump" in rec.scenario_toml and rec.toolpath.n_layers == 2
    assert (truth / "layer_000.ply").stat().st_size > 0
    assert (truth / "layer_001.ply").stat().st_size > 0
    faults = json.loads((truth / "faults.json").read_text())["faults"]
    (bump,) = faults
    assert bump["kind"] == "bump" and bump["sign"] == 1
    # the 0.5 mm bump added after layer 0, measured against the fault-free run
    assert np.isclose(bump["deviation_by_layer_mm"]["0"], 0.5, atol=0.05)
