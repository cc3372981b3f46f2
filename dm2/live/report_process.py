"""Interim reports written by a child process, so plotting never competes with fusion for the GIL.

A live run rewrites its report folder after every analysed layer. Writing it (PLY meshes, PNG
plots, HTML) is a few hundred milliseconds of mostly pure-Python work; on a thread of the
monitoring process it holds the interpreter lock for most of that time, and the fusion loop and
the socket threads stall behind it. :class:`ReportProcess` hands each snapshot to one child
Python process (``python -m dm2.live.report_process``, lower CPU priority; a live run starts it
before the stream, else it starts on first use) over a pipe. The child first answers
``("ready", None)`` once it has loaded the report code; then each request is a length-prefixed
pickle of ``(out_dir, results, tracks, content, kwargs)`` for :func:`dm2.report.write_report`
(``content`` a :class:`~dm2.report.report_content.ReportContent`), and its
answer a pickle of ``("ok", seconds)`` or ``("error", text)``. Requests are answered in order,
one at a time, so two writes never touch the folder together. The pipe only ever carries our
own objects between our own processes.
"""

from __future__ import annotations

import logging
import os
import pickle
import struct
import subprocess
import sys
import time
import traceback
from pathlib import Path

log = logging.getLogger(__name__)

_LEN = struct.Struct("<Q")
CHILD_NICE = 10  # the child's niceness increment: the stream's threads come first


class ReportProcessError(RuntimeError):
    """The report child failed or is gone; the text says why."""


class ReportProcess:
    """One child process writing reports on request (see the module docstring)."""

    def __init__(self):
        self._proc: subprocess.Popen | None = None

    def start(self) -> ReportProcess:
        """Start the child now and wait until it has loaded the report code (about a second
        of CPU), so that cost is paid before a stream starts rather than at its first layer."""
        if self._proc is None or self._proc.poll() is not None:
            self._start()
        return self

    def _start(self) -> subprocess.Popen:
        root = str(Path(__file__).resolve().parents[2])
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
        for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                    "NUMBA_NUM_THREADS"):
            env[var] = "1"
        env.setdefault("MPLBACKEND", "Agg")
        proc = subprocess.Popen([sys.executable, "-m", "dm2.live.report_process"],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env)
        try:
            status, value = pickle.loads(_read_frame(proc.stdout))
        except (OSError, EOFError) as exc:
            proc.kill()
            proc.wait()
            raise ReportProcessError(f"report process did not start: {exc}") from None
        if status != "ready":
            raise ReportProcessError(f"report process did not start: {value}")
        self._proc = proc
        return proc

    def write(self, out_dir: str | Path, results, tracks, content=None, **kwargs) -> float:
        """Write one report (blocks until the child is done); the child's seconds. Arguments
        as :func:`dm2.report.write_report` takes them.

        Raises ReportProcessError when the child failed; a dead child is restarted at the
        next call."""
        proc = self._proc if self._proc is not None and self._proc.poll() is None \
            else self._start()
        data = pickle.dumps((str(out_dir), results, tracks, content, kwargs),
                            protocol=pickle.HIGHEST_PROTOCOL)
        try:
            proc.stdin.write(_LEN.pack(len(data)) + data)
            proc.stdin.flush()
            answer = _read_frame(proc.stdout)
        except (OSError, EOFError) as exc:
            self._proc = None
            raise ReportProcessError(f"report process ended: {exc}") from None
        status, value = pickle.loads(answer)
        if status != "ok":
            raise ReportProcessError(f"report process: {value}")
        return float(value)

    def close(self) -> None:
        """End the child (after the request in progress, if any)."""
        proc, self._proc = self._proc, None
        if proc is None:
            return
        try:
            proc.stdin.close()
        except OSError:
            pass
        try:
            proc.wait(timeout=30.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        proc.stdout.close()


def _read_frame(stream) -> bytes:
    head = stream.read(_LEN.size)
    if len(head) < _LEN.size:
        raise EOFError("no answer")
    (n,) = _LEN.unpack(head)
    body = stream.read(n)
    if len(body) < n:
        raise EOFError("answer cut short")
    return body


def serve(stdin, stdout) -> None:
    """The child's loop: write a report per request until stdin closes."""
    from dm2.report import write_report

    _answer(stdout, ("ready", None))
    while True:
        try:
            request = _read_frame(stdin)
        except EOFError:
            return
        t0 = time.perf_counter()
        try:
            out_dir, results, tracks, content, kwargs = pickle.loads(request)
            write_report(out_dir, results, tracks, content, **kwargs)
            answer = ("ok", time.perf_counter() - t0)
        except Exception as exc:  # noqa: BLE001 - reported to the parent, which logs it
            answer = ("error", f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}")
        _answer(stdout, answer)


def _answer(stdout, answer) -> None:
    data = pickle.dumps(answer)
    stdout.write(_LEN.pack(len(data)) + data)
    stdout.flush()


if __name__ == "__main__":
    logging.basicConfig(level=logging.WARNING, format="report process: %(message)s")
    try:
        os.nice(CHILD_NICE)
    except OSError:
        pass
    # the protocol keeps the original stdout; anything printed goes to stderr
    answers = os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    serve(sys.stdin.buffer, answers)
