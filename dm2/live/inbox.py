"""The bounded queue between the live sources (threads) and the pipeline, with drop counters.

Every source puts ``(message, source name, arrival time [s, monotonic])`` items; a full queue
never blocks a socket thread: the message is dropped and counted as ``queue_full``. Sources
count their own transport-level drops here too, so one :attr:`Inbox.dropped` holds them all.
"""

from __future__ import annotations

import queue
import threading
from collections import Counter

DEFAULT_QUEUE_SIZE = 20000


class Inbox:
    """Thread-safe bounded queue plus a drop counter by reason.

    Parameters
    ----------
    maxsize : int, messages held at most; further ones count ``queue_full``
    """

    def __init__(self, maxsize: int = DEFAULT_QUEUE_SIZE):
        if maxsize <= 0:
            raise ValueError(f"Inbox: maxsize must be positive, got {maxsize}")
        self._q: queue.Queue = queue.Queue(maxsize=int(maxsize))
        self._lock = threading.Lock()
        self._dropped: Counter = Counter()
        self.accepted = 0

    def put(self, msg, source: str, arrival_s: float) -> bool:
        """Queue one message; False (and ``queue_full`` counted) when the queue is full."""
        try:
            self._q.put_nowait((msg, source, arrival_s))
        except queue.Full:
            self.drop("queue_full")
            return False
        with self._lock:
            self.accepted += 1
        return True

    def drop(self, reason: str, n: int = 1) -> None:
        with self._lock:
            self._dropped[reason] += int(n)

    def get(self, timeout_s: float | None = None):
        """Next ``(msg, source, arrival_s)`` or None after ``timeout_s`` without one."""
        try:
            return self._q.get(timeout=timeout_s)
        except queue.Empty:
            return None

    def qsize(self) -> int:
        return self._q.qsize()

    @property
    def dropped(self) -> dict[str, int]:
        with self._lock:
            return {k: int(v) for k, v in self._dropped.items() if v}
