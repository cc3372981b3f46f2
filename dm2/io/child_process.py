"""A Python child process that answers pickled requests over its stdin and stdout.

Work that would hold the interpreter lock for long stretches (plotting a report, serving the 3D
view) runs in a child process of its own, so the fusion loop and the socket threads never stall
behind it. :class:`PickleChild` starts ``python -m MODULE ARGS`` at a lower CPU priority; the
child's module calls :func:`serve` with a handler. The child first answers ``("ready", value)``
(or ``("error", text)`` when it cannot start); then every request is a length-prefixed pickle,
answered in order, one at a time, with a pickle of ``("ok", value)`` or ``("error", text)``.
The pipe only ever carries our own objects between our own processes.
"""

from __future__ import annotations

import logging
import os
import pickle
import signal
import struct
import subprocess
import sys
import traceback
from collections.abc import Callable
from pathlib import Path

_LEN = struct.Struct("<Q")
CHILD_NICE = 10  # the child's niceness increment: the stream's threads come first


class ChildError(RuntimeError):
    """The child failed, would not start or is gone; the text says why."""


def child_env() -> dict:
    """The child's environment: this package importable, one thread per numeric library, a
    non-interactive plotting backend."""
    root = str(Path(__file__).resolve().parents[2])
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                "NUMBA_NUM_THREADS"):
        env[var] = "1"
    env.setdefault("MPLBACKEND", "Agg")
    return env


class PickleChild:
    """One child process ``python -m module *args`` (see the module docstring); its failures
    are raised as ``error`` (ChildError or a subclass of it)."""

    def __init__(self, module: str, args: tuple[str, ...] = (), what: str = "child process",
                 error: type[ChildError] = ChildError):
        self.module, self.args, self.what, self.error = module, tuple(args), what, error
        self.proc: subprocess.Popen | None = None
        self.ready_value = None

    @property
    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def start(self) -> PickleChild:
        """Start the child and wait for its ready answer (it loads its code first, so that cost
        is paid now); raises :attr:`error` with the child's reason when it cannot start."""
        proc = subprocess.Popen([sys.executable, "-m", self.module, *self.args],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=child_env())
        try:
            status, value = pickle.loads(read_frame(proc.stdout))
        except (OSError, EOFError) as exc:
            status, value = "error", str(exc)
        if status != "ready":
            proc.kill()
            proc.wait()
            raise self.error(f"{self.what} did not start: {value}")
        self.proc, self.ready_value = proc, value
        return self

    def request(self, request):
        """Send ``request``, wait for its answer and return its value; raises :attr:`error`
        when the child answered an error or is gone (then :attr:`alive` is False)."""
        proc = self.proc
        if proc is None:
            raise self.error(f"{self.what} is not running")
        data = pickle.dumps(request, protocol=pickle.HIGHEST_PROTOCOL)
        try:
            proc.stdin.write(_LEN.pack(len(data)) + data)
            proc.stdin.flush()
            answer = read_frame(proc.stdout)
        except (OSError, EOFError) as exc:
            self.proc = None
            raise self.error(f"{self.what} ended: {exc}") from None
        status, value = pickle.loads(answer)
        if status != "ok":
            raise self.error(f"{self.what}: {value}")
        return value

    def close(self, timeout_s: float = 30.0) -> None:
        """End the child (after the request in progress, if any): its stdin closes and its
        :func:`serve` loop returns."""
        proc, self.proc = self.proc, None
        if proc is None:
            return
        try:
            proc.stdin.close()
        except OSError:
            pass
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        proc.stdout.close()


def read_frame(stream) -> bytes:
    head = stream.read(_LEN.size)
    if len(head) < _LEN.size:
        raise EOFError("no answer")
    (n,) = _LEN.unpack(head)
    body = stream.read(n)
    if len(body) < n:
        raise EOFError("answer cut short")
    return body


def _answer(stdout, answer) -> None:
    data = pickle.dumps(answer, protocol=pickle.HIGHEST_PROTOCOL)
    stdout.write(_LEN.pack(len(data)) + data)
    stdout.flush()


def serve(name: str, start: Callable[[], tuple[Callable, object]]) -> None:
    """The child's main: lower its priority, keep the protocol on the original stdout (anything
    printed goes to stderr), call ``start()`` for ``(handler, ready_value)`` and answer each
    request with ``handler(request)`` until stdin closes. An exception from ``start`` is the
    "error" answer instead of "ready". Ctrl-C, which the terminal sends to the child too, is
    left to the parent: it ends the child by closing its stdin (or by exiting), so the
    console shows no traceback of the child's."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    logging.basicConfig(level=logging.WARNING, format=f"{name}: %(message)s")
    try:
        os.nice(CHILD_NICE)
    except OSError:
        pass
    answers = os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    requests = sys.stdin.buffer
    try:
        handler, ready_value = start()
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which raises it
        _answer(answers, ("error", f"{type(exc).__name__}: {exc}"))
        return
    _answer(answers, ("ready", ready_value))
    while True:
        try:
            request = read_frame(requests)
        except EOFError:
            return
        try:
            answer = ("ok", handler(pickle.loads(request)))
        except Exception as exc:  # noqa: BLE001 - reported to the parent
            answer = ("error", f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}")
        _answer(answers, answer)
