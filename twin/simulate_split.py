"""How :meth:`twin.simulate.Simulation.messages` shares its work between two threads.

The stream is cut into chunks (:func:`chunk_runs`): motion samples that share a layer and hold
no profile trigger inside. The worker thread deposits a chunk and then casts rays ``0:rays`` of
the profiler fans that end it on the true field; the calling thread yields the chunk's robot
states and casts the remaining rays on a synced mirror. Every ray is cast on its own, so the
messages do not depend on ``rays``: :class:`FanSplit` moves it, chunk by chunk, towards equal
CPU seconds on both threads (the calling thread also does whatever the stream's consumer does
between messages). Without a worker thread (:class:`InlinePool`) the whole fan stays on the
calling thread.
"""

from __future__ import annotations

from concurrent.futures import Future

import numpy as np


class FanSplit:
    """The number of rays of each fan the worker thread casts, balanced on CPU seconds.

    Parameters
    ----------
    n_rays : int, rays per fan
    threaded : bool, whether a worker thread exists (else ``rays`` stays 0)
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
        towards the thread with less work (smoothed over the last few chunks)."""
        if not self.threaded or not self.step_rays:
            return
        self._calling_s = 0.8 * self._calling_s + calling_s
        self._worker_s = 0.8 * self._worker_s + worker_s
        if self._calling_s > self._worker_s:
            self.rays = min(self.rays + self.step_rays, self.n_rays)
        else:
            self.rays = max(self.rays - self.step_rays, 0)


class InlinePool:
    """A pool that runs each task as it is submitted (``scan_thread=False``)."""

    def submit(self, fn, *args) -> Future:
        done: Future = Future()
        done.set_result(fn(*args))
        return done

    def shutdown(self, wait: bool = True, cancel_futures: bool = False) -> None:
        pass


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
