"""``dm2 sweep``: Monte Carlo over seeds and fault sizes on Dask, detection probability
against size."""

from __future__ import annotations

import json
import time
from datetime import datetime
from pathlib import Path

import typer
from rich.table import Table

from dm2.cli.common import app, bad_input_exits, console, fail, fmt_cell, require_extra
from dm2.report.outdir import claim_outputs, prepare_output_dir


def _floats(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ValueError(f"--sizes '{text}': expected comma-separated numbers") from None


@app.command()
def sweep(
    scenario: str = typer.Argument(..., help="Base scenario (name, file) with the fault to vary."),
    param: str = typer.Option("height_mm", "--param", help="Fault field that sets the size."),
    sizes: str = typer.Option("0.2,0.4,0.6,0.8,1.0", "--sizes", help="Comma-separated sizes."),
    seeds: int = typer.Option(5, "--seeds", min=1, help="Seeds per size."),
    seed0: int = typer.Option(1000, "--seed0", help="First seed (seeds are seed0, seed0+1, ...)."),
    fault: int = typer.Option(0, "--fault", min=0, help="Index of the fault to vary."),
    overrides: list[str] = typer.Option([], "--set", help="SECTION.KEY=VALUE on the base."),
    workers: int = typer.Option(2, "--workers", min=1, help="Local worker processes."),
    scheduler: str = typer.Option(None, "--scheduler", help="Dask scheduler ADDRESS (a real "
                                  "cluster) instead of a local cluster."),
    out: Path = typer.Option(None, "--out", "-o",
                             help="Output folder (default runs/sweep-TIME)."),
    force: bool = typer.Option(False, "--force", help="Write into a folder holding an earlier "
                               "dm2 output and other files: replace only dm2's files."),
    controls: bool = typer.Option(True, "--controls/--no-controls", help="Also run the "
                                  "fault-free control (every fault removed) at the same "
                                  "settings over the same seeds, and print its false tracks "
                                  "and false real-time alarms beside each size."),
) -> None:
    """Monte Carlo over seeds and fault sizes on Dask: detection probability against size.

    Writes sweep.json (every case and the probability per size, with the smallest size
    detected in at least 90 % of the seeds from there up, and the fault-free control's false
    tracks and false real-time alarms over the same seeds) and sweep.png.

    Example: `dm2 sweep scenarios/suites/smoke/bump.toml --sizes 0.2,0.4,0.8 --seeds 4`
    """
    require_extra("distributed", "cluster", "dm2 sweep")
    from dm2.bench.suites import apply_overrides
    from dm2.bench.sweep import plot_sweep, run_sweep, summarize_sweep, sweep_cases
    from dm2.core.config import load_scenario, parse_scenario
    from scenarios import resolve_scenario

    with bad_input_exits():
        path = resolve_scenario(scenario)
        base = load_scenario(path).to_toml_dict()
        base = apply_overrides(base, list(overrides))
        parse_scenario(base, str(path))
        size_list = _floats(sizes)
        cases = sweep_cases(base, size_list, list(range(seed0, seed0 + seeds)), param, fault,
                            controls=controls)
        parse_scenario(cases[0]["scenario"], f"{path} (faults[{fault}].{param})")
        out_dir = (out or Path("runs") / f"sweep-{datetime.now():%Y%m%d-%H%M%S}").absolute()
        kept = prepare_output_dir(out_dir, force=force)
    from dm2.cli.bench_runner import sweep_case

    where = scheduler or f"a local cluster of {workers} worker processes"
    console.print(f"[bold]dm2 sweep[/] {len(cases)} cases ({len(size_list)} sizes x {seeds} "
                  f"seeds{f' + {seeds} fault-free controls' if controls else ''}) on {where}")
    t0 = time.perf_counter()
    results = run_sweep(cases, sweep_case, scheduler_address=scheduler, n_workers=workers,
                        progress=lambda d, n: console.print(f"  {d}/{n} cases done"))
    summary = summarize_sweep(results)
    doc = {"schema": "dm2.sweep/1", "scenario": str(path), "fault": fault, "param": param,
           "sizes": size_list, "seeds": list(range(seed0, seed0 + seeds)),
           "overrides": list(overrides), "cases": results, "summary": summary}
    (out_dir / "sweep.json").write_text(json.dumps(doc, indent=1, sort_keys=True),
                                        encoding="utf-8")
    plot_sweep(out_dir / "sweep.png", summary, param, f"{Path(path).stem}: detection vs {param}")
    claim_outputs(out_dir, kept, "dm2 sweep")
    table = Table(title=f"Detection probability against {param}")
    ctrl = summary["control"]
    cols = ["size", "n", "detected", "probability", "P global track", "mean peak mm",
            "FP tracks", "false RT alarms"]
    if ctrl:
        cols += ["control FP tracks", "control false RT"]
    for c in cols:
        table.add_column(c, justify="right")
    for r in summary["by_size"]:
        table.add_row(f"{r['size']:g}", str(r["n"]), str(r["detected"]),
                      f"{r['probability']:.2f}", f"{r['probability_global']:.2f}",
                      fmt_cell(r["mean_peak_height_mm"]),
                      str(r["false_positive_tracks"]), str(r["realtime_false_alarms"]),
                      *([str(ctrl["false_tracks"]), str(ctrl["realtime_false_alarms"])]
                        if ctrl else []))
    console.print(table)
    if ctrl:
        console.print(f"fault-free control (every fault removed, the same settings) over the "
                      f"same {ctrl['n']} seeds: {ctrl['false_tracks']} false track(s), "
                      f"{ctrl['realtime_false_alarms']} false real-time alarm(s), "
                      f"{ctrl['drift_tracks']} drift track(s)")
    smallest = summary["smallest_reliable_size"]
    console.print(f"smallest reliably detected {param} (>= "
                  f"{summary['reliable_probability']:.0%}): "
                  f"{'none' if smallest is None else f'{smallest:g}'}; "
                  f"{out_dir / 'sweep.json'} ({time.perf_counter() - t0:.0f} s)")
    if not results:
        fail("sweep produced no results")
