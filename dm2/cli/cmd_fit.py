"""``dm2 fit-efficiency``: refit the efficiency curve's falloff from a fault-free recording.

Replays the recording through the monitor a few times (:mod:`dm2.pipeline.curve_fit`) and
writes the fitted ``[process] efficiency_cos_exponent`` as a TOML table to ``--out``, to be
copied into the scenario's or the cell file's ``[process]`` table. The recording must be of a
build known to be free of defects: whatever underbuild it shows on its slopes is taken as the
cell's curve.
"""

from __future__ import annotations

from pathlib import Path

import typer

from dm2.cli.common import app, bad_input_exits, console, fail
from dm2.cli.inputs import (
    CALIBRATION_OPTION,
    CONFIG_OPTION,
    MAP_OPTION,
    TOOLPATH_OPTION,
    load_inputs,
)


@app.command("fit-efficiency")
def fit_efficiency(
    run: Path = typer.Argument(..., help="Recording of a fault-free build: MCAP or a rosbag2 "
                               "bag (folder or .db3)."),
    out: Path = typer.Option(..., "--out", "-o", help="TOML file to write (must not exist)."),
    calibration: Path = CALIBRATION_OPTION,
    toolpath: Path = TOOLPATH_OPTION,
    map_path: Path = MAP_OPTION,
    config: Path = CONFIG_OPTION,
) -> None:
    """Fit `[process] efficiency_cos_exponent` (how much faster than the model's curve the
    cell's deposition efficiency falls with the spray angle) from a fault-free recording.

    The recording is replayed 2-9 times; the fitted value, the residual deviation before and
    after and the tracks the monitor raised on the recording at each are printed, and the
    value is written to OUT as a `[process]` table. Exit 2 when the part has no walls or slopes
    (a flat pad does not show the curve) or OUT exists.

    Example: `dm2 fit-efficiency fault_free.mcap --out cell_curve.toml`
    """
    from rich.table import Table

    from dm2.core.toml_write import dump_toml
    from dm2.pipeline.curve_fit import (
        CurveNotObservable,
        fit_efficiency_exponent,
        recording_pipeline,
    )

    if out.exists():
        fail(f"--out {out}: exists; give a new file (nothing is overwritten)")
    with bad_input_exits():
        rec, cal, tp, monitor_cfg, process, plate_mm = load_inputs(run, calibration, toolpath,
                                                                     map_path, config)
    run_pipeline = recording_pipeline(rec.messages, cal, monitor_cfg, plate_mm, tp)
    try:
        with console.status("replaying the recording"):
            fit = fit_efficiency_exponent(run_pipeline, process,
                                          progress=lambda line: console.print(line))
    except CurveNotObservable as exc:
        fail(f"{run}: {exc}")
    finally:
        if hasattr(rec, "close"):
            rec.close()
    header = (f"# dm2 fit-efficiency {run.name}: efficiency_cos_exponent {fit.start:g} -> "
              f"{fit.exponent:.3f}; residual RMS {fit.start_rms_mm:.4f} -> "
              f"{fit.residual_rms_mm:.4f} mm; defect tracks on the recording "
              f"{fit.tracks_at_start} -> {fit.tracks_at_fit}"
              + ("; held at the bound" if fit.at_bound else "") + "\n")
    body = dump_toml({"process": {"efficiency_cos_exponent": round(fit.exponent, 3)}})
    try:
        with open(out, "x", encoding="utf-8") as f:
            f.write(header + body)
    except OSError as exc:
        fail(f"--out {out}: cannot write: {exc.strerror}")
    table = Table(title=f"fit-efficiency: {run.name}")
    for col in ("", "exponent", "residual RMS [mm]", "defect tracks"):
        table.add_column(col, justify="right")
    table.add_row("start", f"{fit.start:g}", f"{fit.start_rms_mm:.4f}", str(fit.tracks_at_start))
    table.add_row("fitted", f"{fit.exponent:.3f}", f"{fit.residual_rms_mm:.4f}",
                  str(fit.tracks_at_fit))
    console.print(table)
    if fit.at_bound and fit.exponent == 0.0:
        console.print("the least-squares optimum lies below 0: the cell's curve is no steeper "
                      "than the model's, whose own curve (0) is the closest allowed",
                      markup=False)
    console.print(f"wrote {out}: copy its [process] table into the scenario or cell file",
                  markup=False)
