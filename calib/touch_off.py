"""Nozzle exit position from a touch-off on the artifact plate (procedure in the artifact's
docs and :mod:`twin.stream.touch_off` for the twin's model of it).

At every touch the nozzle exit centre sits on the plate's centring cone, whose seat point
``mark_A`` is certified in the artifact frame, so the exit lies at ``T_B_F @ T_F_A @ mark_A``.
The mean over touches taken at several yaws is the estimate; the yaws also average a small
error of ``T_F_A``'s rotation. The spread of the touches is reported as their 1-sigma
scatter. A touch fixes a point only: the spray axis (the rotation of ``T_B_N``) is not
observed and stays the prior's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dm2.core.frames import apply, make_T


@dataclass(frozen=True)
class TouchOffResult:
    """``T_B_N`` with the touched exit position and the prior's rotation.

    Attributes
    ----------
    T_B_N : (4, 4) float64
    exit_B_mm : (3,) float64, mean touched exit centre
    scatter_mm : (3,) float64, per-axis sample standard deviation of the touches
    sigma_mm : (3,) float64, standard error of the mean (scatter / sqrt(n))
    n_touches : int
    """

    T_B_N: np.ndarray
    exit_B_mm: np.ndarray
    scatter_mm: np.ndarray
    sigma_mm: np.ndarray
    n_touches: int


def nozzle_exit_from_touches(T_B_F: np.ndarray, T_F_A: np.ndarray, mark_A: np.ndarray,
                             prior_T_B_N: np.ndarray) -> TouchOffResult:
    """Estimate the nozzle exit from touch poses ``T_B_F (n, 4, 4)``; needs n >= 2."""
    T_B_F = np.asarray(T_B_F, dtype=np.float64).reshape(-1, 4, 4)
    if T_B_F.shape[0] < 2:
        raise ValueError(f"touch-off: {T_B_F.shape[0]} touch(es); need >= 2 at different yaws")
    mark = np.asarray(mark_A, dtype=np.float64).reshape(1, 3)
    pts = np.stack([apply(T @ T_F_A, mark)[0] for T in T_B_F])
    mean = pts.mean(axis=0)
    scatter = pts.std(axis=0, ddof=1)
    return TouchOffResult(make_T(np.asarray(prior_T_B_N)[:3, :3], mean), mean, scatter,
                          scatter / np.sqrt(pts.shape[0]), int(pts.shape[0]))
