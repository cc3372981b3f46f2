"""``dm2 monitor`` on recordings of an analytic scene: with and without attachments."""

from __future__ import annotations

import json

import numpy as np
import pytest
import typer
from test_monitor_scene import Scene, make_calibration, raster_run
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
    assert summary["layer_source"] == "marks" and summary["dropped"] == {}
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


def test_monitor_replaces_the_outputs_of_an_earlier_run(tmp_path, stream):
    """A two-layer replay into a folder that holds an earlier five-layer run: the stale
    layer meshes and report go, the user's other files stay."""
    cal, msgs = stream
    t_mid = msgs[len(msgs) // 2].stamp_s
    run = tmp_path / "run.mcap"
    _record(run, msgs, cal, attach=True, marks=[LayerMark(0.0, 0), LayerMark(t_mid, 1)])
    out = tmp_path / "out"
    (out / "report").mkdir(parents=True)
    for k in range(5):
        (out / f"layer_{k:04d}.ply").write_text("stale")
    (out / "report" / "report.json").write_text("{}")
    (out / "report" / "old.png").write_text("stale")
    (out / "notes.txt").write_text("mine")
    res = CliRunner().invoke(app, ["monitor", str(run), "--out", str(out), "--no-analyse"])
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in out.iterdir()) == [
        "layer_0000.ply", "layer_0001.ply", "monitor.json", "monitor.log", "monitor.toml",
        "notes.txt"]
    assert read_ply(out / "layer_0001.ply").n_faces > 1000


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
