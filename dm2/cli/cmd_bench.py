"""``dm2 bench``: a suite of scenarios scored against the twin's fault truth."""

from __future__ import annotations

import json
import time
from datetime import datetime
from pathlib import Path

import typer
from rich.markup import escape
from rich.table import Table

from dm2.cli.common import app, bad_input_exits, console, err_console, fmt_cell
from dm2.report.outdir import claim_outputs, prepare_output_dir

EXIT_FAILED = 1


def bench_table(runs: dict[str, dict]) -> Table:
    table = Table(title="Bench: strict score against the twin's truth maps")
    cols = ("scenario", "fault", "h mm", "detected", "onset L", "delay L", "IoU",
            "height err mm", "tracks T/frag/neu/D/F", "false mm²", "RT alarms F/all", "RMS mm",
            "RTF", "expect")
    for c in cols:
        table.add_column(c, justify="left" if c in ("scenario", "fault") else "right")
    for name, r in runs.items():
        if "error" in r:
            table.add_row(name, "[red]error[/]", *[""] * (len(cols) - 3), "[red]NO[/]")
            continue
        if "invalid_truth" in r:
            table.add_row(name, "[red]invalid truth[/]", *[""] * (len(cols) - 3), "[red]NO[/]")
            continue
        faults = r["faults"] or [None]
        n_false = len(r["false_tracks"])
        counts = (f"{len(r['true_tracks'])}/{len(r['fragments'])}/{len(r['neutral_tracks'])}/"
                  f"{len(r.get('drift_tracks', []))}/"
                  + (f"[red]{n_false}[/]" if n_false else "0"))
        for i, f in enumerate(faults):
            common = [counts, fmt_cell(r["false_area_mm2"], "{:.0f}"),
                      f"{r['realtime_false_alarms']}/{r['realtime_alarms']}",
                      fmt_cell(r["reconstruction_rms_mm"], "{:.3f}"),
                      fmt_cell(r["realtime_factor"], "{:.1f}"),
                      "[green]met[/]" if r["expect_passed"] else "[red]missed[/]"]
            if i:
                common = [""] * len(common)
            if f is None:
                table.add_row(name, "(control)", *[""] * 6, *common)
                continue
            table.add_row(name if i == 0 else "", f["kind"] + ("" if f["qualifies"] else " *"),
                          fmt_cell(f["peak_height_mm"]), fmt_cell(f["detected"]),
                          fmt_cell(f["onset_layer"], "{}"),
                          fmt_cell(f["onset_delay_layers"], "{:+d}"), fmt_cell(f["iou"]),
                          fmt_cell(f["height_error_mm"], "{:+.2f}"), *common)
    return table


def score_line(summary: dict) -> str:
    """The strict score in one line (F1, its parts, detections, drift, false tracks and alarms;
    false process findings count as false tracks, bench.json ``false_findings`` says how many;
    drift tracks, confirmed by the truth, are neither true nor false)."""
    per_h = summary["realtime_false_alarms_per_hour"]
    controls = summary["false_tracks_per_control"]
    return (f"F1 {summary['f1']:.3f} (precision {summary['precision']:.3f} over "
            f"{summary['true_tracks'] + summary['false_tracks']} tracks, recall "
            f"{summary['recall']:.3f} over {summary['qualifying_faults']} faults); "
            f"detections {summary['detected_faults']}/{summary['qualifying_faults']}; "
            f"drift {summary.get('drift_tracks', 0)} track(s) "
            f"({summary.get('drift_area_mm2', 0.0):.0f} mm²); "
            f"false tracks {summary['false_tracks']} ({summary['false_area_mm2']:.0f} mm²; "
            f"where the twin's part itself stands off the reference as measured: "
            f"{summary['false_tracks_part_deviates']}), fragments "
            f"{summary['fragments']}, neutral {summary['neutral_tracks']}; "
            f"false tracks per control {controls or '-'}; real-time false alarms "
            f"{summary['realtime_false_alarms']}/{summary['realtime_alarms']} "
            f"({fmt_cell(per_h, '{:.0f}')} per process hour); worst onset delay "
            f"{summary['max_onset_delay_layers']} layer(s)")


