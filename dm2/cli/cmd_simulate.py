"""``dm2 simulate``: run the digital twin on a scenario and record the stream to MCAP."""

from __future__ import annotations

from pathlib import Path

import typer

from dm2.cli.common import (
    app,
    bad_input_exits,
    cannot_write_exits,
    console,
    fail,
    require_extra,
)


@app.command()
def simulate(
    scenario: str = typer.Argument(None, help="Scenario name or TOML path (default: the "
                                   "seven-sided corner over-build)."),
    out: Path = typer.Option(Path("run.mcap"), "--out", "-o", help="MCAP file to write."),
    truth: Path = typer.Option(None, "--truth", help="Folder for per-layer ground truth."),
    duration_s: float = typer.Option(None, "--duration-s", min=0.001,
                                     help="Stop after this many process seconds."),
    gui: bool = typer.Option(False, "--gui", help="Show the cell in pybullet's GUI while "
                             "simulating (needs a display)."),
    force: bool = typer.Option(False, "--force", help="Replace an --out file dm2 did not "
                               "write, and write --truth into a folder holding an earlier dm2 "
                               "output and other files (only dm2's files are replaced)."),
) -> None:
    """Simulate a build (robot, spray, three profilers) and record it as MCAP.

    The recording opens in Foxglove and ROS 2 tools (PointCloud2, JointState, TF) and carries
    the scenario, toolpath and calibration as attachments, so `dm2 monitor` can replay it.
    """
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    from dm2.core.config import load_scenario
    from dm2.report.outdir import (
        check_output_file,
        claim_outputs,
        discard_partial,
        prepare_output_dir,
    )
    from scenarios import resolve_scenario

    with bad_input_exits():
        path = resolve_scenario(scenario)
        sc = load_scenario(path)
        if duration_s is not None:
            sc = sc.model_copy(update={"duration_s": duration_s})
        if not out.parent.exists():
            raise FileNotFoundError(f"--out {out}: folder {out.parent} does not exist")
        check_output_file(out, force=force, inputs=[path])
        kept = None if truth is None else prepare_output_dir(truth, force=force)
    if gui:
        require_extra("pybullet", "twin", "--gui")
        _require_display()
    from twin.cell.kinematics import ReachError
    from twin.stream.simulate import Simulation
    from twin.stream.simulate import simulate as run_simulation

    with bad_input_exits():
        try:
            sim = Simulation(sc)
        except ReachError as exc:
            fail(f"{path}: the robot cannot follow the toolpath: {exc}")
    viewer = _open_gui(sim) if gui else None

    def discard() -> None:  # a failed write leaves no half recording, no unlisted truth file
        out.with_name(out.name + ".part").unlink(missing_ok=True)
        if truth is not None:
            discard_partial(truth, kept)

    bar = Progress(TextColumn("[bold]simulating[/]"), BarColumn(),
                   TextColumn("{task.completed:.1f}/{task.total:.1f} s"), TimeRemainingColumn(),
                   console=console, transient=True)
    with cannot_write_exits(out, discard), bar:
        task = bar.add_task("sim", total=sim.end_s)

        def progress(done_s: float, total_s: float) -> None:
            bar.update(task, completed=done_s, total=total_s)

        result = run_simulation(sc, out, truth, progress, simulation=sim,
                                on_message=viewer.on_message if viewer is not None else None)
        if truth is not None:
            claim_outputs(truth, kept, "dm2 simulate --truth")
    if viewer is not None:
        viewer.cell.close()
    c = result.counts
    console.print(f"wrote {out}: {result.process_s:.1f} s of process, {result.n_layers} layers, "
                  f"{c.get('Profile', 0)} profiles, {c.get('RobotState', 0)} robot states"
                  + (f"; truth in {truth}" if truth is not None else ""))


class _GuiView:
    """Mirror the recorded robot states in pybullet's GUI (every tenth state)."""

    def __init__(self, cell):
        from twin.cell.pybullet_cell import PybulletCell

        self.cell = PybulletCell(cell, gui=True)

    def on_message(self, msg) -> None:
        from dm2.core.messages import RobotState

        if isinstance(msg, RobotState) and msg.seq % 10 == 0:
            self.cell.set_joints(msg.joints_rad)


def _require_display() -> None:
    import os

    if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
        fail("--gui needs a display (DISPLAY is not set); run without --gui")


def _open_gui(sim) -> _GuiView:
    try:
        return _GuiView(sim.cell)
    except Exception as exc:  # noqa: BLE001 - pybullet reports GUI failures many ways
        fail(f"--gui: cannot open pybullet's GUI: {exc}")
