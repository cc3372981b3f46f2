"""What the scene recording keeps of the raw stream: decimated profiles and robot poses.

:class:`StreamTap` sits on a run's message stream (``dm2 run``, ``dm2 monitor``) and keeps, in
stream order, a decimated copy of what ``scene.mcap`` shows of the raw inputs:

* the robot flange pose ``T_B_F`` at most every :data:`POSE_PERIOD_S` of stamp time;
* each profiler's profiles at most every :data:`PROFILE_PERIOD_S` of stamp time per sensor,
  every :data:`POINT_STEP`-th valid point of each (the decimation rule: the scene shows the
  raw data the fusion saw, not all of it, so that ``scene.mcap`` stays small beside the run's
  own recording).

The kept profiles are registered in the plate frame ``O`` at the end (:meth:`registered`) with
the robot pose interpolated at each profile's stamp, as the fusion registers them (paper eq. 1:
``p_O = T_F_O^-1 T_B_F^-1 T_B_S p_S``). Nothing here touches the messages themselves.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dm2.core.frames import interpolate_pose, invert
from dm2.core.messages import LayerMark, Profile, RobotState

PROFILE_PERIOD_S = 0.25  # one profile per sensor per this much stamp time
POINT_STEP = 4  # every 4th valid point of a kept profile
POSE_PERIOD_S = 0.05  # flange poses at 20 Hz at most


@dataclass
class TappedProfile:
    """One kept profile: its sensor, stamp [s] and valid points ``xz_S`` (k, 2) [mm]."""

    sensor_id: str
    stamp_s: float
    xz_S: np.ndarray


@dataclass
class StreamTap:
    """Keeps the decimated raw inputs of a stream (see the module docstring)."""

    profiles: list[TappedProfile] = field(default_factory=list)
    pose_stamps_s: list[float] = field(default_factory=list)
    poses_T_B_F: list[np.ndarray] = field(default_factory=list)
    layer_marks: list[tuple[float, int]] = field(default_factory=list)
    _last_profile_s: dict = field(default_factory=dict)
    _last_pose_s: float = -np.inf

    def wrap(self, messages):
        """``messages`` unchanged, each one seen by :meth:`see` on the way."""
        for msg in messages:
            self.see(msg)
            yield msg

    def see(self, msg) -> None:
        """Keep what the decimation rule keeps of one message."""
        if isinstance(msg, RobotState):
            if msg.stamp_s - self._last_pose_s >= POSE_PERIOD_S \
                    or msg.stamp_s < self._last_pose_s:
                self._last_pose_s = msg.stamp_s
                self.pose_stamps_s.append(float(msg.stamp_s))
                self.poses_T_B_F.append(np.array(msg.T_B_F, dtype=np.float64))
        elif isinstance(msg, Profile):
            last = self._last_profile_s.get(msg.sensor_id, -np.inf)
            if msg.stamp_s - last >= PROFILE_PERIOD_S or msg.stamp_s < last:
                self._last_profile_s[msg.sensor_id] = msg.stamp_s
                xz = np.asarray(msg.xz_S, dtype=np.float64)[np.asarray(msg.valid, bool)]
                self.profiles.append(TappedProfile(msg.sensor_id, float(msg.stamp_s),
                                                   xz[::POINT_STEP].copy()))
        elif isinstance(msg, LayerMark):
            self.layer_marks.append((float(msg.stamp_s), int(msg.layer)))

    def pose_at(self, stamp_s: float) -> np.ndarray | None:
        """``T_B_F`` interpolated at ``stamp_s`` between the kept poses (None outside them)."""
        t = self.pose_stamps_s
        if not t or stamp_s < t[0] or stamp_s > t[-1]:
            return None
        i = int(np.searchsorted(t, stamp_s))
        if i == 0 or t[i] == stamp_s:
            return self.poses_T_B_F[i]
        a = (stamp_s - t[i - 1]) / (t[i] - t[i - 1])
        return interpolate_pose(self.poses_T_B_F[i - 1], self.poses_T_B_F[i], a)

    def registered(self, calibration) -> list[tuple[float, str, np.ndarray]]:
        """The kept profiles in the plate frame: ``(stamp_s, sensor_id, points_O (k, 3) mm)``
        in stamp order; a profile outside the kept poses' span, or of a sensor the
        calibration lacks, is left out."""
        T_O_F = invert(np.asarray(calibration.T_F_O, dtype=np.float64))
        out = []
        for p in sorted(self.profiles, key=lambda p: p.stamp_s):
            T_B_F = self.pose_at(p.stamp_s)
            T_B_S = calibration.T_B_S.get(p.sensor_id)
            if T_B_F is None or T_B_S is None or not len(p.xz_S):
                continue
            T_O_S = T_O_F @ invert(T_B_F) @ np.asarray(T_B_S, dtype=np.float64)
            pts_S = np.column_stack([p.xz_S[:, 0], np.zeros(len(p.xz_S)), p.xz_S[:, 1]])
            out.append((p.stamp_s, p.sensor_id, pts_S @ T_O_S[:3, :3].T + T_O_S[:3, 3]))
        return out
