"""Shared CLI plumbing: the typer app, the console and error handling with exit codes."""

from __future__ import annotations

import errno
import functools
import logging
import math
from contextlib import contextmanager

import typer
from rich.console import Console
from rich.logging import RichHandler

from dm2 import __version__
from dm2.cli.outcome import EXIT_CANNOT_WRITE

EXAMPLES = """Examples:

```
  dm2 run                 # default scenario: simulate, monitor, report
  dm2 toolpath pad --out tp.csv --plot tp.png --rapid tp.mod
  dm2 simulate seven_sided_corner_overbuild --out run.mcap
  dm2 monitor run.mcap --out runs/replay
  dm2 calibrate --rehearse --poses 24 --noise-mm 0.03
```
"""

# errors of the system, not of the input: the disk is full, the file system read-only, the
# user may not write there (exit 4, EXIT_CANNOT_WRITE)
WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM,
                          errno.EFBIG})


class _App(typer.Typer):
    """Every command runs inside :func:`cannot_write_exits`: a full disk or a refused write
    ends with one line naming the path and exit 4, never a traceback."""

    def command(self, *args, **kwargs):
        register = super().command(*args, **kwargs)

        def decorator(func):
            @functools.wraps(func)
            def guarded(*a, **k):
                _refuse_non_finite(func, k)
                _CLEANUPS.clear()
                try:
                    with cannot_write_exits():
                        return func(*a, **k)
                finally:
                    _CLEANUPS.clear()

            register(guarded)
            return func

        return decorator


def _refuse_non_finite(func, values: dict) -> None:
    """A number option given as ``inf`` or ``nan`` (click reads both as floats): exit 2
    naming the option as the user typed it."""
    import inspect

    bad = [(k, v) for k, v in values.items() if isinstance(v, float) and not math.isfinite(v)]
    if not bad:
        return
    key, value = bad[0]
    default = inspect.signature(func).parameters[key].default
    decls = [d for d in getattr(default, "param_decls", None) or () if d.startswith("--")]
    fail(f"{decls[0] if decls else key} {value}: not a finite number")


app = _App(
    name="dm2",
    help="3D-DM2: in-process 3D deviation mapping and defect monitoring for robotic cold "
    "spray additive manufacturing, with a digital twin.\n\n" + EXAMPLES,
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode="markdown",
)
console = Console(stderr=False)
err_console = Console(stderr=True)
CONSOLE_QUIET = ("dm2.alarms",)  # loggers kept off the console (they go to the run's log file)

EXIT_BAD_INPUT = 2


class _ConsoleFilter(logging.Filter):
    """Off the console: the loggers of CONSOLE_QUIET, and (unless verbose) INFO records of the
    pipeline's per-layer chatter; all of them still reach the run's log file."""

    def __init__(self, verbose: bool):
        super().__init__()
        self.verbose = verbose

    def filter(self, record: logging.LogRecord) -> bool:
        if record.name.startswith(CONSOLE_QUIET):
            return False
        return self.verbose or record.levelno >= logging.WARNING


def setup_logging(verbose: bool) -> None:
    """Log records go through the progress bar's console (``console``: a live bar stays on its
    own line); the console shows warnings (everything with ``-v``)."""
    handler = RichHandler(console=console, show_path=False)
    handler.addFilter(_ConsoleFilter(verbose))
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(message)s",
        handlers=[handler],
        force=True,
    )


@contextmanager
def log_file(path):
    """Write every INFO record (real-time alarms included) to ``path`` while the block runs."""
    handler = logging.FileHandler(path, mode="w", encoding="utf-8")
    handler.setLevel(logging.INFO)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        yield path
    finally:
        root.removeHandler(handler)
        handler.close()


def note_cold_kernel_cache() -> None:
    """Say so when the compiled kernels are not cached yet (the first run after installing
    compiles them, about a minute of silence otherwise). Checked where numba caches them for
    a writable source tree; elsewhere nothing is said."""
    import os
    from pathlib import Path

    import dm2

    root = Path(dm2.__file__).parent
    if os.environ.get("NUMBA_CACHE_DIR") or not os.access(root, os.W_OK):
        return
    if next(root.glob("**/__pycache__/*.nbi"), None) is None:  # (kernels live in subfolders)
        console.print("first run: compiling the numeric kernels (about a minute; cached for "
                      "later runs)")


