"""Registration of profiles into the work-object frame (paper eq 1).

``points_O = T_O_B @ T_B_S @ points_S`` with ``T_B_O(t) = T_B_F(t) @ T_F_O``; the laser's
emission point (the origin of ``S``) is carried along so the TSDF can cast each ray from it.
The deposition spot follows the nozzle axis: ``spot_B = origin(T_B_N) + standoff * z_N`` and
``spot_O = T_O_B @ spot_B``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from dm2.core.messages import Calibration


def spot_B(calibration: Calibration, standoff_mm: float) -> np.ndarray:
    """Deposition spot ``(3,)`` [mm] in ``B``: ``standoff_mm`` along +z_N from the nozzle exit."""
    T = calibration.T_B_N
    return T[:3, 3] + float(standoff_mm) * T[:3, 2]


def register_profile(xz_S: np.ndarray, T_O_S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points ``(n, 3)`` [mm] in ``O`` and the sensor origin ``(3,)`` [mm] in ``O``."""
    T = np.ascontiguousarray(T_O_S, dtype=np.float64)
    return _points_O(np.ascontiguousarray(xz_S, dtype=np.float64), T), T[:3, 3].copy()


@njit(cache=True)
def _points_O(xz_S, T_O_S):
    """``x R[:, 0] + z R[:, 2] + t`` per point: the laser plane's (x, z) placed in ``O``."""
    out = np.empty((xz_S.shape[0], 3))
    for i in range(xz_S.shape[0]):
        for c in range(3):
            out[i, c] = xz_S[i, 0] * T_O_S[c, 0] + xz_S[i, 1] * T_O_S[c, 2] + T_O_S[c, 3]
    return out


@njit(cache=True, nogil=True)
def profile_frames(T_B_F, T_F_O, T_B_S, sensor_index, spot_B, axis_B):
    """Per-profile frames of a batch, each computed alone (the same bits whatever the batch).

    Parameters
    ----------
    T_B_F : (k, 4, 4) float64, flange pose at each profile's stamp
    T_F_O : (4, 4) float64, work object on the flange
    T_B_S : (m, 4, 4) float64, the calibrated sensor poses
    sensor_index : (k,) int64, row of ``T_B_S`` that took each profile
    spot_B, axis_B : (3,) float64, deposition spot [mm] and unit spray axis in ``B``

    Returns
    -------
    T_O_S : (k, 4, 4) float64, ``inv(T_B_F @ T_F_O) @ T_B_S``
    spot_O, axis_O : (k, 3) float64, deposition spot [mm] and spray axis in ``O``
    """
    k = T_B_F.shape[0]
    T_O_S = np.zeros((k, 4, 4))
    spot_O = np.empty((k, 3))
    axis_O = np.empty((k, 3))
    T_B_O = np.empty((4, 4))
    T_O_B = np.zeros((4, 4))
    for j in range(k):
        for r in range(4):
            for c in range(4):
                acc = 0.0
                for m in range(4):
                    acc += T_B_F[j, r, m] * T_F_O[m, c]
                T_B_O[r, c] = acc
        for r in range(3):  # rigid inverse: R^T, -R^T t
            for c in range(3):
                T_O_B[r, c] = T_B_O[c, r]
            T_O_B[r, 3] = -(T_B_O[0, r] * T_B_O[0, 3] + T_B_O[1, r] * T_B_O[1, 3]
                            + T_B_O[2, r] * T_B_O[2, 3])
        T_O_B[3, 3] = 1.0
        s = sensor_index[j]
        for r in range(4):
            for c in range(4):
                acc = 0.0
                for m in range(4):
                    acc += T_O_B[r, m] * T_B_S[s, m, c]
                T_O_S[j, r, c] = acc
        for r in range(3):
            spot_O[j, r] = T_O_B[r, 0] * spot_B[0] + T_O_B[r, 1] * spot_B[1] \
                + T_O_B[r, 2] * spot_B[2] + T_O_B[r, 3]
            axis_O[j, r] = T_O_B[r, 0] * axis_B[0] + T_O_B[r, 1] * axis_B[1] \
                + T_O_B[r, 2] * axis_B[2]
    return T_O_S, spot_O, axis_O


def register_profiles(xz_S: np.ndarray, offsets: np.ndarray, T_O_S: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Points ``(n, 3)`` [mm] in ``O`` and their rays' origins ``(n, 3)`` of a profile batch
    (``xz_S (n, 2)``, ``offsets (k + 1,)``, ``T_O_S (k, 4, 4)``), with the arithmetic of
    :func:`dm2.fusion.tsdf.kernels.fuse_profiles`."""
    counts = np.diff(np.asarray(offsets, dtype=np.int64))
    xz = np.asarray(xz_S, dtype=np.float64)
    R = np.repeat(np.asarray(T_O_S)[:, :3, :3], counts, axis=0)
    origins = np.repeat(np.asarray(T_O_S)[:, :3, 3], counts, axis=0)
    return origins + R[:, :, 0] * xz[:, :1] + R[:, :, 2] * xz[:, 1:], origins