@app.command()
def bench(
    suite: str = typer.Option("regression", "--suite", "-s",
                              help="Suite name (regression, model_error, shapes, smoke, "
                              "paper) or a folder of scenario files."),
    out: Path = typer.Option(None, "--out", "-o", help="Bench folder (default runs/bench-TIME)."),
    overrides: list[str] = typer.Option([], "--set", help="SECTION.KEY=VALUE applied to every "
                                        "scenario, e.g. --set toolpath.max_layers=12."),
    only: list[str] = typer.Option([], "--only", help="Run only these scenario files (stems)."),
    force: bool = typer.Option(False, "--force", help="Write into a folder holding an earlier "
                               "dm2 output and other files: replace only dm2's files."),
    reports: bool = typer.Option(None, "--reports/--no-reports",
                                 help="Full report folders per scenario (default: the suite's)."),
    gate: bool = typer.Option(True, "--gate/--no-gate",
                              help="Exit 1 when a target, an [expect] section or a fault-free "
                              "control (any track at all) fails; --no-gate prints the score "
                              "and fails only when a scenario cannot run."),
    calibration: str = typer.Option("true", "--calibration", help="true: the pipeline gets "
                                    "the twin's calibration; rehearsed: a calibration is "
                                    "rehearsed and solved first on a twin whose profilers "
                                    "stand off the nominal layout, and the build is monitored "
                                    "with it (and, for comparison, with the true one)."),
    curve: str = typer.Option("configured", "--curve", help="configured: the scenarios' "
                              "efficiency curve; fitted: each cell's curve is first fitted "
                              "from a fault-free calibration build on the twin (as `dm2 "
                              "fit-efficiency` does on a recording) and the suite is "
                              "monitored with it."),
    compensate: bool = typer.Option(False, "--compensate", help="Run each scenario open and "
                                    "closed loop (`dm2 run --compensate apply`) from the same "
                                    "seed and score the final part against the design intent "
                                    "instead (closed_loop in bench.json; no gate)."),
) -> None:
    """Run a suite of scenarios with injected faults and score each strictly against the
    twin's truth maps (every track counts; see dm2.bench.scoring).

    Prints a table and the strict score, writes bench.json; exits 1 when a fault-free control
    has any track, a scenario misses its [expect] section or the suite misses its targets
    (F1, onset delay, false tracks, false alarms per hour), unless --no-gate.

    Example: `dm2 bench --suite regression`
    """
    from dm2.bench.scoring import truth_invalid
    from dm2.bench.suite_score import summarize
    from dm2.bench.suites import load_suite_scenario, resolve_suite
    from scenarios import scenario_dir

    with bad_input_exits():
        if calibration not in ("true", "rehearsed"):
            raise ValueError(f"--calibration {calibration}: expected 'true' or 'rehearsed'")
        if curve not in ("configured", "fitted"):
            raise ValueError(f"--curve {curve}: expected 'configured' or 'fitted'")
        spec, files = resolve_suite(suite, scenario_dir() / "suites")
        suite_files = files
        if only:
            files = [f for f in files if f.stem in set(only)]
            if not files:
                raise ValueError(f"--only {only}: no such scenario in suite '{spec.name}'")
        scenarios = [(f, load_suite_scenario(f, overrides)) for f in files]
        if curve == "fitted":  # each cell's curve is fitted on its first scenario's seed
            from dm2.cli.bench_curve import cell_sources

            loaded = {f: sc for f, sc in scenarios}
            sources = cell_sources(loaded.get(f) or load_suite_scenario(f, overrides)
                                   for f in suite_files)
        out_dir = (out or Path("runs") / f"bench-{datetime.now():%Y%m%d-%H%M%S}-{spec.name}")
        out_dir = out_dir.absolute()
        kept = prepare_output_dir(out_dir, force=force)
    full = spec.full_report if reports is None else reports
    console.print(f"[bold]dm2 bench[/] suite [cyan]{spec.name}[/]: {len(scenarios)} scenarios "
                  f"-> {out_dir}")
    from dm2.cli.bench_runner import run_scenario, score_scenario_run

    if compensate:
        return _closed_loop_bench(scenarios, out_dir, kept, full, spec)
    runs: dict[str, dict] = {}
    done_runs = {}
    chain_true, chain_cmp = {}, {}
    curves: dict[str, dict] = {}  # cell -> its fitted curve (--curve fitted)
    t0 = time.perf_counter()
    for path, sc in scenarios:
        t1 = time.perf_counter()
        try:
            if curve == "fitted":
                from dm2.cli.bench_curve import cell_key, fit_cell_curve, with_exponent

                key = cell_key(sc)
                if key not in curves:
                    curves[key] = fit_cell_curve(sources[key])
                    console.print(f"  cell of {path.stem}: efficiency_cos_exponent "
                                  f"{curves[key]['exponent']:.3f} (fitted on "
                                  f"{curves[key]['calibration_build']})")
                sc = with_exponent(sc, curves[key]["exponent"])
            if calibration == "rehearsed":
                from dm2.cli.bench_calibration import compare, run_rehearsed

                run, run_true, info = run_rehearsed(sc, out_dir / path.stem, path, full)
                chain_true[path.stem] = score_scenario_run(run_true)
                chain_cmp[path.stem] = {**compare(score_scenario_run(run),
                                                  chain_true[path.stem]), "calibration": info}
            else:
                run = run_scenario(sc, out_dir / path.stem, scenario_file=path,
                                   full_report=full)
        except Exception as exc:  # one broken scenario must not hide the others' scores
            err_console.print(f"[red]{escape(f'{path.name}: {type(exc).__name__}: {exc}')}[/]")
            runs[path.stem] = {"error": f"{type(exc).__name__}: {exc}", "expect_passed": False}
            continue
        runs[path.stem] = score_scenario_run(run)
        if not runs[path.stem]["truth_valid"]:  # never scored: the twin's truth is unphysical
            reasons = truth_invalid(run.truth_validity)
            err_console.print(f"[red]{escape(f'{path.name}: truth outside validity: ')}"
                              f"{escape('; '.join(reasons))}[/]")
            runs[path.stem] = {"invalid_truth": reasons, "truth_validity": run.truth_validity,
                               "expect_passed": False}
        if curve == "fitted":
            runs[path.stem]["curve"] = curves[key]
        done_runs[path.stem] = run
        console.print(f"  {path.stem}: {time.perf_counter() - t1:.1f} s wall, "
                      f"{run.process_s:.1f} s process, {len(run.report['layers'])} layers")
    ok_runs = {k: v for k, v in runs.items() if "error" not in v and "invalid_truth" not in v}
    summary = summarize(ok_runs, spec.targets)
    if len(ok_runs) < len(runs):
        summary["passed"] = False
        summary["errors"] = sorted(k for k, v in runs.items() if "error" in v)
        summary["invalid_truth"] = sorted(k for k, v in runs.items() if "invalid_truth" in v)
    summary["wall_s"] = time.perf_counter() - t0
    doc = {"schema": "dm2.bench/2", "suite": spec.name, "description": spec.description,
           "overrides": list(overrides), "curve": curve, "runs": runs, "summary": summary}
    if spec.paper:
        doc["paper"] = _paper_outputs(out_dir, done_runs)
    if calibration == "rehearsed":
        from dm2.cli.bench_calibration import chain_summary

        doc["calibration"] = chain_summary(chain_true, chain_cmp, spec.targets)
        c = doc["calibration"]
        console.print(f"rehearsed calibration: F1 {summary['f1']:.3f} (true calibration "
                      f"{c['true_calibration']['summary']['f1']:.3f}); extra false tracks "
                      f"{c['extra_false_tracks']}; same detections {c['same_detections']}; "
                      f"largest reconstruction RMS difference {c['max_rms_difference_mm']} mm")
    (out_dir / "bench.json").write_text(json.dumps(doc, indent=1, default=_json_default),
                                        encoding="utf-8")
    claim_outputs(out_dir, kept, "dm2 bench")
    console.width = max(console.width, 170)
    console.print(bench_table(runs))
    checks = " ".join(f"{k}: {'[green]ok[/]' if v else '[red]missed[/]'}"
                      for k, v in summary["target_checks"].items())
    console.print(escape(score_line(summary)) + f". {checks}")
    console.print(f"bench.json: [bold]{out_dir / 'bench.json'}[/] ({summary['wall_s']:.0f} s)")
    failed = ([n for n, r in runs.items() if not r.get("expect_passed")]
              + [k for k, v in summary["target_checks"].items() if not v]
              + [f"control {n}: {k} track(s)"
                 for n, k in summary["false_tracks_per_control"].items() if k])
    if summary.get("errors") or summary.get("invalid_truth"):
        console.print("[red]bench failed[/]: scenarios that did not run: "
                      + ", ".join(summary.get("errors") or ["none"])
                      + "; scenarios whose truth is outside validity (not scored): "
                      + ", ".join(summary.get("invalid_truth") or ["none"]))
        raise typer.Exit(EXIT_FAILED)
    if not summary["passed"]:
        if not gate:
            console.print("[yellow]not gated (--no-gate)[/], missed: " + escape(", ".join(failed)))
            return
        console.print("[red]bench failed[/]: " + escape(", ".join(failed)))
        raise typer.Exit(EXIT_FAILED)


