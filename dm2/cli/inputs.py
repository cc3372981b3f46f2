"""Resolving a recording's inputs (calibration, toolpath, configuration, topic map), shared by
every command that replays a recording (``dm2 monitor``, ``dm2 fit-efficiency``)."""

from __future__ import annotations

from pathlib import Path

import typer


def _read_toolpath(path: Path):
    """A toolpath file: the canonical CSV, or the RAPID module ``dm2 toolpath`` writes (told
    apart by its ``MODULE`` line)."""
    import re

    from dm2.toolpath.formats import read_csv, read_rapid

    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            head = f.read(4096)
    except OSError as exc:
        raise FileNotFoundError(f"--toolpath {path}: cannot read: {exc.strerror}") from None
    if re.search(r"^\s*MODULE\s+\w+", head, re.MULTILINE):
        return read_rapid(path)
    return read_csv(path)


# the options that resolve a recording's inputs (load_inputs), shared by every command that
# replays one
CALIBRATION_OPTION = typer.Option(None, "--calibration", help="Calibration TOML (default: the "
                                  "recording's attachment, else its /tf_static).")
TOOLPATH_OPTION = typer.Option(None, "--toolpath", help="Toolpath CSV or RAPID module (default: "
                               "the recording's attachment); splits layers without layer marks.")
MAP_OPTION = typer.Option(None, "--map", help="Map TOML from a cell's own topic and frame names "
                          "onto the pipeline's (see README, 'Your own cell's recordings').")
CONFIG_OPTION = typer.Option(None, "--config", help="Scenario, cell or `dm2 fit-efficiency` TOML "
                             "whose [process] and [monitor] tables replace the recording's "
                             "(default: the attached scenario's, else the package defaults).")


def load_inputs(run: Path, calibration: Path | None, toolpath: Path | None,
                map_path: Path | None = None, config: Path | None = None):
    """Open the recording and resolve calibration, toolpath and configuration (the attached
    scenario's, then ``config``'s ``[process]`` / ``[monitor]`` tables over it)."""
    from dm2.core.calibration_io import read_calibration_toml
    from dm2.core.config import MonitorConfig, ProcessConfig, parse_scenario
    from dm2.io.bag_recording import open_recording
    from dm2.io.recording_map import read_map
    from twin.schema import CellConfig

    rmap = read_map(map_path) if map_path is not None else None
    rec = open_recording(run, rmap)
    cal = read_calibration_toml(calibration) if calibration is not None else rec.calibration
    if cal is None:
        raise ValueError(f"{run}: no calibration attached and no complete /tf_static; "
                         "give one with --calibration FILE.toml")
    tp = _read_toolpath(toolpath) if toolpath is not None else rec.toolpath
    monitor_cfg, process, plate_mm = MonitorConfig(), ProcessConfig(), CellConfig().plate_size_mm
    if rec.scenario_toml is not None:
        import tomllib

        try:
            sc = parse_scenario(tomllib.loads(rec.scenario_toml), f"{run}:scenario.toml")
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"{run}: attached scenario is not valid TOML: {exc}") from None
        monitor_cfg, process, plate_mm = sc.monitor, sc.process, sc.cell.plate_size_mm
    if config is not None:
        from dm2.core.config_file import apply_config_file

        process, monitor_cfg = apply_config_file(config, process, monitor_cfg)
    if hasattr(rec, "max_pose_gap_s"):  # rosbag2: tf lookups within the configured gap
        rec.max_pose_gap_s = monitor_cfg.max_pose_gap_s
    if tp is not None:
        check_toolpath_matches(rec, cal, tp, process, toolpath or "the attached toolpath")
    return rec, cal, tp, monitor_cfg, process, plate_mm


def check_toolpath_matches(rec, cal, tp, process, tp_name) -> None:
    """Refuse a toolpath the recorded robot did not follow (before any fusion work), over the
    whole run: see :mod:`dm2.fusion.path_agreement` for the windows and the bound."""
    from dm2.fusion.path_agreement import MAX_MEDIAN_MM, executed_spots, first_departure

    stamps_s, spots_O, marks = executed_spots(rec, cal, process.standoff_mm)
    part = first_departure(stamps_s, spots_O, tp, marks=marks)
    if part is not None:
        raise ValueError(f"{tp_name} does not match the recording {rec.path}: they part at "
                         f"{part.where()}, where the "
                         f"spray spot lies a median {part.median_mm:.1f} mm from the toolpath "
                         f"until {part.end_s:.1f} s (at most {MAX_MEDIAN_MM} mm allowed)")