def fail(message: str, code: int = EXIT_BAD_INPUT) -> None:
    """Print a clear error and exit with ``code`` (2 = bad input). The message is plain text:
    brackets in it (``[live]``, ``[mm]``, lists) are printed, not read as console markup."""
    from rich.markup import escape

    err_console.print(f"[bold red]error:[/] {escape(message)}", highlight=False, soft_wrap=True)
    raise typer.Exit(code)


def require_extra(module: str, extra: str, what: str) -> None:
    """Exit 2 with the line that installs it when ``module``, which only the package's optional
    ``extra`` installs, is missing (``what``: the command or option that needs it)."""
    import importlib

    try:
        importlib.import_module(module)
    except ImportError:
        fail(f"{what} needs the optional package {module}, which this installation lacks: "
             f"pip install 'dm2[{extra}]'")


@contextmanager
def bad_input_exits():
    """Turn the project's input errors into a clear message and exit code 2 (an output folder
    the system does not let dm2 write: 4)."""
    from dm2.core.config import ConfigError
    from dm2.core.messages import MessageError
    from dm2.report.outdir import OutputNotWritable

    try:
        yield
    except OutputNotWritable as exc:
        fail(str(exc), EXIT_CANNOT_WRITE)
    except (ConfigError, MessageError, FileNotFoundError, ValueError) as exc:
        fail(str(exc))


_CLEANUPS: list = []  # the running command's on_write_failure (path, callback) pairs


def on_write_failure(path, cleanup) -> None:
    """Have ``cleanup()`` run when the running command ends on a refused write into ``path``
    (exit 4): it takes away what the failed write left half done (:func:`cannot_write_exits`)."""
    _CLEANUPS.append((path, cleanup))


@contextmanager
def cannot_write_exits(path=None, cleanup=None):
    """A write the system refuses (:data:`WRITE_ERRNOS`: no space, read-only, no permission)
    becomes one line naming the file (else ``path``) and exit 4, after ``cleanup()`` (and
    every :func:`on_write_failure` callback) took away what the failed write left half
    done."""
    try:
        yield
    except OSError as exc:
        if exc.errno not in WRITE_ERRNOS:
            raise
        registered = _CLEANUPS[::-1]
        _CLEANUPS.clear()
        for undo in [cleanup] + [c for _, c in registered]:
            if undo is not None:
                undo()
        where = exc.filename or path or next((p for p, _ in registered), "the output")
        verb = "cannot access" if exc.errno in (errno.EACCES, errno.EPERM) else "cannot write"
        fail(f"{verb} {where}: {exc.strerror or errno.errorcode.get(exc.errno)}",
             EXIT_CANNOT_WRITE)


def version_callback(value: bool) -> None:
    if value:
        console.print(f"dm2 {__version__}")
        raise typer.Exit()


@app.callback()
def main_callback(
    version: bool = typer.Option(False, "--version", callback=version_callback, is_eager=True,
                                 help="Show the version and exit."),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Debug logging."),
) -> None:
    setup_logging(verbose)


def start_live_view(calibration, pose_source, port: int, limit_mm: float = 1.0):
    """The live 3D view (dm2.view.live.LiveView) on 127.0.0.1:port, its URL printed; the
    ``[view]`` extra named when it is missing."""
    require_extra("viser", "view", "--view")
    from dm2.view.live import LiveView

    view = LiveView(calibration, pose_source, limit_mm=limit_mm, port=port)
    console.print(f"3D view: [bold]{view.url}[/]")
    return view


def fmt_cell(v, spec: str = "{:.2f}") -> str:
    """A table cell: ``-`` for none or not finite, yes/NO for a flag, else ``spec``."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "NO"
    return spec.format(v)


def serve_after_run(view=None, fox=None) -> None:
    """Keep the live 3D view (``view``) and the Foxglove server (``fox``) of a finished run
    serving until Ctrl-C, their URLs printed; nothing when neither was started."""
    if view is None and fox is None:
        return
    from dm2.view.live import serve_forever

    if view is not None:
        view.close()
        console.print(f"3D view: [bold]{view.url}[/] (Ctrl-C ends)")
    if fox is not None:
        console.print(f"Foxglove: [bold]{fox.url}[/] (Ctrl-C ends)")
    try:
        serve_forever()
    finally:
        if view is not None:
            view.stop_server()
        if fox is not None:
            fox.stop_server()
