"""Interim reports written by a child process, so plotting never competes with fusion for the GIL.

A live run rewrites its report folder after every analysed layer. Writing it (PLY meshes, PNG
plots, HTML) is a few hundred milliseconds of mostly pure-Python work; on a thread of the
monitoring process it holds the interpreter lock for most of that time, and the fusion loop and
the socket threads stall behind it. :class:`ReportProcess` hands each snapshot to one child
Python process (``python -m dm2.live.report_process``, a :class:`dm2.io.child_process.PickleChild`
at lower CPU priority; a live run starts it before the stream, else it starts on first use) over
a pipe. Each request is ``(out_dir, results, tracks, content, kwargs)`` for
:func:`dm2.report.write_report` (``content`` a :class:`~dm2.report.report_content.ReportContent`),
answered with the child's seconds. Requests are answered in order, one at a time, so two writes
never touch the folder together.
"""

from __future__ import annotations

import time
from pathlib import Path

from dm2.io.child_process import ChildError, PickleChild, serve


class ReportProcessError(ChildError):
    """The report child failed or is gone; the text says why."""


class ReportProcess:
    """One child process writing reports on request (see the module docstring)."""

    def __init__(self):
        self._child = PickleChild("dm2.live.report_process", what="report process",
                                  error=ReportProcessError)

    def start(self) -> ReportProcess:
        """Start the child now and wait until it has loaded the report code (about a second
        of CPU), so that cost is paid before a stream starts rather than at its first layer."""
        if not self._child.alive:
            self._child.start()
        return self

    def write(self, out_dir: str | Path, results, tracks, content=None, **kwargs) -> float:
        """Write one report (blocks until the child is done); the child's seconds. Arguments
        as :func:`dm2.report.write_report` takes them.

        Raises ReportProcessError when the child failed; a dead child is restarted at the
        next call."""
        self.start()
        return float(self._child.request((str(out_dir), results, tracks, content, kwargs)))

    def close(self) -> None:
        """End the child (after the request in progress, if any)."""
        self._child.close()


def _start_child():
    from dm2.report import write_report

    def handle(request) -> float:
        t0 = time.perf_counter()
        out_dir, results, tracks, content, kwargs = request
        write_report(out_dir, results, tracks, content, **kwargs)
        return time.perf_counter() - t0

    return handle, None


if __name__ == "__main__":
    serve("report process", _start_child)
