"""``dm2 toolpath``: plan a part's continuous toolpath and write CSV / RAPID / PNG."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import typer

from dm2.cli.common import app, bad_input_exits, console


def _load_part(part_or_scenario: str):
    """(mesh_O, ToolpathConfig, label) from an STL path or a scenario name/file."""
    from dm2.core.config import ConfigError, PartConfig, ToolpathConfig, load_scenario
    from scenarios import resolve_scenario
    from scenarios.parts import build_part
    from twin.schema import CellConfig

    if part_or_scenario.lower().endswith(".stl"):
        if not Path(part_or_scenario).is_file():
            raise ConfigError(f"{part_or_scenario}: part.stl: file not found")
        part = PartConfig(stl=str(Path(part_or_scenario).resolve()))
        return build_part(part, CellConfig().plate_size_mm), ToolpathConfig(), part_or_scenario
    path = resolve_scenario(part_or_scenario)
    scenario = load_scenario(path)
    try:
        mesh = build_part(scenario.part, scenario.cell.plate_size_mm)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    return mesh, scenario.toolpath, str(path)


def _temp_beside(path: Path) -> Path:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix,
                               dir=path.parent if str(path.parent) else ".")
    os.close(fd)
    os.chmod(tmp, 0o644)
    return Path(tmp)


@app.command()
def toolpath(
    part_or_scenario: str = typer.Argument(
        ..., help="A scenario name or TOML file, or a watertight STL file (default settings)."),
    out: Path = typer.Option(..., "--out", help="Canonical toolpath CSV to write."),
    rapid: Path | None = typer.Option(None, "--rapid", help="Also write an ABB RAPID module."),
    plot: Path | None = typer.Option(None, "--plot", help="Also write a PNG (top view)."),
    force: bool = typer.Option(False, "--force", help="Replace output files dm2 did not "
                               "write (files dm2 wrote are replaced anyway)."),
) -> None:
    """Plan the continuous (C3D-style) toolpath of a part: infill, edges, overhangs, skips."""
    from dm2.core.messages import TOOLPATH_KINDS
    from dm2.report.outdir import check_output_file
    from dm2.toolpath import generate_toolpath
    from dm2.toolpath.formats import write_csv, write_rapid
    from dm2.toolpath.plot import plot_toolpath

    targets = [(out, write_csv)]
    if rapid is not None:
        targets.append((rapid, write_rapid))
    if plot is not None:
        targets.append((plot, plot_toolpath))
    temps: list[Path] = []
    with bad_input_exits():
        for path, _ in targets:
            if not path.parent.exists() and str(path.parent):
                raise FileNotFoundError(f"{path}: output folder {path.parent} does not exist")
            check_output_file(path, force=force, inputs=[Path(part_or_scenario)])
        mesh, cfg, label = _load_part(part_or_scenario)
        tp = generate_toolpath(mesh, cfg)
        try:
            for path, writer in targets:
                temps.append(_temp_beside(path))
                writer(tp, temps[-1])
            for (path, _), tmp in zip(targets, temps, strict=True):
                os.replace(tmp, path)
        finally:
            for tmp in temps:
                tmp.unlink(missing_ok=True)
    step = tp.position_O[1:] - tp.position_O[:-1]
    length = (step ** 2).sum(axis=1) ** 0.5
    duration = float((length / tp.speed_mm_s[1:]).sum())
    console.print(f"{label}: {tp.n_layers} layers, {len(tp)} points, "
                  f"{length.sum() / 1000:.2f} m of path, about {duration / 60:.1f} min")
    for code, name in enumerate(TOOLPATH_KINDS):
        console.print(f"  {name:9s} {float(length[tp.kind[1:] == code].sum()):10.1f} mm")
    console.print(f"wrote {', '.join(str(p) for p, _ in targets)}")
