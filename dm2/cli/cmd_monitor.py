"""``dm2 monitor``: replay a recording through the fusion pipeline, write per-layer surfaces."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from dm2.cli.common import app, bad_input_exits, console, fail


def _load_inputs(run: Path, calibration: Path | None, toolpath: Path | None):
    """Open the recording and resolve calibration, toolpath and configuration."""
    from dm2.calibration_io import read_calibration_toml
    from dm2.config import MonitorConfig, ProcessConfig, parse_scenario
    from dm2.recording import read_recording
    from dm2.toolpath.formats import read_csv

    rec = read_recording(run)
    cal = read_calibration_toml(calibration) if calibration is not None else rec.calibration
    if cal is None:
        raise ValueError(f"{run}: no calibration attached and no complete /tf_static; "
                         "give one with --calibration FILE.toml")
    tp = read_csv(toolpath) if toolpath is not None else rec.toolpath
    monitor_cfg, process = MonitorConfig(), ProcessConfig()
    if rec.scenario_toml is not None:
        import tomllib

        try:
            sc = parse_scenario(tomllib.loads(rec.scenario_toml), f"{run}:scenario.toml")
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"{run}: attached scenario is not valid TOML: {exc}") from None
        monitor_cfg, process = sc.monitor, sc.process
    return rec, cal, tp, monitor_cfg, process


@app.command()
def monitor(
    run: Path = typer.Argument(None, help="MCAP recording (from `dm2 simulate` or the cell)."),
    out: Path = typer.Option(..., "--out", "-o", help="Folder for the per-layer surfaces."),
    calibration: Path = typer.Option(None, "--calibration", help="Calibration TOML (default: "
                                     "the recording's attachment, else its /tf_static)."),
    toolpath: Path = typer.Option(None, "--toolpath", help="Toolpath CSV (default: the "
                                  "recording's attachment); splits layers without layer marks."),
    voxel_mm: float = typer.Option(None, "--voxel-mm", min=0.05, max=2.0,
                                   help="Override the TSDF voxel size [mm]."),
    live: Path = typer.Option(None, "--live", help="Cell file: monitor the live cell (EGM + "
                              "profile sources) instead of a recording; see dm2.live.config."),
) -> None:
    """Reconstruct the part from a recording: sync, register, fuse (TSDF), mesh per layer.

    Writes `layer_NNNN.ply` (frame O, mm, per-vertex `scalar_weight`) for every finished layer,
    `monitor.toml` (the configuration used) and `monitor.json` (counts, drops, layers).
    """
    if live is not None:
        from dm2.cli.cmd_live import run_live_monitor

        if run is not None:
            fail("give either a recording or --live CELL.toml, not both")
        run_live_monitor(live, out)
        return
    if run is None:
        fail("give a recording to replay, or --live CELL.toml")
    from rich.table import Table

    from dm2.config import dump_toml
    from dm2.pipeline import LayerSurface, Monitor

    with bad_input_exits():
        rec, cal, tp, monitor_cfg, process = _load_inputs(run, calibration, toolpath)
        if voxel_mm is not None:
            monitor_cfg = monitor_cfg.model_copy(update={"voxel_mm": voxel_mm})
        if out.exists() and not out.is_dir():
            fail(f"--out {out}: exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    (out / "monitor.toml").write_text(dump_toml({
        "recording": str(run),
        "monitor": monitor_cfg.model_dump(mode="json", exclude_none=True),
        "process": process.model_dump(mode="json", exclude_none=True)}), encoding="utf-8")
    written = []

    def save(ls: LayerSurface) -> None:
        path = out / f"layer_{ls.layer:04d}.ply"
        ls.surface.write_ply(path)
        written.append({"layer": ls.layer, "file": path.name, "stamp_s": ls.stamp_s,
                        "vertices": ls.surface.n_vertices, "faces": ls.surface.n_faces,
                        "area_mm2": round(ls.surface.area_mm2(), 3)})
        console.print(f"layer {ls.layer}: {ls.surface.n_vertices} vertices -> {path}")

    mon = Monitor(cal, monitor_cfg, process, toolpath=tp, on_layer_done=save)
    n_msgs = 0
    with console.status("fusing profiles"):
        for msg in rec.messages():
            mon.feed(msg)
            n_msgs += 1
        mon.finish()
    summary = {"schema": 1, "recording": str(run), "messages": n_msgs,
               "profiles_fused": mon.profiles_fused, "points_fused": mon.points_fused,
               "tsdf_blocks": mon.tsdf.n_blocks, "dropped": mon.dropped,
               "recording_skipped": {k: int(v) for k, v in rec.skipped.items()},
               "layer_source": mon.layers.source, "layers": written}
    (out / "monitor.json").write_text(json.dumps(summary, indent=2), encoding="utf-8")
    table = Table(title=f"monitor: {run.name}")
    table.add_column("what")
    table.add_column("count", justify="right")
    table.add_row("messages", str(n_msgs))
    table.add_row("points fused", str(mon.points_fused))
    table.add_row("layers", f"{len(written)} (from {mon.layers.source})")
    for reason, count in mon.dropped.items():
        table.add_row(f"dropped: {reason}", str(count))
    console.print(table)
    if mon.points_fused == 0:
        fail(f"{run}: no profile could be fused (dropped: {mon.dropped})", code=1)
