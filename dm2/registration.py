"""Registration of profiles into the work-object frame (paper eq 1).

``points_O = T_O_B @ T_B_S @ points_S`` with ``T_B_O(t) = T_B_F(t) @ T_F_O``; the laser's
emission point (the origin of ``S``) is carried along so the TSDF can cast each ray from it.
The deposition spot follows the nozzle axis: ``spot_B = origin(T_B_N) + standoff * z_N`` and
``spot_O = T_O_B @ spot_B``.
"""

from __future__ import annotations

import numpy as np

from dm2.frames import invert
from dm2.messages import Calibration


def spot_B(calibration: Calibration, standoff_mm: float) -> np.ndarray:
    """Deposition spot ``(3,)`` [mm] in ``B``: ``standoff_mm`` along +z_N from the nozzle exit."""
    T = calibration.T_B_N
    return T[:3, 3] + float(standoff_mm) * T[:3, 2]


def profile_points_S(xz_S: np.ndarray) -> np.ndarray:
    """Laser-plane points ``(n, 2)`` [mm] as 3-D points ``(n, 3)`` in ``S`` (``y_S = 0``)."""
    xz = np.asarray(xz_S, dtype=np.float64)
    out = np.zeros((xz.shape[0], 3))
    out[:, 0] = xz[:, 0]
    out[:, 2] = xz[:, 1]
    return out


def T_O_S_at(T_B_F: np.ndarray, T_F_O: np.ndarray, T_B_S: np.ndarray) -> np.ndarray:
    """``T_O_S = inv(T_B_F @ T_F_O) @ T_B_S`` for one pose (4, 4) or a stack (k, 4, 4)."""
    T_B_O = np.asarray(T_B_F) @ np.asarray(T_F_O)
    return invert(T_B_O) @ np.asarray(T_B_S)


def register_profile(xz_S: np.ndarray, T_O_S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points ``(n, 3)`` [mm] in ``O`` and the sensor origin ``(3,)`` [mm] in ``O``."""
    xz = np.asarray(xz_S, dtype=np.float64)
    R = T_O_S[:3, :3]
    pts = np.outer(xz[:, 0], R[:, 0]) + np.outer(xz[:, 1], R[:, 2]) + T_O_S[:3, 3]
    return pts, T_O_S[:3, 3].copy()


def nozzle_axis_O(T_B_O: np.ndarray, calibration: Calibration, standoff_mm: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Deposition spot ``(3,)`` [mm] and unit spray direction ``(3,)`` in ``O`` at ``T_B_O``."""
    T_O_B = invert(T_B_O)
    spot = T_O_B[:3, :3] @ spot_B(calibration, standoff_mm) + T_O_B[:3, 3]
    axis = T_O_B[:3, :3] @ calibration.T_B_N[:3, 2]
    return spot, axis


def distance_to_axis(points_O: np.ndarray, spot_O: np.ndarray, axis_O: np.ndarray) -> np.ndarray:
    """Distance ``(n,)`` [mm] of each point from the nozzle axis line through ``spot_O``."""
    rel = np.asarray(points_O) - spot_O
    along = rel @ axis_O
    return np.sqrt(np.maximum(np.einsum("ij,ij->i", rel, rel) - along * along, 0.0))
