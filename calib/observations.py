"""Calibration observations: one profile's valid points with the flange pose at its stamp."""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from dm2.core.frames import PoseInterpolator, pose_error
from dm2.core.messages import SENSOR_IDS, Profile, RobotState

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Observation:
    """Valid points of one profile and where the flange was when it was taken.

    Attributes
    ----------
    sensor_id : str
    xz_S : (n, 2) float64 [mm], finite points in the laser plane
    T_B_F : (4, 4) float64, flange pose at the profile's stamp [mm]
    pose_index : int, profiles taken at the same (stationary) pose share it
    """

    sensor_id: str
    xz_S: np.ndarray
    T_B_F: np.ndarray
    pose_index: int

    def __post_init__(self):
        if self.sensor_id not in SENSOR_IDS:
            raise ValueError(f"Observation.sensor_id: {self.sensor_id!r} not in {SENSOR_IDS}")
        xz = np.asarray(self.xz_S, dtype=np.float64).reshape(-1, 2)
        if not np.all(np.isfinite(xz)):
            raise ValueError("Observation.xz_S: must hold only finite (valid) points")
        T = np.asarray(self.T_B_F, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError("Observation.T_B_F: expected a finite (4, 4) transform")
        object.__setattr__(self, "xz_S", xz)
        object.__setattr__(self, "T_B_F", T)
        object.__setattr__(self, "pose_index", int(self.pose_index))


def observation_from_profile(profile: Profile, T_B_F: np.ndarray, pose_index: int) -> Observation:
    """Keep the valid, finite points of ``profile``."""
    ok = profile.valid & np.all(np.isfinite(profile.xz_S), axis=1)
    return Observation(profile.sensor_id, profile.xz_S[ok], T_B_F, pose_index)


def observations_from_messages(messages: Iterable, max_pose_gap_s: float = 0.05,
                               same_pose_mm: float = 0.1, same_pose_deg: float = 0.01
                               ) -> tuple[list[Observation], dict[str, int]]:
    """Pair every profile with the flange pose interpolated (SLERP) at its stamp.

    A profile is dropped when no robot state brackets its stamp within ``max_pose_gap_s``
    (unless both bracketing states report the same pose: the robot was standing still).
    Consecutive profiles whose poses agree within ``same_pose_mm`` / ``same_pose_deg`` share
    a pose index.

    Returns
    -------
    observations : list of Observation in stamp order
    dropped : dict reason -> count
    """
    profiles, states = [], []
    for msg in messages:
        if isinstance(msg, Profile):
            profiles.append(msg)
        elif isinstance(msg, RobotState):
            states.append(msg)
    dropped = {"no_pose": 0, "pose_gap": 0}
    if len(states) < 2:
        raise ValueError(f"calibration data holds {len(states)} robot states; need >= 2 to "
                         "know where the artifact was")
    states.sort(key=lambda s: s.stamp_s)
    stamps = np.array([s.stamp_s for s in states])
    keep = np.concatenate([[True], np.diff(stamps) > 0])
    stamps = stamps[keep]
    T = np.stack([s.T_B_F for s in states])[keep]
    interp = PoseInterpolator(stamps, T)
    out: list[Observation] = []
    pose_index, last_T = -1, None
    for p in sorted(profiles, key=lambda m: m.stamp_s):
        if p.stamp_s < stamps[0] or p.stamp_s > stamps[-1]:
            dropped["no_pose"] += 1
            continue
        j = int(np.searchsorted(stamps, p.stamp_s))
        j0, j1 = max(j - 1, 0), min(j, len(stamps) - 1)
        if stamps[j1] - stamps[j0] > max_pose_gap_s:
            dt, dr = pose_error(T[j0], T[j1])
            if dt > same_pose_mm or np.degrees(dr) > same_pose_deg:
                dropped["pose_gap"] += 1
                continue
        T_B_F = interp(np.array([p.stamp_s]))[0]
        if last_T is None:
            pose_index = 0
        else:
            dt, dr = pose_error(last_T, T_B_F)
            if dt > same_pose_mm or np.degrees(dr) > same_pose_deg:
                pose_index += 1
        if last_T is None or pose_index != out[-1].pose_index:
            last_T = T_B_F
        out.append(observation_from_profile(p, T_B_F, pose_index))
    if any(dropped.values()):
        log.info("calibration data: dropped profiles %s", dropped)
    return out, dropped
