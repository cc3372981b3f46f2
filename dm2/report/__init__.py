"""Run-folder report: config, report.json, tracks.csv, PLY/STL meshes, PNG plots, index.html.

:func:`write_report` writes into a temporary folder beside the target and renames it into place
at the end, so a reader never sees a half-written report; an unwritable target fails before any
work is done. The folder's manifest (:mod:`dm2.report.outdir`) lists every file written: an
existing folder is replaced only when it holds an earlier dm2 run, and then only dm2's own
files are (a file a user put there stays, with ``force``; without it the folder is refused).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
import time
from pathlib import Path

from dm2.report.contents import Stage, write_contents
from dm2.report.html import render_index
from dm2.report.outdir import (
    OutputRefused,
    check_output_dir,
    files_below,
    install_folder,
    write_manifest,
)
from dm2.report.report_content import ReportContent
from dm2.report.report_json import REPORT_SCHEMA, build_report, report_track
from dm2.report.summary import by_severity

log = logging.getLogger(__name__)

__all__ = ["REPORT_SCHEMA", "OutputRefused", "ReportContent", "check_output_dir",
           "rerender_index", "write_report"]


def write_report(out_dir: str | Path, results, tracks, content: ReportContent | None = None, *,
                 force: bool = False, inputs=(), command: str = "",
                 include: dict | None = None, stage: Stage | None = None) -> dict:
    """Write the whole run folder; returns the report dict.

    Parameters
    ----------
    out_dir : target folder (an earlier dm2 run's files in it are replaced; see
        :func:`dm2.report.outdir.check_output_dir` for ``force`` and ``inputs``)
    results : list of dm2.defects.layer_analysis.LayerResult
    tracks : list of dm2.defects.track.Track
    content : :class:`~dm2.report.report_content.ReportContent`, the rest of what the report
        says (configuration, drops, timing, meta, sections, injected faults, expectations) and
        how its maps are drawn; None: all defaults
    force, inputs : see :func:`dm2.report.outdir.check_output_dir`
    command : the dm2 command, recorded in the folder's manifest
    include : name -> path of further files or folders (e.g. the recording) moved into the
        folder with the report, listed in its manifest
    stage : called with (stage name, steps done, steps in stage) as the report is written
    """
    content = ReportContent() if content is None else content
    out = check_output_dir(out_dir, force=force, inputs=inputs)
    out.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        umask = os.umask(0o022)
        os.umask(umask)
        tmp.chmod(0o777 & ~umask)  # mkdtemp makes it private; the report folder is not
        ranked = by_severity([report_track(t) for t in tracks])
        stub = {"layers": [{"layer": r.layer, "stamp_s": r.deviation.stamp_s} for r in results],
                "realtime": (content.sections or {}).get("realtime")}
        files = write_contents(tmp, results, tracks, ranked, config_toml=content.config_toml,
                               map_layers=content.map_layers, limit_mm=content.limit_mm,
                               outline=_outline(results, content.toolpath), report_stub=stub,
                               stage=stage)
        if stage is not None:
            stage("report.json and index.html", 0, 1)
        report = build_report(results, tracks, dropped=content.dropped,
                              timing={**(content.timing or {}),
                                      "report_write_s": time.perf_counter() - t0},
                              fault_truth=content.fault_truth, expect=content.expect, files=files,
                              meta=content.meta, sections=content.sections)
        (tmp / "report.json").write_text(json.dumps(report, indent=1), encoding="utf-8")
        (tmp / "index.html").write_text(render_index(report, root=tmp), encoding="utf-8")
        for name, path in (include or {}).items():
            shutil.move(str(path), str(tmp / name))
        write_manifest(tmp, files_below(tmp), command=command or "report")
        install_folder(tmp, out, inputs)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    log.info("report written to %s", out)
    return report



def _outline(results, toolpath):
    from dm2.report.outline import planned_outline, reference_outline

    if not results:
        return []
    if toolpath is not None:
        outline = planned_outline(toolpath, results[-1].layer)
        if outline:
            return outline
    return reference_outline(results[-1].reference)


def rerender_index(run_dir: str | Path) -> Path:
    """Write ``index.html`` of a report folder again from its report.json; the injected-fault
    comparison is kept only while the folder still holds the twin's ``truth/``."""
    run_dir = Path(run_dir)
    try:
        report = json.loads((run_dir / "report.json").read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ValueError(f"{run_dir}: no report.json (not a report folder)") from None
    if not (run_dir / "truth").is_dir():
        report.pop("fault_truth", None)
    path = run_dir / "index.html"
    path.write_text(render_index(report, root=run_dir), encoding="utf-8")
    return path
