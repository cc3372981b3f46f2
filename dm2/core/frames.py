"""Rigid transforms in SE(3) for the cell's frames.

Frames (see ARCHITECTURE.md): ``B`` robot base, ``F`` flange, ``O`` work object (plate corner),
``N`` nozzle exit, ``S1..S3`` laser profilers. A transform ``T_a_b`` is a (4, 4) float64
array with ``p_a = T_a_b @ p_b``; names cancel when composed: ``T_O_S = T_O_B @ T_B_S``.
Units are millimetres and radians; degrees appear only in ``*_deg`` helpers.

Quaternions follow the ABB controller order ``(qw, qx, qy, qz)``; scipy uses
``(qx, qy, qz, qw)`` internally, and the conversion lives here only.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from dm2.core.tolerances import NEAR_ZERO, RELATIVE_LENGTH_ZERO

FRAMES = ("B", "F", "O", "N", "S1", "S2", "S3")


def _check_T(T: np.ndarray, name: str = "T") -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape[-2:] != (4, 4):
        raise ValueError(f"{name}: expected shape (..., 4, 4), got {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError(f"{name}: contains non-finite values")
    return T


def make_T(rotation: Rotation | np.ndarray | None = None, translation_mm=None) -> np.ndarray:
    """Build ``T`` from a scipy ``Rotation`` (or a (3, 3) matrix) and a translation [mm]."""
    T = np.eye(4)
    if rotation is not None:
        R = rotation.as_matrix() if isinstance(rotation, Rotation) else np.asarray(rotation)
        if R.shape != (3, 3):
            raise ValueError(f"rotation: expected (3, 3), got {R.shape}")
        T[:3, :3] = R
    if translation_mm is not None:
        t = np.asarray(translation_mm, dtype=np.float64)
        if t.shape != (3,):
            raise ValueError(f"translation_mm: expected (3,), got {t.shape}")
        T[:3, 3] = t
    return T


def invert(T_a_b: np.ndarray) -> np.ndarray:
    """Return ``T_b_a`` for a rigid ``T_a_b`` (works on stacks (..., 4, 4))."""
    T_a_b = _check_T(T_a_b, "T_a_b")
    R = T_a_b[..., :3, :3]
    t = T_a_b[..., :3, 3]
    Rt = np.swapaxes(R, -1, -2)
    out = np.zeros_like(T_a_b)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def compose(*Ts: np.ndarray) -> np.ndarray:
    """Compose transforms left to right: ``compose(T_a_b, T_b_c) == T_a_c``."""
    if not Ts:
        return np.eye(4)
    out = _check_T(Ts[0])
    for T in Ts[1:]:
        out = out @ _check_T(T)
    return out


def apply(T_a_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Map points ``(n, 3)`` [mm] from frame b to frame a."""
    T_a_b = _check_T(T_a_b, "T_a_b")
    p = np.asarray(points_b, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points: expected (n, 3), got {p.shape}")
    return p @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def rotate(T_a_b: np.ndarray, vectors_b: np.ndarray) -> np.ndarray:
    """Rotate direction vectors ``(n, 3)`` from frame b to frame a (no translation)."""
    v = np.asarray(vectors_b, dtype=np.float64)
    return v @ np.asarray(T_a_b)[:3, :3].T


def from_quat_abb(translation_mm, q_wxyz) -> np.ndarray:
    """Build ``T`` from a translation [mm] and an ABB-ordered quaternion ``(qw, qx, qy, qz)``."""
    q = np.asarray(q_wxyz, dtype=np.float64)
    if q.shape != (4,) or not np.all(np.isfinite(q)) or np.linalg.norm(q) < NEAR_ZERO:
        raise ValueError(f"quaternion (qw, qx, qy, qz) invalid: {q_wxyz!r}")
    return make_T(Rotation.from_quat(q[[1, 2, 3, 0]]), translation_mm)


def to_quat_abb(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(translation_mm (3,), quaternion (qw, qx, qy, qz))`` with ``qw >= 0``."""
    T = _check_T(T)
    q = Rotation.from_matrix(T[:3, :3]).as_quat()  # x, y, z, w
    q = q[[3, 0, 1, 2]]
    if q[0] < 0:
        q = -q
    return T[:3, 3].copy(), q


def from_euler_deg(translation_mm, euler_deg, seq: str = "ZYX") -> np.ndarray:
    """Build ``T`` from a translation [mm] and Euler angles in degrees (ABB uses ``ZYX``)."""
    return make_T(Rotation.from_euler(seq, euler_deg, degrees=True), translation_mm)


def to_euler_deg(T: np.ndarray, seq: str = "ZYX") -> tuple[np.ndarray, np.ndarray]:
    """Return ``(translation_mm, euler_deg)`` for ``T``."""
    T = _check_T(T)
    return T[:3, 3].copy(), Rotation.from_matrix(T[:3, :3]).as_euler(seq, degrees=True)


def from_rotvec(rotvec_rad, translation_mm) -> np.ndarray:
    """Build ``T`` from an axis-angle vector [rad] and a translation [mm]."""
    return make_T(Rotation.from_rotvec(np.asarray(rotvec_rad, dtype=np.float64)), translation_mm)


def to_rotvec(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(rotvec_rad, translation_mm)`` for ``T``."""
    T = _check_T(T)
    return Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3].copy()


def look_at(origin_mm, target_mm, up_hint=(0.0, 0.0, 1.0)) -> np.ndarray:
    """``T_world_frame`` whose +z axis points from ``origin_mm`` to ``target_mm``."""
    o = np.asarray(origin_mm, dtype=np.float64)
    z = np.asarray(target_mm, dtype=np.float64) - o
    n = np.linalg.norm(z)
    if n < NEAR_ZERO:
        raise ValueError("look_at: origin and target coincide")
    z /= n
    up = np.asarray(up_hint, dtype=np.float64)
    if abs(np.dot(up, z)) > 0.999:
        up = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_T(np.column_stack([x, y, z]), o)


def rotation_between(a, b) -> Rotation:
    """Smallest rotation taking unit vector ``a`` onto unit vector ``b``."""
    a = np.asarray(a, dtype=np.float64) / np.linalg.norm(a)
    b = np.asarray(b, dtype=np.float64) / np.linalg.norm(b)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis)
    c = float(np.clip(np.dot(a, b), -1.0, 1.0))
    if s < NEAR_ZERO:
        if c > 0:
            return Rotation.identity()
        perp = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(perp) < RELATIVE_LENGTH_ZERO:
            perp = np.cross(a, [0.0, 1.0, 0.0])
        return Rotation.from_rotvec(np.pi * perp / np.linalg.norm(perp))
    return Rotation.from_rotvec(axis / s * np.arctan2(s, c))


