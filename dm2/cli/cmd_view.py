"""``dm2 view``: a run folder in the browser; ``dm2 report``: its inspection sheet again."""

from __future__ import annotations

from pathlib import Path

import typer

from dm2.cli.common import app, bad_input_exits, console, require_extra

VIEW_PORT = 8080


@app.command()
def view(
    run: Path = typer.Argument(..., help="Run folder (from `dm2 run`, or `dm2 monitor --out`)."),
    host: str = typer.Option("127.0.0.1", "--host", help="Address to serve on."),
    port: int = typer.Option(VIEW_PORT, "--port", min=1, max=65535, help="Port to serve on."),
    limit_mm: float = typer.Option(1.0, "--limit-mm", min=0.01,
                                   help="Colour range of the signed deviation [mm]."),
) -> None:
    """Show a finished run in the browser: the part layer by layer (slider), coloured by signed
    deviation (the report maps' colour scale), tracks as labelled boxes; measured, reference
    or (twin runs) true surface. Serves until Ctrl-C.

    Example: `dm2 view runs/latest` then open the printed URL
    """
    require_extra("viser", "view", "dm2 view")
    from dm2.view.live import serve_forever
    from dm2.view.run_folder import RunFolderView, report_dir
    from dm2.view.scene import start_server, url_of

    with bad_input_exits():
        report_dir(run)
        server = start_server(host, port)
        try:
            RunFolderView(run, server, limit_mm=limit_mm)
        except BaseException:
            server.stop()
            raise
    console.print(f"3D view of {run}: [bold]{url_of(server)}[/]  (Ctrl-C ends)")
    try:
        serve_forever()
    finally:
        server.stop()


@app.command("report")
def report(
    run: Path = typer.Argument(..., help="Run folder (from `dm2 run`, or `dm2 monitor --out`)."),
) -> None:
    """Write the run's index.html again from its report.json (the injected-fault section only
    while the folder holds the twin's truth/).

    Example: `dm2 report runs/latest`
    """
    from dm2.report import rerender_index
    from dm2.view.run_folder import report_dir

    with bad_input_exits():
        path = rerender_index(report_dir(run))
    console.print(f"report: [bold]{path}[/]")
