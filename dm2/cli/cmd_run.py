"""``dm2 run``: the main job — simulate a scenario on the twin, monitor it, write the report."""

from __future__ import annotations

import time
from datetime import datetime
from pathlib import Path

import numpy as np
import typer
from rich.progress import (
    BarColumn,
    Progress,
    SpinnerColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

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
from dm2.cli.outcome import EXIT_MISSED, drop_lines, exit_code


def default_run_dir(root: Path, name: str) -> Path:
    return root / f"{datetime.now().strftime('%Y%m%d-%H%M%S')}-{name}"


def link_latest(run_dir: Path) -> None:
    """Point ``<runs>/latest`` at ``run_dir`` (a relative symlink, replaced atomically)."""
    latest = run_dir.parent / "latest"
    tmp = run_dir.parent / f".latest.{run_dir.name}"
    try:
        if tmp.is_symlink():
            tmp.unlink()
        tmp.symlink_to(run_dir.name)
        tmp.replace(latest)
    except OSError:  # filesystems without symlinks: the printed path is enough
        pass


class NewTracks:
    """Console lines for the new defect tracks of each analysed layer (local ones counted)."""

    MAX_LINES = 12  # further new tracks are only counted (all are in the report)

    def __init__(self, print_line):
        self.print_line = print_line
        self.seen: set[int] = set()
        self.printed = 0
        self.local = 0
        self.held_back = 0

    def __call__(self, result) -> None:
        for region, tid in zip(result.regions, result.track_ids, strict=True):
            if tid in self.seen:
                continue
            self.seen.add(tid)
            if region.kind.startswith("local_"):
                self.local += 1
            elif self.printed >= self.MAX_LINES:
                self.held_back += 1
            else:
                self.printed += 1
                x, y = region.centroid_O[:2]
                self.print_line(f"layer {result.layer}: new track #{tid} {region.kind} at "
                                f"({x:.1f}, {y:.1f}) mm, {region.area_mm2:.0f} mm², "
                                f"{region.max_deviation_mm:+.2f} mm")


def print_summary(report: dict, new: NewTracks | None = None) -> None:
    """The verdict (as index.html opens with it) and one line of counts."""
    from dm2.report.summary import verdict

    v = verdict(report)
    console.print(f"[bold]{v['headline']}[/]")
    for line in v["sentences"]:
        console.print(f"  {line}")
    if v["more"]:
        console.print(f"  … and {v['more']} more defect tracks (see the report)")
    alarms = len((report.get("realtime") or {}).get("alarms", []))
    held = f", {new.held_back} further new tracks not printed" if new and new.held_back else ""
    console.print(f"{len(report.get('tracks', []))} tracks ({v['uncertain']} local), "
                  f"{alarms} real-time alarms{held}: all in the report and run.log")


def progress_bar() -> Progress:
    """Process seconds done of the total, time remaining, then the report stage by name."""
    return Progress(SpinnerColumn(), TextColumn("[progress.description]{task.description}"),
                    BarColumn(), TextColumn("{task.fields[done]}"), TimeRemainingColumn(),
                    TimeElapsedColumn(), console=console, transient=True)


@app.command()
def run(
    scenario: str = typer.Argument(None, help="Scenario name or TOML file (default: the "
                                   "seven-sided part with an injected corner overbuild)."),
    out: Path = typer.Option(None, "--out", "-o", help="Run folder (default runs/TIME-SCENARIO)."),
    runs_root: Path = typer.Option(Path("runs"), "--runs", help="Parent of default run folders."),
    record: bool = typer.Option(True, "--record/--no-record",
                                help="Also write the raw stream to run.mcap in the run folder."),
    duration_s: float = typer.Option(None, "--duration", min=0.1,
                                     help="Stop after this many process seconds."),
    calibration: Path = typer.Option(None, "--calibration", help="Calibration TOML the "
                                     "pipeline uses instead of the scenario's (e.g. one solved "
                                     "by `dm2 calibrate`)."),
    force: bool = typer.Option(False, "--force", help="Write into a folder holding an earlier "
                               "dm2 run and other files: replace only dm2's files."),
    view: bool = typer.Option(False, "--view", help="Show the part growing in the browser "
                              "(3D, coloured by signed deviation) on 127.0.0.1:--view-port."),
    view_port: int = typer.Option(8080, "--view-port", min=1, max=65535),
    scene: bool = typer.Option(True, "--scene/--no-scene", help="Also write scene.mcap, the "
                               "run in Foxglove's schemas, to the run folder."),
    foxglove: bool = typer.Option(False, "--foxglove", help="Serve the growing part, its "
                                  "tracks, alarms and frames to Foxglove over its WebSocket "
                                  "protocol on 127.0.0.1:--foxglove-port."),
    foxglove_port: int = typer.Option(8765, "--foxglove-port", min=0, max=65535),
    compensate: str = typer.Option("off", "--compensate", help="Close the loop: after each "
                                   "layer the next one's speeds corrected from the measured "
                                   "top ([control]); `advise` writes them to corrections/ "
                                   "(RAPID module + CSV per layer), `apply` also has the twin "
                                   "execute them."),
) -> None:
    """Simulate SCENARIO on the twin, monitor it with the 3D-DM2 pipeline and write a report.

    The run folder must be new or empty, or hold an earlier dm2 run (its manifest
    `.dm2-manifest.json`), whose files are then replaced; other files there need `--force` and
    are kept. Exits 1 when an expectation of the scenario's `[expect]` section is missed, or,
    as `dm2 monitor`, when the run fused no profile or lost more than
    `monitor.gates.max_lost_share` of its input.

    Example: `dm2 run` or `dm2 run pad --out runs/pad`
    """
    from dm2.core.calibration_io import read_calibration_toml
    from dm2.core.config import ConfigError, load_scenario
    from dm2.report import check_output_dir
    from scenarios import resolve_scenario

    t_start = time.perf_counter()
    with bad_input_exits():
        path = resolve_scenario(scenario)
        sc = load_scenario(path)
        if duration_s is not None:
            sc = sc.model_copy(update={"duration_s": duration_s})
        if compensate not in ("off", "advise", "apply"):
            raise ConfigError(f"--compensate: {compensate!r} is not one of off, advise, apply")
        cal = read_calibration_toml(calibration) if calibration is not None else None
        run_dir = (out or default_run_dir(runs_root, sc.name)).absolute()
        check_output_dir(run_dir, force=force, inputs=[path, calibration])
    run_dir.parent.mkdir(parents=True, exist_ok=True)
    console.print(f"[bold]dm2 run[/] scenario [cyan]{sc.name}[/] ({path})")
    note_cold_kernel_cache()

    from dm2.cli.bench_runner import run_scenario
    from twin.cell.kinematics import ReachError

    log_path = run_dir.parent / f".{run_dir.name}.run.log"
    # a failed write: the log goes (the report folder being written is removed by its writer)
    on_write_failure(run_dir, lambda: log_path.unlink(missing_ok=True))
    view_handle = None
    fox_handle = None
    with progress_bar() as bar, log_file(log_path):
        task = bar.add_task("simulating + monitoring", total=1.0, done="")
        new_tracks = NewTracks(bar.console.print)

        def on_progress(t, total):
            bar.update(task, completed=t, total=total, done=f"{t:.0f}/{total:.0f} s process")

        def on_stage(name, k, n):
            bar.update(task, description=f"writing the report: {name}", completed=k,
                       total=max(n, 1), done=f"{k}/{n}")

        def on_layer(result):
            new_tracks(result)
            if view_handle is not None:
                view_handle.on_layer(result)
            if fox_handle is not None:
                fox_handle.on_layer(result)

        def on_pipeline(pipeline):
            nonlocal view_handle, fox_handle
            if foxglove:
                from dm2.view.foxglove_live import FoxgloveLive

                fox_handle = FoxgloveLive(pipeline.fusion.calibration, pipeline,
                                          port=foxglove_port)
                bar.console.print(f"Foxglove: connect to [bold]{fox_handle.url}[/]")
            if view:
                from dm2.cli.common import start_live_view

                view_handle = start_live_view(pipeline.fusion.calibration,
                                              lambda: pipeline.last_T_B_F, view_port)

        try:
            done = run_scenario(sc, run_dir, scenario_file=path, record=record,
                                progress=on_progress,
                                on_stream_end=lambda: bar.update(
                                    task, description="comparing with the twin's truth"),
                                calibration=cal, on_layer=on_layer, report_stage=on_stage,
                                on_pipeline=on_pipeline, force=force,
                                include={"run.log": log_path}, scene=scene,
                                compensate=compensate)
        except (ReachError, ConfigError) as exc:
            log_path.unlink(missing_ok=True)
            fail(f"{path}: {exc}")
        except ValueError as exc:  # the run folder changed meanwhile (OutputRefused)
            log_path.unlink(missing_ok=True)
            fail(str(exc))
        finally:
            if fox_handle is not None:
                fox_handle.close()
    report = done.report
    link_latest(run_dir)
    print_summary(report, new_tracks)
    for e in report.get("expectations", []):
        mark = "[green]met[/]" if e.get("passed") else "[red]missed[/]"
        by = "".join(f" (process finding: {f})" for f in e.get("findings") or [])
        console.print(f"expectation {e.get('expect')}: {mark}{by}")
    if done.reconstruction:
        rms = [v["rms_mm"] for v in done.reconstruction.values()]
        console.print(f"reconstruction vs the twin's true surface: RMS {np.median(rms):.3f} mm "
                      f"(median over {len(rms)} layers, worst {max(rms):.3f} mm)")
    wall = time.perf_counter() - t_start
    console.print(f"report: [bold]{run_dir / 'index.html'}[/]  ({wall:.1f} s wall, "
                  f"{done.process_s:.1f} s of process time)")
    for line in drop_lines(report.get("dropped", {})):
        console.print(line, highlight=False)
    missed = [e for e in report.get("expectations", []) if not e.get("passed")]
    code, verdict = done.verdict  # the gate of `dm2 monitor`: fused nothing, lost too much
    if verdict:
        console.print(f"{sc.name}: {verdict}", highlight=False, markup=False)
    if fox_handle is not None:
        fox_handle.send_findings(report)
    serve_after_run(view_handle, fox_handle)
    code = exit_code(code, EXIT_MISSED if missed else 0)
    if code:
        raise typer.Exit(code)

