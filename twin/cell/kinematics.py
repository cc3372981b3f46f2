"""Forward and closed-form inverse kinematics of the cell's 6-axis arm (IRB 4600-40/2.55 class).

Geometry (mm, ABB calibration pose = all joints zero: upper arm vertical, forearm horizontal
along +x_B, flange +z along +x_B and flange +x along -z_B)::

    axis 1  z_B through the base origin
    axis 2  y, at (a1, 0, d1)                      a1 = 175, d1 = 495
    axis 3  y, a2 = 900 above axis 2               (shoulder-elbow)
    axis 4  x, a3 = 175 above axis 3               (forearm offset)
    axis 5  y, d4 = 960 along the forearm          (elbow-wrist)
    axis 6  x, flange d6 = 135 beyond axis 5

The wrist is spherical (axes 4, 5, 6 meet in the wrist centre), so the inverse has a closed form
with eight branches: shoulder front/back, elbow up/down, wrist flip. :func:`ik` returns the
branch nearest the seed, with axes 1, 4 and 6 unwrapped by whole turns towards the seed.
Joint limits and speeds follow the IRB 4600-40/2.55 datasheet. All kernels are numba-compiled.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from dm2.core.tolerances import NEAR_ZERO, SAME_ANGLE_RAD

A1, D1, A2, A3, D4, D6 = 175.0, 495.0, 900.0, 175.0, 960.0, 135.0
GEOMETRY_MM = np.array([A1, D1, A2, A3, D4, D6])
JOINT_LIMITS_DEG = np.array([[-180.0, 180.0], [-90.0, 150.0], [-180.0, 75.0],
                             [-400.0, 400.0], [-125.0, 125.0], [-400.0, 400.0]])
JOINT_SPEED_DEG_S = np.array([175.0, 175.0, 175.0, 250.0, 250.0, 360.0])
JOINT_LIMITS_RAD = np.deg2rad(JOINT_LIMITS_DEG)
JOINT_SPEED_RAD_S = np.deg2rad(JOINT_SPEED_DEG_S)
DEFAULT_WRIST_SINGULARITY_RAD = np.deg2rad(5.0)

# Failure codes of the tracking kernel.
OK, OUT_OF_REACH, JOINT_LIMIT, WRIST_SINGULAR, JOINT_SPEED = 0, 1, 2, 3, 4
FAILURE_TEXT = {OUT_OF_REACH: "pose out of reach", JOINT_LIMIT: "joint limit exceeded",
                WRIST_SINGULAR: "wrist singularity (axis 5 near 0)",
                JOINT_SPEED: "joint speed limit exceeded"}


class ReachError(ValueError):
    """The arm cannot follow a pose; the text names the toolpath index and layer when known."""

    def __init__(self, message: str, index: int | None = None, layer: int | None = None):
        super().__init__(message)
        self.index = index
        self.layer = layer


@njit(cache=True)
def _fk(q, out):
    g = GEOMETRY_MM
    c1, s1 = math.cos(q[0]), math.sin(q[0])
    phi = q[1] + q[2]
    r = g[0] + g[2] * math.sin(q[1]) + g[4] * math.cos(phi) + g[3] * math.sin(phi)
    z = g[1] + g[2] * math.cos(q[1]) - g[4] * math.sin(phi) + g[3] * math.cos(phi)
    # R03 = Rz(q1) Ry(phi); R36 = Rx(q4) Ry(q5) Rx(q6); flange = R06 Ry(90 deg).
    cp, sp = math.cos(phi), math.sin(phi)
    ca, sa = math.cos(q[3]), math.sin(q[3])
    cb, sb = math.cos(q[4]), math.sin(q[4])
    cc, sc = math.cos(q[5]), math.sin(q[5])
    # R36 columns 0..2 (rows a, b, c), R03 = [[c1 cp, -s1, c1 sp], [s1 cp, c1, s1 sp],
    # [-sp, 0, cp]]; flange = R06 Ry(90 deg): x_F = -col2, y_F = col1, z_F = col0.
    m00, m10, m20 = cb, sa * sb, -ca * sb
    m01, m11, m21 = sb * sc, ca * cc - sa * cb * sc, sa * cc + ca * cb * sc
    m02, m12, m22 = sb * cc, -ca * sc - sa * cb * cc, -sa * sc + ca * cb * cc
    for col, (x0, x1, x2), sign in ((2, (m00, m10, m20), 1.0), (1, (m01, m11, m21), 1.0),
                                    (0, (m02, m12, m22), -1.0)):
        out[0, col] = sign * (c1 * cp * x0 - s1 * x1 + c1 * sp * x2)
        out[1, col] = sign * (s1 * cp * x0 + c1 * x1 + s1 * sp * x2)
        out[2, col] = sign * (-sp * x0 + cp * x2)
    out[0, 3] = r * c1 + g[5] * out[0, 2]
    out[1, 3] = r * s1 + g[5] * out[1, 2]
    out[2, 3] = z + g[5] * out[2, 2]
    for i in range(3):
        out[3, i] = 0.0
    out[3, 3] = 1.0


@njit(cache=True)
def _fk_batch(Q):
    out = np.empty((Q.shape[0], 4, 4))
    for k in range(Q.shape[0]):
        _fk(Q[k], out[k])
    return out


@njit(cache=True)
def _wrap(a):
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@njit(cache=True)
def _nearest_turn(a, ref):
    return a + 2.0 * math.pi * round((ref - a) / (2.0 * math.pi))


@njit(cache=True)
def _ik_branch(T, branch, seed, out):
    """Solve one branch (0..7: bit0 shoulder back, bit1 elbow, bit2 wrist flip).

    Returns OK or OUT_OF_REACH; fills ``out`` (6,) with axes 1, 4, 6 unwrapped towards ``seed``.
    """
    g = GEOMETRY_MM
    L = math.sqrt(g[4] * g[4] + g[3] * g[3])
    gam = math.atan2(g[3], g[4])
    wx = T[0, 3] - g[5] * T[0, 2]
    wy = T[1, 3] - g[5] * T[1, 2]
    wz = T[2, 3] - g[5] * T[2, 2]
    rho = math.sqrt(wx * wx + wy * wy)
    if branch & 1:
        q1 = math.atan2(wy, wx) + math.pi
        r = -rho
    else:
        q1 = math.atan2(wy, wx)
        r = rho
    u = r - g[0]
    v = wz - g[1]
    k = (u * u + v * v - g[2] * g[2] - L * L) / (2.0 * g[2] * L)
    if k > 1.0 or k < -1.0:
        return OUT_OF_REACH
    if branch & 2:
        q3 = gam - math.pi + math.asin(k)
    else:
        q3 = gam - math.asin(k)
    psi = q3 - gam
    P = g[2] - L * math.sin(psi)
    Q = L * math.cos(psi)
    q2 = math.atan2(u, v) - math.atan2(Q, P)
    phi = q2 + q3
    c1, s1 = math.cos(q1), math.sin(q1)
    cp, sp = math.cos(phi), math.sin(phi)
    # M = R03^T R06 with R06 columns (z_F, y_F, -x_F); R03 rows as in _fk.
    M = np.empty((3, 3))
    for col in range(3):
        if col == 0:
            x0, x1, x2 = T[0, 2], T[1, 2], T[2, 2]
        elif col == 1:
            x0, x1, x2 = T[0, 1], T[1, 1], T[2, 1]
        else:
            x0, x1, x2 = -T[0, 0], -T[1, 0], -T[2, 0]
        M[0, col] = c1 * cp * x0 + s1 * cp * x1 - sp * x2
        M[1, col] = -s1 * x0 + c1 * x1
        M[2, col] = c1 * sp * x0 + s1 * sp * x1 + cp * x2
    sb = math.sqrt(M[1, 0] * M[1, 0] + M[2, 0] * M[2, 0])
    sgn = -1.0 if branch & 4 else 1.0
    q5 = math.atan2(sgn * sb, M[0, 0])
    if sb > NEAR_ZERO:
        q4 = math.atan2(sgn * M[1, 0], -sgn * M[2, 0])
        q6 = math.atan2(sgn * M[0, 1], sgn * M[0, 2])
    else:  # exactly singular: keep axis 4 at the seed, axis 6 takes the rest
        q4 = seed[3]
        q6 = math.atan2(M[2, 1], M[1, 1]) - q4
    out[0] = _nearest_turn(_wrap(q1), seed[0])
    out[1] = _wrap(q2)
    out[2] = _wrap(q3)
    out[3] = _nearest_turn(q4, seed[3])
    out[4] = q5
    out[5] = _nearest_turn(q6, seed[5])
    return OK


@njit(cache=True)
def _within_limits(q, lim):
    for j in range(6):
        if q[j] < lim[j, 0] - SAME_ANGLE_RAD or q[j] > lim[j, 1] + SAME_ANGLE_RAD:
            return False
    return True


@njit(cache=True)
def _ik_nearest(T, seed, lim):
    """Best branch nearest ``seed`` within limits: (code, branch, q)."""
    best = np.zeros(6)
    cand = np.zeros(6)
    best_d = np.inf
    best_b = -1
    any_reach = False
    for b in range(8):
        if _ik_branch(T, b, seed, cand) != OK:
            continue
        any_reach = True
        if not _within_limits(cand, lim):
            continue
        d = 0.0
        for j in range(6):
            d += (cand[j] - seed[j]) ** 2
        if d < best_d:
            best_d = d
            best_b = b
            best[:] = cand
    if best_b < 0:
        return (JOINT_LIMIT if any_reach else OUT_OF_REACH), -1, best
    return OK, best_b, best


@njit(cache=True)
def _ik_track(T_stack, seed, lim, speed, dt, wrist_min):
    """Follow a pose stream on one branch, each solution seeded by the previous one.

    Returns (joints (m, 6), code, failing sample index).
    """
    m = T_stack.shape[0]
    Q = np.empty((m, 6))
    code, branch, q = _ik_nearest(T_stack[0], seed, lim)
    if code != OK:
        return Q, code, 0
    prev = q.copy()
    cand = np.zeros(6)
    for k in range(m):
        if _ik_branch(T_stack[k], branch, prev, cand) != OK:
            return Q, OUT_OF_REACH, k
        if not _within_limits(cand, lim):
            return Q, JOINT_LIMIT, k
        if abs(math.sin(cand[4])) < wrist_min:
            return Q, WRIST_SINGULAR, k
        if k > 0 and dt > 0.0:
            for j in range(6):
                if abs(cand[j] - prev[j]) > speed[j] * dt * 1.0001:
                    return Q, JOINT_SPEED, k
        Q[k] = cand
        prev[:] = cand
    return Q, OK, -1


def fk(joints_rad: np.ndarray) -> np.ndarray:
    """Flange pose ``T_B_F (4, 4)`` [mm] for joints ``(6,)`` [rad]; a stack (m, 6) -> (m, 4, 4)."""
    q = np.asarray(joints_rad, dtype=np.float64)
    if q.shape[-1] != 6 or q.ndim not in (1, 2):
        raise ValueError(f"fk: joints_rad must be (6,) or (m, 6), got {q.shape}")
    out = _fk_batch(np.ascontiguousarray(q.reshape(-1, 6)))
    return out[0] if q.ndim == 1 else out


def ik(T_B_F: np.ndarray, seed_joints: np.ndarray,
       wrist_singularity_rad: float = DEFAULT_WRIST_SINGULARITY_RAD) -> np.ndarray:
    """Joints ``(6,)`` [rad] reaching flange pose ``T_B_F``, the solution nearest the seed.

    Raises
    ------
    ReachError
        The pose is out of reach, only reachable beyond a joint limit, or at the wrist
        singularity (``|sin q5| < sin(wrist_singularity_rad)``).
    """
    T = np.ascontiguousarray(T_B_F, dtype=np.float64)
    seed = np.ascontiguousarray(seed_joints, dtype=np.float64)
    if T.shape != (4, 4) or seed.shape != (6,):
        raise ValueError(f"ik: expected T_B_F (4, 4) and seed (6,), got {T.shape}, {seed.shape}")
    code, _, q = _ik_nearest(T, seed, JOINT_LIMITS_RAD)
    if code != OK:
        raise ReachError(f"flange pose at {np.round(T[:3, 3], 3).tolist()} mm: "
                         f"{FAILURE_TEXT[code]}")
    if abs(math.sin(q[4])) < math.sin(wrist_singularity_rad):
        raise ReachError(f"flange pose at {np.round(T[:3, 3], 3).tolist()} mm: "
                         f"{FAILURE_TEXT[WRIST_SINGULAR]}")
    return q.copy()


def ik_track(T_B_F: np.ndarray, seed_joints: np.ndarray, dt_s: float = 0.0,
             wrist_singularity_rad: float = DEFAULT_WRIST_SINGULARITY_RAD
             ) -> tuple[np.ndarray, int, int]:
    """Follow flange poses ``(m, 4, 4)`` on the branch chosen nearest the seed at sample 0.

    Parameters
    ----------
    T_B_F : (m, 4, 4) float64 flange poses [mm]
    seed_joints : (6,) float64 [rad], picks the arm configuration
    dt_s : float [s], sample spacing; > 0 also checks the joint speed limits
    wrist_singularity_rad : float [rad], smallest allowed ``|q5|`` (mod pi)

    Returns
    -------
    joints_rad : (m, 6) float64 [rad], valid up to the failing sample
    code : int, ``OK`` (0) or a failure code (see ``FAILURE_TEXT``)
    failed_at : int, index of the failing sample (-1 when OK)
    """
    T = np.ascontiguousarray(T_B_F, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"ik_track: expected (m, 4, 4), got {T.shape}")
    seed = np.ascontiguousarray(seed_joints, dtype=np.float64)
    if T.shape[0] == 0:
        return np.zeros((0, 6)), OK, -1
    Q, code, k = _ik_track(T, seed, JOINT_LIMITS_RAD, JOINT_SPEED_RAD_S, float(dt_s),
                           math.sin(wrist_singularity_rad))
    return Q, int(code), int(k)
