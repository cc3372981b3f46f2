"""``dm2 serve-twin`` and ``dm2 recover``; the live side of ``dm2 monitor --live CELL.toml``."""

from __future__ import annotations

from pathlib import Path

import typer

from dm2.cli.common import app, bad_input_exits, console, fail


@app.command("serve-twin")
def serve_twin(
    scenario: str = typer.Argument(None, help="Scenario name or TOML path."),
    egm: str = typer.Option("127.0.0.1:6510", "--egm", help="HOST:PORT the monitor receives "
                            "EGM datagrams on (UDP)."),
    profiles: str = typer.Option("127.0.0.1:6511", "--profiles", help="HOST:PORT of the "
                                 "monitor's profile server (TCP)."),
    speed: float = typer.Option(1.0, "--speed", help="Process seconds per wall second "
                                "(1 = real time; 0 = as fast as possible)."),
    duration_s: float = typer.Option(None, "--duration-s", min=0.001,
                                     help="Stop after this many process seconds."),
    wait_s: float = typer.Option(60.0, "--wait-s", min=0.0, help="How long to wait for the "
                                 "monitor's profile server before giving up (seconds)."),
    write_cell: Path = typer.Option(None, "--write-cell", help="Write cell.toml (with the "
                                    "calibration and toolpath) for `dm2 monitor --live` into "
                                    "this folder, then serve; its clock tolerance and reorder "
                                    "window are scaled by --speed."),
) -> None:
    """Play the twin as the cell over loopback sockets: EGM robot states (UDP) and profile
    frames (TCP), at their stamps, real time or accelerated.

    Example: `dm2 serve-twin pad --write-cell cell/ --speed 5` with
    `dm2 monitor --live cell/cell.toml --out runs/live` in another shell.
    """
    from dm2.core.config import ConfigError, load_scenario
    from dm2.live.config import parse_host_port
    from scenarios import resolve_scenario

    with bad_input_exits():
        egm_addr = parse_host_port(egm, "--egm")
        prof_addr = parse_host_port(profiles, "--profiles")
        sc = load_scenario(resolve_scenario(scenario))
        if duration_s is not None:
            sc = sc.model_copy(update={"duration_s": duration_s})
    from twin.cell.kinematics import ReachError
    from twin.stream.serve import serve_twin as serve
    from twin.stream.serve import write_cell_files
    from twin.stream.simulate import Simulation

    try:
        sim = Simulation(sc)
    except ReachError as exc:
        fail(f"{sc.name}: the robot cannot follow the toolpath: {exc}")
    except ConfigError as exc:
        fail(str(exc))
    if write_cell is not None:
        path = write_cell_files(sim, write_cell, egm=egm, profiles=profiles, speed=speed)
        console.print(f"cell file: {path}")
    console.print(f"serving {sc.name} ({sim.end_s:.1f} s of process) to EGM udp {egm}, "
                  f"profiles tcp {profiles} at {speed:g}x; the stream starts when the monitor "
                  f"accepts (waiting up to {wait_s:g} s)")
    try:
        result = serve(sc, egm_addr, prof_addr, speed, simulation=sim, connect_timeout_s=wait_s)
    except ConnectionError as exc:
        fail(f"{exc} within {wait_s:g} s (start `dm2 monitor --live` with the cell file)",
             code=1)
    except KeyboardInterrupt:
        fail("interrupted", code=130)
    c = result.counts
    console.print(f"sent {c['RobotState']} robot states, {c['Profile']} profiles, "
                  f"{c['LayerMark']} layer changes")


@app.command()
def recover(
    file: Path = typer.Argument(..., help="Truncated recording (e.g. live.mcap.part)."),
    out: Path = typer.Option(None, "--out", "-o", help="Output file (default: FILE without "
                             ".part, or FILE.recovered.mcap)."),
) -> None:
    """Make a recording cut short by a crash, or damaged, readable again.

    Every chunk up to the first one cut off, undecompressable or failing its CRC is kept; the
    new file records that it was recovered and what was lost (a run on it exits 3 unless
    `--allow-truncated`)."""
    from dm2.live.recover import default_output, recover_recording

    with bad_input_exits():
        target = out if out is not None else default_output(file)
        if target.exists():
            raise ValueError(f"{target}: already exists; choose another --out")
        result = recover_recording(file, target)
    state = ("complete" if result.complete
             else f"cut off or damaged; kept every intact chunk before that: {result.note}")
    upto = f" up to {result.last_stamp_s:.3f} s" if result.messages else ""
    console.print(f"recovered {result.messages} messages and {result.attachments} "
                  f"attachments{upto} ({state}) -> {result.out_path}")
