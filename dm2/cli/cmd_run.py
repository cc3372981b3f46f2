"""``dm2 run``: the main job — simulate a scenario on the twin, monitor it, write the report."""

from __future__ import annotations

import time
from datetime import datetime
from pathlib import Path

import numpy as np
import typer
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from dm2.cli.common import app, bad_input_exits, console, fail, note_cold_kernel_cache
from dm2.cli.outcome import EXIT_MISSED, drop_lines


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


def tracks_table(report: dict) -> Table:
    table = Table(title="Defect tracks", show_lines=False)
    for col in ("id", "kind", "layers", "final area mm²", "final height mm", "trend"):
        table.add_column(col, justify="right" if col != "kind" else "left")
    for t in report.get("tracks", []):
        last = str(t["last_layer"])
        area = t.get("area_mm2", {}).get(last, float("nan"))
        height = t.get("height_mm", {}).get(last, float("nan"))
        table.add_row(str(t["id"]), t["kind"], f"{t['first_layer']}–{t['last_layer']}",
                      f"{area:.1f}", f"{height:.2f}", str(t.get("trend", "")))
    return table


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
) -> None:
    """Simulate SCENARIO on the twin, monitor it with the 3D-DM2 pipeline and write a report.

    The run folder must be new or empty, or hold an earlier dm2 run (its manifest
    `.dm2-manifest.json`), whose files are then replaced; other files there need `--force` and
    are kept. Exits 1 when an expectation of the scenario's `[expect]` section is missed.

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
        cal = read_calibration_toml(calibration) if calibration is not None else None
        run_dir = (out or default_run_dir(runs_root, sc.name)).absolute()
        check_output_dir(run_dir, force=force, inputs=[path, calibration])
    run_dir.parent.mkdir(parents=True, exist_ok=True)
    console.print(f"[bold]dm2 run[/] scenario [cyan]{sc.name}[/] ({path})")
    note_cold_kernel_cache()

    from dm2.cli.bench_runner import run_scenario
    from twin.cell.kinematics import ReachError

    with Progress(TextColumn("[progress.description]{task.description}"), BarColumn(),
                  TextColumn("{task.completed:.0f}/{task.total:.0f} s process"),
                  TimeElapsedColumn(), console=console, transient=True) as bar:
        task = bar.add_task("simulating + monitoring", total=1.0)
        try:
            done = run_scenario(sc, run_dir, scenario_file=path, record=record,
                                progress=lambda t, total: bar.update(task, completed=t,
                                                                     total=total),
                                on_stream_end=lambda: bar.update(task,
                                                                 description="writing the report"),
                                calibration=cal, force=force)
        except (ReachError, ConfigError) as exc:
            fail(f"{path}: {exc}")
        except ValueError as exc:  # the run folder changed meanwhile (OutputRefused)
            fail(str(exc))
    report = done.report
    link_latest(run_dir)
    console.print(tracks_table(report))
    for e in report.get("expectations", []):
        mark = "[green]met[/]" if e.get("passed") else "[red]missed[/]"
        console.print(f"expectation {e.get('expect')}: {mark}")
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
    if missed:
        raise typer.Exit(EXIT_MISSED)

