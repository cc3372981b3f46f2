"""Progress along the programmed toolpath, and the nominal time it is worth.

The near-net reference (paper section 6.1) integrates the Gaussian deposition along the path the
robot executes, at the *programmed* process: nominal feed, nominal efficiency and the programmed
traverse speed. Robot states tell where the spray spot is; this module turns them into path
progress ``s`` [mm] along the toolpath polyline and into nominal seconds ``ds / v_programmed``.

Why not the controller's clock: a robot that stops at a corner (a reorientation, an extra dwell)
keeps spraying, and the real part grows there — the corner overbuild of the paper's
experiments 3 and 4. A reference that integrated the real residence time would grow the same
bump and hide the defect. Progress only advances (a running maximum), so standing still, jitter
of the reported pose and small back-and-forth add no nominal time.

The search is local: each spot is matched within ``window_mm`` ahead of (and a little behind)
the current progress, so crossings of the path with itself (crosshatch layers, contours meeting
infill ends) never make progress jump. A spot farther than ``lock_mm`` from the path there
(approach moves, a gap in the stream) re-locks on the globally nearest path point.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from scipy.spatial import cKDTree

from dm2.messages import Toolpath


@njit(cache=True)
def _advance(points, arc, speed, spots, k, s, back, ahead, lock2, dt_out):
    """Match spots in order; fills ``dt_out``; returns (matched count, k, s).

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
        t = 0.0
        if arc[best] > s:
            # nominal time of the stretch passed, at each stretch's programmed speed
            for j in range(k, best):
                t += (arc[j + 1] - arc[j]) / speed[j + 1]
            s = arc[best]
            k = best
        dt_out[i] = t
    return spots.shape[0], k, s


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

    def advance(self, spots_O: np.ndarray) -> np.ndarray:
        """Nominal seconds ``(m,)`` the spray spends reaching each of ``spots_O (m, 3)`` [mm]."""
        spots = np.ascontiguousarray(spots_O, dtype=np.float64).reshape(-1, 3)
        out = np.zeros(spots.shape[0])
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
                                  out[i:])
            self.index, self.s_mm = int(k), float(s)
            i += done
            if i < spots.shape[0]:  # lost the path here
                self.relocks += 1
                self.index = -1
        return out