def pose_error(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """Translation error [mm] and rotation error [rad] between two poses of the same frame."""
    T_a, T_b = _check_T(T_a), _check_T(T_b)
    dt = float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]))
    dR = T_a[:3, :3].T @ T_b[:3, :3]
    dr = float(Rotation.from_matrix(dR).magnitude())
    return dt, dr


class PoseInterpolator:
    """Interpolate timed poses: SLERP for rotation, linear for translation.

    Parameters
    ----------
    stamps_s : (n,) float64 [s], strictly increasing
    T_a_b : (n, 4, 4) float64 poses at those stamps
    """

    def __init__(self, stamps_s: np.ndarray, T_a_b: np.ndarray):
        t = np.asarray(stamps_s, dtype=np.float64)
        T = _check_T(T_a_b, "T_a_b")
        if t.ndim != 1 or T.shape != (t.size, 4, 4):
            raise ValueError(f"PoseInterpolator: stamps {t.shape} and poses {T.shape} disagree")
        if t.size < 2 or np.any(np.diff(t) <= 0):
            raise ValueError("PoseInterpolator: need >= 2 strictly increasing stamps")
        self.stamps_s = t
        self._translation = T[:, :3, 3].copy()
        self._slerp = Slerp(t, Rotation.from_matrix(T[:, :3, :3]))

    def __call__(self, query_s: np.ndarray) -> np.ndarray:
        """Poses ``(m, 4, 4)`` at ``query_s`` (must lie inside the stamp range)."""
        q = np.atleast_1d(np.asarray(query_s, dtype=np.float64))
        if q.size and (q.min() < self.stamps_s[0] or q.max() > self.stamps_s[-1]):
            raise ValueError("PoseInterpolator: query outside the stamp range")
        out = np.zeros((q.size, 4, 4))
        out[:, :3, :3] = self._slerp(q).as_matrix()
        for k in range(3):
            out[:, k, 3] = np.interp(q, self.stamps_s, self._translation[:, k])
        out[:, 3, 3] = 1.0
        return out


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, alpha: float) -> np.ndarray:
    """Pose at fraction ``alpha`` in [0, 1] between ``T0`` and ``T1``."""
    interp = PoseInterpolator(np.array([0.0, 1.0]), np.stack([_check_T(T0), _check_T(T1)]))
    return interp(np.array([alpha]))[0]
