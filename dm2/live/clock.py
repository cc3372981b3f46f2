"""Align each profiler's clock with the robot controller's clock from arrival times.

Live sources stamp messages with their own clocks (controller time for EGM, sensor time for
profiles); the pipeline needs profile stamps on the pose clock. For every profile, the pose
clock's reading at the profile's arrival (interpolated between the pose messages that arrived
just before and after it, in host time) gives one sample of the skew ``profile stamp - pose
stamp``. The estimate is a Theil-Sen line through the last ``window`` samples (median of
pairwise slopes, then the median intercept) evaluated at the profile's stamp, so it follows a
drifting clock without lag, shrugs off arrival jitter and is immune to any scaling of host time
(accelerated rehearsals). While the estimate stays within
``tolerance_s`` the stamps are trusted as they are (a cell with synchronised clocks is passed
through bit for bit); once it leaves that band the sensor's stamps are corrected from then on.

A profile arriving before its sensor has ``min_samples`` skew samples waits (at most
``max_waiting`` per sensor; more count ``clock_unsynced``), unless every sample so far lies
within the tolerance band: stamps inside the band pass unchanged anyway, so the first profiles
of a synchronised cell are not held back (a later estimate outside the band: see below).

An overloaded host reads one socket late while the other keeps up: the pose clock at a
profile's arrival then looks behind or ahead by the lag (times the speed-up of a rehearsal),
which is no skew of the sensor's clock. So once a sensor's stamps have been passed through, an
estimate outside the band engages the correction only if it stays outside for ``confirm_s`` of
host time (a stall of the process lasts milliseconds, a clock offset persists); meanwhile the
stamps still pass unchanged. Before the first release (a clock that is off from the start) the
correction engages at once, as above.
"""

from __future__ import annotations

import bisect
import logging
from collections import deque

import numpy as np
from numba import njit

from dm2.core.messages import Profile
from dm2.core.tolerances import SAME_TIME_S

log = logging.getLogger(__name__)

CONFIRM_S = 1.0  # [s, host clock] an excursion of the skew estimate must last to be corrected
# [s, host clock] a profile arriving longer than this after the newest pose gets no skew sample:
# the pose clock is not read across a gap in the poses (held back by the plausibility gates
# while a clock step is confirmed, or lost), where the newest pose stamp lags the sensor's
READING_HORIZON_S = 0.25


