"""Closed-form pieces of the calibration: circle fits, sphere centres from arcs, Kabsch."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from dm2.core.frames import make_T
from dm2.core.tolerances import SMALL_ROTATION_RAD


def fit_circle_xz(xz: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Algebraic (Kasa) circle fit to points in a plane.

    Parameters
    ----------
    xz : (n, 2) float64 [mm], n >= 3

    Returns
    -------
    center : (2,) float64 [mm]
    radius_mm : float
    rms_mm : float, RMS of the radial residuals
    """
    m = xz.mean(axis=0)
    p = xz - m
    A = np.column_stack([p, np.ones(len(p))])
    b = -(p * p).sum(axis=1)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    c = -0.5 * sol[:2]
    r2 = c @ c - sol[2]
    radius = float(np.sqrt(max(r2, 0.0)))
    rms = float(np.sqrt(np.mean((np.linalg.norm(p - c, axis=1) - radius) ** 2)))
    return c + m, radius, rms


def robust_circle_fit(xz: np.ndarray, rounds: int = 3,
                      floor_mm: float = 0.05) -> tuple[np.ndarray, float, float, np.ndarray]:
    """Circle fit that drops points farther than 3 RMS (at least ``floor_mm``) and refits.

    Returns center (2,), radius_mm, rms_mm and the (n,) inlier mask.
    """
    keep = np.ones(len(xz), dtype=bool)
    center, radius, rms = fit_circle_xz(xz)
    for _ in range(rounds):
        res = np.abs(np.linalg.norm(xz - center, axis=1) - radius)
        new = res <= max(3.0 * rms, floor_mm)
        if new.sum() < 3 or np.array_equal(new, keep):
            break
        keep = new
        center, radius, rms = fit_circle_xz(xz[keep])
    return center, radius, rms, keep


def sphere_center_from_arc(center_xz: np.ndarray, arc_radius_mm: float, sphere_radius_mm: float,
                           y_sign: float) -> np.ndarray:
    """Sphere centre (3,) in ``S`` from the circle its cut leaves in the laser plane.

    The centre lies ``sqrt(r**2 - rho**2)`` off the plane; ``y_sign`` picks the side.
    """
    h = np.sqrt(max(sphere_radius_mm ** 2 - arc_radius_mm ** 2, 0.0))
    return np.array([center_xz[0], (1.0 if y_sign >= 0 else -1.0) * h, center_xz[1]])


def kabsch(points_S: np.ndarray, points_B: np.ndarray) -> np.ndarray:
    """``T_B_S`` (4, 4) minimising ``sum |T_B_S p_S - p_B|^2`` over (k, 3) correspondences."""
    ms, mb = points_S.mean(axis=0), points_B.mean(axis=0)
    H = (points_S - ms).T @ (points_B - mb)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return make_T(R, mb - R @ ms)


def spread_mm(points: np.ndarray) -> np.ndarray:
    """Singular values (3,) [mm] of centred points / sqrt(k): 2nd ~ 0 means collinear."""
    p = points - points.mean(axis=0)
    s = np.linalg.svd(p, compute_uv=False) / np.sqrt(max(len(p), 1))
    return np.pad(s, (0, 3 - len(s)))


def right_jacobian_so3(rotvec: np.ndarray) -> np.ndarray:
    """Right Jacobian (3, 3) of SO(3): Exp(w + dw) ~ Exp(w) Exp(Jr(w) dw)."""
    th = float(np.linalg.norm(rotvec))
    K = np.array([[0.0, -rotvec[2], rotvec[1]],
                  [rotvec[2], 0.0, -rotvec[0]],
                  [-rotvec[1], rotvec[0], 0.0]])
    if th < SMALL_ROTATION_RAD:
        return np.eye(3) - 0.5 * K
    return (np.eye(3) - (1.0 - np.cos(th)) / th ** 2 * K
            + (th - np.sin(th)) / th ** 3 * (K @ K))


def exp_se3(T0: np.ndarray, x6: np.ndarray) -> np.ndarray:
    """``T0 @ [Exp(rotvec), v]`` for ``x6 = (rotvec_rad (3), v_mm (3))``."""
    return T0 @ make_T(Rotation.from_rotvec(x6[:3]), x6[3:])