def _closed_loop_bench(scenarios, out_dir: Path, kept, full: bool, spec) -> None:
    from dm2.cli.bench_closed_loop import closed_loop_case, closed_loop_lines

    cases, t0 = {}, time.perf_counter()
    tolerance_mm = None
    for path, sc in scenarios:
        tolerance_mm = sc.monitor.delta_global_mm
        try:
            cases[path.stem] = closed_loop_case(sc, out_dir / path.stem, path, full,
                                                tolerance_mm)
        except Exception as exc:  # one broken scenario must not hide the others
            err_console.print(f"[red]{escape(f'{path.name}: {type(exc).__name__}: {exc}')}[/]")
            cases[path.stem] = {"error": f"{type(exc).__name__}: {exc}"}
            continue
        for line in closed_loop_lines(path.stem, cases[path.stem]):
            console.print(escape(line), highlight=False)
    doc = {"schema": "dm2.bench/2", "suite": spec.name, "description": spec.description,
           "closed_loop": {"tolerance_mm": tolerance_mm, "runs": cases,
                           "wall_s": time.perf_counter() - t0}}
    (out_dir / "bench.json").write_text(json.dumps(doc, indent=1, default=_json_default),
                                        encoding="utf-8")
    claim_outputs(out_dir, kept, "dm2 bench")
    console.print(f"bench.json: [bold]{out_dir / 'bench.json'}[/]")
    if any("error" in c for c in cases.values()):
        raise typer.Exit(EXIT_FAILED)


def _paper_outputs(out_dir: Path, runs: dict) -> dict:
    from dm2.bench.paper import format_table_markdown, paper_table_row, plot_track_evolution

    fig_dir = out_dir / "figures"
    fig_dir.mkdir(exist_ok=True)
    rows, figures = [], {}
    for name, run in runs.items():
        rows.append(paper_table_row(run.run_dir, run.report,
                                    run.scenario.process.powder_density_g_cm3))
        figures[name] = str(plot_track_evolution(fig_dir / f"{name}_tracks.png", run.report,
                                                 f"{name}: defect area and height per layer"))
    table = format_table_markdown(rows)
    (out_dir / "paper_table.md").write_text(table, encoding="utf-8")
    console.print(table)
    return {"table": rows, "table_file": str(out_dir / "paper_table.md"), "figures": figures}


def _json_default(obj):
    import numpy as np

    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")
