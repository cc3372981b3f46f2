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

from dm2.report.html import render_index
from dm2.report.meshes import write_deviation_ply, write_reference_stl
from dm2.report.outdir import (
    OutputRefused,
    check_output_dir,
    files_below,
    install_folder,
    write_manifest,
)
from dm2.report.plots import plot_deviation_map, plot_track
from dm2.report.report_json import REPORT_SCHEMA, build_report, write_tracks_csv

log = logging.getLogger(__name__)

__all__ = ["REPORT_SCHEMA", "OutputRefused", "check_output_dir", "write_report"]


def write_report(out_dir: str | Path, results, tracks, *, config_toml: str | None = None,
                 dropped: dict | None = None, timing: dict | None = None,
                 fault_truth=None, expect=None, map_layers=None, limit_mm: float = 1.0,
                 meta: dict | None = None, sections: dict | None = None,
                 force: bool = False, inputs=(), command: str = "",
                 include: dict | None = None) -> dict:
    """Write the whole run folder; returns the report dict.

    Parameters
    ----------
    out_dir : target folder (an earlier dm2 run's files in it are replaced; see
        :func:`dm2.report.outdir.check_output_dir` for ``force`` and ``inputs``)
    results : list of dm2.defects.layer_analysis.LayerResult
    tracks : list of dm2.defects.track.Track
    config_toml : the resolved configuration text (``dm2.core.toml_write.dump_toml``), written as-is
    dropped, timing : dicts copied into report.json
    fault_truth : dict/list of injected faults to compare the tracks with (or None)
    expect : dm2.core.config.ExpectConfig to check (or None)
    map_layers : layers to render as PNG deviation maps (default: up to 6 spread evenly,
        always including the last)
    limit_mm : colour range of the deviation maps and PLY colours [mm]
    meta : run description copied into report.json
    sections : further top-level report.json sections, e.g. ``realtime`` (alarms, latency)
        and ``reconstruction`` (distance to the true surface per layer)
    force, inputs : see :func:`dm2.report.outdir.check_output_dir`
    command : the dm2 command, recorded in the folder's manifest
    include : name -> path of further files or folders (e.g. the recording) moved into the
        folder with the report, listed in its manifest
    """
    out = check_output_dir(out_dir, force=force, inputs=inputs)
    out.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        umask = os.umask(0o022)
        os.umask(umask)
        tmp.chmod(0o777 & ~umask)  # mkdtemp makes it private; the report folder is not
        files = _write_contents(tmp, results, tracks, config_toml, map_layers, limit_mm)
        report = build_report(results, tracks, dropped=dropped,
                              timing={**(timing or {}),
                                      "report_write_s": time.perf_counter() - t0},
                              fault_truth=fault_truth, expect=expect, files=files, meta=meta,
                              sections=sections)
        (tmp / "report.json").write_text(json.dumps(report, indent=1), encoding="utf-8")
        (tmp / "index.html").write_text(render_index(report), encoding="utf-8")
        for name, path in (include or {}).items():
            shutil.move(str(path), str(tmp / name))
        write_manifest(tmp, files_below(tmp), command=command or "report")
        install_folder(tmp, out, inputs)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    log.info("report written to %s", out)
    return report


def _write_contents(tmp: Path, results, tracks, config_toml, map_layers, limit_mm) -> dict:
    files: dict[str, list[str]] = {"meshes": [], "deviation_maps": [], "track_plots": [],
                                   "reference": []}
    if config_toml is not None:
        (tmp / "config.toml").write_text(config_toml, encoding="utf-8")
    write_tracks_csv(tmp / "tracks.csv", tracks)
    for sub in ("meshes", "maps", "plots"):
        (tmp / sub).mkdir()
    for r in results:
        name = f"meshes/layer_{r.layer:03d}.ply"
        write_deviation_ply(tmp / name, r.deviation, limit_mm)
        files["meshes"].append(name)
    if results:
        name = f"meshes/reference_layer_{results[-1].layer:03d}.stl"
        write_reference_stl(tmp / name, results[-1].reference)
        files["reference"].append(name)
    by_layer = {r.layer: r for r in results}
    if map_layers is None:
        keys = sorted(by_layer)
        idx = sorted({round(i * (len(keys) - 1) / 5) for i in range(6)}) if keys else []
        map_layers = [keys[i] for i in idx]
    for layer in map_layers:
        r = by_layer.get(layer)
        if r is None:
            raise ValueError(f"write_report: no result for requested map layer {layer}")
        name = f"maps/deviation_layer_{layer:03d}.png"
        plot_deviation_map(tmp / name, r.deviation, r.regions, r.track_ids, limit_mm)
        files["deviation_maps"].append(name)
    for t in tracks:
        name = f"plots/track_{t.id:03d}_{t.kind}.png"
        plot_track(tmp / name, t)
        files["track_plots"].append(name)
    return files
