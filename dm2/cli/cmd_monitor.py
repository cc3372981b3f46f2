"""``dm2 monitor``: replay a recording through the pipeline; per-layer surfaces and a report."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import typer

from dm2.cli.common import (
    app,
    bad_input_exits,
    console,
    fail,
    log_file,
    note_cold_kernel_cache,
    on_write_failure,
    serve_after_run,
)
from dm2.cli.inputs import (
    CALIBRATION_OPTION,
    CONFIG_OPTION,
    MAP_OPTION,
    TOOLPATH_OPTION,
    load_inputs,
)

log = logging.getLogger(__name__)


@app.command()
def monitor(
    run: Path = typer.Argument(None, help="Recording: MCAP (from `dm2 simulate` or the "
                               "cell), a rosbag2 bag folder, or a .db3 bag."),
    out: Path = typer.Option(..., "--out", "-o", help="Folder for the per-layer surfaces."),
    calibration: Path = CALIBRATION_OPTION,
    toolpath: Path = TOOLPATH_OPTION,
    map_path: Path = MAP_OPTION,
    config: Path = CONFIG_OPTION,
    voxel_mm: float = typer.Option(None, "--voxel-mm", min=0.05, max=2.0,
                                   help="Override the TSDF voxel size [mm]."),
    live: Path = typer.Option(None, "--live", help="Cell file: monitor the live cell (EGM + "
                              "profile sources) instead of a recording; see dm2.live.config."),
    analyse: bool = typer.Option(True, "--analyse/--no-analyse", help="Also compare each layer "
                                 "with the near-net reference and write OUT/report/."),
    view: bool = typer.Option(False, "--view", help="Show the part growing in the browser "
                              "(3D, coloured by signed deviation) on 127.0.0.1:--view-port."),
    view_port: int = typer.Option(8080, "--view-port", min=1, max=65535),
    scene: bool = typer.Option(True, "--scene/--no-scene", help="Also write scene.mcap, the "
                               "run in Foxglove's schemas, to OUT."),
    foxglove: bool = typer.Option(False, "--foxglove", help="Serve the growing part to "
                                  "Foxglove over its WebSocket protocol (with --live: on the "
                                  "cell file's [live] foxglove address; else "
                                  "127.0.0.1:--foxglove-port)."),
    foxglove_port: int = typer.Option(8765, "--foxglove-port", min=0, max=65535),
    force: bool = typer.Option(False, "--force", help="Write into a folder holding an earlier "
                               "dm2 run and other files: replace only dm2's files."),
    allow_truncated: bool = typer.Option(False, "--allow-truncated", help="Exit 0 (not 3) "
                                         "when the recording is truncated or damaged."),
) -> None:
    """Monitor a recording: sync, register, fuse (TSDF), mesh per layer, deviation, tracks.

    Writes `layer_NNNN.ply` (frame O, mm, per-vertex `scalar_weight`) for every finished layer,
    `monitor.toml` (the configuration used), `monitor.json` (counts, drops, layers) and, unless
    `--no-analyse`, the report folder `report/` (report.json, tracks.csv, deviation meshes and
    maps, index.html) comparing each layer with the near-net reference. OUT must be new or
    empty, or hold an earlier dm2 run (its manifest `.dm2-manifest.json`): those files are
    replaced; other files there need `--force` and are kept. A truncated or damaged recording
    is monitored up to where it can be read, said so in `monitor.json` and `report.json`
    (`input`) and exits 3 unless `--allow-truncated`. With `--live`, the folder must not hold a
    live recording yet (`live.mcap`, or a `live.mcap.part` left by a crash: `dm2 recover` it).

    Example: `dm2 monitor run.mcap --out runs/replay`;
    a cell's rosbag2 bag: `dm2 monitor bag_folder --map cell_map.toml --out runs/cell`
    """
    note_cold_kernel_cache()
    if live is not None:
        from dm2.cli.live_monitor import run_live_monitor

        if run is not None:
            fail("give either a recording or --live CELL.toml, not both")
        run_live_monitor(live, out, force=force, view_port=view_port if view else None,
                         scene=scene, foxglove=foxglove)
        return
    if run is None:
        fail("give a recording to replay, or --live CELL.toml")
    from rich.table import Table

    from dm2.cli.outcome import (
        EXIT_CANNOT_WRITE,
        damaged_input_sentence,
        drop_lines,
        exit_code,
        run_verdict,
    )
    from dm2.core.toml_write import dump_toml
    from dm2.fusion.gates import InputGates
    from dm2.pipeline.pipeline import Pipeline
    from dm2.report.outdir import (
        add_to_manifest,
        check_output_dir,
        clear_outputs,
        discard_partial,
        files_below,
    )

    t_start = time.perf_counter()
    with bad_input_exits():
        rec, cal, tp, monitor_cfg, process, plate_mm = load_inputs(run, calibration,
                                                                     toolpath, map_path, config)
        if voxel_mm is not None:
            monitor_cfg = monitor_cfg.model_copy(update={"voxel_mm": voxel_mm})
        check_output_dir(out, force=force,
                         inputs=[run, calibration, toolpath, map_path, config])
    try:
        out.mkdir(parents=True, exist_ok=True)
        clear_outputs(out, inputs=[run])  # the earlier run's files: no stale layer survives
        before = set(files_below(out))  # a user's files (--force), kept
        add_to_manifest(out, ["monitor.toml", "monitor.log"], command="dm2 monitor")
    except OSError as exc:
        fail(f"--out {out}: cannot prepare the folder: {exc.strerror}", EXIT_CANNOT_WRITE)
    on_write_failure(out, lambda: discard_partial(out, before))  # a full disk: no unlisted debris
    config_toml = dump_toml({
        "recording": str(run),
        "monitor": monitor_cfg.model_dump(mode="json", exclude_none=True),
        "process": process.model_dump(mode="json", exclude_none=True)})
    (out / "monitor.toml").write_text(config_toml, encoding="utf-8")
    written = []

    def save(result) -> None:  # each layer's surface is on disk as soon as it is analysed
        entry = pipeline.write_layer_surface(out)
        add_to_manifest(out, [entry["file"]])
        written.append({**entry, "regions": len(result.regions)})
        console.print(f"layer {entry['layer']}: {entry['vertices']} vertices, "
                      f"{len(result.regions)} region(s) -> {out / entry['file']}")

    live_view = None
    fox = None

    def on_layer(result) -> None:
        save(result)
        if live_view is not None:
            live_view.on_layer(result)
        if fox is not None:
            fox.on_layer(result)

    gates = InputGates(monitor_cfg.gates)
    pipeline = Pipeline(cal, monitor_cfg, process, plate_size_mm=plate_mm, toolpath=tp,
                        on_layer=on_layer, gates=gates)
    if view:
        from dm2.cli.common import start_live_view

        live_view = start_live_view(cal, lambda: pipeline.last_T_B_F, view_port)
    if foxglove:
        from dm2.view.foxglove_live import FoxgloveLive

        with bad_input_exits():
            fox = FoxgloveLive(cal, pipeline, port=foxglove_port)
        console.print(f"Foxglove: connect to [bold]{fox.url}[/]")
    from dm2.report.scene_inputs import StreamTap

    tap = StreamTap() if scene else None
    mon = pipeline.fusion
    with console.status("fusing profiles"), log_file(out / "monitor.log"):
        pipeline.run(tap.wrap(rec.messages()) if tap is not None else rec.messages())
    if fox is not None:
        fox.close()
    n_msgs = pipeline.messages
    input_info = (rec.input_summary() if hasattr(rec, "input_summary")  # other readers:
                  else {"file": str(run), "complete": True})  # complete unless they say so
    dropped = {**pipeline.dropped, **{f"recording_{k}": int(v) for k, v in rec.skipped.items()}}
    summary = {"schema": 1, "recording": str(run),
               **({"map": str(map_path)} if map_path is not None else {}), "messages": n_msgs,
               "profiles_fused": mon.profiles_fused, "points_fused": mon.points_fused,
               "tsdf_blocks": mon.tsdf.n_blocks, "dropped": pipeline.dropped,
               "recording_skipped": {k: int(v) for k, v in rec.skipped.items()},
               "recording_problems": list(getattr(rec, "problems", [])),
               "clock_steps": gates.steps, "input": input_info,
               "layer_source": mon.layers.source, "layers": written}
    (out / "monitor.json").write_text(json.dumps(summary, indent=2), encoding="utf-8")
    add_to_manifest(out, ["monitor.json"])
    if hasattr(rec, "close"):  # a rosbag2 recording holds its files open while read
        rec.close()
    if analyse and pipeline.results:
        pipeline.write_outputs(out / "report", config_toml=config_toml, dropped=dropped,
                               timing=pipeline.timing(wall_s=time.perf_counter() - t_start),
                               meta={"recording": str(run), "layers": len(pipeline.results)},
                               sections=pipeline.sections(input=input_info), inputs=[run],
                               command="dm2 monitor", force=force)
        add_to_manifest(out, ["report/"])
    if tap is not None:
        from dm2.report.scene_mcap import add_scene_to_run, scene_items

        report = json.loads((out / "report" / "report.json").read_text(encoding="utf-8")) \
            if analyse and pipeline.results else None
        add_scene_to_run(out, scene_items(pipeline.results, report, cal, tap))
        if fox is not None and report is not None:
            fox.send_findings(report)
    table = Table(title=f"monitor: {run.name}")
    table.add_column("what")
    table.add_column("count", justify="right")
    table.add_row("messages", str(n_msgs))
    table.add_row("points fused", str(mon.points_fused))
    table.add_row("layers", f"{len(written)} (from {mon.layers.source})")
    table.add_row("defect tracks", str(len(pipeline.tracks)))
    console.print(table)
    from rich.markup import escape

    for problem in getattr(rec, "problems", []):
        console.print(f"[bold yellow]warning:[/] {escape(problem)}", highlight=False)
    for line in drop_lines(dropped):
        console.print(line, highlight=False)
    if analyse and pipeline.results:
        console.print(f"report: [bold]{out / 'report' / 'index.html'}[/]")
    code, verdict = run_verdict(profiles_fused=mon.profiles_fused, dropped=dropped,
                                messages_in=n_msgs, max_lost_share=monitor_cfg.gates.max_lost_share)
    damaged = damaged_input_sentence(input_info)
    if damaged:
        console.print(damaged, highlight=False, markup=False)
    if verdict:
        problems = "".join("; " + p for p in getattr(rec, "problems", []))
        console.print(f"{run.name}: {verdict}{problems}", highlight=False, markup=False)
    code = exit_code(code, 3 if damaged and not allow_truncated else 0)
    serve_after_run(live_view, fox)

    if code:
        raise typer.Exit(code)
