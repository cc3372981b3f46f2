"""``dm2 monitor`` on recordings of an analytic scene: with and without attachments."""

from __future__ import annotations

import json

import numpy as np
import pytest
import typer
from test_monitor_scene import Scene, make_calibration, raster_run
from test_sync import input_drops
from typer.testing import CliRunner

from dm2.cli.main import app
from dm2.core.calibration_io import calibration_to_toml, write_calibration_toml
from dm2.core.messages import LayerMark
from dm2.fusion.surface import read_ply
from dm2.io.recording_writer import RecordingWriter

SCENE = Scene(boxes=[((50, 50, 0), (66, 66, 6))])


@pytest.fixture(scope="module")
def stream():
    cal = make_calibration()
    msgs, _ = raster_run(SCENE, cal, [((40, 58, 0), (80, 58, 0)), ((80, 64, 0), (40, 64, 0))],
                         step_mm=1.5, noise_mm=0.05, seed=11, t0_s=1.0)
    return cal, msgs


def _record(path, msgs, cal, attach: bool, marks=()):
    atts = {"calibration.toml": calibration_to_toml(cal).encode()} if attach else {}
    w = RecordingWriter(path, attachments=atts)
    if not attach:
        w.write_static_tf(cal)
    for m in sorted(list(msgs) + list(marks), key=lambda m: m.stamp_s):
        w.write(m)
    w.close()


