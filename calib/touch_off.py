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

import tomllib
from dataclasses import dataclass

import numpy as np

from dm2.core.config import ConfigError
from dm2.core.frames import apply, from_quat_abb, make_T, to_quat_abb
from dm2.core.tolerances import UNIT_NORM_TOL
from dm2.core.toml_write import dump_toml


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


TOUCH_OFF_SCHEMA = 1
TOUCH_OFF_ATTACHMENT = "touch_off.toml"


def touch_off_to_toml(T_B_F: np.ndarray) -> str:
    """Touch-off flange poses as TOML: ``schema = 1`` and ``[[touches]]`` tables with
    ``translation_mm`` and ``quaternion_wxyz`` (ABB order), as a calibration run records them."""
    touches = []
    for T in np.asarray(T_B_F, dtype=np.float64).reshape(-1, 4, 4):
        t, q = to_quat_abb(T)
        touches.append({"translation_mm": [float(v) for v in t],
                        "quaternion_wxyz": [float(v) for v in q]})
    return ("# nozzle touch-off: flange poses at each contact [mm]\n"
            + dump_toml({"schema": TOUCH_OFF_SCHEMA, "touches": touches}))


def touch_off_from_toml(text: str, source: str = "<touch-off>") -> np.ndarray:
    """Flange poses ``(n, 4, 4)`` of a touch-off TOML text. Raises ConfigError naming
    ``source`` and the field."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: not valid TOML: {exc}") from None
    if data.get("schema") != TOUCH_OFF_SCHEMA:
        raise ConfigError(f"{source}: field 'schema': expected {TOUCH_OFF_SCHEMA}, got "
                          f"{data.get('schema')!r}")
    touches = data.get("touches")
    if not isinstance(touches, list) or not touches:
        raise ConfigError(f"{source}: field 'touches': expected [[touches]] tables")
    out = []
    for i, tab in enumerate(touches):
        try:
            t = np.asarray(tab["translation_mm"], dtype=np.float64)
            q = np.asarray(tab["quaternion_wxyz"], dtype=np.float64)
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"{source}: field 'touches[{i}]': {exc}") from None
        if t.shape != (3,) or q.shape != (4,) or not np.all(np.isfinite(np.r_[t, q])):
            raise ConfigError(f"{source}: field 'touches[{i}]': expected 3 + 4 finite numbers")
        if abs(np.linalg.norm(q) - 1.0) > UNIT_NORM_TOL:
            raise ConfigError(f"{source}: field 'touches[{i}].quaternion_wxyz': not a unit "
                              f"quaternion (norm {np.linalg.norm(q):.9g})")
        out.append(from_quat_abb(t, q))
    return np.stack(out)
