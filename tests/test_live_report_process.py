"""Interim reports written by the report child process: same report.json as in process, errors
come back as ReportProcessError naming the cause, a dead child is replaced at the next write."""

import json

import pytest

from dm2.live.report_process import ReportProcess, ReportProcessError
from dm2.report import ReportContent, write_report


def _json(folder):
    report = json.loads((folder / "report.json").read_text())
    report["timing"].pop("report_write_s")
    return report


def test_child_writes_the_report_the_parent_would(tmp_path):
    meta = {"mode": "live", "events": {"sensor_dropout": 2}}
    dropped = {"queue_full": 3, "empty_profile": 7}
    child = ReportProcess()
    try:
        content = ReportContent(meta=meta, dropped=dropped, timing={"fusion_s": 1.5},
                                config_toml="schema = 1\n")
        seconds = child.write(tmp_path / "child", [], [], content)
        assert seconds > 0
        write_report(tmp_path / "here", [], [], content)
        assert _json(tmp_path / "child") == _json(tmp_path / "here")
        assert _json(tmp_path / "child")["dropped"] == dropped
        # a second write replaces the folder
        child.write(tmp_path / "child", [], [], ReportContent(meta={"mode": "second"}))
        assert _json(tmp_path / "child")["meta"]["mode"] == "second"
    finally:
        child.close()
    assert child._child.proc is None


def test_child_errors_are_raised_and_a_dead_child_is_replaced(tmp_path):
    (tmp_path / "a_file").write_text("not a folder")
    child = ReportProcess()
    try:
        with pytest.raises(ReportProcessError, match="exists and is not a folder"):
            child.write(tmp_path / "a_file", [], [])
        first = child._child.proc
        child.write(tmp_path / "ok", [], [], ReportContent(meta={"n": 1}))  # the same child
        assert child._child.proc is first
        first.kill()
        first.wait()
        child.write(tmp_path / "ok", [], [], ReportContent(meta={"n": 2}))
        assert child._child.proc is not first and child._child.proc.poll() is None
        assert _json(tmp_path / "ok")["meta"]["n"] == 2
    finally:
        child.close()
