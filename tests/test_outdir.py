"""Output folders: what a dm2 manifest lets dm2 replace, and what it never touches."""

import pytest

from dm2.report.outdir import (
    MANIFEST_NAME,
    OutputRefused,
    check_output_dir,
    clear_outputs,
    install_folder,
    prepare_output_dir,
    write_manifest,
)


def _dm2_folder(path, files):
    path.mkdir()
    for f in files:
        (path / f).parent.mkdir(parents=True, exist_ok=True)
        (path / f).write_text(f"dm2 wrote {f}")
    write_manifest(path, files, command="test")


def test_clearing_an_earlier_run_never_removes_the_input_or_a_users_file(tmp_path):
    out = tmp_path / "run"
    _dm2_folder(out, ["report.json", "run.mcap", "meshes/layer_000.ply"])
    (out / "notes.txt").write_text("mine")
    with pytest.raises(OutputRefused, match="notes.txt"):
        check_output_dir(out)
    kept = prepare_output_dir(out, force=True, inputs=[out / "run.mcap"])
    assert kept == {"notes.txt", "run.mcap"}
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt", "run.mcap"]
    assert (out / "run.mcap").read_text() == "dm2 wrote run.mcap"


def test_a_new_output_never_lands_on_the_input_or_a_users_file(tmp_path):
    out = tmp_path / "run"
    _dm2_folder(out, ["report.json", "run.mcap"])
    new = tmp_path / "new"
    _dm2_folder(new, ["report.json", "run.mcap"])
    with pytest.raises(OutputRefused, match="run.mcap is this run's input"):
        install_folder(new, out, inputs=[out / "run.mcap"])
    assert (out / "run.mcap").read_text() == "dm2 wrote run.mcap"
    (kept,) = [p for p in tmp_path.iterdir() if p.name.startswith("run.dm2-")]
    assert (kept / "report.json").exists() and (kept / MANIFEST_NAME).exists()


def test_nested_dm2_folders_are_cleared_through_their_own_manifest(tmp_path):
    out = tmp_path / "replay"
    _dm2_folder(out, ["monitor.json"])
    _dm2_folder(out / "report", ["report.json", "maps/a.png"])
    write_manifest(out, ["monitor.json", "report/"])
    (out / "report" / "mine.png").write_text("mine")
    clear_outputs(out)
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*")) == [
        "report", "report/mine.png"]
