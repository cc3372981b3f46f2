"""A full disk or a read-only target (issue 57, item 9): exit 4 with one line naming the path,
no half-written ``.part`` file and no file the manifest does not list, so that a rerun into
the same place works without ``--force``.

The tests run as root on the project's machines, where a read-only folder does not stop a
write, and a tiny full file system needs a mount: the full disk is therefore made at the
lowest layer that writes, the file objects of the MCAP writer (``dm2.io.recording_writer``) and
of the PLY writer (``dm2.io.ply``), whose ``write`` raises ``OSError(ENOSPC)`` once a byte
budget is spent, as a full disk does. The read-only folder is tested for real where the tests
do not run as root.
"""

from __future__ import annotations

import errno
import os

import pytest
from test_monitor_cli import _record
from test_monitor_scene import Scene, make_calibration, raster_run
from typer.testing import CliRunner

import dm2.io.ply
import dm2.io.recording_writer
from dm2.cli.main import app
from dm2.core.messages import LayerMark
from dm2.report.outdir import MANIFEST_NAME, foreign_files, read_manifest

AS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0


class _FullDisk:
    """A file whose writes fail with ENOSPC after ``budget`` bytes (what a full disk does:
    the bytes before are written, the call that does not fit raises, without a file name)."""

    def __init__(self, f, budget: int):
        self._f, self._left = f, budget

    def write(self, data):
        if len(data) > self._left:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self._left -= len(data)
        return self._f.write(data)

    def __getattr__(self, name):
        return getattr(self._f, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._f.close()


def _fill_disk(monkeypatch, module, budget: int) -> None:
    def full_open(path, mode="r", *args, **kwargs):
        f = open(path, mode, *args, **kwargs)  # noqa: SIM115 (closed by its user)
        return _FullDisk(f, budget) if "w" in mode else f

    monkeypatch.setattr(module, "open", full_open, raising=False)


def _one_line_exit_4(res, path) -> None:
    assert res.exit_code == 4, res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), res.exception
    (line,) = [ln for ln in res.output.splitlines() if "error:" in ln]
    assert str(path) in line and "No space left on device" in line, line


def test_simulate_on_a_full_disk_exits_4_and_leaves_nothing(tmp_path, monkeypatch):
    """The recording and the truth folder: exit 4 naming the recording, no ``x.mcap.part``,
    every truth file already written listed in its manifest; the rerun needs no --force."""
    out, truth = tmp_path / "x.mcap", tmp_path / "truth"
    args = ["simulate", "pad", "--out", str(out), "--truth", str(truth), "--duration-s", "3"]
    _fill_disk(monkeypatch, dm2.io.recording_writer, budget=60_000)
    res = CliRunner().invoke(app, args)
    _one_line_exit_4(res, out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["truth"]
    assert foreign_files(truth) == [] and read_manifest(truth) is not None
    monkeypatch.undo()
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    assert out.is_file() and foreign_files(truth) == []


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    cal = make_calibration()
    msgs, _ = raster_run(Scene(boxes=[((50, 50, 0), (66, 66, 6))]), cal,
                         [((40, 58, 0), (80, 58, 0)), ((80, 64, 0), (40, 64, 0))],
                         step_mm=1.5, noise_mm=0.05, seed=11, t0_s=1.0)
    path = tmp_path_factory.mktemp("rec") / "run.mcap"
    t_mid = msgs[len(msgs) // 2].stamp_s
    _record(path, msgs, cal, attach=True, marks=[LayerMark(0.0, 0), LayerMark(t_mid, 1)])
    return path


def test_monitor_on_a_full_disk_exits_4_and_the_folder_is_reused(tmp_path, monkeypatch,
                                                                 recording):
    """The second layer's surface does not fit: exit 4 naming --out, no ``layer_0001.ply.part``,
    ``monitor.log`` and the first layer listed in the manifest (nothing else there), and the
    same command then runs into the same folder without --force."""
    out = tmp_path / "out"
    args = ["monitor", str(recording), "--out", str(out), "--no-analyse"]
    writes = []
    real_open = open

    def second_layer_full(path, mode="r", *a, **k):
        f = real_open(path, mode, *a, **k)  # noqa: SIM115 (closed by its user)
        writes.append(path)
        return _FullDisk(f, 1000) if len(writes) == 2 else f

    monkeypatch.setattr(dm2.io.ply, "open", second_layer_full, raising=False)
    res = CliRunner().invoke(app, args)
    _one_line_exit_4(res, out)
    files = sorted(p.name for p in out.iterdir())
    assert files == [MANIFEST_NAME, "layer_0000.ply", "monitor.log", "monitor.toml"], files
    assert foreign_files(out) == []
    monkeypatch.undo()
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    assert (out / "layer_0001.ply").is_file() and foreign_files(out) == []


@pytest.mark.skipif(AS_ROOT, reason="root writes into a read-only folder")
def test_a_read_only_folder_exits_4_before_any_work(tmp_path, recording):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        for args in (["simulate", "pad", "--out", str(locked / "x.mcap")],
                     ["monitor", str(recording), "--out", str(locked / "out")]):
            res = CliRunner().invoke(app, args)
            assert res.exit_code == 4, res.output
            assert "not writable" in res.output and str(locked) in res.output
            assert list(locked.iterdir()) == []
    finally:
        locked.chmod(0o755)


def test_a_folder_the_system_reports_unwritable_exits_4(tmp_path, monkeypatch, recording):
    """The same check where the tests run as root: ``os.access`` answers for ``locked`` as
    it does for a read-only file system (EROFS holds for root too)."""
    locked = tmp_path / "locked"
    locked.mkdir()
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, *a, **k: False if str(p) == str(locked)
                        and mode & os.W_OK else real_access(p, mode, *a, **k))
    for args in (["simulate", "pad", "--out", str(locked / "x.mcap")],
                 ["monitor", str(recording), "--out", str(locked / "out")]):
        res = CliRunner().invoke(app, args)
        assert res.exit_code == 4, res.output
        (line,) = [ln for ln in res.output.splitlines() if "error:" in ln]
        assert "not writable" in line and str(locked) in line, line
        assert list(locked.iterdir()) == []
