"""A forged manifest never reaches a file outside its folder: the attack of issue 57, item 1."""

from __future__ import annotations

import json

import pytest
from test_monitor_cli import _record
from test_monitor_scene import Scene, make_calibration, raster_run
from typer.testing import CliRunner

from dm2.cli.main import app
from dm2.report.outdir import (
    MANIFEST_NAME,
    UnsafeManifest,
    check_output_dir,
    clear_outputs,
    read_manifest,
)


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    cal = make_calibration()
    msgs, _ = raster_run(Scene(), cal, [((40, 58, 0), (80, 58, 0))], step_mm=3.0, noise_mm=0.05,
                         seed=5, t0_s=1.0)
    path = tmp_path_factory.mktemp("rec") / "in.mcap"
    _record(path, msgs, cal, attach=True)
    return path


def _victims(tmp_path):
    (tmp_path / "victim_rel.txt").write_text("relative victim")
    absolute = tmp_path / "abs" / "path" / "victim.txt"
    absolute.parent.mkdir(parents=True)
    absolute.write_text("absolute victim")
    (tmp_path / "victimdir").mkdir()
    (tmp_path / "victimdir" / "a.txt").write_text("victim in a folder")
    return {tmp_path / "victim_rel.txt": "relative victim", absolute: "absolute victim",
            tmp_path / "victimdir" / "a.txt": "victim in a folder"}


def test_the_manifest_attack_through_the_cli_touches_nothing(tmp_path, recording):
    """The reproduction of the issue: three entries outside ``trap``; `dm2 monitor` exits 2
    naming the manifest and the first bad entry, and every victim, the emptied-out folder
    included, is still there, as is the manifest itself."""
    victims = _victims(tmp_path)
    trap = tmp_path / "trap"
    trap.mkdir()
    forged = json.dumps({"schema": 1, "files": ["../victim_rel.txt",
                                                str(tmp_path / "abs" / "path" / "victim.txt"),
                                                "../victimdir/a.txt"]})
    (trap / MANIFEST_NAME).write_text(forged)
    res = CliRunner().invoke(app, ["monitor", str(recording), "--out", str(trap)])
    assert res.exit_code == 2, res.output
    assert res.exception is None or isinstance(res.exception, SystemExit)
    text = " ".join(res.output.split())
    assert MANIFEST_NAME in text and "'../victim_rel.txt'" in text
    for path, content in victims.items():
        assert path.read_text() == content
    assert (trap / MANIFEST_NAME).read_text() == forged
    assert sorted(p.name for p in trap.iterdir()) == [MANIFEST_NAME]
    # --force does not change that
    res = CliRunner().invoke(app, ["monitor", str(recording), "--out", str(trap), "--force"])
    assert res.exit_code == 2, res.output
    assert all(path.read_text() == content for path, content in victims.items())


@pytest.mark.parametrize("entry, problem", [
    ("../victim_rel.txt", "normalised"), ("sub/../../victim_rel.txt", "normalised"),
    ("./a.txt", "normalised"), ("a//b.txt", "normalised"), ("", "not a file name"),
    ("/", "not a file name"), (7, "not a file name"), ("a\\..\\..\\b", "backslash")])
def test_every_kind_of_bad_entry_is_named(tmp_path, entry, problem):
    trap = tmp_path / "trap"
    trap.mkdir()
    (trap / MANIFEST_NAME).write_text(json.dumps({"schema": 1, "files": [entry]}))
    with pytest.raises(UnsafeManifest, match=problem) as err:
        check_output_dir(trap)
    assert str(trap / MANIFEST_NAME) in str(err.value) and repr(entry) in str(err.value)


def test_a_symlink_inside_the_folder_is_never_followed_out(tmp_path):
    """Entries through a symlinked folder that leads outside are refused (file or nested
    dm2 folder alike); a listed symlink to an outside file is removed as a link, its target
    kept; a symlinked folder inside the folder is fine."""
    victims = _victims(tmp_path)
    trap = tmp_path / "trap"
    trap.mkdir()
    (trap / "escape").symlink_to(tmp_path / "victimdir")
    for entry in ("escape/a.txt", "escape/"):
        (trap / MANIFEST_NAME).write_text(json.dumps({"schema": 1, "files": [entry]}))
        with pytest.raises(UnsafeManifest, match="symlink"):
            check_output_dir(trap, force=True)
        with pytest.raises(UnsafeManifest):
            clear_outputs(trap)
    (trap / "escape").unlink()
    (trap / "link.txt").symlink_to(tmp_path / "victim_rel.txt")
    (trap / "inner").mkdir()
    (trap / "inner" / "x.txt").write_text("dm2's")
    (trap / "alias").symlink_to("inner")
    (trap / MANIFEST_NAME).write_text(json.dumps({"schema": 1,
                                                  "files": ["link.txt", "alias/x.txt"]}))
    assert read_manifest(trap)["files"] == ["link.txt", "alias/x.txt"]
    clear_outputs(trap)
    assert not (trap / "link.txt").is_symlink() and not (trap / "inner" / "x.txt").exists()
    assert all(path.read_text() == content for path, content in victims.items())