class ClockAligner:
    """Map profile stamps onto the pose clock.

    Parameters
    ----------
    tolerance_s : float [s], skews within this are not corrected
    window : int, skew samples in the running median
    min_samples : int, samples needed before a sensor's profiles are released
    max_waiting : int, profiles held per sensor while waiting for samples
    confirm_s : float [s, host clock], how long an estimate outside the band must last before
        a sensor whose profiles were already passed through is corrected
    """

    def __init__(self, tolerance_s: float = 0.05, window: int = 15, min_samples: int = 3,
                 max_waiting: int = 64, confirm_s: float = CONFIRM_S):
        self.tolerance_s = float(tolerance_s)
        self.window = int(window)
        self.min_samples = int(min_samples)
        self.max_waiting = int(max_waiting)
        self.confirm_s = float(confirm_s)
        self._released: set[str] = set()  # sensors with profiles passed through already
        self._outside_since: dict[str, float] = {}  # arrival [s] the estimate left the band
        self._arr: list[float] = []  # pose arrivals [s, host clock], non-decreasing
        self._stamp: list[float] = []  # their stamps [s, robot clock]
        self._samples: dict[str, deque] = {}
        self._waiting: dict[str, list] = {}
        self.correction_s: dict[str, float] = {}  # applied correction per sensor (0 = none)
        self.engaged: set[str] = set()
        self.dropped: dict[str, int] = {}

    def pose(self, stamp_s: float, arrival_s: float) -> None:
        """Note a pose message's stamp and arrival (host clock)."""
        arr, st = self._arr, self._stamp
        if arr and arrival_s < arr[-1]:
            arrival_s = arr[-1]
        arr.append(arrival_s)
        st.append(stamp_s)
        if len(arr) > 2048:
            del arr[:1024], st[:1024]

    def _pose_clock_at(self, arrival_s: float) -> float | None:
        arr, st = self._arr, self._stamp
        if len(arr) < 2 or arrival_s > arr[-1] + READING_HORIZON_S or arrival_s < arr[0]:
            return None
        i = bisect.bisect_right(arr, arrival_s)
        if i >= len(arr):  # after the newest pose: the newest stamp is the best reading
            return float(max(st[-8:]))
        a0, s0 = arr[i - 1], st[i - 1]
        a1, s1 = arr[i], st[i]
        if a1 <= a0:
            return float(s1)
        return float(s0 + (s1 - s0) * (arrival_s - a0) / (a1 - a0))

    def profile(self, p: Profile, arrival_s: float) -> list[Profile]:
        """Take a profile; return the profiles now released, stamps on the pose clock."""
        sid = p.sensor_id
        ref = self._pose_clock_at(arrival_s)
        samples = self._samples.setdefault(sid, deque(maxlen=self.window))
        if ref is not None:
            samples.append((p.stamp_s, p.stamp_s - ref))
        waiting = self._waiting.setdefault(sid, [])
        if len(samples) < self.min_samples and (
                not samples or sid in self.engaged
                or any(abs(k) > self.tolerance_s for _, k in samples)):
            if len(waiting) >= self.max_waiting:
                self.dropped["clock_unsynced"] = self.dropped.get("clock_unsynced", 0) + 1
            else:
                waiting.append(p)
            return []
        skew = self._estimate(samples, p.stamp_s)
        if sid not in self.engaged and abs(skew) > self.tolerance_s:
            # before the first release a skew is corrected at once; later it must last
            since = self._outside_since.setdefault(sid, arrival_s)
            if sid not in self._released or arrival_s - since >= self.confirm_s:
                self.engaged.add(sid)
                log.warning("clock of %s differs from the robot's by %.3f s: correcting its "
                            "stamps", sid, skew)
        else:
            self._outside_since.pop(sid, None)
        self._released.add(sid)
        corr = skew if sid in self.engaged else 0.0
        self.correction_s[sid] = corr
        out = [self._shift(q, corr) for q in waiting] + [self._shift(p, corr)]
        waiting.clear()
        return out

    @staticmethod
    def _estimate(samples, stamp_s: float) -> float:
        """Theil-Sen skew line through ``(stamp, skew)`` samples, evaluated at ``stamp_s``."""
        s = np.array(samples, dtype=np.float64)
        return float(_theil_sen_at(s[:, 0], s[:, 1], float(stamp_s)))

    @staticmethod
    def _shift(p: Profile, corr: float) -> Profile:
        if corr == 0.0:
            return p
        stamp = p.stamp_s - corr
        if stamp < 0:
            stamp = 0.0
        return Profile(p.sensor_id, stamp, p.counter, p.xz_S, p.valid, p.intensity)

    def flush(self) -> list[Profile]:
        """Release every waiting profile with the correction known now (end of the stream)."""
        out = []
        for sid, waiting in self._waiting.items():
            corr = self.correction_s.get(sid, 0.0)
            out.extend(self._shift(q, corr) for q in waiting)
            waiting.clear()
        return out


@njit(cache=True)
def _theil_sen_at(t, k, stamp_s):
    """Theil-Sen line through ``(t, k)`` (median pairwise slope over pairs more than 1 ns
    apart, 0 without any; then the median intercept) evaluated at ``stamp_s``."""
    n = t.shape[0]
    slopes = np.empty(n * (n - 1) // 2)
    m = 0
    for i in range(n):
        for j in range(i + 1, n):
            dt = t[j] - t[i]
            if dt > SAME_TIME_S:
                slopes[m] = (k[j] - k[i]) / dt
                m += 1
    slope = np.median(slopes[:m]) if m else 0.0
    return np.median(k + slope * (stamp_s - t))
