"""Nozzle touch-off in the twin: the robot seats a centring cone of the artifact plate on the
nozzle exit, from several yaws, and reports its flange pose at each contact.

Procedure (as on the cell)
--------------------------
The artifact plate carries a centring cone whose seat point (where the nozzle exit's centre
sits once the exit rim rests in the cone) is certified in the artifact frame ``A``
(``touch_mark_mm`` of the artifact file). With the plate level and facing the nozzle, the
operator jogs the robot up until the cone seats on the exit, then records the flange pose;
this is repeated at ``n`` yaws about the vertical. Since ``T_B_F @ T_F_A @ mark_A`` is the
nozzle exit centre at every contact, the mean over the touches gives the exit position in
``B`` once ``T_F_A`` is known (:func:`calib.touch_off.nozzle_exit_from_touches`). A touch
fixes a point, not the spray axis: the nozzle's orientation stays the cell file's.

Errors modelled: the seat is off by ``N(0, seat_error_mm)`` per axis (cone and rim form,
contact detection), and the controller's reported flange position is off the true one by the
robot's repeatability (ISO 9283 RP, as in the calibration run).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from dm2.core.frames import invert, make_T


def touch_off_poses(mark_A: np.ndarray, true_T_F_A: np.ndarray, true_T_B_N: np.ndarray,
                    R_B_A_level: np.ndarray, n: int, rng: np.random.Generator,
                    seat_error_mm: float, robot_sigma_mm: float, reachable) -> np.ndarray:
    """Reported flange poses ``(n, 4, 4)`` at ``n`` touches of the mark on the nozzle exit.

    Parameters
    ----------
    mark_A : (3,) [mm], the cone's seat point in the artifact frame
    true_T_F_A, true_T_B_N : the artifact's true mount and the nozzle's true pose
    R_B_A_level : (3, 3), the level artifact orientation the yaws are taken about
    reachable : ``reachable(T_B_F) -> bool``; unreachable yaws are skipped

    Raises
    ------
    ValueError : fewer than ``n`` reachable touches over the yaws tried
    """
    exit_B = true_T_B_N[:3, 3]
    out = []
    yaws = np.linspace(0.0, 2.0 * np.pi, 4 * n, endpoint=False)
    order = np.concatenate([yaws[i::4] for i in range(4)])  # spread first, then fill in
    for yaw in order:
        R = Rotation.from_euler("z", yaw).as_matrix() @ R_B_A_level
        seat_B = exit_B + rng.normal(0.0, seat_error_mm, 3)
        T_B_A = make_T(R, seat_B - R @ np.asarray(mark_A, dtype=np.float64))
        T_true_B_F = T_B_A @ invert(true_T_F_A)
        if not reachable(T_true_B_F):
            continue
        reported = T_true_B_F.copy()
        reported[:3, 3] += rng.normal(0.0, robot_sigma_mm, 3)
        out.append(reported)
        if len(out) == n:
            return np.stack(out)
    raise ValueError(f"touch-off: only {len(out)} of {n} touches reachable")

