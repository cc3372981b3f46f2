"""One worker thread that runs a session's per-layer jobs in submission order.

A live session hands each finished layer (meshing its surface, deviation, segmentation,
tracking) to :class:`LayerWorker` so the fusion thread goes straight back to the next
profiles. Jobs run one after the other, in the order submitted, so the results are those of
running them inline. The first failure stops further jobs and is re-raised in the submitting
thread at the next :meth:`LayerWorker.submit` or at :meth:`LayerWorker.join`.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable

log = logging.getLogger(__name__)


class LayerWorker:
    """Run ``fn(*job)`` for every submitted job on one daemon thread, in order.

    Parameters
    ----------
    fn : the job function
    name : the thread's name
    """

    def __init__(self, fn: Callable, name: str = "layer-analysis"):
        self.fn = fn
        self.name = name
        self._jobs: queue.Queue = queue.Queue()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def submit(self, *job) -> None:
        """Queue one job (starts the thread on first use); re-raises an earlier failure."""
        self._raise()
        if self._thread is None:
            self._thread = threading.Thread(target=self._work, name=self.name, daemon=True)
            self._thread.start()
        self._jobs.put(job)

    @property
    def busy(self) -> bool:
        """A submitted job has not finished yet."""
        return self._jobs.unfinished_tasks > 0

    def join(self) -> None:
        """Wait until every queued job has run; re-raises a failure."""
        if self._thread is not None:
            self._jobs.put(None)
            self._thread.join()
            self._thread = None
        self._raise()

    def _raise(self) -> None:
        if self._error is not None:
            raise RuntimeError(f"{self.name} failed on its worker thread") from self._error

    def _work(self) -> None:
        while True:
            job = self._jobs.get()
            try:
                if job is None:
                    return
                if self._error is None:
                    try:
                        self.fn(*job)
                    except BaseException as exc:  # noqa: BLE001 - re-raised in the feeder
                        log.exception("%s: a job failed", self.name)
                        self._error = exc
            finally:
                self._jobs.task_done()