def test_monitor_replays_a_recording_with_layer_marks(tmp_path, stream):
    cal, msgs = stream
    t_mid = msgs[len(msgs) // 2].stamp_s
    run = tmp_path / "run.mcap"
    _record(run, msgs, cal, attach=True, marks=[LayerMark(0.0, 0), LayerMark(t_mid, 1)])
    res = CliRunner().invoke(app, ["monitor", str(run), "--out", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    summary = json.loads((tmp_path / "out" / "monitor.json").read_text())
    assert [row["layer"] for row in summary["layers"]] == [0, 1]
    assert summary["layer_source"] == "marks" and input_drops(summary["dropped"]) == {}
    surf = read_ply(tmp_path / "out" / "layer_0001.ply")
    assert surf.n_faces > 1000 and surf.weight.min() >= 1.0
    rms = np.sqrt(np.mean(SCENE.sdf(surf.vertices_O) ** 2))
    assert rms < 0.25
    assert (tmp_path / "out" / "monitor.toml").read_text().count("voxel_mm = 0.5") == 1


def test_monitor_without_attachments_uses_tf_static_and_one_layer(tmp_path, stream):
    cal, msgs = stream
    run = tmp_path / "bare.mcap"
    _record(run, msgs, cal, attach=False)
    res = CliRunner().invoke(app, ["monitor", str(run), "--out", str(tmp_path / "o"),
                                   "--voxel-mm", "1.0"])
    assert res.exit_code == 0, res.output
    summary = json.loads((tmp_path / "o" / "monitor.json").read_text())
    assert [row["layer"] for row in summary["layers"]] == [0]
    assert summary["layer_source"] == "single"
    surf = read_ply(tmp_path / "o" / "layer_0000.ply")
    assert np.sqrt(np.mean(SCENE.sdf(surf.vertices_O) ** 2)) < 0.4


def test_monitor_replaces_only_its_own_earlier_outputs(tmp_path, stream):
    """A two-layer replay into the folder of an earlier one: dm2's files (its manifest) are
    replaced; once a user's file is there the folder is refused, and --force replaces dm2's
    files only; a folder dm2 never wrote is refused even with --force."""
    cal, msgs = stream
    t_mid = msgs[len(msgs) // 2].stamp_s
    run = tmp_path / "run.mcap"
    _record(run, msgs, cal, attach=True, marks=[LayerMark(0.0, 0), LayerMark(t_mid, 1)])
    out = tmp_path / "out"
    args = ["monitor", str(run), "--out", str(out), "--no-analyse"]
    assert CliRunner().invoke(app, args).exit_code == 0
    first = (out / "layer_0001.ply").stat().st_mtime_ns
    assert CliRunner().invoke(app, args).exit_code == 0  # an earlier dm2 run: replaced
    assert (out / "layer_0001.ply").stat().st_mtime_ns >= first
    (out / "notes.txt").write_text("mine")
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 2 and "notes.txt" in res.output and "--force" in res.output
    res = CliRunner().invoke(app, [*args, "--force"])
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in out.iterdir()) == [
        ".dm2-manifest.json", "layer_0000.ply", "layer_0001.ply", "monitor.json",
        "monitor.log", "monitor.toml", "notes.txt", "scene.mcap"]
    assert (out / "notes.txt").read_text() == "mine"
    assert read_ply(out / "layer_0001.ply").n_faces > 1000
    thesis = tmp_path / "thesis"
    thesis.mkdir()
    (thesis / "thesis.tex").write_text("\\documentclass{book}")
    (thesis / "layer_0000.ply").write_text("a user's mesh")
    for extra in ([], ["--force"]):
        res = CliRunner().invoke(app, ["monitor", str(run), "--out", str(thesis), *extra])
        assert res.exit_code == 2 and "did not write" in res.output
    assert sorted(p.name for p in thesis.iterdir()) == ["layer_0000.ply", "thesis.tex"]
    assert (thesis / "layer_0000.ply").read_text() == "a user's mesh"


def test_monitor_flags_a_truncated_recording_and_exits_3(tmp_path, stream):
    cal, msgs = stream
    t_mid = msgs[len(msgs) // 2].stamp_s
    full = tmp_path / "full.mcap"
    _record(full, msgs, cal, attach=True, marks=[LayerMark(0.0, 0), LayerMark(t_mid, 1)])
    data = full.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    res = CliRunner().invoke(app, ["monitor", str(cut), "--out", str(tmp_path / "o")])
    assert res.exit_code == 3, res.output
    assert "is truncated or damaged: it was read up to" in " ".join(res.output.split())
    summary = json.loads((tmp_path / "o" / "monitor.json").read_text())
    info = summary["input"]
    assert info["complete"] is False and info["truncated"] is True
    assert 0 < info["bytes_skipped"] < len(data) // 2
    assert msgs[0].stamp_s < info["last_stamp_s"] < msgs[-1].stamp_s
    report = json.loads((tmp_path / "o" / "report" / "report.json").read_text())
    assert report["input"] == info
    res = CliRunner().invoke(app, ["monitor", str(cut), "--out", str(tmp_path / "o2"),
                                   "--allow-truncated"])
    assert res.exit_code == 0, res.output
    res = CliRunner().invoke(app, ["monitor", str(full), "--out", str(tmp_path / "o3")])
    assert res.exit_code == 0, res.output
    whole = json.loads((tmp_path / "o3" / "monitor.json").read_text())["input"]
    assert whole["complete"] is True and whole["bytes_skipped"] == 0


def test_monitor_bad_input_exits_2_without_output(tmp_path, stream):
    cal, msgs = stream
    runner = CliRunner()
    res = runner.invoke(app, ["monitor", str(tmp_path / "missing.mcap"), "--out",
                              str(tmp_path / "x")])
    assert res.exit_code == 2 and "missing.mcap" in res.output
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap at all")
    res = runner.invoke(app, ["monitor", str(junk), "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and "junk.mcap" in res.output
    # no calibration anywhere
    nocal = tmp_path / "nocal.mcap"
    w = RecordingWriter(nocal)
    for m in msgs[:50]:
        w.write(m)
    w.close()
    res = runner.invoke(app, ["monitor", str(nocal), "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and "--calibration" in res.output
    assert not (tmp_path / "x").exists()
    # ... which --calibration then supplies
    cal_path = tmp_path / "cal.toml"
    write_calibration_toml(cal, cal_path)
    res = runner.invoke(app, ["monitor", str(nocal), "--out", str(tmp_path / "x"),
                              "--calibration", str(cal_path)])
    assert res.exit_code == 0, res.output


def test_error_messages_keep_their_brackets(tmp_path):
    """Errors are plain text: a cell file's ``[live]`` section or a unit like ``[mm]`` in a
    message is printed, not swallowed as console markup."""
    cell = tmp_path / "cell.toml"
    (tmp_path / "c.toml").write_text("")
    cell.write_text('calibration = "c.toml"\n[live]\nbogus = 1\n')
    res = CliRunner().invoke(app, ["monitor", "--live", str(cell), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2
    text = " ".join(res.output.split())
    assert "live.bogus" in text and str(cell) in text

    from dm2.cli.common import err_console, fail

    with err_console.capture() as cap, pytest.raises(typer.Exit):
        fail("cell.toml: [live] egm: step [mm] of x[1]")
    assert "cell.toml: [live] egm: step [mm] of x[1]" in cap.get()


def test_replayed_stamps_far_off_cost_only_their_message(tmp_path, stream):
    """A robot state stamped 1000 s ahead is dropped as implausible_stamp; the replay fuses
    exactly what the clean one fuses."""
    import dataclasses

    from dm2.core.messages import RobotState

    cal, msgs = stream
    clean, bad = tmp_path / "clean.mcap", tmp_path / "bad.mcap"
    _record(clean, msgs, cal, attach=True)
    states = [i for i, m in enumerate(msgs) if isinstance(m, RobotState)]
    out = list(msgs)
    out[states[40]] = dataclasses.replace(out[states[40]], stamp_s=msgs[states[40]].stamp_s + 1e3)
    _record(bad, out, cal, attach=True)
    got = {}
    for name, path in (("clean", clean), ("bad", bad)):
        res = CliRunner().invoke(app, ["monitor", str(path), "--out", str(tmp_path / name),
                                       "--no-analyse"])
        assert res.exit_code == 0, res.output
        got[name] = json.loads((tmp_path / name / "monitor.json").read_text())
    assert input_drops(got["clean"]["dropped"]) == {}
    assert input_drops(got["bad"]["dropped"]) == {"implausible_stamp": 1}
    assert got["bad"]["profiles_fused"] == got["clean"]["profiles_fused"]


def test_a_replay_that_fuses_nothing_says_so_and_exits_1(tmp_path, stream):
    from dm2.core.messages import RobotState

    cal, msgs = stream
    poses_only = tmp_path / "poses.mcap"
    _record(poses_only, [m for m in msgs if isinstance(m, RobotState)], cal, attach=True)
    res = CliRunner().invoke(app, ["monitor", str(poses_only), "--out", str(tmp_path / "o")])
    assert res.exit_code == 1, res.output
    assert "fused no profile" in " ".join(res.output.split())
