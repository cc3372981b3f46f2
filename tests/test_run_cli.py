"""``dm2 run``: the main job's command line, its outputs and its refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from dm2.cli.main import app


def test_run_writes_the_report_folder_and_links_latest(tmp_path):
    runs = tmp_path / "runs"
    res = CliRunner().invoke(app, ["run", "pad", "--runs", str(runs), "--duration", "12",
                                   "--no-record"])
    assert res.exit_code == 0, res.output
    (run_dir,) = [p for p in runs.iterdir() if p.name != "latest" and not p.name.startswith(".")]
    assert (runs / "latest").resolve() == run_dir.resolve()
    report = json.loads((run_dir / "report.json").read_text())
    assert report["meta"]["scenario"] == "pad" and report["layers"]
    assert (run_dir / "index.html").exists() and (run_dir / "config.toml").exists()
    assert (run_dir / "truth").is_dir() and not (run_dir / "run.mcap").exists()
    assert "reconstruction vs the twin's true surface" in res.output


@pytest.mark.slow
def test_default_run_finds_the_corner_overbuild(tmp_path):
    """The README's main job: the 150-degree corner dwell of the default scenario is found as
    an overbuild track at that corner (its [expect] section), from the dwell's first layer,
    and nothing else: no other track, every real-time alarm an overbuild within the dwell's
    blob (12 mm of the corner vertex, the plume's reach around the dwelled spot)."""
    runs = tmp_path / "runs"
    res = CliRunner().invoke(app, ["run", "--runs", str(runs), "--no-record"])
    assert res.exit_code == 0, res.output
    report = json.loads((runs / "latest" / "report.json").read_text())
    (expect,) = report["expectations"]
    assert expect["passed"] and expect["track_ids"], expect
    tracks = {t["id"]: t for t in report["tracks"]}
    corner = np.array([77.6, 59.3])
    for tid in expect["track_ids"]:
        assert tracks[tid]["kind"] == "overbuild"
        assert tracks[tid]["first_layer"] >= 1  # the dwell starts in layer 1
        last = tracks[tid]["history"][-1]["centroid_O_mm"][:2]
        assert np.linalg.norm(np.asarray(last) - corner) <= 8.0
    assert set(tracks) == set(expect["track_ids"]), "a track the dwell does not explain"
    alarms = report["realtime"]["alarms"]
    assert alarms, "the dwell raised no real-time alarm"
    for alarm in alarms:
        assert alarm["kind"] == "overbuild", alarm
        assert np.linalg.norm(np.asarray(alarm["centroid_xy_O_mm"]) - corner) <= 12.0, alarm


def test_bad_scenarios_exit_2_and_write_nothing(tmp_path):
    bad = tmp_path / "blind.toml"
    bad.write_text('name = "blind"\n[part]\ngenerator = "pad"\n'
                   '[cell]\nsensor_distance_mm = 400.0\n')
    out = tmp_path / "out"
    res = CliRunner().invoke(app, ["run", str(bad), "--out", str(out)])
    assert res.exit_code == 2 and "cell.sensor_distance_mm" in res.output
    assert not out.exists()
    res = CliRunner().invoke(app, ["run", "no_such_scenario", "--out", str(out)])
    assert res.exit_code == 2 and "neither a file nor a shipped scenario" in res.output
    typo = tmp_path / "typo.toml"
    typo.write_text('name = "t"\n[part]\ngenerator = "pad"\n[toolpath]\nlayer_mmm = 0.8\n')
    res = CliRunner().invoke(app, ["run", str(typo), "--out", str(out)])
    assert res.exit_code == 2 and "toolpath.layer_mmm" in res.output and "unknown key" in res.output
    assert not out.exists()


def test_unwritable_output_is_refused_before_any_work(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    res = CliRunner().invoke(app, ["run", "pad", "--out", str(blocker)])
    assert res.exit_code == 2 and "not a folder" in res.output
    assert blocker.read_text() == "x"


def test_first_run_says_the_kernels_are_being_compiled(tmp_path, monkeypatch):
    """With no compiled kernel cached beside the sources, the first run says why it is slow;
    with the cache in place it says nothing."""
    import dm2
    from dm2.cli import common

    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    fake = tmp_path / "dm2"
    (fake / "__pycache__").mkdir(parents=True)
    monkeypatch.setattr(dm2, "__file__", str(fake / "__init__.py"))
    with common.console.capture() as cap:
        common.note_cold_kernel_cache()
    assert "compiling the numeric kernels" in cap.get()
    (fake / "fusion" / "tsdf" / "__pycache__").mkdir(parents=True)
    (fake / "fusion" / "tsdf" / "__pycache__" / "kernels.fuse_profiles-163.py311.nbi"
     ).write_bytes(b"")  # where the package keeps its kernels
    with common.console.capture() as cap:
        common.note_cold_kernel_cache()
    assert cap.get() == ""


def test_a_users_folder_is_refused_and_its_files_survive(tmp_path):
    out = tmp_path / "thesis"
    out.mkdir()
    (out / "thesis.tex").write_text("\\documentclass{book}")
    for extra in ([], ["--force"]):
        res = CliRunner().invoke(app, ["run", "pad", "--out", str(out), "--no-record", *extra])
        assert res.exit_code == 2 and "thesis.tex" in res.output
    assert [p.name for p in tmp_path.iterdir()] == ["thesis"]
    assert [p.name for p in out.iterdir()] == ["thesis.tex"]
    assert (out / "thesis.tex").read_text() == "\\documentclass{book}"
