"""Time-sorted robot flange poses with bracketed interpolation at query stamps.

Rotation is interpolated by SLERP and translation linearly between the two robot states that
bracket a stamp, only if they are at most ``max_gap_s`` apart (numba kernels; the same result
as :class:`dm2.core.frames.PoseInterpolator` on each bracket).
"""

from __future__ import annotations

import numpy as np
from numba import njit

_WAITING = 256  # poses that wait in a list before they are merged into the sorted arrays


class PoseBuffer:
    """Time-sorted robot flange poses with bracketed SLERP interpolation.

    A pose newer than all others (the usual case) is appended to the sorted arrays in place; a
    late one waits in a short list (with any pose after it) and is merged into the sorted arrays
    in one step when poses are next queried.

    Parameters
    ----------
    horizon_s : float [s], poses older than the newest minus this are pruned
    """

    def __init__(self, horizon_s: float = 5.0, capacity: int = 4096):
        self.horizon_s = float(horizon_s)
        self._t = np.empty(capacity)
        self._T = np.empty((capacity, 4, 4))
        self._n = 0
        self._new_t: list[float] = []  # waiting to be merged, poses in _new_T[:len(_new_t)]
        self._new_T = np.empty((_WAITING, 4, 4))
        self._new_sorted = True  # the waiting stamps increase and follow the buffered ones
        self._known: set[float] = set()  # stamps buffered or waiting, for the duplicate test
        self._latest = -np.inf

    def __len__(self) -> int:
        return self._n + len(self._new_t)

    @property
    def latest_s(self) -> float:
        return float(self._latest)

    @property
    def stamps_s(self) -> np.ndarray:
        self._merge()
        return self._t[: self._n]

    def add(self, stamp_s: float, T_B_F: np.ndarray) -> bool:
        """Insert a pose; False when a pose with the same stamp is already buffered."""
        known = self._known
        if stamp_s in known:
            return False
        known.add(stamp_s)
        new_t = self._new_t
        if stamp_s > self._latest:
            self._latest = stamp_s
            if not new_t:  # in order: straight into the sorted arrays
                n = self._n
                if n == self._t.shape[0]:
                    self._compact(np.array([stamp_s]))
                    n = self._n
                self._t[n] = stamp_s
                self._T[n] = T_B_F
                self._n = n + 1
                return True
        else:
            self._new_sorted = False
        m = len(new_t)
        self._new_T[m] = T_B_F
        new_t.append(stamp_s)
        if m + 1 == _WAITING:
            self._merge()
        return True

    def _merge(self) -> None:
        if not self._new_t:
            return
        t_new = np.array(self._new_t)
        m = t_new.size
        T_new = self._new_T[:m]
        self._new_t.clear()
        in_order, self._new_sorted = self._new_sorted, True
        if self._n + m > len(self._t):
            self._compact(t_new)
        n = self._n
        if in_order:
            self._t[n: n + m] = t_new
            self._T[n: n + m] = T_new
        else:  # late arrivals: merge the two sorted runs
            t_all = np.concatenate([self._t[:n], t_new])
            order = np.argsort(t_all, kind="stable")
            self._T[: n + m] = np.concatenate([self._T[:n], T_new])[order]
            self._t[: n + m] = t_all[order]
        self._n = n + m

    def _compact(self, t_new: np.ndarray) -> None:
        """Drop poses older than the horizon; grow when the horizon needs more room for the
        poses ``t_new`` about to be merged."""
        n, incoming = self._n, t_new.size
        k0 = int(np.searchsorted(self._t[:n], self._latest - self.horizon_s)) if n else 0
        k = n - k0
        if k + incoming + 2 >= len(self._t):
            size = 2 * max(len(self._t), k + incoming + 2)
            t, T = np.empty(size), np.empty((size, 4, 4))
            t[:k], T[:k] = self._t[k0:n], self._T[k0:n]
            self._t, self._T = t, T
        else:
            self._t[:k] = self._t[k0:n].copy()
            self._T[:k] = self._T[k0:n].copy()
        self._n = k
        if k0:
            self._known = set(self._t[:k].tolist()) | set(t_new.tolist())

    def covers(self, stamp_s: float) -> bool:
        return self._latest >= stamp_s

    def pose_at(self, stamp_s: float, max_gap_s: float) -> tuple[np.ndarray, bool]:
        """Interpolated pose ``(4, 4)`` at one ``stamp_s`` and whether two poses at most
        ``max_gap_s`` apart bracket it (the same bits as :meth:`poses_at`)."""
        if self._new_t:
            self._merge()
        out = np.empty((4, 4))
        return out, _pose_at(self._t, self._T, self._n, float(stamp_s), float(max_gap_s), out)

    def poses_at(self, stamps_s: np.ndarray, max_gap_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Interpolated poses ``(k, 4, 4)`` at ``stamps_s (k,)`` and ``ok (k,) bool`` (False
        where no two poses at most ``max_gap_s`` apart bracket the stamp)."""
        self._merge()
        q = np.ascontiguousarray(stamps_s, dtype=np.float64).reshape(-1)
        out = np.empty((q.size, 4, 4))
        ok = np.zeros(q.size, dtype=np.bool_)
        _poses_at(self._t, self._T, self._n, q, float(max_gap_s), out, ok)
        return out, ok


@njit(cache=True, nogil=True)
def _poses_at(t, T, n, q_s, max_gap_s, out, ok):
    for k in range(q_s.shape[0]):
        ok[k] = _pose_at(t, T, n, q_s[k], max_gap_s, out[k])


@njit(cache=True, nogil=True)
def _pose_at(t, T, n, q_s, max_gap_s, out):
    """Pose at ``q_s`` into ``out (4, 4)`` (identity when not bracketed); whether bracketed."""
    out[:] = np.eye(4)
    if n == 0:
        return False
    i1 = np.searchsorted(t[:n], q_s)
    if i1 < n and t[i1] == q_s:
        out[:] = T[i1]
        return True
    if 0 < i1 < n and t[i1] - t[i1 - 1] <= max_gap_s:
        _interp_pose(T, t, i1 - 1, i1, q_s, out)
        return True
    return False


@njit(cache=True)
def _quat_from_matrix(R):
    """Unit quaternion (w, x, y, z) of a rotation matrix (Shepperd's method)."""
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    q = np.empty(4)
    if tr > 0.0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q[0], q[1] = 0.25 * s, (R[2, 1] - R[1, 2]) / s
        q[2], q[3] = (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q[0], q[1] = (R[2, 1] - R[1, 2]) / s, 0.25 * s
        q[2], q[3] = (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q[0], q[1] = (R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s
        q[2], q[3] = 0.25 * s, (R[1, 2] + R[2, 1]) / s
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q[0], q[1] = (R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s
        q[2], q[3] = (R[1, 2] + R[2, 1]) / s, 0.25 * s
    return q / np.sqrt((q * q).sum())


@njit(cache=True)
def _interp_pose(T, t, a, b, q_s, out):
    """SLERP rotation and lerp translation between poses ``T[a]`` and ``T[b]`` at ``q_s``."""
    alpha = (q_s - t[a]) / (t[b] - t[a])
    q0 = _quat_from_matrix(T[a, :3, :3])
    q1 = _quat_from_matrix(T[b, :3, :3])
    dot = (q0 * q1).sum()
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:
        q = q0 + alpha * (q1 - q0)
    else:
        th = np.arccos(min(dot, 1.0))
        q = (np.sin((1.0 - alpha) * th) * q0 + np.sin(alpha * th) * q1) / np.sin(th)
    w, x, y, z = q / np.sqrt((q * q).sum())
    out[0, 0], out[0, 1], out[0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - z * w), \
        2 * (x * z + y * w)
    out[1, 0], out[1, 1], out[1, 2] = 2 * (x * y + z * w), 1 - 2 * (x * x + z * z), \
        2 * (y * z - x * w)
    out[2, 0], out[2, 1], out[2, 2] = 2 * (x * z - y * w), 2 * (y * z + x * w), \
        1 - 2 * (x * x + y * y)
    for j in range(3):
        out[j, 3] = (1.0 - alpha) * T[a, j, 3] + alpha * T[b, j, 3]
    out[3, :3] = 0.0
    out[3, 3] = 1.0
