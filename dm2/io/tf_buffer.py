"""A tf tree read from ``/tf`` and ``/tf_static``: lookups through chains of dynamic and static
transforms at any stamp.

Each frame has at most one parent (as in ROS 2 tf2). A static edge (from ``/tf_static``) holds
one transform; a dynamic edge (from ``/tf``) holds its time series, sorted by header stamp. A
lookup ``T_a_b(t)`` walks both frames up to their common ancestor and composes the edges; every
dynamic edge on the way is interpolated at ``t`` on its own (SLERP of the rotation, linear
translation) between the two samples that bracket ``t``, only if they are at most
``max_gap_s`` apart. Outside an edge's samples the nearest sample is held if it is at most
``max_gap_s`` from ``t``; anything further would extrapolate and the lookup fails (None).

Translations are in mm (tf's metres are converted on reading), rotations as matrices.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from dm2.core.frames import invert
from dm2.core.tolerances import STILL_POSE_MM, STILL_POSE_RAD


class TfError(ValueError):
    """The tf tree cannot answer a lookup (unknown frame, no path, two parents)."""


class _DynamicEdge:
    """Time series of one ``parent -> child`` transform."""

    def __init__(self):
        self._rows: list[tuple[float, np.ndarray]] = []
        self.t_s = np.empty(0)
        self.q_xyzw = np.empty((0, 4))
        self.p_mm = np.empty((0, 3))

    def add(self, stamp_s: float, T: np.ndarray) -> None:
        self._rows.append((stamp_s, T))

    def finish(self) -> None:
        rows = sorted(self._rows, key=lambda r: r[0])
        self._rows = []
        t = np.array([r[0] for r in rows])
        keep = np.ones(t.size, dtype=bool)
        keep[1:] = np.diff(t) > 0  # one sample per stamp (a message recorded twice)
        T = np.array([r[1] for r in rows])[keep]
        self.t_s = t[keep]
        q = Rotation.from_matrix(T[:, :3, :3]).as_quat()
        dots = np.einsum("ij,ij->i", q[1:], q[:-1])  # same hemisphere as the previous sample
        flip = np.concatenate([[1.0], np.cumprod(np.where(dots < 0, -1.0, 1.0))])
        self.q_xyzw = q * flip[:, None]
        self.p_mm = T[:, :3, 3]

    def moves(self, tol_mm: float = STILL_POSE_MM, tol_rad: float = STILL_POSE_RAD) -> bool:
        """Whether the samples differ (a fixed transform republished on ``/tf`` does not)."""
        if self.t_s.size < 2:
            return False
        dp = float(np.abs(self.p_mm - self.p_mm[0]).max())
        dots = np.clip(np.abs(self.q_xyzw @ self.q_xyzw[0]), 0.0, 1.0)
        return dp > tol_mm or float(2 * np.arccos(dots.min())) > tol_rad

    def at(self, stamp_s: float, max_gap_s: float) -> np.ndarray | None:
        t = self.t_s
        n = t.size
        if n == 0:
            return None
        i = int(np.searchsorted(t, stamp_s))
        if i < n and t[i] == stamp_s:
            return self._matrix(self.q_xyzw[i], self.p_mm[i])
        if i == 0 or i == n:  # outside the samples: hold the nearest one within the gap
            j = 0 if i == 0 else n - 1
            if abs(t[j] - stamp_s) > max_gap_s:
                return None
            return self._matrix(self.q_xyzw[j], self.p_mm[j])
        t0, t1 = t[i - 1], t[i]
        if t1 - t0 > max_gap_s:
            return None
        a = (stamp_s - t0) / (t1 - t0)
        q0, q1 = self.q_xyzw[i - 1], self.q_xyzw[i]
        dot = float(np.dot(q0, q1))
        if dot > 0.9995:
            q = q0 + a * (q1 - q0)
        else:
            th = np.arccos(min(dot, 1.0))
            q = (np.sin((1 - a) * th) * q0 + np.sin(a * th) * q1) / np.sin(th)
        return self._matrix(q, (1 - a) * self.p_mm[i - 1] + a * self.p_mm[i])

    @staticmethod
    def _matrix(q_xyzw: np.ndarray, p_mm: np.ndarray) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat(q_xyzw).as_matrix()
        T[:3, 3] = p_mm
        return T


class TfBuffer:
    """The whole tf tree of a recording (see the module docstring).

    Fill it with :meth:`add` (``static`` for ``/tf_static``), call :meth:`finish`, then
    :meth:`lookup`.
    """

    def __init__(self):
        self.parent: dict[str, str] = {}
        self.static: dict[str, np.ndarray] = {}  # child -> T_parent_child
        self.dynamic: dict[str, _DynamicEdge] = {}  # child -> its series

    @property
    def frames(self) -> list[str]:
        return sorted(set(self.parent) | set(self.parent.values()))

    def add(self, stamp_s: float, parent: str, child: str, T_parent_child: np.ndarray,
            static: bool, source: str = "") -> None:
        """One transform; a frame with a second, different parent raises TfError. A leading
        ``/`` of a frame name (ROS 1 style) is dropped, as tf2 does."""
        parent, child = parent.lstrip("/"), child.lstrip("/")
        known = self.parent.get(child)
        if known is not None and known != parent:
            raise TfError(f"{source}: frame {child!r} has two parents in the tf tree "
                          f"({known!r} and {parent!r})")
        self.parent[child] = parent
        if static:
            if child in self.dynamic:
                raise TfError(f"{source}: edge {parent!r} -> {child!r} is on both /tf and "
                              "/tf_static")
            self.static[child] = np.asarray(T_parent_child, dtype=np.float64)
        else:
            if child in self.static:
                raise TfError(f"{source}: edge {parent!r} -> {child!r} is on both /tf and "
                              "/tf_static")
            self.dynamic.setdefault(child, _DynamicEdge()).add(stamp_s, T_parent_child)

    def finish(self) -> None:
        for edge in self.dynamic.values():
            edge.finish()

    def _to_root(self, frame: str) -> list[str]:
        """``[frame, parent, grandparent, ..., root]``."""
        chain = [frame]
        while chain[-1] in self.parent:
            chain.append(self.parent[chain[-1]])
            if len(chain) > len(self.parent) + 1:
                raise TfError(f"the tf tree has a cycle through {frame!r}")
        return chain

    def path(self, a: str, b: str) -> tuple[list[str], list[str]]:
        """The frames from ``a`` and from ``b`` up to (not including) their common ancestor;
        TfError if a frame is unknown or the two are not connected."""
        frames = set(self.frames)
        for f in (a, b):
            if f not in frames:
                raise TfError(f"frame {f!r} is not in the tf tree")
        up_a, up_b = self._to_root(a), self._to_root(b)
        common = next((f for f in up_a if f in set(up_b)), None)
        if common is None:
            raise TfError(f"frames {a!r} and {b!r} are not connected in the tf tree "
                          f"(roots {up_a[-1]!r} and {up_b[-1]!r})")
        return up_a[:up_a.index(common)], up_b[:up_b.index(common)]

    def dynamic_edges(self, a: str, b: str, moving_only: bool = False) -> list[tuple[str, str]]:
        """The ``(parent, child)`` dynamic edges between ``a`` and ``b`` (``moving_only``: only
        those whose samples differ)."""
        pa, pb = self.path(a, b)
        return [(self.parent[c], c) for c in pa + pb if c in self.dynamic
                and (not moving_only or self.dynamic[c].moves())]

    def _up(self, chain: list[str], stamp_s: float, max_gap_s: float) -> np.ndarray | None:
        """``T_ancestor_frame`` of ``chain = [frame, ..., child of ancestor]``."""
        T = np.eye(4)
        for child in chain:  # from the frame upwards: T = T_parent_child @ T
            E = self.static.get(child)
            if E is None:
                E = self.dynamic[child].at(stamp_s, max_gap_s)
                if E is None:
                    return None
            T = E @ T
        return T

    def lookup(self, a: str, b: str, stamp_s: float = 0.0,
               max_gap_s: float = np.inf) -> np.ndarray | None:
        """``T_a_b`` (pose of ``b`` in ``a``, mm) at ``stamp_s``; None where a dynamic edge on
        the path would be extrapolated beyond ``max_gap_s``."""
        pa, pb = self.path(a, b)
        T_c_a = self._up(pa, stamp_s, max_gap_s)
        T_c_b = self._up(pb, stamp_s, max_gap_s)
        if T_c_a is None or T_c_b is None:
            return None
        return invert(T_c_a) @ T_c_b
