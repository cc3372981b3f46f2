"""One stream per sensor: which connection a sensor's profiles come from, and their counters.

A live cell has one bridge (or one scanCONTROL source) per profiler. :class:`StreamGuard` sees
every inbox item before the plausibility gates, in O(1) per message:

``duplicate_source`` (dropped)
    A profile for a sensor that already has a live stream, arriving on another connection.
    The first stream is kept. Only when the owning connection has closed (a bridge whose link
    dropped and that reconnected), or has sent nothing for that sensor for ``handover_s`` of
    host time (a bridge that restarted), does the new connection take the sensor over (logged).

``counter_jump`` / ``counter_backwards`` (counted, not dropped)
    On the owning stream, a counter more than :data:`COUNTER_JUMP` ahead of the previous one
    (modulo :data:`~dm2.core.messages.COUNTER_MODULO`), or behind it. Such frames are real
    frames of the one stream the sensor has: a run of lost frames or a restarted sensor makes a
    jump, a bridge that resends a buffered frame a step back. Dropping them would lose the rest
    of a restarted sensor's run. What must not be fused is handled where it can be told: a
    second connection here, a counter received twice (``duplicate_counter``, in sync), a stamp
    the host clock disagrees with (``implausible_stamp``, in the gates). The counter then
    continues from the new value, so a restart counts once.

:attr:`received` counts each stream's messages (``robot`` and each sensor) on its own
connection; the run's verdict takes the lost share of each stream from it.
"""

from __future__ import annotations

import logging
from collections import Counter

from dm2.core.messages import COUNTER_MODULO, Profile, RobotState

log = logging.getLogger(__name__)

COUNTER_JUMP = 1000  # counters skipped at most before a frame counts ``counter_jump``
HALF = COUNTER_MODULO // 2


class StreamGuard:
    """Stream ownership per sensor and counter continuity (see the module docstring).

    Parameters
    ----------
    handover_s : float [s, host clock], how long a sensor's stream must be silent before
        another connection may take it over
    """

    def __init__(self, handover_s: float = 1.0):
        self.handover_s = float(handover_s)
        self.dropped: Counter = Counter()  # duplicate_source
        self.counters: Counter = Counter()  # counter_jump, counter_backwards
        self.received: Counter = Counter()  # per stream: "robot", "S1", ...
        self.intruders: Counter = Counter()  # (sensor, source) -> frames dropped
        self._owner: dict[str, list] = {}  # sensor -> [source, last arrival]
        self._counter: dict[str, int] = {}
        self._closed: set[str] = set()  # sources whose connection has closed

    def source_closed(self, source: str) -> None:
        """The connection ``source`` has closed (called from a listener's thread)."""
        self._closed.add(source)

    def admit(self, msg, source: str, arrival_s: float) -> bool:
        """Whether ``msg`` (from ``source``, arrived at ``arrival_s``) goes on."""
        if isinstance(msg, RobotState):
            self.received["robot"] += 1
            return True
        if not isinstance(msg, Profile):
            return True
        sid = msg.sensor_id
        own = self._owner.get(sid)
        if own is None:
            self._owner[sid] = [source, arrival_s]
        elif own[0] != source:
            if own[0] not in self._closed and arrival_s - own[1] <= self.handover_s:
                self.dropped["duplicate_source"] += 1
                if not self.intruders[(sid, source)]:
                    log.warning("a second source (%s) sends frames for %s, which already "
                                "streams from %s: its frames are dropped", source, sid, own[0])
                self.intruders[(sid, source)] += 1
                return False
            log.info("%s: the stream from %s ended (closed, or silent for %.1f s); %s takes "
                     "it over", sid, own[0], arrival_s - own[1], source)
            own[0] = source
            self._counter.pop(sid, None)
        self._owner[sid][1] = arrival_s
        self.received[sid] += 1
        last = self._counter.get(sid)
        c = int(msg.counter)
        if last is not None:
            d = (c - last) % COUNTER_MODULO
            if d > HALF:
                self.counters["counter_backwards"] += 1
            elif d > COUNTER_JUMP:
                self.counters["counter_jump"] += 1
        self._counter[sid] = c
        return True

    def report(self) -> dict:
        """The streams for report.json: each sensor's source, the duplicate sources and their
        dropped frames, and the counter anomalies."""
        return {"sources": {sid: own[0] for sid, own in sorted(self._owner.items())},
                "duplicate_sources": [{"sensor": sid, "source": src, "frames_dropped": n}
                                      for (sid, src), n in sorted(self.intruders.items())],
                "counters": dict(self.counters)}
