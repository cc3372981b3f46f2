"""Stream synchronisation: reorder window, pose interpolation at profile stamps, drop counting.

The stream is never trusted to be ordered or complete. Robot states go into a time-sorted pose
buffer as they arrive; profiles and layer marks wait in a heap ordered by stamp and are released
in stamp order as soon as the pose buffer reaches past their stamp, or at the latest when the
newest stamp seen is ``reorder_window_s`` beyond them. A layer mark also waits until every
profiler heard from so far has sent a profile stamped at or after it (the profiles travel on
other links than the robot states, and a profile stamped before the mark belongs to the layer
the mark ends), at the latest until the window has passed it. Poses are interpolated (SLERP
rotation, linear translation) between the two robot states that bracket a profile's stamp, only
if those are at most ``max_pose_gap_s`` apart.

Drop reasons (``StreamSync.dropped``; message counts unless marked as points):

``bad_message``      not a Profile / RobotState / LayerMark
``unknown_sensor``   profile from a sensor the calibration does not know
``late_message``     stamp older than the newest stamp seen minus ``reorder_window_s``
``duplicate_counter`` a profile whose (sensor, counter) was already received
``duplicate_stamp``  a profile without counter (rosbag2) whose (sensor, stamp) was already received
``duplicate_state``  a robot state with the stamp of one already buffered
``duplicate_mark``   a layer mark for a layer already marked
``nan_points``       points (not profiles) flagged valid whose coordinates are not finite
``empty_profile``    a profile without any valid finite point
``pose_gap``         a profile whose stamp is not bracketed by poses within ``max_pose_gap_s``
"""

from __future__ import annotations

import heapq
import logging
from collections import Counter
from dataclasses import dataclass

import numpy as np
from numba import njit

from dm2.core.messages import LayerMark, Profile, RobotState
from dm2.fusion.posebuffer import PoseBuffer

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SyncedProfile:
    """A profile with its usable points and the flange pose interpolated at its stamp.

    Attributes
    ----------
    profile : the original message
    xz_S : (k, 2) float64 [mm], valid finite points only
    T_B_F : (4, 4) float64, flange pose at ``profile.stamp_s``
    """

    profile: Profile
    xz_S: np.ndarray
    T_B_F: np.ndarray


