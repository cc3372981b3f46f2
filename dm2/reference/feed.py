"""Robot states into the near-net reference, on the path clock, in any slicing.

:class:`ReferenceFeed` buffers the robot states a session receives and integrates them into a
:class:`~dm2.reference.model.NearNetReference` on request, up to a stamp and at most so many at a
time. With a toolpath, each state advances the reference's clock along the path it covered
(:mod:`dm2.reference.path_clock`): by the controller's time while the spray spot progresses, but
not while it stands still (``reference_clock = "executed"``, MonitorConfig's default: a dwell or
a reorientation stop grows the part, not the reference), or by the programmed time of the path
covered (``"programmed"``: every slowdown of the robot grows the part more than the reference).
The clock is summed one state after the other, so the reference is the same however the states
are sliced. Late or duplicated states cannot rewind the reference.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from dm2.core.messages import Toolpath
from dm2.reference.model import NearNetReference
from dm2.reference.path_clock import ToolpathProgress


@njit(cache=True, nogil=True)
def fresh_states(stamps, last_stamp_s):
    """Which of a batch's states to integrate, and the controller time into each.

    A state counts when it is later than the state before it in the batch and than the last
    one integrated (``last_stamp_s``, -inf before any): late or duplicated states cannot
    rewind the reference. Returns the kept indices and, per kept state, the time since the
    previously kept one (0 for the very first state of the stream)."""
    n = stamps.shape[0]
    kept = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        if (i == 0 or stamps[i] - stamps[i - 1] > 0) and stamps[i] > last_stamp_s:
            kept[m] = i
            m += 1
    elapsed = np.empty(m)
    prev = last_stamp_s if m == 0 or np.isfinite(last_stamp_s) else stamps[kept[0]]
    for j in range(m):
        t = stamps[kept[j]]
        elapsed[j] = t - prev
        prev = t
    return kept[:m], elapsed


INITIAL_CAPACITY = 4096  # robot states the buffers hold before they first make room


class ReferenceFeed:
    """Buffered robot states -> :class:`NearNetReference`.

    Parameters
    ----------
    reference : the reference to grow
    toolpath : the programmed toolpath, or None (then the controller's clock, dwells included)
    clock : ``"executed"`` or ``"programmed"`` (see the module docstring)
    dwell_speed_mm_s : [mm/s] progress slower than this counts as standing still
    """

    def __init__(self, reference: NearNetReference, toolpath: Toolpath | None = None,
                 clock: str = "programmed", dwell_speed_mm_s: float = 1.0):
        if clock not in ("executed", "programmed"):
            raise ValueError(f"ReferenceFeed: unknown clock {clock!r}")
        self.reference = reference
        self.clock = clock
        self.dwell_speed_mm_s = float(dwell_speed_mm_s)
        self.progress = ToolpathProgress(toolpath) if toolpath is not None else None
        # the states waiting are rows _head:_count, sorted while _sorted
        self._stamps = np.empty(INITIAL_CAPACITY)
        self._poses = np.empty((INITIAL_CAPACITY, 4, 4))
        self._head = 0
        self._count = 0
        self._sorted = True
        self._last_stamp_s = -np.inf
        self._nominal_s = 0.0
        self.last_T_B_F: np.ndarray | None = None

    def __len__(self) -> int:
        """Robot states waiting."""
        return self._count - self._head

    def push(self, stamp_s: float, T_B_F: np.ndarray) -> None:
        n = self._count
        if n > self._head and stamp_s < self._stamps[n - 1]:
            self._sorted = False  # a late state: sorted (stably) at the next flush
        if n == self._stamps.shape[0]:
            self._make_room()
            n = self._count
        self._stamps[n] = stamp_s
        self._poses[n] = T_B_F
        self._count = n + 1

    def _make_room(self) -> None:
        """Drop the consumed rows; double the buffers when more than half of them wait."""
        head, n = self._head, self._count
        if 2 * (n - head) > self._stamps.shape[0]:
            stamps = np.empty(2 * self._stamps.shape[0])
            poses = np.empty((stamps.shape[0], 4, 4))
        else:
            stamps, poses = self._stamps, self._poses
        stamps[: n - head] = self._stamps[head:n]
        poses[: n - head] = self._poses[head:n]
        self._stamps, self._poses = stamps, poses
        self._head, self._count = 0, n - head

    def flush(self, upto_s: float = np.inf, max_states: int | None = None) -> bool:
        """Integrate the states stamped up to ``upto_s`` (at most ``max_states`` of them);
        True when none stamped up to ``upto_s`` is left."""
        head, end = self._head, self._count
        if end == head:
            return True
        if not self._sorted:
            order = np.argsort(self._stamps[head:end], kind="stable") + head
            self._stamps[head:end] = self._stamps[order]
            self._poses[head:end] = self._poses[order]
            self._sorted = True
        n_due = int(np.searchsorted(self._stamps[head:end], upto_s, side="right"))
        n = n_due if max_states is None else min(n_due, int(max_states))
        if n == 0:
            return True
        stamps = self._stamps[head: head + n].copy()  # (the rows are reused once consumed)
        poses = self._poses[head: head + n].copy()
        self._head = head + n
        kept, elapsed = fresh_states(stamps, self._last_stamp_s)
        if kept.size:
            stamps, poses = stamps[kept], poses[kept]
            self._last_stamp_s = float(stamps[-1])
            self.last_T_B_F = poses[-1]
            if self.progress is not None:  # programmed timing along the executed path
                spots, _ = self.reference.spot_O(poses)
                dt = (self.progress.advance(spots) if self.clock == "programmed" else
                      self.progress.advance(spots, elapsed, self.dwell_speed_mm_s))
                stamps = np.cumsum(np.concatenate([[self._nominal_s], dt]))[1:]
                self._nominal_s = float(stamps[-1])
            self.reference.add_states(stamps, poses, checked=True)
        return n == n_due
