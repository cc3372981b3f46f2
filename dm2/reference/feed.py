"""Robot states into the near-net reference, on the programmed clock, in any slicing.

:class:`ReferenceFeed` buffers the robot states a session receives and integrates them into a
:class:`~dm2.reference.model.NearNetReference` on request, up to a stamp and at most so many at a
time. With a toolpath, each state advances the reference's clock along the path it covered
(:mod:`dm2.reference.path_clock`): by the controller's time while the spray spot progresses, but
not while
it stands still (``reference_clock = "executed"``: a dwell or a reorientation stop grows the
part, not the reference), or by the programmed time of the path covered (``"programmed"``,
MonitorConfig's default: every slowdown of the robot grows the part more than the
reference).
The clock is summed one state after the other, so the reference is the
same however the states are sliced. Late or duplicated states cannot rewind
the reference.
"""

from __future__ import annotations

import bisect

import numpy as np

from dm2.core.messages import Toolpath
from dm2.reference.model import NearNetReference
from dm2.reference.path_clock import ToolpathProgress


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
        self._stamps: list[float] = []  # waiting from self._head on, sorted while _sorted
        self._poses: list[np.ndarray] = []
        self._head = 0
        self._sorted = True
        self._last_stamp_s = -np.inf
        self._nominal_s = 0.0
        self.last_T_B_F: np.ndarray | None = None

    def __len__(self) -> int:
        """Robot states waiting."""
        return len(self._stamps) - self._head

    def push(self, stamp_s: float, T_B_F: np.ndarray) -> None:
        if len(self._stamps) > self._head and stamp_s < self._stamps[-1]:
            self._sorted = False  # a late state: sorted (stably) at the next flush
        self._stamps.append(stamp_s)
        self._poses.append(T_B_F)

    def flush(self, upto_s: float = np.inf, max_states: int | None = None) -> bool:
        """Integrate the states stamped up to ``upto_s`` (at most ``max_states`` of them);
        True when none stamped up to ``upto_s`` is left."""
        head = self._head
        if len(self._stamps) == head:
            return True
        if not self._sorted:
            order = np.argsort(np.asarray(self._stamps[head:]), kind="stable") + head
            self._stamps = [self._stamps[i] for i in order]
            self._poses = [self._poses[i] for i in order]
            head = self._head = 0
            self._sorted = True
        n_due = bisect.bisect_right(self._stamps, upto_s, lo=head) - head
        n = n_due if max_states is None else min(n_due, int(max_states))
        if n == 0:
            return True
        stamps = np.array(self._stamps[head: head + n])
        poses = np.stack(self._poses[head: head + n])
        self._head = head + n
        if self._head > 4096 and 2 * self._head > len(self._stamps):  # drop the consumed
            del self._stamps[: self._head], self._poses[: self._head]
            self._head = 0
        keep = np.concatenate([[True], np.diff(stamps) > 0]) & (stamps > self._last_stamp_s)
        if np.any(keep):
            stamps, poses = stamps[keep], poses[keep]
            prev = self._last_stamp_s if np.isfinite(self._last_stamp_s) else stamps[0]
            elapsed = np.diff(np.concatenate([[prev], stamps]))
            self._last_stamp_s = float(stamps[-1])
            self.last_T_B_F = poses[-1]
            if self.progress is not None:  # programmed timing along the executed path
                spots, _ = self.reference.spot_O(poses)
                dt = (self.progress.advance(spots) if self.clock == "programmed" else
                      self.progress.advance(spots, elapsed, self.dwell_speed_mm_s))
                stamps = np.cumsum(np.concatenate([[self._nominal_s], dt]))[1:]
                self._nominal_s = float(stamps[-1])
            self.reference.add_states(stamps, poses)
        return n == n_due
