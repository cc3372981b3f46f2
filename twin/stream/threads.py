"""How :meth:`twin.stream.simulate.Simulation.messages` shares its work between two threads.

The stream is cut into chunks (:func:`chunk_runs`): motion samples that share a layer and hold
no profile trigger inside. The worker thread (:class:`ChunkWorker`) runs a few chunks ahead:
it deposits a chunk, casts rays ``0:rays`` of the profiler fans that end it on the true field
(measuring them into profiles too when that is the whole fan) and hands over the cells the chunk
changed; the calling thread yields the chunk's robot states,
applies the changes to its mirror of the field and casts the remaining rays there. Every ray is
cast on its own, so the messages do not depend on ``rays``: :class:`FanSplit` moves it, chunk
by chunk, towards equal CPU seconds on both threads (the calling thread also does whatever the
stream's consumer does between messages). Without a worker thread, the calling thread
produces each chunk when it needs it and casts whole fans on the true field itself.
"""

from __future__ import annotations

import queue
import threading

import numpy as np

# per chunk, the CPU seconds each thread spent so far are scaled by this before a chunk's are
# added: about 30 chunks (a second of process) decide where the rays go. At 0.8 (5 chunks) the
# share swung with single chunks (a layer's end on the calling thread), and the calling thread,
# the busier one over a run, cast and measured whole fans' remainders in 35-43 % of the chunks
# of a 600 s tower slice; at 0.97 in 15-33 %, with 3-9 % less CPU on the calling thread
BALANCE_DECAY = 0.97


class FanSplit:
    """The number of rays of each fan the worker thread casts, balanced on CPU seconds.

    Parameters
    ----------
    n_rays : int, rays per fan
    threaded : bool, whether a worker thread exists (else ``rays`` stays 0: the calling
        thread casts whole fans)
    share : float, the worker's starting share of a fan
    step_rays : int, rays moved per chunk towards balance (0: the share stays)
    """

    def __init__(self, n_rays: int, threaded: bool, share: float = 0.3, step_rays: int = 8):
        if not 0.0 <= share <= 1.0:
            raise ValueError(f"FanSplit: share must lie in [0, 1], got {share}")
        self.n_rays = int(n_rays)
        self.threaded = bool(threaded)
        self.rays = int(round(share * self.n_rays)) if threaded else 0
        self.step_rays = int(step_rays)
        self._calling_s = 0.0
        self._worker_s = 0.0

    def balance(self, calling_s: float, worker_s: float) -> None:
        """Account one chunk's CPU seconds [s] of both threads and move ``rays`` by a step
        towards the thread with less work (smoothed over about 30 chunks:
        ``BALANCE_DECAY``)."""
        if not self.threaded or not self.step_rays:
            return
        self._calling_s = BALANCE_DECAY * self._calling_s + calling_s
        self._worker_s = BALANCE_DECAY * self._worker_s + worker_s
        if self._calling_s > self._worker_s:
            self.rays = min(self.rays + self.step_rays, self.n_rays)
        else:
            self.rays = max(self.rays - self.step_rays, 0)


class ChunkWorker:
    """Runs ``produce(c)`` for chunks ``c = 0 .. n - 1`` in order, on a worker thread that
    keeps up to ``depth`` results ahead of the consumer (``threaded``), or on the calling
    thread when :meth:`result` asks for them.

    :meth:`result` must be asked for ``c = 0, 1, 2, ...`` in turn; it re-raises the worker's
    exception. :meth:`close` stops the worker (after the chunk it is producing) and waits for
    it.
    """

    def __init__(self, produce, n: int, threaded: bool, depth: int = 8,
                 name: str = "twin-worker"):
        self.produce = produce
        self.n = int(n)
        self.threaded = bool(threaded)
        self._next = 0
        if self.threaded:
            self._queue: queue.Queue = queue.Queue(maxsize=max(int(depth), 1))
            self._stop = threading.Event()
            self._thread = threading.Thread(target=self._run, name=name, daemon=True)
            self._thread.start()

    def _run(self) -> None:
        try:
            for c in range(self.n):
                if self._stop.is_set() or not self._put((True, self.produce(c))):
                    return
        except BaseException as exc:  # handed to the consumer, which re-raises it
            self._put((False, exc))

    def _put(self, item) -> bool:
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def result(self, c: int):
        """The result of chunk ``c`` (the next one not yet taken)."""
        if c != self._next:
            raise ValueError(f"ChunkWorker: chunk {c} asked for, {self._next} is next")
        self._next += 1
        if not self.threaded:
            return self.produce(c)
        ok, value = self._queue.get()
        if not ok:
            raise value
        return value

    def close(self) -> None:
        if self.threaded:
            self._stop.set()
            self._thread.join()


def chunk_runs(t_s: np.ndarray, layer: np.ndarray, trig_s: np.ndarray):
    """Runs ``[a, b)`` of motion samples that share a layer and hold no profile trigger inside.

    A trigger at ``trig_s`` is answered right after the last sample at or before it (the first
    sample when it precedes them all), and a layer change starts a new run, so each run's
    robot states, then its deposition, then the triggers it ends with, keep the stream's order
    and every profile sees the surface exactly as it stands at its stamp.
    """
    n = t_s.size
    after = np.maximum(np.searchsorted(t_s, trig_s, side="right") - 1, 0)
    cuts = np.concatenate([after + 1, np.flatnonzero(np.diff(layer)) + 1, [n]])
    cuts = np.unique(cuts[(cuts > 0) & (cuts <= n)])
    a = 0
    for b in cuts.tolist():
        yield a, b
        a = b
