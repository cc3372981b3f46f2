"""Progress along the programmed toolpath, and the deposition time it is worth.

The near-net reference (paper section 6.1) integrates the Gaussian deposition along the path the
robot executes at the nominal process (feed, efficiency). Robot states tell where the spray spot
is; this module turns them into path progress ``s`` [mm] along the toolpath polyline and into
deposition time, in one of two clocks:

- executed: the controller's time between states, except that progress slower than
  ``dwell_speed_mm_s`` counts as standing still. The acceleration at raster turns and corner
  blends is part of the program's real execution and is in the reference; a robot that stops
  and keeps spraying (an extra dwell, a reorientation stop at a tilted corner) grows the real
  part but not the reference — that is the corner overbuild of the paper's experiments 3 and 4.
  A reference on the raw controller clock would grow the same bump and hide the defect.
- programmed: path length over the programmed speed (``ds / v_programmed``), as if
  the robot held its programmed speed everywhere; every slowdown then shows as overbuild.

Progress only advances (a running maximum), so standing still, jitter of the reported pose and
small back-and-forth add no time.

The search is local: each spot is matched within ``window_mm`` ahead of (and a little behind)
the current progress, so crossings of the path with itself (crosshatch layers, contours meeting
infill ends) never make progress jump. A spot farther than ``lock_mm`` from the path there
(approach moves, a gap in the stream) re-locks on the globally nearest path point.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from scipy.spatial import cKDTree

from dm2.core.messages import Toolpath


@njit(cache=True, nogil=True)
def _advance(points, arc, speed, spots, k, s, back, ahead, lock2, ds_out, v_out):
    """Match spots in order; fills the path progress ``ds_out`` [mm] of each spot and the
    programmed speed ``v_out`` [mm/s] where it is; returns (matched count, k, s).

    Stops at the first spot farther than ``sqrt(lock2)`` from the path near ``k``."""
    n = points.shape[0]
    for i in range(spots.shape[0]):
        lo = max(k - back, 0)
        hi = min(k + ahead, n - 1)
        best, best_d2 = k, 1e300
        for j in range(lo, hi + 1):
            dx = points[j, 0] - spots[i, 0]
            dy = points[j, 1] - spots[i, 1]
            dz = points[j, 2] - spots[i, 2]
            d2 = dx * dx + dy * dy + dz * dz
            if d2 < best_d2:
                best_d2 = d2
                best = j
        if best_d2 > lock2:
            return i, k, s
        ds = 0.0
        t = 0.0
        if arc[best] > s:
            # the stretch passed, and its programmed time at each piece's programmed speed
            for j in range(k, best):
                t += (arc[j + 1] - arc[j]) / speed[j + 1]
            ds = arc[best] - s
            s = arc[best]
            k = best
        ds_out[i] = ds
        v_out[i] = ds / t if t > 0.0 else speed[k]
    return spots.shape[0], k, s


@njit(cache=True, nogil=True)
def _executed_time(ds, elapsed, dwell_speed, acc):
    """Credit the controller's time accumulated since the last progress when progress is made,
    at most ``ds / dwell_speed`` (the resampled path advances in steps, so slow motion shows as
    a few states without progress and then a step); returns (time (m,), carried time)."""
    out = np.zeros(ds.shape[0])
    for i in range(ds.shape[0]):
        acc += elapsed[i]
        if ds[i] > 0.0:
            out[i] = min(acc, ds[i] / dwell_speed)
            acc = 0.0
    return out, acc


class ToolpathProgress:
    """Track the spray spot along a toolpath; convert motion into nominal process time.

    Parameters
    ----------
    toolpath : the programmed toolpath (positions in ``O``, speeds per move)
    spacing_mm : float [mm], resampling step of the polyline (the progress resolution)
    window_mm : float [mm], how far ahead of the current progress a spot is searched
    lock_mm : float [mm], a spot farther than this from the path re-locks globally
    """

    def __init__(self, toolpath: Toolpath, spacing_mm: float = 0.1, window_mm: float = 5.0,
                 lock_mm: float = 1.0):
        if len(toolpath) < 2:
            raise ValueError("ToolpathProgress: the toolpath needs at least two points")
        p = toolpath.position_O
        seg = np.diff(p, axis=0)
        seg_len = np.linalg.norm(seg, axis=1)
        steps = np.maximum(np.ceil(seg_len / spacing_mm).astype(np.int64), 1)
        seg_idx = np.repeat(np.arange(len(seg)), steps)
        frac = (np.arange(steps.sum()) - np.repeat(np.cumsum(steps) - steps, steps)) / \
            np.repeat(steps, steps)
        self.points_O = np.ascontiguousarray(np.vstack([p[seg_idx] + seg[seg_idx] *
                                                        frac[:, None], p[-1:]]))
        seg_start = np.concatenate([[0.0], np.cumsum(seg_len)])
        self.arc_mm = np.concatenate([seg_start[seg_idx] + seg_len[seg_idx] * frac,
                                      seg_start[-1:]])
        # the speed of the move a point lies on (the programmed speed into its end vertex)
        self.speed_mm_s = np.concatenate([toolpath.speed_mm_s[seg_idx + 1],
                                          toolpath.speed_mm_s[-1:]]).astype(np.float64)
        self._tree = cKDTree(self.points_O)
        self._back = max(int(round(1.0 / spacing_mm)), 1)
        self._ahead = max(int(round(window_mm / spacing_mm)), 2)
        self._lock2 = float(lock_mm) ** 2
        self.index = -1
        self.s_mm = 0.0
        self.relocks = 0
        self._waiting_s = 0.0  # executed clock: controller time since the last progress

    def advance(self, spots_O: np.ndarray, elapsed_s: np.ndarray | None = None,
                dwell_speed_mm_s: float = 1.0) -> np.ndarray:
        """Nominal seconds ``(m,)`` the spray spends reaching each of ``spots_O (m, 3)`` [mm].

        Without ``elapsed_s``: the programmed time of the path covered (distance over the
        programmed speed). With ``elapsed_s (m,)`` [s], the controller's time since the previous
        state: the time since the last progress is credited when the spot progresses, at most
        ``ds / dwell_speed_mm_s`` of it, so standing still counts for (almost) nothing — at most
        one resampling step over ``dwell_speed_mm_s`` per stop.
        """
        spots = np.ascontiguousarray(spots_O, dtype=np.float64).reshape(-1, 3)
        ds = np.zeros(spots.shape[0])
        v = np.ones(spots.shape[0])
        i = 0
        while i < spots.shape[0]:
            if self.index < 0:  # (re)lock on the globally nearest path point; no time passes
                d, k = self._tree.query(spots[i])
                if d * d <= self._lock2:
                    self.index, self.s_mm = int(k), float(self.arc_mm[k])
                i += 1
                continue
            done, k, s = _advance(self.points_O, self.arc_mm, self.speed_mm_s, spots[i:],
                                  self.index, self.s_mm, self._back, self._ahead, self._lock2,
                                  ds[i:], v[i:])
            self.index, self.s_mm = int(k), float(s)
            i += done
            if i < spots.shape[0]:  # lost the path here
                self.relocks += 1
                self.index = -1
        if elapsed_s is None:
            return ds / v
        out, self._waiting_s = _executed_time(ds, np.asarray(elapsed_s, dtype=np.float64),
                                              float(dwell_speed_mm_s), self._waiting_s)
        return out
