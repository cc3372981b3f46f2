"""The bounded queue between the live sources (threads) and the pipeline, with drop counters.

Every source puts ``(message, source name, arrival time [s, monotonic])`` items; a full queue
never blocks a socket thread: the message is dropped and counted as ``queue_full``. Sources
count their own transport-level drops here too, so one :attr:`Inbox.dropped` holds them all.

The live loop takes items without ever waiting on a lock while items are queued: the queue is a
``collections.deque`` (appends and pops are atomic), and the event that wakes an idle loop is
only touched when the loop found the queue empty. A ``queue.Queue`` takes a mutex on every get
and put; when a socket thread was switched out holding it, the loop had to give up the
interpreter lock and then wait up to a switch interval to get it back.
"""

from __future__ import annotations

import threading
import time
from collections import Counter, deque

DEFAULT_QUEUE_SIZE = 20000


class Inbox:
    """Thread-safe bounded queue plus a drop counter by reason (one consumer).

    Parameters
    ----------
    maxsize : int, messages held at most (each concurrent source may add one more while
        another is being counted); further ones count ``queue_full``
    """

    def __init__(self, maxsize: int = DEFAULT_QUEUE_SIZE):
        if maxsize <= 0:
            raise ValueError(f"Inbox: maxsize must be positive, got {maxsize}")
        self.maxsize = int(maxsize)
        self._items: deque = deque()
        self._nonempty = threading.Event()
        self._lock = threading.Lock()
        self._dropped: Counter = Counter()
        self.accepted = 0

    def put(self, msg, source: str, arrival_s: float) -> bool:
        """Queue one message; False (and ``queue_full`` counted) when the queue is full."""
        if len(self._items) >= self.maxsize:
            self.drop("queue_full")
            return False
        self._items.append((msg, source, arrival_s))
        if not self._nonempty.is_set():  # the consumer may be waiting
            self._nonempty.set()
        with self._lock:
            self.accepted += 1
        return True

    def drop(self, reason: str, n: int = 1) -> None:
        with self._lock:
            self._dropped[reason] += int(n)

    def get(self, timeout_s: float | None = None):
        """Next ``(msg, source, arrival_s)`` or None after ``timeout_s`` without one."""
        items = self._items
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            try:
                return items.popleft()
            except IndexError:
                pass
            remaining = None if deadline is None else deadline - time.monotonic()
            if remaining is not None and remaining <= 0:
                return None
            self._nonempty.clear()
            if items:  # put between the pop and the clear
                continue
            self._nonempty.wait(remaining)

    def qsize(self) -> int:
        return len(self._items)

    @property
    def dropped(self) -> dict[str, int]:
        with self._lock:
            return {k: int(v) for k, v in self._dropped.items() if v}
