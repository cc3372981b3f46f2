"""``dm2 monitor --live``: the live loop of the cell (the monitor command starts it)."""

from __future__ import annotations

from pathlib import Path

import typer

from dm2.cli.common import bad_input_exits, console, fail, log_file


def run_live_monitor(cell_path: Path, out: Path, max_duration_s: float | None = None,
                     force: bool = False, view_port: int | None = None, scene: bool = True,
                     foxglove: bool = False) -> None:
    """``dm2 monitor --live CELL.toml --out DIR``: monitor the cell until it goes quiet or
    Ctrl-C / SIGTERM; ``DIR/live.mcap`` records the stream, ``DIR/report`` the results,
    ``DIR/scene.mcap`` (``scene``) the scene in Foxglove's schemas, written from the recording
    at the end; ``foxglove`` serves the scene live on the cell file's ``[live] foxglove``
    address. Ends
    with one line per drop reason, and exit 1 when nothing was fused or more than
    ``monitor.gates.max_lost_share`` of the input was lost."""
    import signal
    import threading

    from dm2.cli.outcome import (
        drop_lines,
        duplicate_source_lines,
        exit_code,
        run_verdict,
        stream_verdicts,
    )
    from dm2.live.config import load_cell_file
    from dm2.live.runner import LiveRunner
    from dm2.report.outdir import add_to_manifest, check_output_dir

    with bad_input_exits():
        cell = load_cell_file(cell_path)
        if (out / "live.mcap").exists():
            raise ValueError(f"--out {out}: already holds a live recording (live.mcap); "
                             "choose a new folder")
        if (out / "live.mcap.part").exists():
            raise ValueError(f"--out {out}: holds a live recording cut short (live.mcap.part); "
                             f"restore it with `dm2 recover {out / 'live.mcap.part'}` or choose "
                             "a new folder")
        check_output_dir(out, force=force, inputs=[cell_path])
        out.mkdir(parents=True, exist_ok=True)
        add_to_manifest(out, ["live.mcap", "monitor.log", "report/"],
                        command="dm2 monitor --live")
        runner = LiveRunner(cell, out, cell_toml=cell_path.read_text(encoding="utf-8"))
    try:
        addresses = runner.open_sources()
    except OSError as exc:
        runner.close()
        fail(f"{cell_path}: cannot open the live sources: {exc}")
    view = None
    if view_port is not None:
        from dm2.cli.common import start_live_view

        pipeline = runner.analysis.pipeline
        view = start_live_view(runner.calibration, lambda: pipeline.last_T_B_F, view_port)
        runner.analysis.layer_listeners.append(view.on_layer)
    fox = None
    if foxglove:
        from dm2.live.config import parse_host_port
        from dm2.view.foxglove_live import FoxgloveLive

        host, port = parse_host_port(cell.live.foxglove, "foxglove")
        try:
            fox = FoxgloveLive(runner.calibration, runner.analysis.pipeline, host=host,
                               port=port, allow_remote=cell.live.allow_remote)
        except ValueError as exc:
            runner.close()
            fail(f"{cell_path}: [live] foxglove: {exc}")
        runner.analysis.layer_listeners.append(fox.on_layer)
        console.print(f"Foxglove: connect to [bold]{fox.url}[/]")
    stop = threading.Event()
    previous = signal.signal(signal.SIGTERM, lambda *_: stop.set())
    console.print(f"listening: EGM udp {addresses['egm'][0]}:{addresses['egm'][1]}, profiles "
                  f"tcp {addresses['profiles'][0]}:{addresses['profiles'][1]}; Ctrl-C ends")
    try:
        out.mkdir(parents=True, exist_ok=True)
        with log_file(out / "monitor.log"):  # every record, the real-time alarms included
            runner.run(stop=stop, max_duration_s=max_duration_s)
    except KeyboardInterrupt:
        runner.finish()
    finally:
        signal.signal(signal.SIGTERM, previous)
        if view is not None:
            view.close()
            view.stop_server()
        if fox is not None:
            fox.close()
    a = runner.analysis
    if scene:
        try:
            _write_live_scene(runner, out)
        except (OSError, ValueError) as exc:  # the run's own outputs are written already
            console.print(f"[bold yellow]warning:[/] no scene.mcap: {exc}", highlight=False)
    if fox is not None:
        fox.stop_server()
    dropped = a.dropped
    console.print(f"{runner.messages_in} messages, {a.fusion.profiles_fused} profiles fused, "
                  f"{len(a.results)} layers, {len(a.tracks)} tracks"
                  + ("" if dropped else "; nothing dropped"))
    for line in drop_lines(dropped):
        console.print(line, highlight=False)
    for step in runner.gates.steps:
        console.print(f"the clock of {step['source']} stepped {step['step_s']:+.3f} s at "
                      f"{step['at_s']:.3f} s and was re-synced", highlight=False)
    streams = runner.stream_report()
    for line in duplicate_source_lines(streams):
        console.print(line, highlight=False, markup=False)
    console.print(f"recording: {runner.recording_path}  report: {runner.report_dir}")
    transport = sum(v for k, v in runner.inbox.dropped.items())
    # a second source's frames are no part of the cell's input: not in its lost share
    foreign = dropped.get("duplicate_source", 0)
    own = {k: v for k, v in dropped.items() if k != "duplicate_source"}
    max_lost = cell.monitor.gates.max_lost_share
    code, verdict = run_verdict(profiles_fused=a.fusion.profiles_fused, dropped=own,
                                messages_in=runner.messages_in + transport - foreign,
                                max_lost_share=max_lost)
    stream_code, stream_lines = stream_verdicts(streams["per_stream"], max_lost)
    for line in ([verdict] if verdict else []) + stream_lines:
        console.print(f"{cell_path.name}: {line}", highlight=False, markup=False)
    code = exit_code(code, stream_code)
    if code:
        raise typer.Exit(code)


def _write_live_scene(runner, out: Path) -> None:
    """``out/scene.mcap`` from the live recording and the session's results."""
    import json

    from dm2.io.recording import read_recording
    from dm2.report.scene_inputs import StreamTap
    from dm2.report.scene_mcap import add_scene_to_run, scene_items

    tap = StreamTap()
    if runner.recording_path.exists():
        for msg in read_recording(runner.recording_path).messages():
            tap.see(msg)
    report_path = runner.report_dir / "report.json"
    report = json.loads(report_path.read_text(encoding="utf-8")) \
        if report_path.exists() else None
    alarms = runner.analysis.pipeline.session.realtime_summary()["alarms"]  # not in the report
    add_scene_to_run(out, scene_items(runner.analysis.results, report, runner.calibration, tap,
                                      alarms=alarms))