class StreamSync:
    """Reorders a message stream and attaches interpolated poses to profiles.

    Parameters
    ----------
    sensor_ids : sensors the calibration knows
    max_pose_gap_s : float [s], largest robot-state gap to interpolate across
    reorder_window_s : float [s], how late a message may arrive and still be used
    """

    def __init__(self, sensor_ids, max_pose_gap_s: float = 0.05, reorder_window_s: float = 0.5):
        self.sensor_ids = frozenset(sensor_ids)
        self.max_pose_gap_s = float(max_pose_gap_s)
        self.reorder_window_s = float(reorder_window_s)
        self.poses = PoseBuffer(horizon_s=max(2.0, 4 * (reorder_window_s + max_pose_gap_s)))
        self.dropped: Counter = Counter()
        self.watermark_s = -np.inf
        self._heap: list = []
        self._tie = 0
        self._seen_counters: dict[str, dict[int, float]] = {s: {} for s in self.sensor_ids}
        self._seen_stamps: dict[str, dict[float, float]] = {s: {} for s in self.sensor_ids}
        self._marked_layers: set[int] = set()
        self._newest_profile_s: dict[str, float] = {}  # per sensor, of the accepted profiles

    def push(self, msg) -> list:
        """Take one message; return what became ready: ``SyncedProfile`` and ``LayerMark``
        items in stamp order."""
        if type(msg) is RobotState or isinstance(msg, RobotState):
            stamp = msg.stamp_s
            if stamp < self.watermark_s - self.reorder_window_s:
                self.dropped["late_message"] += 1
                return []
            if not self.poses.add(stamp, msg.T_B_F):
                self.dropped["duplicate_state"] += 1
                return []
            if stamp > self.watermark_s:
                self.watermark_s = stamp
            if not self._heap:
                return []
            return self._release_if_ready()
        if isinstance(msg, Profile):
            if not self._accept_profile(msg):
                return []
        elif isinstance(msg, LayerMark):
            if msg.stamp_s < self.watermark_s - self.reorder_window_s:
                self.dropped["late_message"] += 1
                return []
            if msg.layer in self._marked_layers:
                self.dropped["duplicate_mark"] += 1
                return []
            self._marked_layers.add(msg.layer)
        else:
            self.dropped["bad_message"] += 1
            log.debug("StreamSync: ignoring %s", type(msg).__name__)
            return []
        heapq.heappush(self._heap, (msg.stamp_s, self._tie, msg))
        self._tie += 1
        self._advance(msg.stamp_s)
        return self._release_if_ready()

    def flush(self) -> list:
        """Release everything still waiting (end of stream)."""
        return self._release(final=True)

    @property
    def pending(self) -> int:
        return len(self._heap)

    def _advance(self, stamp_s: float) -> None:
        if stamp_s > self.watermark_s:
            self.watermark_s = stamp_s

    def _accept_profile(self, p: Profile) -> bool:
        if p.sensor_id not in self.sensor_ids:
            self.dropped["unknown_sensor"] += 1
            return False
        if p.stamp_s < self.watermark_s - self.reorder_window_s:
            self.dropped["late_message"] += 1
            return False
        if p.counter is None:  # no counter in the source: (sensor, stamp) identifies it
            seen = self._seen_stamps[p.sensor_id]
            if p.stamp_s in seen:
                self.dropped["duplicate_stamp"] += 1
                return False
            seen[p.stamp_s] = p.stamp_s
        else:
            seen = self._seen_counters[p.sensor_id]
            if p.counter in seen:
                self.dropped["duplicate_counter"] += 1
                return False
            seen[p.counter] = p.stamp_s
        if p.stamp_s > self._newest_profile_s.get(p.sensor_id, -np.inf):
            self._newest_profile_s[p.sensor_id] = p.stamp_s
        if len(seen) > 4096:  # forget counters far outside the window (24-bit counters wrap)
            horizon = self.watermark_s - 10 * (self.reorder_window_s + 1.0)
            for c in [c for c, t in seen.items() if t < horizon]:
                del seen[c]
        return True

    def _release_if_ready(self) -> list:
        first = self._heap[0][0]
        if first > self.poses.latest_s and first > self.watermark_s - self.reorder_window_s:
            return []  # the first waiting item is neither covered nor due: nothing to do
        return self._release(final=False)

    def _release(self, final: bool) -> list:
        """Pop waiting messages in stamp order: a profile as soon as two poses within the gap
        bracket it, a layer mark once the poses and every profiler heard from are past it; at
        the latest when the window has passed it (a profile then possibly as pose_gap)."""
        ready = []
        limit = self.watermark_s - self.reorder_window_s
        heap = self._heap
        while heap:
            stamp, _, msg = heap[0]
            due = final or stamp <= limit
            if isinstance(msg, LayerMark):
                profiles_past = all(t >= stamp for t in self._newest_profile_s.values())
                if not (due or (self.poses.covers(stamp) and profiles_past)):
                    break
                ready.append(heapq.heappop(heap)[2])
                continue
            if not (due or self.poses.covers(stamp)):
                break
            T, ok = self.poses.pose_at(stamp, self.max_pose_gap_s)
            if not (ok or due):
                break  # a missing robot state may still arrive within the window
            heapq.heappop(heap)
            item = self._synced(msg, T, ok)
            if item is not None:
                ready.append(item)
        return ready

    def _synced(self, p: Profile, T_B_F: np.ndarray, pose_ok: bool) -> SyncedProfile | None:
        xz, n_nan = _usable_points(p.xz_S, p.valid)
        if n_nan:
            self.dropped["nan_points"] += n_nan
        if not xz.shape[0]:
            self.dropped["empty_profile"] += 1
            return None
        if not pose_ok:
            self.dropped["pose_gap"] += 1
            return None
        return SyncedProfile(p, xz, T_B_F)


@njit(cache=True, nogil=True)
def _usable_points(xz_S, valid):
    """Valid finite points ``(k, 2)`` of a profile and the number flagged valid but not finite."""
    out = np.empty_like(xz_S)
    k = 0
    n_nan = 0
    for i in range(xz_S.shape[0]):
        if valid[i]:
            x, z = xz_S[i, 0], xz_S[i, 1]
            if np.isfinite(x) and np.isfinite(z):
                out[k, 0] = x
                out[k, 1] = z
                k += 1
            else:
                n_nan += 1
    return out[:k], n_nan
